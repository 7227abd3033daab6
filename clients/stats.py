"""The validation statistics of the source documents, as pure functions.

Arrays in, numbers out: no files, no plots (``report`` does those). Each
function names the equation it implements:

- range of motion and repetitions of one joint angle channel;
- RMS error and Pearson's correlation coefficient against a reference
  (000 seed, ch. 5, eq. 27);
- repeatability across trials: range and standard deviation of the trial
  means (000 seed, ch. 6.3.1, eq. 28-31);
- intra-class correlation across trials (000 seed, ch. 6.3.2, eq. 32);
- Type A standard uncertainty of a still sensor (003 seed, ch. 8.4, eq. 8.1-8.3).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pandas as pd
import pingouin
from scipy import signal, stats

Array = npt.ArrayLike

#: A peak counts as a repetition when its prominence is at least this share of
#: the channel's span...
REP_REL_PROMINENCE = 0.5
#: ...and at least this many degrees (so a still channel's noise counts none).
REP_MIN_PROMINENCE_DEG = 5.0
#: Each trial is time-normalised to this many points (0, 1, ... 100 % of it).
TRIAL_POINTS = 101


class StatsError(ValueError):
    """Data the statistic cannot be computed from (too short, too few trials...)."""


def _vector(x: Array, name: str, at_least: int = 1) -> npt.NDArray[np.float64]:
    a = np.asarray(x, dtype=float)
    if a.ndim != 1:
        raise StatsError(f"{name}: expected one channel, got shape {a.shape}")
    if a.size < at_least:
        raise StatsError(f"{name}: {a.size} samples, at least {at_least} needed")
    if not np.all(np.isfinite(a)):
        raise StatsError(f"{name}: has missing or non-finite samples")
    return a


@dataclass(frozen=True, slots=True)
class Rom:
    """Range of motion of one channel (degrees)."""

    minimum: float
    maximum: float

    @property
    def span(self) -> float:
        return self.maximum - self.minimum


def range_of_motion(x: Array) -> Rom:
    """Smallest and largest value of a channel."""
    a = _vector(x, "range of motion")
    return Rom(float(a.min()), float(a.max()))


def repetitions(
    x: Array,
    rel_prominence: float = REP_REL_PROMINENCE,
    min_prominence: float = REP_MIN_PROMINENCE_DEG,
) -> npt.NDArray[np.intp]:
    """Indices of the peaks of a channel's movement cycles, one per repetition.

    The rule: a repetition is a local maximum (``scipy.signal.find_peaks``) whose
    prominence -- how far it stands above the deeper of the two valleys around
    it -- is at least ``rel_prominence`` of the channel's span and at least
    ``min_prominence`` degrees. A peak must have a valley on both sides within
    the data, so a movement cut off by the end of the recording does not count.
    """
    a = _vector(x, "repetitions")
    threshold = max(min_prominence, rel_prominence * float(np.ptp(a)))
    peaks, _ = signal.find_peaks(a, prominence=threshold)
    return peaks


def trial_bounds(x: Array, peaks: npt.ArrayLike) -> list[tuple[int, int]]:
    """Cut a channel into one trial per repetition peak: ``(start, stop)`` indices.

    Trials meet at the lowest sample between two consecutive peaks. The first
    starts at the lowest sample within half a cycle (half the median spacing of
    the peaks) before the first peak, the last ends at the lowest within half a
    cycle after the last peak, so a still stretch before or after the movement
    stays out of the trials. ``stop`` is inclusive.
    """
    a = _vector(x, "trials")
    p = np.asarray(peaks, dtype=int)
    if p.size == 0:
        return []
    half = int(np.median(np.diff(p)) // 2) if p.size > 1 else a.size
    lo = max(0, p[0] - half)
    edges = [int(lo + np.argmin(a[lo : p[0] + 1]))]
    edges += [int(lo + np.argmin(a[lo : hi + 1])) for lo, hi in itertools.pairwise(p)]
    edges.append(int(p[-1] + np.argmin(a[p[-1] : p[-1] + half + 1])))
    return list(itertools.pairwise(edges))


def roughness(x: Array) -> float:
    """Standard deviation of the sample-to-sample change over the span: small
    for a smooth movement, large for a channel that jumps (an ambiguity, a clamp)."""
    a = _vector(x, "roughness", 3)
    span = float(np.ptp(a))
    return float(np.std(np.diff(a))) / span if span > 0 else float("inf")


def time_normalise(t: Array, x: Array, points: int = TRIAL_POINTS) -> npt.NDArray[np.float64]:
    """One trial resampled (linear interpolation) at ``points`` equally spaced
    instants from its first to its last sample, so trials of different
    durations line up point by point."""
    tt, a = _vector(t, "trial time", 2), _vector(x, "trial", 2)
    if tt.size != a.size:
        raise StatsError("trial: times and values differ in length")
    return np.interp(np.linspace(tt[0], tt[-1], points), tt, a)


def _pair(x: Array, ref: Array) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    a, b = _vector(x, "measured", 2), _vector(ref, "reference", 2)
    if a.size != b.size:
        raise StatsError(f"measured and reference differ in length ({a.size}, {b.size})")
    return a, b


def rms_error(x: Array, ref: Array) -> float:
    """Root mean square of the difference between measured and reference samples."""
    a, b = _pair(x, ref)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def correlation(x: Array, ref: Array) -> float:
    """Pearson's correlation coefficient of two data sets (000 seed, eq. 27)."""
    a, b = _pair(x, ref)
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        raise StatsError("correlation: one of the channels is constant")
    return float(stats.pearsonr(a, b).statistic)


