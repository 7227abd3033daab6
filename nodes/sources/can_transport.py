"""The CAN transport: python-can messages and logs, whatever the source on the bus."""

from __future__ import annotations

import contextlib
import logging
import math
import re
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from itertools import chain
from pathlib import Path
from typing import IO, Any

import can
from can.io.blf import BLFParseError

from bodynet.core.codecs.smartsuit_can import CanFrame
from bodynet.core.errors import Reason, Rejected
from bodynet.nodes.sources.base import CaptureError, CaptureStats, time_refused

#: suffixes of the logs python-can's ``LogReader`` reads that bodynet takes
LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc")


def frame_of(msg: can.Message) -> CanFrame:
    """The core's frame for a python-can message."""
    return CanFrame(
        msg.arbitration_id,
        bytes(msg.data or b""),
        msg.is_extended_id,
        msg.is_remote_frame,
        msg.is_error_frame,
        msg.dlc,
    )


class BusClock:
    """The wall-clock time of a bus's frames, from python-can's ``msg.timestamp``.

    Where that is on the wall clock (socketcan's kernel time, slcan's and the
    virtual bus's host time, the vendor libraries python-can sets to it: pcan,
    kvaser, vector, ixxat, etas) it is kept as it is. Some interfaces give the
    adapter's own counter instead (gs_usb/candleLight, cantact, systec, usb2can,
    canalystii, serial): 1970 plus the adapter's uptime, a 32-bit microsecond
    one going back to 0 every 71.6 minutes. Of such a time only the spacing
    of the frames is kept: anchored to ``time.time()`` at the first frame, never
    ahead of it (a frame that came sooner than any before moves the anchor back
    to it), following an adapter clock slower than the host's by up to
    :attr:`DRIFT`, and anchored again when the counter goes back (it wrapped or
    the adapter restarted) or falls :attr:`MAX_LAG_S` behind the wall clock.
    The times it gives never go back.
    """

    #: a timestamp further than this from ``time.time()`` is the adapter's own clock
    ON_WALL_S = 10.0
    #: how fast (s/s) the anchor follows an adapter clock slower than the host's
    DRIFT = 1e-3
    #: how far behind the wall clock an adapter's times may fall before anchoring again
    MAX_LAG_S = 1.0

    def __init__(self) -> None:
        self._offset: float | None = None  # wall clock minus the adapter's
        self._last = (0.0, 0.0)  # the last adapter time and wall-clock time

    def reset(self) -> None:
        """The adapter was opened again: its counter may have started over."""
        self._offset = None

    def wall(self, stamp: float | None, now: float) -> float:
        """The time of a frame python-can stamped ``stamp``, received at ``now``."""
        if not stamp or not math.isfinite(stamp):
            return now
        if abs(stamp - now) <= self.ON_WALL_S:
            return stamp
        last_stamp, last_now = self._last
        self._last = (stamp, now)
        if self._offset is None or stamp < last_stamp:
            self._offset = now - stamp  # the first frame, or the counter went back
        else:
            self._offset = min(now - stamp, self._offset + self.DRIFT * max(0.0, now - last_now))
            if now - (stamp + self._offset) > self.MAX_LAG_S:
                self._offset = now - stamp
        return stamp + self._offset


#: what python-can's vendor wrappers say when a library will not load (a ctypes
#: ``OSError`` without an errno: "pcanbasic library not found.", "...: cannot open
#: shared object file"), unlike an absent device (an errno: ENODEV, ENOENT...)
_NO_LIBRARY = re.compile(
    r"library not found|could not be loaded|cannot open shared object|not installed"
    r"|no module named|please install",
    re.IGNORECASE,
)


def unusable(exc: BaseException) -> str | None:
    """Why ``exc``, raised by ``can.Bus(...)``, will not go away by waiting (the
    interface's driver, vendor library or Python module missing, another OS, options
    that do not suit it), or None if it may (a device unplugged, busy, not up yet)."""
    if isinstance(exc, NotImplementedError):  # CanInterfaceNotImplementedError
        return str(exc)
    if isinstance(exc, ImportError | NameError):  # NameError: kvaser without its canlib
        return f"its driver or library is not installed ({type(exc).__name__}: {exc})"
    if isinstance(exc, OSError) and exc.errno is None and _NO_LIBRARY.search(str(exc)):
        return f"its driver or library is not installed ({exc})"
    if isinstance(exc, TypeError | ValueError):  # "Must specify a serial port."...
        return f"the options do not suit it ({exc})"
    return None


