"""What the serial sources share on the command line and in emulation."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from bodynet.nodes.sources.base import Source
from bodynet.session import argtypes


class SerialSource(Source):
    """A source on a serial port (``bodynet bridge NAME --port ... --baud ...``),
    emulated on a pseudo-terminal behind ``--link``."""

    @classmethod
    def add_bridge_args(cls, p: argparse.ArgumentParser) -> None:
        p.add_argument("--port", required=True, type=argtypes.free_text(200),
                       help="serial device, e.g. /dev/ttyUSB0")  # fmt: skip
        p.add_argument("--baud", type=argtypes.bounded_int(50, 4_000_000, "baud"), default=None,
                       help=f"default {cls.BAUD}")  # fmt: skip

    @classmethod
    def bridge_name(cls, args: argparse.Namespace) -> str:
        return f"{cls.name}-{Path(args.port).name}"

    def bridge(self, session: Any, stop: Any, name: str, args: argparse.Namespace) -> None:
        self.run_bridge(session, stop, name, args.port, args.baud or self.BAUD,
                        batch_s=args.batch_ms / 1e3)  # fmt: skip

    def run_bridge(self, session: Any, stop: Any, name: str, port: str,
                   baud: int | None = None, batch_s: float = 0.0) -> None:  # fmt: skip
        from bodynet.nodes.sources.live import SerialBridge

        bridge = SerialBridge(session, self, name)
        bridge.publisher.batch(batch_s)
        try:
            bridge.run(port, stop, baud)
        finally:
            bridge.close()

    @classmethod
    def add_emulate_args(cls, device: str, p: argparse.ArgumentParser) -> None:
        p.add_argument("--link", type=argtypes.link_path, required=True,
                       help="path of the symlink to the pseudo-terminal")  # fmt: skip
