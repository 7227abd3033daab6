"""``bodynet report``: the source documents' validation statistics of a recording.

Reads the poses of one or more recordings (``mcap_store``), computes with the
pure functions of ``stats`` and writes a Markdown or HTML report with its
plots (PNG, beside the report):

- range of motion and repetitions of every observed joint angle;
- RMS error and correlation against a reference: the ground truth in the
  recording (``.../truth``, recorded from emulated nodes), or ``--reference``:
  another recording (its truth if it has any, else its poses) or a CSV with
  ``t_s`` and ``<joint>_<dof>_deg`` columns (what ``bodynet export csv``
  writes). The reference is interpolated linearly at the recording's pose
  times, over the time both cover; both use the recording's time base;
- repeatability and ICC across trials: the repetitions of one channel (the
  one that moves most, or ``joint``) cut at the valleys between them, every
  channel cut at the same instants; or, given several recordings, each
  recording is one trial. Trials are time-normalised to 101 points;
- Type A uncertainty over a still window (``still`` in seconds from the
  start, else the ``still_s`` seconds after calibration in which the angles
  moved least).

Only measured samples count (``core.metrics.measured_angles``: no flag, or
``clamped``; in a recording from before the ``stale`` reason, not resting on a
stale sensor either): a sample flagged ``uncalibrated``, ``unobserved`` or
``held`` is left out of
range of motion, RMS and correlation, trials, ICC and Type A, and the report
says per joint angle how many it left out and why. Trials and the still
window come from after the T-pose calibration (after the last pose with a dof
flagged ``uncalibrated``).

Nothing is written until every figure is computed; the report file appears
complete or not at all (its plots are moved in place just before it).
"""

from __future__ import annotations

import csv
import html
import math
import os
import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pandas as pd

from bodynet.clients import stats
from bodynet.clients.mcap_store import StoreError, read_poses, read_truth
from bodynet.core import metrics
from bodynet.core.codecs import pose
from bodynet.session.outputs import OutputError, check_output, scratch_folder

#: At most this many channels get a panel of their own in a plot.
MAX_PANELS = 12


class ReportError(RuntimeError):
    """Input a report cannot be made from, with the reason (for the command line)."""


@dataclass
class Series:
    """Joint angles over time: ``t_s`` (s, the recording's time base) and one
    column per ``<joint>_<dof>_deg``."""

    source: str
    t_s: npt.NDArray[np.float64]
    angles: pd.DataFrame

    @property
    def t_rel(self) -> npt.NDArray[np.float64]:
        return self.t_s - self.t_s[0]


@dataclass
class Recording(Series):
    """A recording's poses; ``angles`` holds NaN where a sample was not measured."""

    observed: list[str] = field(default_factory=list)  # measured in 2 or more poses
    left_out: dict[str, dict[str, int]] = field(default_factory=dict)  # channel -> flag -> n
    calibrated_at: int = 0  # the pose after the last one with a dof flagged uncalibrated


def load_recording(path: Path) -> Recording:
    """The poses of a recording, each sample with no measurement behind it
    (``metrics.measured_angles``) left out (NaN) and counted by its flag
    (``stale`` for one an older gateway did not flag)."""
    times: list[int] = []
    rows: list[dict[str, float]] = []
    left_out: dict[str, dict[str, int]] = {}
    calibrated_at: int | None = None
    try:
        for t_ns, frame in read_poses(path):
            times.append(t_ns)
            row = dict(frame.angles_deg)
            measured = metrics.measured_angles(frame)
            for n in [n for n in row if n not in measured]:
                row[n] = math.nan
                f = frame.flags.get(n, pose.STALE)  # unflagged: on a stale sensor
                counts = left_out.setdefault(n, {})
                counts[f] = counts.get(f, 0) + 1
            if pose.UNCALIBRATED in frame.flags.values():
                calibrated_at = len(rows) + 1  # after the last uncalibrated pose
            rows.append(row)
    except StoreError as exc:
        raise ReportError(str(exc)) from None
    except ValueError as exc:  # a body/pose message that is not a pose
        raise ReportError(f"{path}: not a bodynet pose recording ({exc})") from None
    if len(rows) < 2:
        raise ReportError(
            f"{path}: {len(rows)} poses; a report needs a recording with poses "
            "(record while the gateway runs, or `bodynet process` a capture)"
        )
    angles = pd.DataFrame(rows)
    observed = [c for c in angles.columns if int(angles[c].notna().sum()) >= 2]
    t = np.asarray(times, dtype=float) / 1e9
    return Recording(str(path), t, angles, observed, left_out,
                     min(calibrated_at or 0, len(rows) - 1))  # fmt: skip