def open_bus(**bus_args: Any) -> can.BusABC:
    """``can.Bus(**bus_args)``; :class:`DeviceError` if its interface can never open
    here (:func:`unusable`). What python-can logs meanwhile is dropped then (the
    error says it: "Kvaser canlib is unavailable."), else logged after."""
    with _held_logs() as held:
        try:
            return can.Bus(**bus_args)
        except Exception as exc:
            if why := unusable(exc):
                # here, not at the top: device.py loads Zenoh, which captures do not
                from bodynet.nodes.device import DeviceError

                held.clear()
                interface = bus_args.get("interface")
                raise DeviceError(f"python-can's {interface} interface cannot be used "
                                  f"here: {why}") from None  # fmt: skip
            raise


class _Held(logging.Handler):
    """python-can's log records of this thread, held; other threads' passed on."""

    def __init__(self) -> None:
        super().__init__()
        self.thread = threading.get_ident()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.records.append(record)
        else:
            logging.getLogger().handle(record)

    def clear(self) -> None:
        self.records.clear()


@contextlib.contextmanager
def _held_logs() -> Iterator[_Held]:
    """Hold what python-can logs in the block; log what was not cleared after it."""
    logger, held = logging.getLogger("can"), _Held()
    logger.addHandler(held)
    logger.propagate = False
    try:
        yield held
    finally:
        logger.removeHandler(held)
        logger.propagate = True
        for record in held.records:
            logging.getLogger(record.name).handle(record)


class _Lines:
    """A text file's lines for a python-can reader, numbered. Every line handed
    out waits in ``pending`` until the reader yields a message (that line gave
    it; the ones before were skipped) or raises (that line was bad): so a line
    a reader passes over without a word is still seen. ``again`` hands a line
    out once more (a reader that swallowed it while looking for its header)."""

    def __init__(self, f: IO[str]) -> None:
        self._f = f
        self.number = 0
        self.again: tuple[int, str] | None = None
        self.pending: list[tuple[int, str]] = []

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        if self.again is not None:
            self.pending.append(self.again)
            line = self.again[1]
            self.again = None
            return line
        line = next(self._f)
        self.number += 1
        self.pending.append((self.number, line))
        return line

    def readline(self) -> str:
        try:
            return next(self)
        except StopIteration:
            return ""

    def take(self, last_used: bool) -> list[tuple[int, str]]:
        """The lines handed out since the last call that gave no message (all
        but the last one when ``last_used``: it gave a message or was bad)."""
        pending, self.pending = self.pending, []
        return pending[:-1] if last_used and pending else pending

    def close(self) -> None:
        self._f.close()

    def __getattr__(self, name: str) -> object:
        return getattr(self._f, name)


#: What a python-can reader raises on a line or object it cannot parse.
_PARSE_ERRORS = (ValueError, IndexError, KeyError, TypeError, AttributeError, struct.error,
                 zlib.error, can.CanError, BLFParseError)  # fmt: skip

_TEXT_READERS: dict[str, type] = {
    ".log": can.CanutilsLogReader,
    ".asc": can.ASCReader,
    ".trc": can.TRCReader,
    ".csv": can.CSVReader,
}

# -- lines a reader passes over: the format's own non-frame lines, or garbled ---------
#
# python-can's .asc and .trc readers skip, without a word, every line that is
# not a frame they read: comments and events of the format (bus statistics, a
# chip status, a system variable...), but also a frame line garbled past
# recognition (a timestamp "1.0Z0", a direction "Rq"). Each line a reader
# passed over is looked at here: one of the format's own non-frame lines is
# left alone; any other is counted as garbled, with its line number. The
# format's lines are listed by name, so that no damage of one character turns a
# frame line into one of them; where it can (an empty line, a .trc comment or
# record type), such a line among frames that reads as a frame once put back is
# counted as well.

_ASC_HEADER = re.compile(  # the header lines python-can's ASCReader looks for, and comments
    r"(date\s+\w+\s|base\s+(hex|dec)|(no)?\s*internal\s+events\s+logged|//"
    r"|end\s+triggerblock)",
    re.IGNORECASE,
)
_ASC_EVENT_TIME = re.compile(r"\d+\.\d+\s+(?P<rest>.*)", re.ASCII)
#: Vector's events that are not CAN frames, after their time: the start of the
#: measurement, log triggers, a CAN channel's statistics, chip status, overload
#: frames and J1939 transport messages, system and environment variables, test
#: feature sets, and the frames of other buses (Ethernet, FlexRay, MOST, K-Line,
#: ARINC 429, AFDX). Nothing else passes: an event line of another kind is counted.
_ASC_EVENTS = re.compile(
    r"(Start\s+of\s+measurement|log\s+trigger\s+event|log\s+direct\s+(start|stop)\b"
    r"|CAN\s+\d+\s+(Status|Error):"
    r"|\d+\s+(Statistic:|J1939TP\s|OverloadFrame\b)"
    r"|(SV|TFS|GPS):"
    r"|[A-Za-z_]\w*\s+:=\s"
    r"|(ETH|FR|Fr|MOST\w*|KLine|A429|AFDX)\s)",
    re.ASCII,
)


