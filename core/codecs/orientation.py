"""Orientation files: OpenSim/OpenSense quaternion ``.sto`` and a plain CSV.

Both are tables of per-segment (or per-sensor) unit quaternions with their own
timestamps; the parsers take the file's lines (no I/O here) and give
:class:`Table` rows, or raise :class:`OrientationFileError` naming the line.

``.sto`` (OpenSense's IMU orientation files, what ``TimeSeriesTableQuaternion``
reads): header lines ``key=value`` (``DataRate``, ``DataType=Quaternion``,
``version``, ``OpenSimVersion``, optionally ``sensor_to_opensim_rotations``)
up to ``endheader``, then a tab-separated row of column labels (``time``,
then ``<body>_imu`` columns) and one row per frame: the time in seconds and
each cell ``w,x,y,z``.

CSV: a header row with a time column (``time``, ``t_s`` or ``timestamp``) and
four columns per segment, ``<name>_w``, ``<name>_x``, ``<name>_y``,
``<name>_z``; one row per frame, comma separated.

Refused, each with the line: no ``endheader``; ``DataType`` other than
Quaternion; a row of the wrong width; a cell that is not four numbers; a
quaternion not finite or with a norm outside 0.9..1.1 (``NaN`` cells, as
exports write where nothing was measured, are taken as "no sample"); time not
increasing.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from ..errors import DecodeError
from ._common import unit_quat

QuatWxyz = tuple[float, float, float, float]
TIME_COLUMNS = ("time", "t_s", "timestamp")
COMPONENTS = ("w", "x", "y", "z")


class OrientationFileError(ValueError):
    """A file that cannot be read as an orientation file; says where."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(f"line {line}: {message}")
        self.line = line


@dataclass
class Table:
    """The columns of an orientation file and, per frame, the quaternions it holds."""

    columns: list[str]
    header: dict[str, str] = field(default_factory=dict)
    #: (line number, time in s, {column index: w, x, y, z}); NaN cells left out
    rows: list[tuple[int, float, dict[int, QuatWxyz]]] = field(default_factory=list)
    #: the line of each header key (a ``.sto`` file's), to name in an error about its value
    header_lines: dict[str, int] = field(default_factory=dict)


def _quat(values: list[str], line: int, what: str) -> QuatWxyz | None:
    try:
        w, x, y, z = (float(v) for v in values)
    except ValueError:
        cell = ",".join(values)
        raise OrientationFileError(line, f"{what}: not four numbers: {cell!r}") from None
    if all(math.isnan(c) for c in (w, x, y, z)):
        return None
    try:
        return unit_quat(w, x, y, z)
    except DecodeError as exc:
        raise OrientationFileError(line, f"{what}: {exc}") from None


def _time(text: str, line: int, last: float | None) -> float:
    try:
        t = float(text)
    except ValueError:
        raise OrientationFileError(line, f"time {text!r} is not a number") from None
    if not math.isfinite(t):
        raise OrientationFileError(line, f"time {text!r} is not finite")
    if last is not None and t <= last:
        raise OrientationFileError(line, f"time {t:g} s does not follow {last:g} s")
    return t


def parse_sto(lines: Iterable[str]) -> Table:
    """An OpenSense quaternion ``.sto`` file's lines (line ends optional)."""
    numbered: Iterator[tuple[int, str]] = enumerate(lines, start=1)
    header: dict[str, str] = {}
    header_lines: dict[str, int] = {}
    n = 0
    for n, raw in numbered:  # n: where the header ends, for the errors below
        text = raw.strip()
        if text.lower() == "endheader":
            break
        key, sep, value = text.partition("=")
        if sep:
            header[key.strip()] = value.strip()
            header_lines[key.strip()] = n
    else:
        raise OrientationFileError(n if header else 1, "no 'endheader' line: not a .sto file")
    kind = header.get("DataType", "Quaternion")
    if kind != "Quaternion":
        raise OrientationFileError(n, f"DataType={kind}: an orientation file holds Quaternion")
    labels: list[str] | None = None
    table = Table([], header, header_lines=header_lines)
    last: float | None = None
    for n, raw in numbered:
        if not raw.strip():
            continue
        cells = raw.rstrip("\r\n").split("\t")
        if labels is None:
            labels = [c.strip() for c in cells]
            if not labels or labels[0].lower() != "time":
                raise OrientationFileError(n, "the column labels must start with 'time'")
            table.columns = labels[1:]
            continue
        if len(cells) != len(labels):
            raise OrientationFileError(n, f"{len(cells)} cells, {len(labels)} columns")
        last = t = _time(cells[0], n, last)
        quats = {}
        for i, cell in enumerate(cells[1:]):
            q = _quat(cell.split(","), n, labels[i + 1])
            if q is not None:
                quats[i] = q
        table.rows.append((n, t, quats))
    if labels is None:
        raise OrientationFileError(n, "no column labels after 'endheader'")
    return table


def parse_csv(lines: Iterable[str]) -> Table:
    """A CSV of per-segment quaternions (see the module docstring)."""
    import csv

    reader = csv.reader(lines)
    table: Table | None = None
    groups: list[tuple[str, list[int]]] = []
    time_index = 0
    last: float | None = None
    while True:
        try:
            row = next(reader, None)
        except csv.Error as exc:  # a field past csv's limit (128 KiB), a NUL byte
            raise OrientationFileError(reader.line_num, f"not a CSV row ({exc})") from None
        if row is None:
            break
        n = reader.line_num
        if not any(c.strip() for c in row):
            continue
        if table is None:
            names = [c.strip() for c in row]
            times = [i for i, c in enumerate(names) if c.lower() in TIME_COLUMNS]
            if not times:
                raise OrientationFileError(n, f"no time column ({', '.join(TIME_COLUMNS)})")
            time_index = times[0]
            seen: dict[str, dict[str, int]] = {}
            for i, name in enumerate(names):
                base, _, comp = name.rpartition("_")
                if i != time_index and comp.lower() in COMPONENTS and base:
                    seen.setdefault(base, {})[comp.lower()] = i
            for base, comps in seen.items():
                if set(comps) != set(COMPONENTS):
                    missing = sorted(set(COMPONENTS) - set(comps))
                    raise OrientationFileError(n, f"{base}: no column {base}_{missing[0]}")
                groups.append((base, [comps[c] for c in COMPONENTS]))
            if not groups:
                raise OrientationFileError(n, "no quaternion columns (<name>_w, _x, _y, _z)")
            table = Table([base for base, _ in groups])
            width = len(names)
            continue
        if len(row) != width:
            raise OrientationFileError(n, f"{len(row)} cells, {width} columns")
        last = t = _time(row[time_index], n, last)
        quats = {}
        for g, (base, idx) in enumerate(groups):
            q = _quat([row[i] for i in idx], n, base)
            if q is not None:
                quats[g] = q
        table.rows.append((n, t, quats))
    if table is None:
        raise OrientationFileError(1, "empty file: no header row")
    return table