def _truth(path: Path) -> Series | None:
    by_time: dict[int, dict[str, float]] = {}
    try:
        for _, t_ns, angles in read_truth(path):
            by_time.setdefault(t_ns, {}).update(angles)
    except StoreError as exc:
        raise ReportError(str(exc)) from None
    if not by_time:
        return None
    times = sorted(by_time)
    frame = pd.DataFrame([by_time[t] for t in times]).ffill()
    return Series(f"ground truth in {path}", np.asarray(times, dtype=float) / 1e9, frame)


#: what a reference CSV leaves out: a whole row, or a cell taken as missing
_ROWS, _CELLS = "rows left out", "cells not numbers"


def _reference_csv(path: Path) -> tuple[pd.DataFrame, list[tuple[str, str]]]:
    """A reference CSV's good rows, and what was left out (``_ROWS`` or ``_CELLS``)
    and why, in the file's order: a row with more or fewer fields than the
    header, or no number for t_s; an angle cell that is not a number, taken as
    missing (an empty or ``nan`` cell is one)."""
    left_out: list[tuple[str, str]] = []
    rows: list[list[str]] = []
    try:
        with path.open(newline="", encoding="utf-8-sig", errors="replace") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise ReportError(f"{path}: the reference CSV is empty")
            header = [h.strip() for h in header]
            if "t_s" not in header or not any(h.endswith("_deg") for h in header):
                raise ReportError(f"{path}: a reference CSV needs a t_s column and *_deg columns")
            t_col = header.index("t_s")
            angle_cols = [i for i, h in enumerate(header) if h.endswith("_deg")]
            for row in reader:
                line = reader.line_num
                if not row or all(not cell.strip() for cell in row):
                    continue
                if len(row) != len(header):
                    left_out.append((_ROWS, f"line {line} left out: {len(row)} fields, the "
                                           f"header has {len(header)}"))  # fmt: skip
                    continue
                try:
                    t = float(row[t_col])
                except ValueError:
                    t = math.nan
                if not math.isfinite(t):
                    left_out.append((_ROWS, f"line {line} left out: t_s {row[t_col][:20]!r} is "
                                           "not a finite number"))  # fmt: skip
                    continue
                for i in angle_cols:
                    cell = row[i].strip()
                    if cell and cell.lower() != "nan":
                        try:
                            float(cell)
                        except ValueError:
                            left_out.append((_CELLS, f"line {line}: {header[i]} {cell[:20]!r} is "
                                                    "not a number, taken as missing"))  # fmt: skip
                            row[i] = ""
                rows.append(row)
    except (OSError, csv.Error) as exc:
        raise ReportError(f"{path}: cannot read the reference CSV ({exc})") from None
    if not rows:
        raise ReportError(f"{path}: the reference CSV has no usable row"
                          + (f" ({left_out[0][1]}...)" if left_out else ""))  # fmt: skip
    table = pd.DataFrame(rows, columns=header)
    table["t_s"] = table["t_s"].astype(float)
    return table, left_out


def load_reference(path: Path) -> Series:
    """A reference: a CSV (``t_s`` and angle columns) or a recording (truth, else poses)."""
    if path.suffix.lower() == ".csv":
        table, left_out = _reference_csv(path)
        columns = [c for c in table.columns if str(c).endswith("_deg")]
        table = table.sort_values("t_s", kind="stable")
        values = table[columns].apply(pd.to_numeric, errors="coerce")
        for _, why in left_out:
            print(f"bodynet report: {path}: {why}", file=sys.stderr)
        source = str(path)
        for what in (_ROWS, _CELLS):
            if said := [why for kind, why in left_out if kind == what]:
                shown = "; ".join(said[:5]) + (f"; and {len(said) - 5} more"
                                               if len(said) > 5 else "")  # fmt: skip
                source += f" ({len(said)} {what}: {shown})"
        return Series(source, table["t_s"].to_numpy(float), values.reset_index(drop=True))
    truth = _truth(path)
    if truth is not None:
        return truth
    rec = load_recording(path)
    return Series(f"poses of {path}", rec.t_s, rec.angles[rec.observed])