def _asc_known(line: str) -> bool:
    """An .asc line python-can skips on purpose: blank, a comment, a header or
    trigger block line, or one of Vector's events that are not frames."""
    text = line.strip()
    if not text or _ASC_HEADER.match(text) or can.io.asc.ASC_TRIGGER_REGEX.match(text):
        return True
    timed = _ASC_EVENT_TIME.match(text)
    return timed is not None and _ASC_EVENTS.match(timed["rest"]) is not None


#: PCAN trace record types that are not frames (PEAK's TRC format 1.1 to 2.1):
#: error frames, error counter and status changes, events, bus warnings
_TRC_NOT_FRAMES = {"ER", "EC", "ST", "EV", "Warng", "Error"}


def _trc_frame(text: str, reader: can.TRCReader) -> bool:
    """Does ``text`` read as a frame of the reader's format?"""
    try:
        return reader._parse_line(text) is not None
    except _PARSE_ERRORS:
        return False


def _trc_known(line: str, reader: can.TRCReader, among_frames: bool = False) -> bool:
    """A .trc line python-can skips on purpose: blank, a ``;`` comment, or a
    record of a type that is not a frame (``ST``, ``ER``...), or a 1.0 bus
    information line (id FFFFFFFF). Among frames, a comment that reads as a
    frame without its ``;`` (or with a digit in its place) is not, nor a record
    that reads as a frame with the type ``DT``: a frame line one character of
    which was changed."""
    text = line.strip()
    if not text:
        return True
    if text.startswith(";"):  # a ";" put before a frame's line, or over its first character
        framed = (_trc_frame(t, reader) for t in (text[1:], "0" + text[1:]))
        return not (among_frames and any(framed))
    cols = text.split()
    version = reader.file_version
    v2 = version >= can.io.trc.TRCFileVersion.V2_0  # (it has >=, not <)
    try:
        if v2:
            at = reader.columns["T"]
        elif version == can.io.trc.TRCFileVersion.V1_3:
            at = 3
        elif version == can.io.trc.TRCFileVersion.V1_1:
            at = 2
        else:
            return cols[2] == "FFFFFFFF"
        if cols[at] not in _TRC_NOT_FRAMES:
            return False
    except (IndexError, KeyError):
        return False
    if not v2:
        return True
    cols[at] = "DT"
    return not _trc_frame(" ".join(cols), reader)


def _not_frame(suffix: str, line: str, number: int, reader: object,
               among_frames: bool) -> str | None:  # fmt: skip
    """Why a line a reader passed over is counted (None: it is one of the
    format's own non-frame lines). An empty line is one of them, but not among
    frames: there it is most likely a frame line cut to nothing."""
    if not line.strip():
        return "an empty line among frames" if among_frames else None
    if suffix == ".asc":
        known = _asc_known(line)
    elif suffix == ".trc":
        known = _trc_known(line, reader, among_frames)  # type: ignore[arg-type]
    else:
        known = suffix == ".csv" and number == 1  # a CSV's header
    return None if known else f"not a frame python-can reads: {line.strip()[:60]!r}"


def can_log_messages(path: Path, stats: CaptureStats) -> Iterator[can.Message]:
    """python-can's messages of a log (candump ``.log``, ``.asc``, ``.trc``,
    ``.csv``, ``.blf``); a line (or BLF object) it cannot parse, or passes over
    when it is not one of its format's own non-frame lines, or a text line
    whose time no sample holds (NaN, inf, beyond 64-bit ns), is counted with
    its line number (byte offset) and skipped, and the lines after it are read.

    python-can's readers stop at the first line they cannot parse: here the
    same reader, its header already read, is started again after that line.

    Times are the log's, in order: a Vector ASC log's ``timestamps relative``
    (each the time since the event before, which python-can's reader gives as
    they are) are added up; a frame whose time is out of order with the frames
    on both sides of it (a garbled time) is counted and skipped like a garbled
    line; times that go back and stay back (a clock stepped back, logs joined out
    of order) are a :class:`CaptureError` naming the line, as in an orientation file.
    """
    if path.suffix.lower() == ".blf":
        blf = _blf_messages(path, stats)
        yield from _in_order(path, stats, ((m, f"frame {n}") for n, m in enumerate(blf, 1)))
    else:
        yield from _in_order(path, stats, _text_log_messages(path, stats))


