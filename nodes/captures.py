"""Reading captures of the sources' wire formats from files.

A capture is what a logger saw on a source's link (a CAN log, a Data
Concentrator serial exchange, an IMU central data matrix...) or a file a
source writes itself (an orientation file). :func:`read_capture` finds the
source that reads the format in the registry (``nodes.sources``) and decodes
the file with that source's decoder and adapter (the live bridge's), giving
each sample the capture's own time: the logged timestamp where the format has
one, otherwise the source's counter (reply, tick) divided by its rate.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from bodynet.core.messages import RESUMED, OleAccel
from bodynet.nodes import sources
from bodynet.nodes.sources.base import CapturedSample, CaptureError, CaptureStats
from bodynet.nodes.sources.can_transport import can_log_messages, frame_of

__all__ = [
    "RECORDING",
    "CaptureError",
    "CaptureStats",
    "CapturedSample",
    "can_log_messages",
    "format_of",
    "formats",
    "frame_of",
    "looks_else",
    "looks_like",
    "read_capture",
    "sample_json",
]


#: The format of a bodynet recording (MCAP) read as a capture: its raw samples.
RECORDING = "mcap"


def formats() -> list[str]:
    """Every capture format a registered source reads."""
    return list(sources.formats())


def format_of(path: Path) -> str | None:
    """The format a file's suffix implies (``.log`` a CAN log...), if any."""
    suffix = path.suffix.lower()
    for cls in sources.all_sources():
        if suffix in cls.suffixes:
            return cls.suffixes[suffix]
    return None


def read_capture(
    path: str | Path,
    fmt: str,
    stats: CaptureStats,
    rate_hz: float | None = None,
    options: Mapping[str, Any] | None = None,
) -> Iterator[CapturedSample]:
    """Decode a capture file into samples, counting everything else in ``stats``;
    ``CaptureError`` if it cannot be read. ``options``: the sources' capture
    options (``map`` of orientation files)."""
    source = sources.by_format(str(fmt)).from_options(options or {})
    yield from source.read(Path(path), str(fmt), stats, rate_hz)


def add_capture_args(parser: argparse.ArgumentParser) -> None:
    """Every source's options for reading its files (``--map``...)."""
    for cls in sources.all_sources():
        cls.add_capture_args(parser)


def capture_options(args: argparse.Namespace) -> dict[str, Any]:
    return {k: v for k, v in vars(args).items() if k in ("map", "time_unit")}


def sample_json(sample: CapturedSample) -> dict[str, object]:
    """The JSON object ``bodynet decode`` prints for a sample."""
    r = sample.reading
    out: dict[str, object] = {"node": r.node, "key": sample.site.raw_key, "t_s": sample.t_s}
    if isinstance(r, OleAccel):
        out["encoder"] = r.encoder
        out["accel"] = list(r.accel)
        if sample.flags & RESUMED:
            out["resumed"] = True
    else:
        out["quat_wxyz"] = list(r.wxyz)
    return out


_SNIFFERS: tuple[tuple[str, re.Pattern[bytes]], ...] = (
    ("an MCAP recording (for export, report, view or replay)", re.compile(rb"\A\x89MCAP")),
    ("a BLF CAN log (--format can-log, named .blf)", re.compile(rb"\ALOGG")),
    ("a candump CAN log (--format can-log, named .log)",
     re.compile(rb"^\(\d+\.\d+\)\s+\S+\s+[0-9A-Fa-f]+#", re.M)),
    ("candump's screen output, not a log: record with `candump -l` (or `candump -L`)",
     re.compile(rb"^\s*(\(\d+\.\d+\)\s+)?\S+\s+[0-9A-Fa-f]{3,8}\s+\[\d+\]", re.M)),
    ("a Vector ASC CAN log (--format can-log, named .asc)",
     re.compile(rb"^\s*(date\s|base\s+(hex|dec)|begin triggerblock)", re.M | re.I)),
    ("a PCAN TRC CAN log (--format can-log, named .trc)", re.compile(rb"^;\$FILEVERSION", re.M)),
    ("a python-can CSV CAN log (--format can-log, named .csv)",
     re.compile(rb"\Atimestamp,arbitration_id,")),
    ("a Data Concentrator capture (--format concentrator)",
     re.compile(rb"[A-Z]E[0-9A-Fa-f]{4}X[0-9A-Fa-f]{4}Y[0-9A-Fa-f]{4}Z")),
    ("an IMU central capture (--format imu-central)", re.compile(rb"\A([0-9a-fA-F]{52,56}\r?\n)+")),
    ("an OpenSense orientation file (--format sto, named .sto)",
     re.compile(rb"^\s*endheader\s*$", re.M | re.I)),
)  # fmt: skip


def looks_else(path: Path, fmt: str) -> str:
    """``"; it looks like <what>"`` when a file without samples of ``fmt``
    looks like something else (another format, or a CAN log misnamed), else ""
    (it looks like what was asked: it holds nothing that reads)."""
    what = looks_like(path)
    if what is None:
        return ""
    named = re.search(r", named (\.\w+)\)$", what)
    if f"--format {fmt}" in what and (named is None or named[1] == path.suffix.lower()):
        return ""
    return f"; it looks like {what}"


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
