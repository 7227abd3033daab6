"""SmartSuit nodes on a CAN bus (000 seed, ch. 3): any python-can interface, or a log.

The transport's unit is a frame: python-can's ``Message``, turned into the
core's :class:`~bodynet.core.codecs.smartsuit_can.CanFrame` and decoded by the
sans-io frame codec. Frames carry no sequence number: a node's samples are
numbered by arrival (a missed 10 ms period is a gap). The same source serves
real adapters (``socketcan``, ``slcan``, ``pcan``...), the emulators, and
``--replay`` of a candump/asc/blf log at its recorded speed.
"""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import can

from bodynet.core.codecs import smartsuit_can as codec
from bodynet.core.codecs.smartsuit_can import CanFrame
from bodynet.core.messages import Source as SourceId
from bodynet.core.messages import StreamEvent
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.sources.base import (
    Adapter,
    CapturedSample,
    CaptureSink,
    CaptureStats,
    EmulatorError,
    NodeParts,
    PeriodicAdapter,
    Source,
    Transport,
)
from bodynet.nodes.sources.can_transport import (
    LOG_SUFFIXES,
    can_log_messages,
    frame_of,
    open_bus,
)
from bodynet.nodes.sources.serial_port import SerialSource
from bodynet.session import argtypes


def can_interface(text: str) -> str:
    """A python-can interface name (socketcan, slcan, pcan...): an argparse type."""
    if text not in can.VALID_INTERFACES:
        known = ", ".join(sorted(can.VALID_INTERFACES))
        argtypes.fail(f"{text[:60]!r} is not a python-can interface (python-can's: {known})")
    return text


class FrameDecoder:
    """Frames in, the SmartSuit readings (or rejections) they carry out."""

    def feed(self, frame: CanFrame) -> list[StreamEvent]:
        return codec.frame_events(frame)

    def close(self) -> list[StreamEvent]:
        return []