# -- the figures ---------------------------------------------------------------


@dataclass
class Accuracy:
    reference: str
    table: pd.DataFrame  # channel -> samples, RMS error, correlation
    t_s: npt.NDArray[np.float64]  # the compared instants (recording time base)
    measured: pd.DataFrame
    expected: pd.DataFrame


@dataclass
class Trials:
    how: str
    channel_trials: dict[str, npt.NDArray[np.float64]]  # channel -> (trials, points)
    bounds_s: list[tuple[float, float]]  # trials' start and end (s from start), one recording
    repeatability: pd.DataFrame
    icc: pd.DataFrame
    icc_form: str


@dataclass
class Uncertainty:
    window_s: tuple[float, float]  # from the recording's start
    how: str
    table: pd.DataFrame


@dataclass
class Analysis:
    recordings: list[Recording]
    rom: list[pd.DataFrame]  # one per recording
    accuracy: Accuracy | None
    accuracy_note: str
    trials: Trials | None
    uncertainty: Uncertainty
    clinical: list[pd.DataFrame] = field(default_factory=list)  # one per recording


def _moving(rec: Recording) -> list[str]:
    """Channels measured throughout after calibration that move enough to repeat."""
    after = rec.angles.iloc[rec.calibrated_at :]
    return [c for c in rec.observed if len(after) >= 2 and bool(after[c].notna().all())
            and float(np.ptp(after[c])) >= stats.REP_MIN_PROMINENCE_DEG]  # fmt: skip


def left_out_table(rec: Recording) -> pd.DataFrame:
    """Per joint angle, how many samples the report left out (not measured) and why."""
    rows = []
    for c in rec.angles.columns:
        counts = rec.left_out.get(c, {})
        if not counts:
            continue
        why = ", ".join(f"{n} {f}" for f, n in sorted(counts.items(), key=lambda kv: -kv[1]))
        rows.append({"channel": c, "left out": sum(counts.values()), "of": len(rec.angles),
                     "why": why})  # fmt: skip
    return pd.DataFrame(rows, columns=["channel", "left out", "of", "why"])


def clinical_table(path: Path) -> pd.DataFrame:
    """The clinical metrics of a recording's poses, by the module the live
    ``body/@metrics`` publisher uses (``core.metrics``), fed the same way: each
    pose's measured angles at its source time. The numbers at the end of the
    recording, per observed dof."""
    body = metrics.BodyMetrics()
    try:
        for _, frame in read_poses(path):
            body.add(frame.t_ns, metrics.measured_angles(frame))
    except StoreError as exc:
        raise ReportError(str(exc)) from None
    except ValueError as exc:
        raise ReportError(f"{path}: not a bodynet pose recording ({exc})") from None
    rows = [{"channel": name, "min (deg)": d["min_deg"], "max (deg)": d["max_deg"],
             "range (deg)": d["range_deg"], "repetitions": d["repetitions"],
             "SPARC (last movement)": d["sparc"], "samples": d["samples"]}
            for name, d in body.snapshot()["dofs"].items()]  # fmt: skip
    return pd.DataFrame(rows)


def rom_table(rec: Recording) -> pd.DataFrame:
    rows = []
    for c in rec.observed:
        x = rec.angles[c].dropna()
        rom = stats.range_of_motion(x)
        reps = len(stats.repetitions(x))
        rows.append({"channel": c, "min (deg)": rom.minimum, "max (deg)": rom.maximum,
                     "span (deg)": rom.span, "repetitions": reps})  # fmt: skip
    return pd.DataFrame(rows)