def _text_log_messages(path: Path, stats: CaptureStats) -> Iterator[tuple[can.Message, str]]:
    """A text log's messages and their lines (see :func:`can_log_messages`)."""
    suffix = path.suffix.lower()
    reader_type = _TEXT_READERS.get(suffix)
    if reader_type is None:
        stats.count(
            Rejected(
                Reason.TRUNCATED,
                f"{path.name}: not a CAN log python-can "
                f"reads (.log, .asc, .trc, .csv, .blf): {suffix or 'no suffix'}",
            )
        )
        return
    with path.open(encoding="ascii", errors="replace", newline=None) as f:
        lines = _Lines(f)
        reader = reader_type(lines)
        if suffix == ".trc":  # its own parser drops a short line silently: count it
            reader._parse_line = _strict_trc(reader)
        if suffix == ".asc":
            reader._extract_header = _asc_header(reader, lines)

        frames = 0  # read so far

        def passed_over(skipped: list[tuple[int, str]], then_frame: bool) -> None:
            """Count the lines a reader passed over; ``then_frame``: a frame (or a
            bad line) comes after them, so they lie among frames if one came before."""
            for number, line in skipped:
                if not number:
                    continue  # a line handed out again: not the file's
                why = _not_frame(suffix, line, number, reader, frames > 0 and then_frame)
                if why is None:
                    continue
                where = f"line {number}"
                stats.count(Rejected(Reason.GARBAGE, f"{path.name} {where}: {why}"))
                stats.bad_places.append(where)

        messages = iter(reader)
        add_up = _relative_times(reader)
        while True:
            try:  # only the reader's errors are the file's (not this function's own)
                msg = next(messages)
            except StopIteration:
                passed_over(lines.take(last_used=False), then_frame=False)
                return
            except _PARSE_ERRORS as exc:
                passed_over(lines.take(last_used=True), then_frame=True)
                where = f"line {lines.number}" if lines.number else "its header"
                stats.count(Rejected(Reason.GARBAGE, f"{path.name} {where}: {exc}"))
                stats.bad_places.append(where)
                if not lines.number:
                    return
                # on again from the next line, without reading a header again
                reader._extract_header = lambda: None
                if suffix == ".csv":
                    lines.again = (0, "header\n")  # the reader skips a first (header) line
                messages = iter(reader)
                continue
            passed_over(lines.take(last_used=True), then_frame=True)
            frames += 1
            where = f"line {lines.number}"
            if _untimed(msg, where, path, stats):
                continue
            add_up(msg)
            yield msg, where


def _relative_times(reader: object) -> Callable[[can.Message], None]:
    """What makes a message's time absolute: an ASC log's ``timestamps relative``
    added up (the header is read with the first message)."""
    elapsed = 0.0

    def add_up(msg: can.Message) -> None:
        nonlocal elapsed
        if getattr(reader, "timestamps_format", None) == "relative":
            start = reader.start_time  # type: ignore[attr-defined]
            elapsed += msg.timestamp - start
            msg.timestamp = start + elapsed

    return add_up


def _order(before: float | None, t_s: float, later: list[float]) -> str:
    """``ok``, ``odd`` (out of order with the frames around it, which are in order
    with each other) or ``step`` (it and the next go back from ``before``): the
    order of a frame at ``t_s`` after one at ``before``, the next two at ``later``."""
    after = later[0] if later else None
    if before is not None and t_s < before:
        return "step" if after is not None and after < before else "odd"
    if after is None or t_s <= after or (len(later) > 1 and later[1] >= t_s):
        return "ok"  # in order, or the next is the odd one
    return "odd" if before is None or after >= before else "ok"  # else the next steps back


def _in_order(path: Path, stats: CaptureStats,
              frames: Iterator[tuple[can.Message, str]]) -> Iterator[can.Message]:  # fmt: skip
    """A log's frames whose times keep order (see :func:`can_log_messages`)."""
    before: float | None = None
    window: deque[tuple[can.Message, str]] = deque()
    for frame in chain(frames, [None]):
        if frame is not None:
            window.append(frame)
        while len(window) == 3 or (frame is None and window):
            msg, where = window.popleft()
            t_s = msg.timestamp
            order = _order(before, t_s, [m.timestamp for m, _ in window])
            if order == "step":
                raise CaptureError(f"{path}: {where}: time {t_s:.6f} s goes back from "
                                   f"{before:.6f} s, and the frames after it too (a clock "
                                   "stepped back?): a log's times must not decrease")  # fmt: skip
            if order == "odd":
                why = f"time {t_s:.6f} s out of order with the frames around it"
                stats.count(Rejected(Reason.OUT_OF_ORDER, f"{path.name} {where}: {why}"))
                stats.bad_places.append(where)
                continue
            before = t_s
            yield msg


