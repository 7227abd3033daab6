"""The CAN transport: python-can messages and logs, whatever the source on the bus."""

from __future__ import annotations

import struct
import threading
import time
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

import can
from can.io.blf import BLFParseError

from bodynet.core.codecs.smartsuit_can import CanFrame
from bodynet.core.errors import Reason, Rejected
from bodynet.nodes.sources.base import CaptureStats

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
        while True:
            try:
                yield from reader
                return
            except _PARSE_ERRORS as exc:
                where = f"line {lines.number}" if lines.number else "its header"
                stats.count(Rejected(Reason.GARBAGE, f"{path.name} {where}: {exc}"))
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