def accuracy(rec: Recording, ref: Series) -> Accuracy:
    """RMS error and correlation of every channel the reference and recording share."""
    lo, hi = max(rec.t_s[0], ref.t_s[0]), min(rec.t_s[-1], ref.t_s[-1])
    inside = (rec.t_s >= lo) & (rec.t_s <= hi)
    if inside.sum() < 2:
        raise ReportError(f"the reference ({ref.source}) does not overlap the recording in time")
    t = rec.t_s[inside]
    shared = [c for c in rec.observed if c in ref.angles.columns]
    if not shared:
        raise ReportError(f"the reference ({ref.source}) has none of the recording's channels")
    rows, measured, expected = [], {}, {}
    for c in shared:
        known = ref.angles[c].notna().to_numpy()
        if known.sum() < 2:
            continue
        x = rec.angles[c].to_numpy(float)[inside]
        y = np.interp(t, ref.t_s[known], ref.angles[c].to_numpy(float)[known])
        measured[c], expected[c] = x, y
        ok = np.isfinite(x)  # measured samples only
        if ok.sum() < 2:
            continue
        try:
            r: float | None = stats.correlation(x[ok], y[ok])
        except stats.StatsError:
            r = None  # a constant channel: correlation undefined
        rows.append({"channel": c, "samples": int(ok.sum()),
                     "RMS error (deg)": stats.rms_error(x[ok], y[ok]),
                     "correlation r": r})  # fmt: skip
    return Accuracy(ref.source, pd.DataFrame(rows), t, pd.DataFrame(measured),
                    pd.DataFrame(expected))  # fmt: skip


def default_driver(rec: Recording, channels: Sequence[str]) -> str:
    """The channel whose repetitions cut the trials: of the channels that repeat
    (two or more repetitions), the smoothest (``stats.roughness``), so that a
    channel jumping between two solutions does not; else the one moving most."""
    angles = {c: rec.angles[c].to_numpy(float) for c in channels}
    repeating = [c for c in channels if len(stats.repetitions(angles[c])) >= 2]
    if repeating:
        return min(repeating, key=lambda c: stats.roughness(angles[c]))
    return max(channels, key=lambda c: float(np.ptp(angles[c])))


def trials_of(recs: Sequence[Recording], joint: str | None) -> Trials:
    """Trials of the moving channels (measured throughout, after calibration),
    with their repeatability and ICC."""
    start_s = recs[0].t_s[0]
    recs = [_after_calibration(r) for r in recs]
    if len(recs) > 1:
        channels = [c for c in _moving(recs[0]) if all(c in _moving(r) for r in recs[1:])]
        names = ", ".join(f"trial {k}: {r.source}" for k, r in enumerate(recs, 1))
        how = f"each of the {len(recs)} recordings is one trial ({names})"
        segments = [[(r.t_s, r.angles[c].to_numpy(float)) for r in recs] for c in channels]
        bounds: list[tuple[float, float]] = []
    else:
        rec = recs[0]
        channels = _moving(rec)
        if not channels:
            raise ReportError(f"{rec.source}: no joint angle moves {stats.REP_MIN_PROMINENCE_DEG:g}"
                              " degrees or more, so there are no trials")  # fmt: skip
        driver = joint or default_driver(rec, channels)
        if driver not in rec.observed:
            raise ReportError(f"{rec.source}: no observed channel {driver!r}")
        x = rec.angles[driver].to_numpy(float)
        cuts = stats.trial_bounds(x, stats.repetitions(x))
        how = (f"the {len(cuts)} repetitions of {driver}"
               f"{' (--joint)' if joint else ' (the smoothest repeating channel)'}, cut at the "
               "lowest sample between peaks (and within half a cycle before the first and "
               "after the last); every channel cut at the same instants")  # fmt: skip
        segments = [
            [(rec.t_s[a : b + 1], rec.angles[c].to_numpy(float)[a : b + 1]) for a, b in cuts]
            for c in channels
        ]
        bounds = [(rec.t_s[a] - start_s, rec.t_s[b] - start_s) for a, b in cuts]
    if not channels or len(segments[0]) < 2:
        n = len(segments[0]) if channels else 0
        raise ReportError(
            f"too few trials for repeatability and ICC ({n}; 2 or more needed): {how}. "
            "Pass several recordings, choose another --joint, or --no-trials"
        )
    per_channel = {
        c: np.vstack([stats.time_normalise(t, v) for t, v in segs])
        for c, segs in zip(channels, segments, strict=True)
    }
    rep_rows, icc_rows = [], []
    form = stats.ICC_NAMES[stats.ICC_FORM]
    for c, m in per_channel.items():
        rep = stats.repeatability(m)
        rep_rows.append({"channel": c, "trials": m.shape[0], "range (deg)": rep.range,
                         "SD (deg)": rep.sd})  # fmt: skip
        try:
            result = stats.icc(m)
        except stats.StatsError:
            continue
        icc_rows.append({"channel": c, form: result.value, "95% CI low": result.ci95[0],
                         "95% CI high": result.ci95[1], "ICC(1,1)": result.forms["ICC(1,1)"],
                         "ICC(2,1)": result.forms["ICC(2,1)"]})  # fmt: skip
    rep_table = pd.DataFrame(rep_rows)
    mean_row = {"channel": "average", "trials": np.nan,
                "range (deg)": rep_table["range (deg)"].mean(),
                "SD (deg)": rep_table["SD (deg)"].mean()}  # fmt: skip
    rep_table = pd.concat([rep_table, pd.DataFrame([mean_row])], ignore_index=True)
    return Trials(how, per_channel, bounds, rep_table, pd.DataFrame(icc_rows), form)


