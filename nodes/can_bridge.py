"""CAN bridge: SmartSuit frames from any python-can bus (or a log) onto Zenoh.

The same code serves real adapters (``socketcan``, ``slcan``, ``pcan``...) and
the emulators; ``replay`` plays a candump/asc/blf log back at its recorded
speed instead of reading a bus.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import can
import serial
import zenoh

from bodynet.core.codecs.smartsuit_can import decode_frame
from bodynet.core.errors import DecodeError, Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import Source
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.captures import CaptureStats, can_log_messages, frame_of
from bodynet.nodes.device import keep_connected
from bodynet.nodes.hardware import CAN_PERIOD_S
from bodynet.nodes.publisher import PeriodicSeq, SitePublisher

log = logging.getLogger(__name__)

DEVICE_ERRORS = (can.CanError, OSError, serial.SerialException)


class CanBridge:
    """Reads a bus (or a log) and publishes every SmartSuit frame it decodes."""

    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        sites: Mapping[int, Site] = SMARTSUIT_SITES,
        period_s: float = CAN_PERIOD_S,
    ) -> None:
        self.publisher = SitePublisher(session, sites, Source.CAN, name, period_s)
        self._seq = PeriodicSeq(period_s)

    def handle(self, msg: can.Message) -> None:
        """Decode and publish one message (bad frames are counted, never raised)."""
        try:
            reading = decode_frame(frame_of(msg))
        except DecodeError as exc:
            node = msg.arbitration_id >> 18 if msg.is_extended_id else None
            self.publisher.reject(Rejected.of(exc, bytes(msg.data or b"")), node)
            return
        stamp = msg.timestamp or time.time()
        self.publisher.publish(reading, self._seq.next(reading.node, stamp), int(stamp * 1e9))

    def run_bus(self, stop: threading.Event, **bus_args: Any) -> None:
        """Serve ``can.Bus(**bus_args)`` until ``stop``, reopening it when it fails."""

        def serve(bus: can.BusABC) -> None:
            while not stop.is_set():
                msg = bus.recv(timeout=0.1)
                if msg is not None:
                    self.handle(msg)

        keep_connected(
            self.publisher,
            lambda: can.Bus(**bus_args),
            serve,
            lambda bus: bus.shutdown(),
            DEVICE_ERRORS,
            stop,
        )

    def run_replay(self, path: Path, stop: threading.Event, loop: bool = False) -> None:
        """Play a CAN log back at its recorded speed, stamped with the time of play."""
        self.publisher.set_device("replay")
        while not stop.is_set():
            stats = CaptureStats()
            for msg in _paced(can_log_messages(path, stats), stop):
                msg.timestamp = time.time()
                self.handle(msg)
            for reason, n in stats.rejected.items():
                for _ in range(n):
                    self.publisher.reject(Rejected(reason, "log line"))
            if not loop:
                break

    def close(self) -> None:
        self.publisher.close()


def _paced(messages: Iterable[can.Message], stop: threading.Event) -> Iterable[can.Message]:
    start, first = time.monotonic(), None
    for msg in messages:
        first = msg.timestamp if first is None else first
        if stop.wait(max(0.0, start + (msg.timestamp - first) - time.monotonic())):
            return
        yield msg
