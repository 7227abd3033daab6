"""The CAN transport: python-can messages and logs, whatever the source on the bus."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import can

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


def can_log_messages(path: Path, stats: CaptureStats) -> Iterator[can.Message]:
    """python-can's messages of a log; a candump line it cannot parse is counted.

    python-can's readers stop at the first line they cannot parse, so candump
    logs (one frame per line) are read a line at a time to survive a garbled
    line; other formats are read whole and a failure ends them, counted.
    """
    if path.suffix.lower() == ".log":
        with path.open(encoding="ascii", errors="replace") as f:
            for line in f:
                if not line.strip():
                    continue
                try:
                    yield from can.CanutilsLogReader(io.StringIO(line))
                except (ValueError, IndexError) as exc:
                    stats.count(Rejected(Reason.GARBAGE, f"log line: {exc}", line[:64].encode()))
        return
    try:
        with can.LogReader(path) as reader:
            yield from reader
    except (ValueError, IndexError, OSError, can.CanError) as exc:
        stats.count(Rejected(Reason.TRUNCATED, f"log reader stopped: {exc}"))


def paced(messages: Iterable[can.Message], stop: threading.Event) -> Iterable[can.Message]:
    """Messages at their logged pace."""
    start, first = time.monotonic(), None
    for msg in messages:
        first = msg.timestamp if first is None else first
        if stop.wait(max(0.0, start + (msg.timestamp - first) - time.monotonic())):
            return
        yield msg