def _after_calibration(rec: Recording) -> Recording:
    """The part of a recording from its calibration on (its time base kept)."""
    a = rec.calibrated_at
    if a == 0:
        return rec
    return Recording(rec.source, rec.t_s[a:], rec.angles.iloc[a:].reset_index(drop=True),
                     rec.observed, rec.left_out, 0)  # fmt: skip


def uncertainty(rec: Recording, still: tuple[float, float] | None, still_s: float) -> Uncertainty:
    """Type A evaluation over the still window (from after calibration) of every
    channel measured throughout it."""
    t = rec.t_rel
    start = min(rec.calibrated_at, len(t) - 1)
    after = rec.angles.iloc[start:]
    # the window is chosen on the channels measured throughout after calibration
    steady = [c for c in rec.observed if bool(after[c].notna().all())] or rec.observed
    try:
        if still is None:
            a, b = stats.still_window(t[start:], after[steady].to_numpy(float), still_s)
            a, b = a + start, b + start
            how = (f"auto: the {still_s:g} s in which the angles moved least"
                   + (" after calibration" if start else ""))  # fmt: skip
        else:
            # a window past either end is not the one asked for: said, not clipped
            step = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
            if still[0] < t[0] - step or still[1] > t[-1] + step:
                raise ReportError(f"{rec.source}: the still window {still[0]:g}-{still[1]:g} s "
                                  f"(--still) is not within the recording, "
                                  f"{t[0]:.2f}-{t[-1]:.2f} s")  # fmt: skip
            a = int(np.searchsorted(t, still[0], side="left"))
            b = int(np.searchsorted(t, still[1], side="right"))
            how = "given (--still)"
    except stats.StatsError as exc:
        raise ReportError(f"{rec.source}: {exc}") from None
    if b - a < 2:
        raise ReportError(f"{rec.source}: the still window holds {max(b - a, 0)} poses, 2 needed")
    rows = []
    for c in steady:  # the channels the window was chosen on: still in it
        window = rec.angles[c].to_numpy(float)[a:b]
        if not np.isfinite(window).all():
            continue  # not measured throughout the window
        ta = stats.type_a(window)
        rows.append({"channel": c, "n": ta.n, "best estimate q̄ (deg)": ta.mean,
                     "s²(q_k) (deg²)": ta.variance, "s(q_k) (deg)": ta.sd,
                     "s²(q̄) (deg²)": ta.variance_of_mean, "s(q̄) (deg)": ta.sd_of_mean})  # fmt: skip
    return Uncertainty((float(t[a]), float(t[b - 1])), how, pd.DataFrame(rows))


