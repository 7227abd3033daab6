"""Orientation files as a source: OpenSense ``.sto`` and per-segment quaternion CSV.

The parsers are ``core.codecs.orientation`` (pure); this source maps each
column to a site and gives the samples the file's own times (no
``--rate-hz``). Default column -> site map: OpenSense's ``<body>_imu`` labels
(``pelvis_imu``, ``torso_imu``, ``femur_r_imu``... see ``core.opensim``) and
bodynet's segment names (``pelvis``, ``thorax``, ``left_forearm``...), each on
the IMU site of its segment; ``--map COLUMN=SITE`` (``left-arm/upperarm``)
overrides it or adds a column, ``--map COLUMN=`` leaves one out. Two columns on
one site (``pelvis`` and ``pelvis_imu``; a ``--map`` onto a taken site), or a
``--map`` of a column the file does not have, are refused: never two sensors'
samples mixed into one.

Frames: a ``.sto`` file's orientations are taken as OpenSense gives them to
OpenSim: rotated by the header's ``sensor_to_opensim_rotations`` (X, Y, Z
body-fixed Euler angles in radians, ``0 0 0`` if absent) into OpenSim's ground
frame (Y up), then into bodynet's (Z up) by ``core.opensim.OPENSIM_FROM_BODYNET``
(``q = m^-1 * q_opensim * m``, the inverse of what ``bodynet export sto``
does). A CSV is taken in bodynet's frame as it is. Either way, a quaternion
is the sensor's orientation; its mount on the segment is the profile's (or
calibrated from the first ``--tpose-s`` seconds, as for any orientation
sensor): a file of segment orientations, as bodynet exports, is processed with
``--tpose-s 0``.
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.codecs.orientation import (
    TIME_UNITS,
    OrientationFileError,
    Table,
    parse_csv,
    parse_sto,
)
from bodynet.core.errors import Reason, Rejected
from bodynet.core.keys import (
    LEFT_ARM,
    LEFT_LEG,
    RIGHT_ARM,
    RIGHT_LEG,
    TRUNK,
    KeySpaceError,
    Site,
    site_name,
    site_named,
)
from bodynet.core.messages import Quat, StreamEvent, Tick
from bodynet.core.messages import Source as SourceId
from bodynet.core.opensim import IMU_BODIES, OPENSIM_FROM_BODYNET, SENSOR_TO_OPENSIM, imu_label
from bodynet.nodes.sources.base import (
    CapturedSample,
    CaptureError,
    CaptureSink,
    CaptureStats,
    Source,
    Transport,
    time_refused,
)

log = logging.getLogger(__name__)

#: the ``.sto`` header key of the first row's time (ns), as ``bodynet export sto`` writes it
START_NS = "bodynet_start_ns"

#: bodynet segment -> the IMU site on it
SEGMENT_SITES: Mapping[str, Site] = {
    "pelvis": Site(TRUNK, "sacrum"),
    "thorax": Site(TRUNK, "chest"),
    "head": Site(TRUNK, "forehead"),
    **{
        f"{branch.side}_{segment}": Site(branch, segment)
        for branch, segments in ((LEFT_ARM, ("upperarm", "forearm", "hand")),
                                 (RIGHT_ARM, ("upperarm", "forearm", "hand")),
                                 (LEFT_LEG, ("thigh", "shank", "foot")),
                                 (RIGHT_LEG, ("thigh", "shank", "foot")))
        for segment in segments
    },
}  # fmt: skip

#: column -> site, both kinds of names
DEFAULT_MAP: Mapping[str, Site] = {
    **SEGMENT_SITES,
    **{imu_label(seg): site for seg, site in SEGMENT_SITES.items() if seg in IMU_BODIES},
}


def parse_map(text: str) -> tuple[str, Site | None]:
    """``COLUMN=SITE`` (an argparse type); ``COLUMN=``: the column left out (None)."""
    column, sep, site = text.partition("=")
    try:
        if not sep or not column.strip():
            raise ValueError(f"not COLUMN=SITE: {text!r}")
        return column.strip(), site_named(site) if site.strip() else None
    except (ValueError, KeySpaceError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _to_bodynet(table: Table) -> Rotation:
    """The rotation that takes a ``.sto`` file's orientations into bodynet's frame
    (applied on the left; on the right its inverse, see the module docstring)."""
    text = table.header.get(SENSOR_TO_OPENSIM, "0 0 0")
    try:
        angles = [float(v) for v in text.split()]
        if len(angles) != 3 or not all(abs(a) <= 2 * math.pi for a in angles):  # NaN too
            raise ValueError
    except ValueError:
        raise OrientationFileError(
            table.header_lines.get(SENSOR_TO_OPENSIM, 1),
            f"{SENSOR_TO_OPENSIM}={text}: not three angles in radians, each within +-2 pi",
        ) from None
    to_opensim = Rotation.from_euler("XYZ", angles)
    return Rotation.from_matrix(np.array(OPENSIM_FROM_BODYNET)).inv() * to_opensim


def _start_s(table: Table) -> float:
    """A ``.sto`` file's ``bodynet_start_ns`` (what ``bodynet export sto`` writes:
    the time of its first row), in seconds; 0 if absent."""
    text = table.header.get(START_NS)
    if text is None:
        return 0.0
    try:
        start = float(text) / 1e9
    except ValueError:
        start = math.nan
    if time_refused(start) is not None:
        raise OrientationFileError(table.header_lines.get(START_NS, 1),
                                   f"{START_NS}={text[:40]}: not a time in ns")  # fmt: skip
    return start


def _encoding(path: Path) -> str:
    """UTF-16 for a file that starts with its byte order mark (Excel's "Unicode
    text", a Windows editor's "Unicode"), else UTF-8 (its mark, if any, skipped)."""
    with path.open("rb") as f:
        head = f.read(2)
    return "utf-16" if head in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"


class OrientationFile(Source):
    name = "orientation-file"
    wire_id = SourceId.ORIENTATION_FILE
    transport = Transport.FILE
    help = "orientation files: OpenSense quaternion .sto, per-segment quaternion CSV"
    formats: ClassVar = {
        "sto": "OpenSense IMU orientations (.sto, DataType=Quaternion)",
        "orientation-csv": "a CSV of per-segment quaternions w, x, y, z",
    }
    suffixes: ClassVar = {".sto": "sto", ".csv": "orientation-csv"}

    def __init__(self, sites: Mapping[int, Site] | None = None, period_s: float | None = None,
                 column_map: Mapping[str, Site | None] | None = None,
                 time_unit: str | None = None) -> None:  # fmt: skip
        super().__init__(sites, period_s)
        self.asked = dict(column_map or {})
        self.column_map = {**DEFAULT_MAP, **self.asked}
        self.time_unit = time_unit

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> OrientationFile:
        return cls(column_map=dict(options.get("map") or ()), time_unit=options.get("time_unit"))

    @classmethod
    def add_capture_args(cls, p: argparse.ArgumentParser) -> None:
        p.add_argument("--map", type=parse_map, action="append", default=[],
                       metavar="COLUMN=SITE",
                       help="orientation files: put a column on a site (left-arm/upperarm) "
                            "over the default map; COLUMN= leaves it out (repeatable)")  # fmt: skip
        p.add_argument("--time-unit", choices=sorted(TIME_UNITS, key=TIME_UNITS.__getitem__),
                       help="orientation CSV: the time column's unit where its name says none "
                            "(default s)")  # fmt: skip

    def read(self, path: Path, fmt: str, stats: CaptureStats,
             rate_hz: float | None = None) -> Iterator[CapturedSample]:  # fmt: skip
        if rate_hz is not None:
            log.warning("%s: an orientation file keeps its own times; --rate-hz is not used",
                        path)  # fmt: skip
        try:
            with path.open(encoding=_encoding(path), errors="replace", newline="") as f:
                table = parse_sto(f) if fmt == "sto" else parse_csv(f, self.time_unit)
            to_bodynet = _to_bodynet(table) if fmt == "sto" else None
            start = _start_s(table) if fmt == "sto" else 0.0
        except OrientationFileError as exc:
            from bodynet.nodes.captures import looks_else

            raise CaptureError(f"{path}: {exc}{looks_else(path, fmt)}") from None
        sites, events = self._sites(path, table)
        for line, t, _ in table.rows:  # all refused before a sample is given
            why = time_refused(start + t)
            if why is not None:
                raise CaptureError(f"{path}: line {line}: {why}")
        if (doubt := table.unit_doubt()) is not None:
            raise CaptureError(f"{path}: {doubt}")
        self.sites = sites
        stats.no_sample += table.empty
        if table.ignored:
            shown = ", ".join(table.ignored[:6]) + (", ..." if len(table.ignored) > 6 else "")
            stats.notes.append(f"left out {len(table.ignored)} columns that are not "
                               f"quaternions ({shown})")  # fmt: skip
        unmapped = [c for c in table.columns
                    if self.column_map.get(c) is None and c not in self.asked]  # fmt: skip
        if unmapped:  # each also a rejection (counted): here by name, for --map
            shown = ", ".join(unmapped[:8]) + (", ..." if len(unmapped) > 8 else "")
            stats.notes.append(f"left out {len(unmapped)} quaternion columns with no site "
                               f"({shown}): --map COLUMN=SITE takes one")  # fmt: skip
        adapter, sink = self.adapter(), CaptureSink(sites, stats)
        adapter.events(events, None, sink)
        for row, (_, t, quats) in enumerate(table.rows):
            found: list[StreamEvent] = [Tick(row)]
            for i, q in quats.items():
                if i + 1 in sites:
                    found.append(Quat(i + 1, self._frame(q, to_bodynet)))
            adapter.events(found, start + t, sink)
            yield from sink.take()

    def _sites(self, path: Path, table: Table) -> tuple[dict[int, Site], list[StreamEvent]]:
        """Node (column number) -> site, and a rejection per column with none;
        :class:`CaptureError` for two columns on one site, a ``--map`` of a column
        the file does not have, or no column with a site."""
        where = f"{path}: line {table.labels_line}"
        columns = ", ".join(table.columns)
        for column in self.asked:
            if column not in table.columns:
                raise CaptureError(f"{where}: --map {column}: no such column (the file's: "
                                   f"{columns})")  # fmt: skip
        sites: dict[int, Site] = {}
        events: list[StreamEvent] = []
        taken: dict[Site, str] = {}
        for i, column in enumerate(table.columns):
            site = self.column_map.get(column)
            if site is None:
                if column not in self.asked:  # not left out on purpose
                    why = f"column {column!r} has no site (--map COLUMN=SITE)"
                    events.append(Rejected(Reason.UNKNOWN_NODE, why))
                continue
            if site in taken:
                raise CaptureError(f"{where}: columns {taken[site]} and {column} are both on "
                                   f"{site_name(site)} (use --map COLUMN=SITE, or COLUMN= to "
                                   "leave one out)")  # fmt: skip
            taken[site] = column
            sites[i + 1] = site
        if not sites:
            one = (f"; a file of one sensor (as Movella DOT exports): --map {table.columns[0]}"
                   "=SITE, and, to solve sensors together, their columns in one file "
                   "(<name>_w, _x, _y, _z each) on one time column"
                   if len(table.columns) == 1 else "")  # fmt: skip
            raise CaptureError(f"{where}: no column is on a site ({columns}): --map "
                               f"COLUMN=SITE (left-arm/upperarm){one}")  # fmt: skip
        return sites, events

    @staticmethod
    def _frame(q: tuple[float, float, float, float],
               to_bodynet: Rotation | None) -> tuple[float, float, float, float]:  # fmt: skip
        if to_bodynet is None:
            return q
        m = Rotation.from_matrix(np.array(OPENSIM_FROM_BODYNET))
        r = to_bodynet * Rotation.from_quat(q, scalar_first=True) * m
        w, x, y, z = r.as_quat(canonical=True, scalar_first=True)
        return (float(w), float(x), float(y), float(z))
