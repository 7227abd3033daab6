"""The Data Concentrator (000 seed, ch. 3.4.2, 4.1): SmartSuit nodes polled over serial.

The bridge writes each request character and feeds both what it wrote and
what came back to the sans-io decoder, exactly as a capture of the link reads,
so pairing, missing replies and garbage are handled in one place. A sample's
sequence number is the poll cycle (a missed reply is a gap); a capture, which
has no clock, times the replies by their order at one per 22 ms.
"""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

from bodynet.core.codecs import concentrator as codec
from bodynet.core.keys import Site
from bodynet.core.messages import OleAccel, Reading, Tick
from bodynet.core.messages import Source as SourceId
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.sources.base import Adapter, Feed, NodeParts, Transport
from bodynet.nodes.sources.serial_port import SerialSource
from bodynet.session import argtypes

REPLY_TIMEOUT_S = 0.1


class CycleAdapter(Adapter):
    """Numbered by poll cycle (the bridge's ticks); timed, without a clock, by
    reply order at ``rate_hz``."""

    def __init__(self, period_s: float, rate_hz: float | None = None) -> None:
        super().__init__(period_s, rate_hz or 1.0 / codec.CYCLE_S)
        self.replies = 0

    def stamp(self, reading: Reading, t_s: float | None) -> tuple[int, float]:
        if t_s is None:
            t_s = self.replies / self.rate_hz
        self.replies += 1
        return self.base + self.tick, t_s


class Concentrator(SerialSource):
    name = "concentrator"
    wire_id = SourceId.CONCENTRATOR
    transport = Transport.SERIAL
    help = "the concentrator on a serial port (115200 baud)"
    SERIAL_TIMEOUT_S = 0.01
    SITES = SMARTSUIT_SITES
    PERIOD_S = codec.CYCLE_S
    BAUD = codec.BAUD
    formats: ClassVar = {"concentrator": "a capture of the concentrator's serial exchange"}
    emulators: ClassVar = {"concentrator": "a Data Concentrator with SmartSuit nodes"}

    def __init__(self, sites: Mapping[int, Site] | None = None, period_s: float | None = None,
                 nodes: Sequence[int] = (1, 2, 3)) -> None:  # fmt: skip
        self.nodes = list(nodes)
        super().__init__(sites, period_s or codec.CYCLE_S * len(self.nodes))

    def decoder(self) -> codec.ConcentratorDecoder:
        return codec.ConcentratorDecoder()

    def adapter(self, rate_hz: float | None = None) -> Adapter:
        return CycleAdapter(self.period_s, rate_hz)

    def serve(self, link: Any, stop: threading.Event, bridge: Feed) -> None:
        """Poll each node in turn, a cycle after another, until ``stop``."""
        decoder = self.decoder()
        cycle = 0
        while not stop.is_set():
            bridge.feed([Tick(cycle)])
            for node in self.nodes:
                request = codec.request(node)
                link.write(request)
                bridge.feed(decoder.feed(request))
                deadline = time.monotonic() + REPLY_TIMEOUT_S
                while time.monotonic() < deadline and not stop.is_set():
                    events = decoder.feed(link.read(max(1, link.in_waiting)))
                    bridge.feed(events)
                    if any(isinstance(e, OleAccel) for e in events):
                        break
            cycle += 1

    @classmethod
    def add_bridge_args(cls, p: argparse.ArgumentParser) -> None:
        super().add_bridge_args(p)
        p.add_argument("--nodes", type=argtypes.number_list(1, codec.MAX_NODES), default="1-3",
                       help=f"nodes to poll, 1..{codec.MAX_NODES} (default 1-3)")  # fmt: skip

    def bridge(self, session: Any, stop: Any, name: str, args: argparse.Namespace) -> None:
        Concentrator(self.sites, None, args.nodes).run_bridge(
            session, stop, name, args.port, args.baud or self.BAUD
        )

    def emulated_sensors(self, sensors: Any = None, branches: Any = None) -> list[Any]:
        from bodynet.nodes.emulator import smartsuit_sensors

        return smartsuit_sensors(branches)

    def emulator(self, device: str, body: Any, truth: Any, opts: dict[str, Any]) -> Any:
        from bodynet.nodes.hardware import ConcentratorEmulator

        return ConcentratorEmulator(opts["link"], body, truth=truth,
                                    silent=opts.get("silent", ()))  # fmt: skip

    def node(self, device: str, body: Any, where: Path, clock: Any, truth: Any,
             sensors: list[Any], label: str) -> NodeParts:  # fmt: skip
        from bodynet.nodes.hardware import ConcentratorEmulator

        emulator = ConcentratorEmulator(where / label, body, clock, truth)
        nodes = tuple(s.node for s in sensors)
        source = Concentrator(self.sites, None, nodes)
        return emulator, source.run_bridge, {"port": str(where / label)}