def analyse(
    paths: Sequence[Path],
    reference: Path | None = None,
    joint: str | None = None,
    still: tuple[float, float] | None = None,
    still_s: float = 2.0,
    with_trials: bool = True,
) -> Analysis:
    """Every figure of the report, computed; raises ``ReportError`` on bad input."""
    if not paths:
        raise ReportError("no recording given")
    recs = [load_recording(p) for p in paths]
    for rec in recs:
        if not rec.observed:  # every sample of every joint angle flagged
            counts: dict[str, int] = {}
            for by_flag in rec.left_out.values():
                for flag, n in by_flag.items():
                    counts[flag] = counts.get(flag, 0) + n
            why = ", ".join(f"{n} {f}" for f, n in sorted(counts.items(), key=lambda kv: -kv[1]))
            raise ReportError(f"{rec.source}: no joint angle was measured in it (every sample "
                              f"has a flag: {why}); a report needs measured samples")  # fmt: skip
    first = recs[0]
    if joint is not None and joint not in first.observed:
        known = ", ".join(first.observed[:8]) + (", ..." if len(first.observed) > 8 else "")
        raise ReportError(f"{first.source}: no measured joint angle {joint!r} (--joint); "
                          f"its measured ones: {known}")  # fmt: skip
    if reference is not None:
        ref: Series | None = load_reference(reference)
        note = ""
    else:
        ref = _truth(paths[0])
        which = "the recording" if len(recs) == 1 else f"{first.source} (the first recording)"
        note = "" if ref else f"no reference: {which} holds no ground truth and no " \
                              "--reference was given"  # fmt: skip
    acc = accuracy(first, ref) if ref is not None else None
    tri = trials_of(recs, joint) if with_trials else None
    return Analysis(recs, [rom_table(r) for r in recs], acc, note, tri,
                    uncertainty(first, still, still_s),
                    [clinical_table(Path(p)) for p in paths])  # fmt: skip


# -- writing -------------------------------------------------------------------

Block = tuple[str, object]  # ("h1" | "h2" | "p" | "table" | "img", content)


def _blocks(an: Analysis, images: dict[str, str]) -> list[Block]:
    first = an.recordings[0]
    out: list[Block] = [("h1", f"bodynet report: {', '.join(r.source for r in an.recordings)}")]
    for rec in an.recordings:
        never = [c for c in rec.angles.columns if c not in rec.observed]
        out.append(("p", f"{rec.source}: {len(rec.t_s)} poses over {rec.t_rel[-1]:.2f} s, "
                         f"{len(rec.observed)} joint angles measured; "
                         f"{len(never)} never measured"
                         + (f" ({', '.join(never)})" if never else "") + "."))  # fmt: skip
        table = left_out_table(rec)
        if len(table):
            out += [("p", "Samples with no measurement behind them, left out of every figure "
                          "below (uncalibrated: before the T-pose calibration; unobserved: no "
                          "sensor measures it; held: gravity cannot see it in that posture, "
                          "its last value held):"),
                    ("table", table)]  # fmt: skip
    out += [("h2", "Range of motion and repetitions"),
            ("p", "Smallest and largest value of each observed joint angle. A repetition is a "
                  f"peak (scipy.signal.find_peaks) standing out by at least "
                  f"{stats.REP_REL_PROMINENCE:.0%} of the channel's span and at least "
                  f"{stats.REP_MIN_PROMINENCE_DEG:g} deg above the valleys around it."),
            ]  # fmt: skip
    for rec, table in zip(an.recordings, an.rom, strict=True):
        if len(an.recordings) > 1:
            out.append(("p", rec.source))
        out.append(("table", table))
    several = len(an.recordings) > 1
    if several:
        out.append(("p", f"Joint angles over time of the first recording, {first.source}:"))
    out.append(("img", images["angles"]))
    out += _clinical_blocks(an)

    out.append(("h2", "Accuracy against a reference (000 seed, ch. 5)"))
    if an.accuracy is None:
        out.append(("p", an.accuracy_note))
    else:
        whose = (f"the first recording's ({first.source}; the others are not compared)"
                 if several else "the recording's")  # fmt: skip
        out += [("p", f"Reference: {an.accuracy.reference}, interpolated at {whose} "
                      f"{len(an.accuracy.t_s)} pose times they share. RMS error "
                      "sqrt(mean((x - ref)^2)); Pearson's correlation coefficient (eq. 27), "
                      "blank where a channel is constant."),
                ("table", an.accuracy.table)]  # fmt: skip
        if "reference" in images:
            out.append(("img", images["reference"]))

    out.append(("h2", "Repeatability and reliability across trials (000 seed, ch. 6.3)"))
    if an.trials is None:
        out.append(("p", "Left out (--no-trials)."))
    else:
        tr = an.trials
        gaps = [c for c in first.observed if c not in tr.channel_trials
                and float(np.nanmax(first.angles[c]) - np.nanmin(first.angles[c]))
                >= stats.REP_MIN_PROMINENCE_DEG]  # fmt: skip
        if gaps:
            out.append(("p", "Moving joint angles not measured throughout after calibration, "
                             f"left out of the trials: {', '.join(gaps)}."))  # fmt: skip
        out += [("p", f"Trials: {tr.how}; each time-normalised to {stats.TRIAL_POINTS} points. "
                      "Range and SD (n - 1) of the trial means (eq. 28-31); the last row "
                      "averages the channels, as the seed's average range and SD."),
                ("table", tr.repeatability),
                ("p", f"Intra-class correlation (eq. 32), {tr.icc_form} by pingouin: two-way "
                      "mixed, consistency, single measure, with the points along the movement "
                      "as targets and the trials as raters. Eq. 32 is the ratio of the "
                      "between-target variance to it plus the error variance, with no term for "
                      "a trial's systematic offset: ICC(3,1), SPSS's default, which the seed "
                      "used. ICC(2,1) also counts such offsets as error (absolute agreement)."),
                ("table", tr.icc), ("img", images["trials"])]  # fmt: skip

    un = an.uncertainty
    out += [("h2", "Type A standard uncertainty of a still sensor (003 seed, ch. 8.4)"),
            ("p", f"Still window {un.window_s[0]:.2f}-{un.window_s[1]:.2f} s of {first.source} "
                  f"({un.how}). Best estimate q̄ (eq. 8.1), experimental variance and SD "
                  "(eq. 8.2, n - 1), variance and SD of the mean (eq. 8.3). Joint angles not "
                  "measured throughout the recording after calibration are left out (the "
                  "window is chosen where the others are still)."),
            ("table", un.table)]  # fmt: skip
    return out


