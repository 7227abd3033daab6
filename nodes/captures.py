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
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from bodynet.core.messages import OleAccel
from bodynet.nodes import sources
from bodynet.nodes.sources.base import CapturedSample, CaptureError, CaptureStats
from bodynet.nodes.sources.can_transport import can_log_messages, frame_of

__all__ = [
    "CaptureError",
    "CaptureStats",
    "CapturedSample",
    "can_log_messages",
    "format_of",
    "formats",
    "frame_of",
    "read_capture",
    "sample_json",
]


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
    return {k: v for k, v in vars(args).items() if k in ("map",)}


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
