"""Reading captures of the source systems' wire formats from files.

A capture is what a logger saw on one of the seeds' links: a CAN log
(anything python-can's ``LogReader`` reads: candump ``.log``, ``.asc``,
``.blf``, ``.trc``...), a Data Concentrator serial exchange, or an IMU central
data matrix. :func:`read_capture` decodes one with the core codecs and gives
each sample the capture's own time: the logged timestamp where the format has
one, otherwise the index of the reply (concentrator) or tick (IMU central)
divided by the link's rate.
"""

from __future__ import annotations

import logging
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import IO

import can
from can.io.blf import BLFParseError

from bodynet.core.codecs.concentrator import ConcentratorDecoder
from bodynet.core.codecs.imu_matrix import ImuMatrixDecoder
from bodynet.core.codecs.smartsuit_can import CanFrame, decode_frame
from bodynet.core.errors import DecodeError, Reason, RejectCounts, Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import NoNewData, OleAccel, Quat, Reading, SensorAbsent, Tick
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES

log = logging.getLogger(__name__)

CHUNK = 1 << 16

#: The Data Concentrator answers one request every 22 ms (000 seed, ch. 3.4.2).
CONCENTRATOR_RATE_HZ = 1 / 0.022
#: One tick of the IMU central: about what 230400 baud carries for 15 sensors.
IMU_CENTRAL_RATE_HZ = 25.0


class Format(StrEnum):
    CAN_LOG = "can-log"
    CONCENTRATOR = "concentrator"
    IMU_CENTRAL = "imu-central"


@dataclass(frozen=True, slots=True)
class CapturedSample:
    """A decoded reading, where it sits, and the capture's time of it."""

    t_s: float
    reading: Reading
    site: Site


@dataclass(slots=True)
class CaptureStats:
    """What a capture held besides its samples."""

    decoded: int = 0
    rejected: RejectCounts = field(default_factory=RejectCounts)
    no_new_data: int = 0
    sensor_absent: int = 0
    #: where each line (byte, in a binary log) skipped as garbled was: "line 12"
    bad_places: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """``decoded N, rejected M (reason: count, ...)`` plus idle lines if any."""
        total = sum(self.rejected.values())
        text = f"decoded {self.decoded}, rejected {total}"
        if total:
            text += f" ({self.rejected.summary()})"
        idle = [(n, what) for n, what in ((self.no_new_data, "no new data"),
                (self.sensor_absent, "sensor absent")) if n]  # fmt: skip
        if idle:
            text += "; not samples: " + ", ".join(f"{what} {n}" for n, what in idle)
        if self.bad_places:
            shown = ", ".join(self.bad_places[:10])
            more = f" and {len(self.bad_places) - 10} more" if len(self.bad_places) > 10 else ""
            text += f"; skipped garbled {shown}{more}"
        return text


def default_rate_hz(fmt: Format) -> float | None:
    return {Format.CONCENTRATOR: CONCENTRATOR_RATE_HZ, Format.IMU_CENTRAL: IMU_CENTRAL_RATE_HZ}.get(
        fmt
    )


def read_capture(
    path: str | Path,
    fmt: Format | str,
    stats: CaptureStats,
    rate_hz: float | None = None,
) -> Iterator[CapturedSample]:
    """Decode a capture file into samples, counting everything else in ``stats``."""
    fmt = Format(fmt)
    if fmt is Format.CAN_LOG:
        yield from _can_log(Path(path), stats)
        return
    rate = rate_hz or default_rate_hz(fmt)
    assert rate is not None
    if fmt is Format.CONCENTRATOR:
        yield from _concentrator(Path(path), stats, rate)
    else:
        yield from _imu_central(Path(path), stats, rate)


def _chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as f:
        while chunk := f.read(CHUNK):
            yield chunk
    yield b""  # the end: decoders' close() follows


def _count(stats: CaptureStats, rejected: Rejected) -> None:
    stats.rejected[rejected.reason] += 1
    log.debug("rejected %s: %s %r", rejected.reason, rejected.detail, rejected.data)


def _sample(stats: CaptureStats, t_s: float, reading: Reading, site: Site) -> CapturedSample:
    stats.decoded += 1
    return CapturedSample(round(t_s, 9), reading, site)


def _concentrator(path: Path, stats: CaptureStats, rate: float) -> Iterator[CapturedSample]:
    decoder = ConcentratorDecoder()
    index = 0
    for chunk in _chunks(path):
        for event in decoder.feed(chunk) if chunk else decoder.close():
            if isinstance(event, Rejected):
                _count(stats, event)
            else:
                yield _sample(stats, index / rate, event, SMARTSUIT_SITES[event.node])
                index += 1


def _imu_central(path: Path, stats: CaptureStats, rate: float) -> Iterator[CapturedSample]:
    decoder = ImuMatrixDecoder()
    tick = 0
    for chunk in _chunks(path):
        for event in decoder.feed(chunk) if chunk else decoder.close():
            if isinstance(event, Quat):
                yield _sample(stats, tick / rate, event, IMU_SITES[event.node])
            elif isinstance(event, Tick):
                tick = event.index
            elif isinstance(event, Rejected):
                _count(stats, event)
            elif isinstance(event, NoNewData):
                stats.no_new_data += 1
            elif isinstance(event, SensorAbsent):
                stats.sensor_absent += 1


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