def _clinical_blocks(an: Analysis) -> list[Block]:
    """The "Clinical metrics" section: what ``body/@metrics`` said live at the end."""
    out: list[Block] = [
        ("h2", "Clinical metrics"),
        ("p", "The numbers `bodynet metrics` publishes live on body/@metrics, computed by the "
              "same module (core/metrics.py) over the recording's measured samples only "
              "(an angle flagged anything but clamped is left out): range of motion so far; "
              "repetitions, each a swing from the lower quarter of the range to the upper "
              f"quarter and back (range at least {metrics.MIN_SPAN_DEG:g} deg); smoothness "
              "of the last movement (the last stretch faster than "
              f"{metrics.MOVING_DEG_S:g} deg/s) as its spectral arc length SPARC "
              "(Balasubramanian et al. 2015; closer to 0 is smoother, a single minimum-jerk "
              "movement gives -1.41; blank without a movement)."),
    ]  # fmt: skip
    for rec, table in zip(an.recordings, an.clinical, strict=False):
        if len(an.recordings) > 1:
            out.append(("p", rec.source))
        out.append(("table", table) if len(table) else ("p", "No measured joint angle."))
    return out


def _plots(an: Analysis, folder: Path, stem: str) -> dict[str, str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = {}
    first = an.recordings[0]

    def save(fig: object, name: str) -> None:
        fname = f"{stem}-{name}.png"
        fig.savefig(folder / fname, dpi=90)  # type: ignore[attr-defined]
        plt.close(fig)  # type: ignore[arg-type]
        images[name] = fname

    moving = _moving(first)[:MAX_PANELS] or first.observed[:MAX_PANELS]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    for c in moving:
        ax.plot(first.t_rel, first.angles[c], label=c, lw=1)
    if an.trials is not None:
        for a, _ in an.trials.bounds_s[1:]:
            ax.axvline(a, color="grey", lw=0.6, ls="--")
    ax.axvspan(*an.uncertainty.window_s, color="tab:green", alpha=0.15, label="still window")
    ax.set(xlabel="time (s)", ylabel="angle (deg)", title=f"Joint angles: {first.source}")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    save(fig, "angles")

    acc = an.accuracy
    if acc is not None:
        shown = [c for c in acc.expected.columns if np.ptp(acc.expected[c]) > 0][:MAX_PANELS]
        if shown:
            fig, axes = plt.subplots(len(shown), 1, figsize=(10, 2.2 * len(shown)), squeeze=False)
            t = acc.t_s - first.t_s[0]
            for ax, c in zip(axes[:, 0], shown, strict=True):
                ax.plot(t, acc.expected[c], label="reference", lw=1.5, color="black")
                ax.plot(t, acc.measured[c], label="measured", lw=1, color="tab:red")
                ax.set(ylabel="deg", title=c)
                ax.legend(fontsize=7, loc="upper right")
            axes[-1, 0].set_xlabel("time (s)")
            fig.tight_layout()
            save(fig, "reference")

    if an.trials is not None:
        chans = list(an.trials.channel_trials)[:MAX_PANELS]
        cols = min(3, len(chans))
        rows = -(-len(chans) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
        pct = np.linspace(0, 100, stats.TRIAL_POINTS)
        for ax, c in zip(axes.flat, chans, strict=False):
            for j, trial in enumerate(an.trials.channel_trials[c]):
                ax.plot(pct, trial, lw=1, label=f"trial {j + 1}")
            ax.set(title=c, xlabel="% of trial", ylabel="deg")
        for ax in list(axes.flat)[len(chans) :]:
            ax.set_visible(False)
        axes[0, 0].legend(fontsize=6)
        fig.tight_layout()
        save(fig, "trials")
    return images


def _markdown(blocks: list[Block]) -> str:
    parts = []
    for kind, content in blocks:
        if kind == "h1":
            parts.append(f"# {content}")
        elif kind == "h2":
            parts.append(f"## {content}")
        elif kind == "p":
            parts.append(str(content))
        elif kind == "table":
            assert isinstance(content, pd.DataFrame)
            table = content.astype(object).where(content.notna(), None)
            parts.append(table.to_markdown(index=False, floatfmt=".4g", missingval=""))
        elif kind == "img":
            parts.append(f"![{content}]({content})")
    return "\n\n".join(parts) + "\n"


def _html(blocks: list[Block]) -> str:
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>bodynet report</title>",
             "<style>body{font-family:sans-serif;max-width:60em;margin:auto}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;"
             "text-align:right}img{max-width:100%}</style></head><body>"]  # fmt: skip
    for kind, content in blocks:
        if kind in ("h1", "h2", "p"):
            parts.append(f"<{kind}>{html.escape(str(content))}</{kind}>")
        elif kind == "table":
            assert isinstance(content, pd.DataFrame)
            parts.append(content.to_html(index=False, na_rep="", float_format="{:.4g}".format))
        elif kind == "img":
            src = html.escape(str(content))
            parts.append(f"<p><img src='{src}' alt='{src}'></p>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_report(an: Analysis, out: Path, inputs: Sequence[Path | None] = ()) -> list[Path]:
    """Write the report (Markdown, or HTML for ``.html``/``.htm``) and its PNG plots
    beside it; returns every file written, the report first. Each file is checked
    as an output (``check_output``: none of ``inputs``, a folder, read-only...)
    before any is put in place: ``OutputError`` naming it, and nothing written."""
    folder = out.parent
    folder.mkdir(parents=True, exist_ok=True)
    tmp = scratch_folder(out)  # one a killed run left is removed by the next
    try:
        images = _plots(an, tmp, out.stem)
        blocks = _blocks(an, images)
        text = _html(blocks) if out.suffix.lower() in (".html", ".htm") else _markdown(blocks)
        (tmp / out.name).write_text(text, encoding="utf-8")
        written = [folder / name for name in images.values()]
        for path in (out, *written):
            check_output(path, inputs)
        for path in (*written, out):
            _put(tmp / path.name, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [out, *written]


def _put(made: Path, path: Path) -> None:
    try:
        os.replace(made, path)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None


def make_report(
    paths: Sequence[Path],
    out: Path,
    reference: Path | None = None,
    joint: str | None = None,
    still: tuple[float, float] | None = None,
    still_s: float = 2.0,
    with_trials: bool = True,
) -> list[Path]:
    """Analyse the recordings and write the report; returns the files written."""
    an = analyse(paths, reference, joint, still, still_s, with_trials)
    return write_report(an, out, [*paths, reference])