class SmartSuitCan(Source):
    name = "can"
    wire_id = SourceId.CAN
    transport = Transport.CAN
    help = "SmartSuit nodes on any python-can interface, or a log"
    SITES = SMARTSUIT_SITES
    PERIOD_S = codec.PERIOD_S
    formats: ClassVar = {"can-log": "a CAN log (candump .log, .asc, .blf, .trc)"}
    suffixes: ClassVar = dict.fromkeys(LOG_SUFFIXES, "can-log")
    emulators: ClassVar = {
        "slcan": "a slcan USB-CAN adapter with SmartSuit nodes",
        "can": "SmartSuit nodes on a python-can bus",
    }
    TIMING: ClassVar = frozenset({"timers", "clock_ppm", "jitter_s", "drop"})

    def decoder(self) -> FrameDecoder:
        return FrameDecoder()

    def adapter(self, rate_hz: float | None = None) -> Adapter:
        return PeriodicAdapter(self.period_s, rate_hz)

    def read(self, path: Path, fmt: str, stats: CaptureStats,
             rate_hz: float | None = None) -> Iterator[CapturedSample]:  # fmt: skip
        decoder, adapter = self.decoder(), self.adapter(rate_hz)
        sink = CaptureSink(self.sites, stats)
        for msg in can_log_messages(path, stats):
            frame = frame_of(msg)
            if (kind := codec.foreign(frame)) is not None:
                stats.foreign[kind] += 1  # another device's on the bus: not bad input
                continue
            adapter.events(decoder.feed(frame), msg.timestamp, sink)
            yield from sink.take()

    # --- live ---------------------------------------------------------------------------
    @classmethod
    def add_bridge_args(cls, p: argparse.ArgumentParser) -> None:
        p.add_argument("--interface", default="socketcan", type=can_interface,
                       help="python-can interface (socketcan, slcan, pcan...)")  # fmt: skip
        p.add_argument("--channel", type=argtypes.free_text(200),
                       help="channel: can0, /dev/ttyACM0 (slcan)...")  # fmt: skip
        p.add_argument("--bitrate", default=None,
                       type=argtypes.bounded_int(1000, 8_000_000, "bit/s"))  # fmt: skip
        p.add_argument("--replay", type=argtypes.input_file,
                       help="play a candump/asc/blf log at its recorded speed")  # fmt: skip
        p.add_argument("--loop", action="store_true", help="with --replay: play again and again")

    @classmethod
    def bridge_name(cls, args: argparse.Namespace) -> str:
        return f"can-{args.channel or 'replay'}"

    def bridge(self, session: Any, stop: threading.Event, name: str,
               args: argparse.Namespace) -> None:  # fmt: skip
        bus_args = {"interface": args.interface, "channel": args.channel}
        if args.bitrate:
            bus_args["bitrate"] = args.bitrate
        run_bridge(session, stop, name, args.replay, args.loop, args.batch_ms / 1e3, **bus_args)

    # --- emulation ----------------------------------------------------------------------
    @classmethod
    def add_emulate_args(cls, device: str, p: argparse.ArgumentParser) -> None:
        if device == "can":
            p.add_argument("--interface", default="socketcan", type=can_interface)
            p.add_argument("--channel", default="vcan0", type=argtypes.free_text(200))
        else:
            SerialSource.add_emulate_args(device, p)

    def emulated_sensors(self, sensors: Any = None, branches: Any = None) -> list[Any]:
        from bodynet.nodes.emulator import smartsuit_sensors

        return smartsuit_sensors(branches)

    def emulator(self, device: str, body: Any, truth: Any, opts: dict[str, Any]) -> Any:
        from bodynet.nodes.hardware import SlcanAdapterEmulator

        timing = opts.get("timing")
        if device == "can":
            return _BusNodes(dict(opts.get("bus_args") or {}), body, truth, timing=timing)
        return SlcanAdapterEmulator(opts["link"], body, truth=truth, timing=timing)

    def node(self, device: str, body: Any, where: Path, clock: Any, truth: Any,
             sensors: list[Any], label: str, timing: Any = None) -> NodeParts:  # fmt: skip
        from bodynet.nodes.hardware import SlcanAdapterEmulator

        if device == "can":
            channel = f"bodynet-{label}-{time.monotonic_ns()}"
            bus_args = {"interface": "virtual", "channel": channel}
            return _BusNodes(bus_args, body, truth, clock, timing), run_bridge, bus_args
        link = str(where / label)
        emulator = SlcanAdapterEmulator(where / label, body, clock, truth, timing=timing)
        return emulator, run_bridge, {"interface": "slcan", "channel": link,
                                      "sleep_after_open": 0}  # fmt: skip


class _BusNodes:
    """Emulated nodes on a python-can bus this object opens and closes."""

    def __init__(self, bus_args: dict[str, Any], body: Any, truth: Any, clock: Any = None,
                 timing: Any = None) -> None:  # fmt: skip
        self.bus_args, self.body, self.truth, self.clock = bus_args, body, truth, clock
        self.timing = timing
        self.link = bus_args.get("channel")
        self._bus: can.BusABC | None = None
        self._nodes: Any = None

    def start(self) -> None:
        from bodynet.nodes.hardware import CanNodes

        try:
            self._bus = open_bus(**self.bus_args)
        except (can.CanError, OSError) as exc:  # no such interface, channel or port
            where = ", ".join(f"{k} {v}" for k, v in self.bus_args.items() if v is not None)
            raise EmulatorError(f"cannot open the CAN bus ({where}): {exc}") from None
        self._nodes = CanNodes(self._bus, self.body, self.clock, self.truth, timing=self.timing)
        self._nodes.start()

    def stop(self) -> None:
        if self._nodes is not None:
            self._nodes.stop()
        if self._bus is not None:
            self._bus.shutdown()


def run_bridge(session: Any, stop: threading.Event, name: str, replay: Path | None = None,
               loop: bool = False, batch_s: float = 0.0, **bus_args: Any) -> None:  # fmt: skip
    """A CAN bridge on ``can.Bus(**bus_args)`` (or playing ``replay``) until ``stop``;
    its samples in batches of ``batch_s`` at most if not 0."""
    from bodynet.nodes.sources.live import CanBusBridge

    bridge = CanBusBridge(session, SmartSuitCan(), name)
    bridge.publisher.batch(batch_s)
    try:
        if replay is not None:
            bridge.run_replay(replay, stop, loop)
        else:
            bridge.run_bus(stop, **bus_args)
    finally:
        bridge.close()