class _Lines:
    """A text file's lines for a python-can reader, numbered, so that a line
    the reader cannot parse is reported by its number; ``again`` hands out a
    line once more without counting it (a reader that skips a header line)."""

    def __init__(self, f: IO[str]) -> None:
        self._f = f
        self.number = 0
        self.again: str | None = None

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        if self.again is not None:
            line, self.again = self.again, None
            return line
        line = next(self._f)
        self.number += 1
        return line

    def readline(self) -> str:
        try:
            return next(self)
        except StopIteration:
            return ""

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


def can_log_messages(path: Path, stats: CaptureStats) -> Iterator[can.Message]:
    """python-can's messages of a log (candump ``.log``, ``.asc``, ``.trc``,
    ``.csv``, ``.blf``); a line (or BLF object) it cannot parse is counted with
    its line number (byte offset) and skipped, and the lines after it are read.

    python-can's readers stop at the first line they cannot parse: here the
    same reader, its header already read, is started again after that line.
    """
    suffix = path.suffix.lower()
    if suffix == ".blf":
        yield from _blf_messages(path, stats)
        return
    reader_type = _TEXT_READERS.get(suffix)
    if reader_type is None:
        _count(stats, Rejected(Reason.TRUNCATED, f"{path.name}: not a CAN log python-can "
                               f"reads (.log, .asc, .trc, .csv, .blf): {suffix or 'no suffix'}"))
        return
    with path.open(encoding="ascii", errors="replace", newline=None) as f:
        lines = _Lines(f)
        reader = reader_type(lines)
        if suffix == ".trc":  # its own parser drops a short line silently: count it
            reader._parse_line = _strict_trc(reader)
        while True:
            try:
                yield from reader
                return
            except _PARSE_ERRORS as exc:
                where = f"line {lines.number}" if lines.number else "its header"
                _count(stats, Rejected(Reason.GARBAGE, f"{path.name} {where}: {exc}"))
                stats.bad_places.append(where)
                if not lines.number:
                    return
            # on again from the next line, without reading a header again
            reader._extract_header = lambda: None
            if suffix == ".csv":
                lines.again = "header\n"  # the reader skips a first (header) line


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
            _count(stats, Rejected(Reason.GARBAGE, f"{path.name}: not a BLF file ({exc})"))
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
            _count(stats, Rejected(Reason.GARBAGE, f"{start} {where}: {exc or 'garbled'}"))
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
                _count(stats, Rejected(Reason.GARBAGE, f"{start} {where}: garbage between objects"))
                stats.bad_places.append(where)
            pos = nxt


def _blf_offset(path: Path, data: bytes) -> int:
    """Where ``data`` (the file after its header) starts in the file."""
    return path.stat().st_size - len(data)


def _can_log(path: Path, stats: CaptureStats) -> Iterator[CapturedSample]:
    for msg in can_log_messages(path, stats):
        try:
            reading = decode_frame(frame_of(msg))
        except DecodeError as exc:
            _count(stats, Rejected.of(exc, bytes(msg.data or b"")))
            continue
        yield _sample(stats, msg.timestamp, reading, SMARTSUIT_SITES[reading.node])


def sample_json(sample: CapturedSample) -> dict[str, object]:
    """The JSON object ``bodynet decode`` prints for a sample."""
    r = sample.reading
    out: dict[str, object] = {"node": r.node, "key": sample.site.raw_key, "t_s": sample.t_s}
    if isinstance(r, OleAccel):
        out["encoder"] = r.encoder
        out["accel"] = list(r.accel)
    else:
        out["quat_wxyz"] = list(r.wxyz)
    return out


_SNIFFERS: tuple[tuple[str, re.Pattern[bytes]], ...] = (
    ("an MCAP recording (for export, report, view or replay)", re.compile(rb"\A\x89MCAP")),
    ("a BLF CAN log (--format can-log, named .blf)", re.compile(rb"\ALOGG")),
    ("a candump CAN log (--format can-log, named .log)",
     re.compile(rb"^\(\d+\.\d+\)\s+\S+\s+[0-9A-Fa-f]+#", re.M)),
    ("a Vector ASC CAN log (--format can-log, named .asc)",
     re.compile(rb"^\s*(date\s|base\s+(hex|dec)|begin triggerblock)", re.M | re.I)),
    ("a PCAN TRC CAN log (--format can-log, named .trc)", re.compile(rb"^;\$FILEVERSION", re.M)),
    ("a python-can CSV CAN log (--format can-log, named .csv)",
     re.compile(rb"\Atimestamp,arbitration_id,")),
    ("a Data Concentrator capture (--format concentrator)",
     re.compile(rb"[A-Z]E[0-9A-Fa-f]{4}X[0-9A-Fa-f]{4}Y[0-9A-Fa-f]{4}Z")),
    ("an IMU central capture (--format imu-central)", re.compile(rb"\A([0-9a-fA-F]{52,56}\r?\n)+")),
)  # fmt: skip


def looks_like(path: Path) -> str | None:
    """What a file's first bytes look like, as a capture format (or a
    recording) ``bodynet`` reads, with the option that reads it; None if none."""
    try:
        with path.open("rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    for what, pattern in _SNIFFERS:
        if pattern.search(head):
            return what
    return None
