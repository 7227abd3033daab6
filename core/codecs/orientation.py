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

CSV: a header row with a time column and four columns per sensor,
``<name>_w``, ``_x``, ``_y``, ``_z`` (or ``_qw``.., Movella DOT's ``Quat_W``..);
one row per frame, separated by commas, semicolons or tabs (the header's
separator). The time column is ``time``, ``t`` or ``timestamp``, in seconds
unless its name or the caller says the unit (``timestamp_ms``, ``time_us``,
``t_s``), or Movella DOT's ``SampleTimeFine`` (microseconds, a 32-bit counter
that wraps). Other columns (accelerations, ``_x/_y/_z`` groups with no ``_w``,
counters) are left out and listed; lines before the header that are not it
(an exporter's ``key:,value`` metadata) are taken as the header's
:attr:`Table.header`.

Refused, each with the line: no ``endheader``; ``DataType`` other than
Quaternion; a row of the wrong width (one trailing empty cell, a separator
left at each line's end, is dropped); a cell that is not four numbers; a
quaternion not finite or with a norm outside 0.9..1.1 (``NaN`` or four empty
cells, as exports write where nothing was measured or a sample was dropped,
are "no sample" and counted); time not increasing. Where a file was written
another way than these, the message says how (labels not tab separated, four
``.sto`` columns per quaternion, a decimal comma, UTF-16 text).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

from ..errors import DecodeError
from ._common import unit_quat

QuatWxyz = tuple[float, float, float, float]
#: a time column's names (any case); with a unit: ``time_ms``, ``timestamp [us]``
TIME_NAMES = ("time", "t", "timestamp")
TIME_UNITS: Mapping[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
_TIME_NAME = re.compile(r"(time|t|timestamp)(?:_| ?\[| ?\()(s|ms|us|ns)[\])]?")
#: Movella DOT's time column: microseconds of a 32-bit counter that wraps
DOT_TIME = "sampletimefine"
DOT_WRAP = 2**32
COMPONENTS = ("w", "x", "y", "z")
_COMPONENT = {c: c for c in COMPONENTS} | {f"q{c}": c for c in COMPONENTS}
#: how many lines before a CSV's header may hold an exporter's metadata
HEADER_WITHIN = 64
DELIMITERS = {",": "commas", ";": "semicolons", "\t": "tabs"}
#: a median step of this many seconds or more is no body's sampling: likely not seconds
SLOW_STEP_S = 1.0


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
    #: (line number, time in s, {column index: w, x, y, z}); NaN or empty cells left out
    rows: list[tuple[int, float, dict[int, QuatWxyz]]] = field(default_factory=list)
    #: the line of each header key (a ``.sto`` file's), to name in an error about its value
    header_lines: dict[str, int] = field(default_factory=dict)
    #: the line of the column labels
    labels_line: int = 1
    #: the time column's unit as the file (or the caller) says it; None: said nowhere
    time_unit: str | None = "s"
    #: columns that are not quaternions (accelerations, counters), left out
    ignored: list[str] = field(default_factory=list)
    #: cells with no sample (NaN or empty)
    empty: int = 0

    def unit_doubt(self) -> OrientationFileError | None:
        """Why the times, whose unit the file does not say, are likely not seconds:
        a median step of :data:`SLOW_STEP_S` or more (milliseconds read as seconds)."""
        if self.time_unit is not None or len(self.rows) < 2:
            return None
        steps = sorted(b[1] - a[1] for a, b in zip(self.rows, self.rows[1:], strict=False))
        median = steps[len(steps) // 2]
        if median < SLOW_STEP_S:
            return None
        return OrientationFileError(
            self.labels_line,
            f"the times step by {median:g} (median): not seconds of a body's motion; "
            "say their unit in the time column's name (timestamp_ms, time_us, time_ns, "
            "time_s) or with --time-unit",
        )


def _comma(text: str) -> str:
    """A hint for a number written with a decimal comma."""
    return " (a decimal comma? numbers are read with '.')" if "," in text else ""


def _quat(values: list[str], line: int, what: str) -> QuatWxyz | None:
    if not any(v.strip() for v in values):
        return None  # a dropped sample
    try:
        w, x, y, z = (float(v) for v in values)
    except ValueError:
        cell = ",".join(values)
        hint = _comma("".join(values))  # a comma within a value, not the one joining them
        raise OrientationFileError(line, f"{what}: not four numbers: {cell!r}{hint}") from None
    if all(math.isnan(c) for c in (w, x, y, z)):
        return None
    try:
        return unit_quat(w, x, y, z)
    except DecodeError as exc:
        raise OrientationFileError(line, f"{what}: {exc}") from None


class _Clock:
    """A time column's values in seconds, each after the last; a counter that
    wraps (``wrap``, in the column's unit) unwrapped."""

    def __init__(self, unit: str | None = "s", wrap: int | None = None) -> None:
        self.scale = TIME_UNITS[unit or "s"]
        self.wrap = wrap
        self.offset = 0.0
        self.last_raw: float | None = None
        self.last: float | None = None

    def __call__(self, text: str, line: int) -> float:
        try:
            raw = float(text)
        except ValueError:
            raise OrientationFileError(
                line, f"time {text!r} is not a number{_comma(text)}"
            ) from None
        if not math.isfinite(raw):
            raise OrientationFileError(line, f"time {text!r} is not finite")
        if self.wrap and self.last_raw is not None and self.last_raw - raw > self.wrap / 2:
            self.offset += self.wrap
        self.last_raw = raw
        t = (raw + self.offset) * self.scale
        if self.last is not None and t <= self.last:
            raise OrientationFileError(line, f"time {t:g} s does not follow {self.last:g} s")
        self.last = t
        return t


def _trim(cells: list[str], width: int | None = None) -> list[str]:
    """A row less one trailing empty cell: the separator some writers leave at each
    line's end (OpenSim's reader takes it); with ``width``, only from a row one too wide."""
    if len(cells) > 1 and not cells[-1].strip() and width in (None, len(cells) - 1):
        return cells[:-1]
    return cells


def _four_columns(labels: list[str]) -> str | None:
    """The base label when a .sto's labels give each quaternion four columns
    (``pelvis_imu_w``.. or OpenSim's flattened ``pelvis_imu_1``..)."""
    groups = [labels[i : i + 4] for i in range(1, len(labels), 4)]
    if not groups or len(groups[-1]) != 4:
        return None
    for group in groups:
        parts = [label.rpartition("_") for label in group]
        suffixes = "".join(suffix.lower() for _, _, suffix in parts)
        if suffixes not in ("wxyz", "1234") or len({base for base, _, _ in parts}) != 1:
            return None
    return groups[0][0].rpartition("_")[0]


def _not_labels(first: str) -> str:
    """Why a .sto's labels line does not start with ``time``."""
    for sep, name in (*DELIMITERS.items(), (" ", "spaces")):
        if sep != "\t" and first.split(sep, maxsplit=1)[0].strip().lower() == "time":
            return (f"the column labels are separated by {name}: a .sto file separates "
                    "columns with tabs, each cell w,x,y,z")  # fmt: skip
    return "the column labels must start with 'time'"


def _no_nul(line: str, n: int) -> None:
    if "\x00" in line:
        raise OrientationFileError(n, "NUL characters: UTF-16 text? (save it as UTF-8)")


def parse_sto(lines: Iterable[str]) -> Table:
    """An OpenSense quaternion ``.sto`` file's lines (line ends optional)."""
    numbered: Iterator[tuple[int, str]] = enumerate(lines, start=1)
    header: dict[str, str] = {}
    header_lines: dict[str, int] = {}
    n = 0
    for n, raw in numbered:  # n: where the header ends, for the errors below
        _no_nul(raw, n)
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
        raise OrientationFileError(
            header_lines["DataType"], f"DataType={kind}: an orientation file holds Quaternion"
        )
    labels: list[str] | None = None
    table = Table([], header, header_lines=header_lines)
    clock = _Clock()
    for n, raw in numbered:
        if not raw.strip():
            continue
        cells = raw.rstrip("\r\n").split("\t")
        if labels is None:
            labels = _trim([c.strip() for c in cells])
            if not labels or labels[0].lower() != "time":
                raise OrientationFileError(n, _not_labels(labels[0] if labels else ""))
            base = _four_columns(labels)
            if base is not None:
                raise OrientationFileError(n, f"four columns per quaternion ({labels[1]}..): "
                                              "a .sto cell holds the whole quaternion, w,x,y,z, "
                                              f"under one label ({base})")  # fmt: skip
            table.columns = labels[1:]
            table.labels_line = n
            continue
        cells = _trim(cells, len(labels))
        if len(cells) != len(labels):
            raise OrientationFileError(n, f"{len(cells)} cells, {len(labels)} columns")
        t = clock(cells[0], n)
        quats = {}
        for i, cell in enumerate(cells[1:]):
            q = _quat(cell.split(","), n, labels[i + 1])
            if q is not None:
                quats[i] = q
            else:
                table.empty += 1
        table.rows.append((n, t, quats))
    if labels is None:
        raise OrientationFileError(n, "no column labels after 'endheader'")
    return table


def _time_column(name: str) -> tuple[str | None, int | None] | None:
    """(its unit, None if the name says none; where its counter wraps) of a CSV's
    time column, or None if ``name`` is not one."""
    text = name.strip().strip('"').lower()
    if text == DOT_TIME:
        return "us", DOT_WRAP
    if text in TIME_NAMES:
        return None, None
    m = _TIME_NAME.fullmatch(text)
    return (m.group(2), None) if m else None


def _has_w(cells: list[str]) -> bool:
    """Whether ``cells`` name a quaternion's w (``<name>_w`` or ``<name>_qw``)."""
    for cell in cells:
        base, _, comp = cell.strip().strip('"').rpartition("_")
        if base and _COMPONENT.get(comp.lower()) == "w":
            return True
    return False


def _find_header(lines: list[str]) -> tuple[int, str]:
    """The index of a CSV's header line (the first with a time column and a
    quaternion's w, within :data:`HEADER_WITHIN` lines; else the first with a time
    column: an exporter's metadata can hold a cell ``t``) and its separator."""
    first, timed = None, None
    for i, line in enumerate(lines[:HEADER_WITHIN]):
        _no_nul(line, i + 1)
        if not line.strip():
            continue
        first = i if first is None else first
        for sep in DELIMITERS:
            cells = line.split(sep)
            if any(_time_column(cell) is not None for cell in cells):
                if _has_w(cells):
                    return i, sep
                timed = timed or (i, sep)
    if timed is not None:
        return timed  # no quaternion columns: _columns says so
    if first is None:
        raise OrientationFileError(1, "empty file: no header row")
    names = ", ".join((*TIME_NAMES, "time_ms", "time_us", "SampleTimeFine"))
    raise OrientationFileError(first + 1, f"no time column ({names})")


def _columns(names: list[str], n: int, time_unit: str | None,
             table: Table) -> tuple[int, list[tuple[str, list[int]]], _Clock]:  # fmt: skip
    """A CSV header's time column, quaternions (name, its w, x, y, z columns) and
    clock; the table's columns, time unit and left-out columns set."""
    times = [(i, u) for i, c in enumerate(names) if (u := _time_column(c)) is not None]
    if not times:  # a name split by a quoted separator
        raise OrientationFileError(n, "no time column")
    time_index, (unit, wrap) = times[0]
    if time_unit is not None and unit is not None and unit != time_unit:
        raise OrientationFileError(n, f"the time column {names[time_index]!r} is in "
                                      f"{unit}, not {time_unit} (--time-unit)")  # fmt: skip
    table.time_unit = unit or time_unit
    seen: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        base, _, comp = name.rpartition("_")
        c = _COMPONENT.get(comp.lower())
        if i != time_index and c and base:
            comps = seen.setdefault(base, {})
            if c in comps:
                raise OrientationFileError(n, f"{base}: two columns of its {c}: "
                                              f"{names[comps[c]]!r} and {name!r}")  # fmt: skip
            comps[c] = i
    groups = []
    for base, comps in seen.items():
        if "w" not in comps:
            continue  # x, y, z of something else: an acceleration, a rate
        if set(comps) != set(COMPONENTS):
            missing = sorted(set(COMPONENTS) - set(comps))
            raise OrientationFileError(n, f"{base}: no column {base}_{missing[0]}")
        groups.append((base, [comps[c] for c in COMPONENTS]))
    if not groups:
        raise OrientationFileError(n, "no quaternion columns (<name>_w, _x, _y, _z)")
    used = {time_index, *(i for _, idx in groups for i in idx)}
    table.columns = [base for base, _ in groups]
    table.ignored = [c for i, c in enumerate(names) if i not in used and c]
    table.labels_line = n
    return time_index, groups, _Clock(table.time_unit, wrap)


def parse_csv(lines: Iterable[str], time_unit: str | None = None) -> Table:
    """A CSV of per-segment quaternions (see the module docstring); ``time_unit``
    (``s``, ``ms``, ``us``, ``ns``): the time column's, where its name says none."""
    import csv

    text = list(lines)
    start, sep = _find_header(text)
    table = Table([], time_unit=None)
    for meta in csv.reader(text[:start], delimiter=sep):  # an exporter's metadata
        if len(meta) >= 2 and meta[0].strip():
            table.header[meta[0].strip().rstrip(":")] = meta[1].strip()
    reader = csv.reader(text[start:], delimiter=sep)
    groups: list[tuple[str, list[int]]] = []
    time_index, width = 0, 0
    clock = _Clock()
    n = start + 1
    while True:
        try:
            row = next(reader, None)
        except csv.Error as exc:  # a field past csv's limit (128 KiB), a NUL byte
            raise OrientationFileError(start + reader.line_num, f"not a CSV row ({exc})") from None
        if row is None:
            break
        n = start + reader.line_num
        if not any(c.strip() for c in row):
            continue
        if not width:
            names = _trim([c.strip() for c in row])
            time_index, groups, clock = _columns(names, n, time_unit, table)
            width = len(names)
            continue
        row = _trim(row, width)
        if len(row) != width:
            raise OrientationFileError(n, f"{len(row)} cells, {width} columns")
        t = clock(row[time_index], n)
        quats = {}
        for g, (base, idx) in enumerate(groups):
            q = _quat([row[i] for i in idx], n, base)
            if q is not None:
                quats[g] = q
            else:
                table.empty += 1
        table.rows.append((n, t, quats))
    return table
