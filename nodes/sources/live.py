"""A source live: its transport's units through its decoder and adapter onto Zenoh.

:class:`Bridge` is what every source's bridge is made of: a
:class:`~bodynet.nodes.publisher.SitePublisher` for its sites, the source's
adapter (the same one its capture reader uses) and a sink between them.
:class:`SerialBridge` adds the loop of a source on a serial port: open the
port (again after an unplug), feed what it reads to the decoder.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import can
import serial
import zenoh

from bodynet.core.codecs import smartsuit_can as can_codec
from bodynet.core.errors import Reason, Rejected
from bodynet.core.messages import (
    RESUMED,
    NodeStatus,
    NoNewData,
    Reading,
    SensorAbsent,
    StreamEvent,
)
from bodynet.nodes.device import DecodeWatch, DeviceError, in_use, keep_connected
from bodynet.nodes.publisher import SitePublisher
from bodynet.nodes.sources.base import BLIND_S, CaptureError, CaptureStats, Source
from bodynet.nodes.sources.can_transport import (
    BusClock,
    can_log_messages,
    frame_of,
    open_bus,
    paced,
)

log = logging.getLogger(__name__)

SERIAL_ERRORS = (serial.SerialException, OSError)
CAN_ERRORS = (can.CanError, OSError, serial.SerialException)
#: What python-can's interfaces raise, out of ``recv``, on what the adapter sent that
#: they cannot parse: slcan on ``T0006FFZZ8...`` (``int(..., 16)``) or on a line cut
#: before its DLC (``IndexError``), the ``serial`` interface on a frame cut short
#: (``struct.error``, ``ord(b"")``). One bad frame: the next one is read.
BAD_FRAME_ERRORS = (ValueError, IndexError, TypeError, struct.error)
#: Unreadable frames in a row after which the bus is taken for broken and reopened.
MAX_UNREADABLE = 1000
#: How long one read of the bus waits for a frame (s)
RECV_TIMEOUT_S = 0.1


class Bridge:
    """One source's events onto Zenoh: samples published on their sites, node
    states and rejections counted in health."""

    def __init__(self, session: zenoh.Session, source: Source, name: str) -> None:
        self.source = source
        self.publisher = SitePublisher(session, source.sites, source.wire_id, name,
                                       source.period_s)  # fmt: skip
        self.adapter = source.adapter()
        self.absent: set[int] = set()  # nodes the device says it has never seen

    def feed(self, events: Iterable[StreamEvent], t_s: float | None = None) -> None:
        """Events decoded from one unit that arrived at ``t_s`` (now if None)."""
        self.adapter.events(events, time.time() if t_s is None else t_s, self)

    # --- the adapter's sink -------------------------------------------------------------
    def sample(self, reading: Reading, seq: int, t_s: float, flags: int = 0) -> None:
        self.absent.discard(reading.node)
        if flags & RESUMED:
            log.warning("%s: node %d sends again after a silence in which it may have "
                        "rebooted: its encoder's zero is lost until a calibration pose",
                        self.publisher.name, reading.node)  # fmt: skip
        self.publisher.publish(reading, seq, round(t_s * 1e9), flags)

    def reject(self, rejected: Rejected) -> None:
        self.publisher.reject(rejected, rejected.node)

    def status(self, event: NoNewData | SensorAbsent | NodeStatus) -> None:
        if isinstance(event, SensorAbsent):
            self.absent.add(event.node)
        elif isinstance(event, NodeStatus):
            self.publisher.set_status(event.node, event.key, event.value)
        # NoNewData shows as a gap: the node's next sample skips this tick

    def close(self) -> None:
        self.publisher.close()


class SerialBridge(Bridge):
    """A source on a serial port: the source serves the open port (by default
    reading and decoding what comes); reopened after an unplug.

    The port is opened exclusively (``flock``, as pyserial's ``exclusive``): a
    port another bridge holds when this one starts is refused (:class:`DeviceError`,
    exit 2); one taken by another program after an unplug is said and retried.
    Bytes that come without anything decoding from them are said on the
    console (:class:`DecodeWatch`: a wrong ``--baud``)."""

    watch: DecodeWatch | None = None

    def run(self, port: str, stop: threading.Event, baud: int | None = None) -> None:
        source = self.source
        speed = baud or source.BAUD
        watch = self.watch = DecodeWatch(self.publisher, port, f"wrong --baud (it is {speed})?")
        tries = 0

        def open_port() -> serial.Serial:
            nonlocal tries
            tries += 1
            try:
                return serial.Serial(port, speed, timeout=source.SERIAL_TIMEOUT_S, exclusive=True)
            except SERIAL_ERRORS as exc:
                if not in_use(exc):
                    raise
                why = f"{port} is in use by another program (another bridge? ModemManager?)"
                if tries == 1:  # held when we start: a mistake to say, not to wait out
                    raise DeviceError(why) from None
                raise serial.SerialException(why) from None  # taken meanwhile: retried

        def serve(link: serial.Serial) -> None:
            watch.restart()
            try:
                self.source.serve(_Counted(link, watch), stop, self)
            finally:
                self.adapter.restart()

        keep_connected(self.publisher, open_port, serve, lambda link: link.close(),
                       SERIAL_ERRORS, stop, path=port)  # fmt: skip

    def sample(self, reading: Reading, seq: int, t_s: float, flags: int = 0) -> None:
        if self.watch is not None:
            self.watch.decoded()
        super().sample(reading, seq, t_s, flags)

    def status(self, event: NoNewData | SensorAbsent | NodeStatus) -> None:
        if self.watch is not None:
            self.watch.decoded()
        super().status(event)


class _Counted:
    """A serial port whose reads are told to a :class:`DecodeWatch`."""

    def __init__(self, link: serial.Serial, watch: DecodeWatch) -> None:
        self._link = link
        self._watch = watch

    def read(self, size: int = 1) -> bytes:
        data: bytes = self._link.read(size)
        self._watch.received(len(data))
        return data

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)


class CanBusBridge(Bridge):
    """A source on a python-can bus (or a log of one played back at its pace)."""

    def __init__(self, session: zenoh.Session, source: Source, name: str) -> None:
        super().__init__(session, source, name)
        self._decoder = source.decoder()
        self.clock = BusClock()
        self._unreadable = 0  # frames python-can could not read, in a row
        self.adapter.watched = True  # an adapter may stamp frames when read (slcan)

    def handle(self, msg: can.Message, read_from: float | None = None) -> None:
        """Decode and publish one message (bad frames are counted, never raised),
        at its time on the wall clock (:class:`BusClock`); another device's frame
        is counted as foreign. ``read_from``: when the read that got it began, if
        it came back on time (the bus was watched quiet from then to the frame)."""
        frame = frame_of(msg)
        t_s = self.clock.wall(msg.timestamp, time.time())
        if read_from is not None and t_s > read_from:
            self.adapter.quiet(read_from, t_s)
        if (kind := can_codec.foreign(frame)) is not None:
            self.publisher.count_foreign(kind)
            self.adapter.seen(t_s)  # the bus is alive
            return
        self.feed(self._decoder.feed(frame), t_s)

    def run_bus(self, stop: threading.Event, **bus_args: Any) -> None:
        """Serve ``can.Bus(**bus_args)`` until ``stop``, reopening it when it fails (not
        when it can never open: :func:`open_bus`)."""

        def serve(bus: can.BusABC) -> None:
            self.clock.reset()  # the adapter's own clock may have started over
            self.adapter.restart()  # and how late its frames came tells nothing now
            while not stop.is_set():
                msg, read_from = self._receive(bus)
                if msg is not None:
                    self.handle(msg, read_from)

        keep_connected(self.publisher, lambda: open_bus(**bus_args), serve,
                       lambda bus: bus.shutdown(), CAN_ERRORS, stop,
                       path=str(bus_args.get("channel") or "") or None)  # fmt: skip

    def _receive(self, bus: can.BusABC) -> tuple[can.Message | None, float | None]:
        """The bus's next message, or None: none came within 0.1 s, or what the
        adapter sent could not be read as a frame (counted as garbage: the device is
        still there, the next frame is read); and when the read began if it came
        back on time (else None: this thread did not run all along).

        A read that waited, got nothing and came back on time watched the bus quiet
        (:meth:`Adapter.quiet`). One such read is no proof that the bus was: nodes
        emulated beside the bridge stall with it under load (and then send what
        they owe at once), so only several in a row across a long quiet count
        (a whole suit switched off and on: base.PeriodicAdapter)."""
        start = time.time()
        try:
            msg = bus.recv(timeout=RECV_TIMEOUT_S)
        except BAD_FRAME_ERRORS as exc:
            why = f"{type(exc).__name__}: {exc}"
        except can.CanOperationError as exc:
            # python-can's slcan decodes each line as text: a byte that is not
            # (line noise, a wrong baud rate) is this error, not a device gone
            if not isinstance(exc.__cause__, UnicodeDecodeError) or not _drop_bad_line(bus):
                raise
            why = f"not text: {exc.__cause__}"
        else:
            self._unreadable = 0
            end = time.time()
            if end - start > RECV_TIMEOUT_S + BLIND_S / 2:
                return msg, None
            if msg is None:
                self.adapter.quiet(start, end)
            return msg, start
        self.publisher.reject(Rejected(Reason.GARBAGE, f"a frame python-can cannot read ({why})"))
        self._unreadable += 1
        if self._unreadable >= MAX_UNREADABLE:  # the same error over and over (a closed
            self._unreadable = 0  # port's ValueError, say): no frame is coming, reopen
            raise can.CanOperationError(f"{MAX_UNREADABLE} unreadable frames in a row ({why})")
        return None, None

    def run_replay(self, path: Path, stop: threading.Event, loop: bool = False) -> None:
        """Play a CAN log back at its recorded speed, stamped with the time of play."""
        self.publisher.set_device("replay")
        self.adapter.watched = False  # the log's spacing is the bus's record
        while not stop.is_set():
            stats = CaptureStats()
            frames = 0
            for msg in paced(can_log_messages(path, stats), stop):
                msg.timestamp = time.time()
                self.handle(msg)
                frames += 1
            for reason, n in stats.rejected.items():
                for _ in range(n):
                    self.publisher.reject(Rejected(reason, "log line"))
            _replayed(self.publisher.name, path, frames, stats, stop.is_set())
            if not loop:
                break


def _drop_bad_line(bus: can.BusABC) -> bool:
    """Drop the line python-can's slcan could not decode as text: it clears its
    buffer only after decoding a line, so that line's bytes would spoil every line
    after it. False if the bus keeps no such buffer (then it is reopened)."""
    buffer = getattr(bus, "_buffer", None)
    if not isinstance(buffer, bytearray):
        return False
    buffer.clear()
    return True


def _replayed(name: str, path: Path, frames: int, stats: CaptureStats, stopped: bool) -> None:
    """Say what a pass over a CAN log replayed (a warning if it skipped lines);
    ``CaptureError`` if the whole file held no frame."""
    total = sum(stats.rejected.values())
    skipped = f"; skipped {total} ({stats.rejected.summary()})" if total else ""
    if stats.bad_places:
        skipped += f" at {', '.join(stats.bad_places[:10])}"
    if not frames and not stopped:
        from bodynet.nodes.captures import looks_else

        raise CaptureError(f"no CAN frame in {path}{skipped}{looks_else(path, 'can-log')}")
    say = log.warning if total else log.info
    say("%s: %d frames replayed from %s%s", name, frames, path, skipped)