def _untimed(msg: can.Message, where: str, path: Path, stats: CaptureStats) -> bool:
    """Count a message whose time no sample holds (python-can reads a candump
    line's "(nan)" or "(1e300)" as its time); True if it was."""
    why = time_refused(msg.timestamp)
    if why is None:
        return False
    reason = Reason.OUT_OF_RANGE if math.isfinite(msg.timestamp) else Reason.NOT_FINITE
    stats.count(Rejected(reason, f"{path.name} {where}: {why}"))
    stats.bad_places.append(where)
    return True


def _asc_header(reader: can.ASCReader, lines: _Lines):  # type: ignore[no-untyped-def]
    """python-can's header reader, but the first line after the header (which
    it reads to know the header has ended, and drops) is handed out again."""
    extract = reader._extract_header

    def header() -> None:
        extract()
        if lines.pending:
            number, line = lines.pending[-1]
            if not re.match(r"(no)?\s*internal\s+events\s+logged", line.strip(), re.I):
                lines.pending.pop()
                lines.again = (number, line)

    return header


def _strict_trc(reader: can.TRCReader):  # type: ignore[no-untyped-def]
    def parse(line: str) -> can.Message | None:
        return reader._parse_cols(tuple(line.split(maxsplit=reader._num_columns)))

    return parse


_BLF_OBJECT = b"LOBJ"


def _blf_messages(path: Path, stats: CaptureStats) -> Iterator[can.Message]:
    """A BLF log's messages, container by container (python-can's reader does
    the parsing); a container that does not parse (bad compression, a broken
    object) is counted with its byte offset and the next one is read."""
    from can.io import blf

    header = blf.OBJ_HEADER_BASE_STRUCT
    with path.open("rb") as f:
        try:
            reader = can.BLFReader(f)
        except _PARSE_ERRORS as exc:
            stats.count(Rejected(Reason.GARBAGE, f"{path.name}: not a BLF file ({exc})"))
            stats.bad_places.append("its header")
            return
        data = f.read()
    pos = data.find(_BLF_OBJECT)
    start = f"{path.name}"
    resync = False
    while 0 <= pos < len(data):
        try:
            _, _, _, size, kind = header.unpack_from(data, pos)
            if size < header.size:
                raise ValueError(f"object size {size}")
            body = data[pos + header.size : pos + size]
            if len(body) < size - header.size:
                raise ValueError("cut short")
            messages: list[can.Message] = []
            if kind == blf.LOG_CONTAINER:
                method, _ = blf.LOG_CONTAINER_STRUCT.unpack_from(body)
                chunk = body[blf.LOG_CONTAINER_STRUCT.size :]
                if method == blf.ZLIB_DEFLATE:
                    chunk = zlib.decompressobj().decompress(chunk)
                if resync:  # after a bad container: from this one's first whole object
                    at = chunk.find(_BLF_OBJECT)
                    chunk = chunk[at:] if at >= 0 else b""
                    resync = False
                messages = list(reader._parse_container(chunk))
        except _PARSE_ERRORS as exc:
            where = f"byte {pos + _blf_offset(path, data)}"
            stats.count(Rejected(Reason.GARBAGE, f"{start} {where}: {exc or 'garbled'}"))
            stats.bad_places.append(where)
            reader._tail = b""
            resync = True
            pos = data.find(_BLF_OBJECT, pos + 1)
            continue
        yield from messages
        pos += size + size % 4
        if data[pos : pos + 4] != _BLF_OBJECT:
            nxt = data.find(_BLF_OBJECT, pos)
            if nxt > pos:
                where = f"byte {pos + _blf_offset(path, data)}"
                stats.count(Rejected(Reason.GARBAGE, f"{start} {where}: garbage between objects"))
                stats.bad_places.append(where)
            pos = nxt


def _blf_offset(path: Path, data: bytes) -> int:
    """Where ``data`` (the file after its header) starts in the file."""
    return path.stat().st_size - len(data)


def paced(messages: Iterable[can.Message], stop: threading.Event) -> Iterable[can.Message]:
    """Messages at their logged pace."""
    start, first = time.monotonic(), None
    for msg in messages:
        first = msg.timestamp if first is None else first
        if stop.wait(max(0.0, start + (msg.timestamp - first) - time.monotonic())):
            return
        yield msg