@dataclass(frozen=True, slots=True)
class Repeatability:
    """Range and standard deviation of the trial means of one channel."""

    trial_means: tuple[float, ...]
    range: float
    sd: float


def repeatability(trials: Array) -> Repeatability:
    """Repeatability across trials (000 seed, ch. 6.3.1).

    ``trials`` holds one row per trial j and one column per position i. Each
    trial's mean over its positions (eq. 29) is X_j; the range is
    ``max_j X_j - min_j X_j`` (eq. 28) and the standard deviation that of the
    X_j about their mean (eq. 30-31), with n - 1 in the denominator, as SPSS,
    which the seed used, computes it.
    """
    m = np.asarray(trials, dtype=float)
    if m.ndim != 2 or m.shape[0] < 2:
        raise StatsError(f"repeatability needs two or more trials, got {m.shape[0]}")
    means = m.mean(axis=1)
    return Repeatability(
        tuple(float(v) for v in means), float(np.ptp(means)), float(np.std(means, ddof=1))
    )


@dataclass(frozen=True, slots=True)
class Icc:
    """Intra-class correlation: the form reported, its 95 % interval, and all six forms."""

    form: str
    value: float
    ci95: tuple[float, float]
    forms: dict[str, float]


#: The form reported. Eq. 32, ICC = s_t^2 / (s_t^2 + s_e^2), has two variance
#: components: between positions (targets) and random error. ICC(3,1) (two-way
#: mixed, consistency, single measure; SPSS's default, which the seed used)
#: estimates exactly that ratio, a systematic offset of a whole trial being left
#: out of the error. ICC(2,1) adds the trials' variance to the denominator
#: (absolute agreement) and ICC(1,1) folds it into the error; both are reported too.
ICC_FORM = "ICC3"
ICC_NAMES = {"ICC1": "ICC(1,1)", "ICC2": "ICC(2,1)", "ICC3": "ICC(3,1)",
             "ICC1k": "ICC(1,k)", "ICC2k": "ICC(2,k)", "ICC3k": "ICC(3,k)"}  # fmt: skip


def icc(trials: Array, form: str = ICC_FORM) -> Icc:
    """Intra-class correlation across trials (000 seed, ch. 6.3.2, eq. 32), by pingouin.

    ``trials`` holds one row per trial (the raters, in Shrout & Fleiss' terms)
    and one column per position along the movement (the targets).
    """
    m = np.asarray(trials, dtype=float)
    if m.ndim != 2 or m.shape[0] < 2:
        raise StatsError(f"ICC needs two or more trials, got {m.shape[0] if m.ndim == 2 else 0}")
    if m.shape[1] < 2:
        raise StatsError("ICC needs two or more positions per trial")
    if not np.all(np.isfinite(m)):
        raise StatsError("ICC: trials have missing or non-finite samples")
    if np.ptp(m.mean(axis=0)) == 0:
        raise StatsError("ICC: the channel does not move (no variance between positions)")
    trial, position = np.indices(m.shape)
    long = pd.DataFrame({"trial": trial.ravel(), "position": position.ravel(), "x": m.ravel()})
    # identical trials leave no error variance: ICC 1, pingouin divides by zero on the way
    with np.errstate(divide="ignore", invalid="ignore"):
        table = pingouin.intraclass_corr(long, targets="position", raters="trial", ratings="x")
    table = table.set_index("Type")
    low, high = table.loc[form, "CI95%"]
    return Icc(
        ICC_NAMES[form],
        float(table.loc[form, "ICC"]),
        (float(low), float(high)),
        {ICC_NAMES[k]: float(v) for k, v in table["ICC"].items()},
    )


@dataclass(frozen=True, slots=True)
class TypeA:
    """Type A evaluation of standard uncertainty (JCGM 100, as in 003 seed Table 8.3)."""

    n: int
    mean: float  # best estimate q-bar, eq. 8.1
    variance: float  # experimental variance s^2(q_k), eq. 8.2
    sd: float  # experimental standard deviation s(q_k)
    variance_of_mean: float  # s^2(q-bar), eq. 8.3
    sd_of_mean: float  # experimental standard deviation of the mean s(q-bar)


def type_a(x: Array) -> TypeA:
    """Mean, experimental variance and SD, and those of the mean, of n observations."""
    a = _vector(x, "Type A", 2)
    var = float(np.var(a, ddof=1))
    sem = float(stats.sem(a, ddof=1))
    return TypeA(a.size, float(a.mean()), var, float(np.sqrt(var)), sem * sem, sem)


def still_window(t: Array, channels: Array, seconds: float) -> tuple[int, int]:
    """The ``seconds`` long stretch in which the channels moved least:
    ``(start, stop)`` indices (stop exclusive) of the window with the smallest
    sum over channels of the standard deviation. ``channels`` is (samples, channels)."""
    tt = _vector(t, "still window time", 2)
    m = np.asarray(channels, dtype=float).reshape(tt.size, -1)
    dt = float(np.median(np.diff(tt)))
    if dt <= 0:
        raise StatsError("still window: sample times do not increase")
    width = round(seconds / dt) + 1
    if width > tt.size:
        raise StatsError(f"still window: the recording is shorter than {seconds:g} s")
    # a window counts only where every channel was measured throughout (NaN: not)
    spread = pd.DataFrame(m).rolling(width).std(ddof=1).sum(axis=1, min_count=m.shape[1])
    spread = spread.to_numpy()
    if np.isnan(spread).all():
        raise StatsError(f"still window: no {seconds:g} s in which every channel was measured")
    stop = int(np.nanargmin(spread)) + 1
    return stop - width, stop
