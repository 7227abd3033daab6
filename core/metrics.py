"""Clinical numbers of joint angles, sample by sample: range of motion so far,
repetitions, and the smoothness of the current movement (SPARC).

One pure module (numpy only, no clock, no I/O) used by the live publisher of
``body/@metrics`` and by the offline report, so both give the same numbers
for the same samples. Feed :class:`BodyMetrics` each pose's measured angles
(:func:`measured_angles`: what the team's convention calls measured,
``pose.is_measured``, less what rests on a stale sensor an older gateway did
not flag) and ask it for :meth:`BodyMetrics.snapshot`.

Per dof (``<joint>_<dof>_deg``):

- **range of motion**: the least and greatest measured value so far;
- **repetitions**: movement cycles, counted as they end. With the range so
  far ``[lo, hi]`` and its span at least ``MIN_SPAN_DEG`` (5 deg), a cycle is
  the angle going from the lower quarter of the range (``<= lo + span/4``; a
  dof that has not yet moved 5 deg counts as there) to the upper quarter
  (``>= hi - span/4``) and back: an excursion of at least
  half the span, the rule of the report's peak count (prominence at least half
  the span and at least 5 deg), made causal;
- **smoothness** of the current movement: the spectral arc length SPARC
  (Balasubramanian, Melendez-Calderon, Roby-Brami & Burdet, "On the analysis
  of movement smoothness", J NeuroEng Rehabil 12:112, 2015) of the angular
  speed profile of the latest movement: the last stretch where the speed
  exceeded ``MOVING_DEG_S`` (10 deg/s), from where it rose above that until it
  fell below (or until now, if still moving), resampled at ``SPARC_RATE_HZ``.
  SPARC is negative; closer to 0 is smoother (a single minimum-jerk reach gives
  -1.41; several sub-movements make it more negative). No maintained
  SPARC package installs from PyPI, so :func:`sparc` follows the authors'
  published reference code (fc = 10 Hz, amplitude threshold 0.05, zero
  padding 4), tested against the closed form of a Gaussian speed profile.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt

from . import keys
from .codecs.pose import STALE, PoseFrame, is_measured
from .profile import mount
from .skeleton import build_skeleton

MIN_SPAN_DEG = 5.0
MOVING_DEG_S = 10.0
SPARC_RATE_HZ = 100.0
#: Samples of each dof kept for the current movement (at 100 Hz: 20 s).
HISTORY = 2000
#: The shortest movement SPARC is computed for (s).
MIN_MOVEMENT_S = 0.1
#: A jump of the poses' time by more than this (s), forward or back, ends a
#: dof's speed history: no movement spans it (the stream paused, or a time that
#: is no clock's; a movement across 2**63 ns asked numpy for terabytes).
GAP_S = 1.0
#: Dofs one body keeps metrics of (the body model has 32): names past this many
#: (a publisher inventing them) are passed over, so memory stays bounded.
MAX_DOFS = 64

FloatArray = npt.NDArray[np.float64]


@lru_cache(maxsize=64)
def _angles_at(segment: str) -> frozenset[str]:
    """The angles of the joints on either end of ``segment`` (those a sensor on it
    takes part in measuring)."""
    return frozenset(n for j in build_skeleton().joints if segment in (j.parent, j.child)
                     for n in j.angle_names())  # fmt: skip


def unflagged_stale_angles(frame: PoseFrame) -> frozenset[str]:
    """The angles resting on a stale sensor that ``frame`` does not flag: a pose
    from a gateway (or recording) before the ``stale`` reason lists its stale
    sites and flags none of their dofs. Then the old rule holds: the angles of the
    joints at either end of the segment each stale sensor rides on (the default
    profile's mounts; unknown keys passed over). Empty when nothing is stale or
    some dof carries the ``stale`` reason (the gateway flagged them itself)."""
    if not frame.stale or any(STALE in r for r in frame.reasons.values()):
        return frozenset()
    out: set[str] = set()
    for key in frame.stale:
        try:
            site, _ = keys.parse(keys.split_subject(key)[1])
        except keys.KeySpaceError:
            continue
        out |= _angles_at(mount(site).segment)
    return frozenset(out)


def measured_angles(frame: PoseFrame) -> dict[str, float]:
    """The angles of ``frame`` a measurement stands behind now: :func:`is_measured`
    (the gateway flags what rests on a stale sensor, reason ``stale``) and, for a
    pose from before that reason, not resting on a stale sensor
    (:func:`unflagged_stale_angles`). Every client's test of a pose's angles."""
    stale = unflagged_stale_angles(frame)
    return {n: v for n, v in frame.angles_deg.items() if is_measured(frame, n) and n not in stale}


def sparc(speed: npt.ArrayLike, fs: float, pad_level: int = 4, fc: float = 10.0,
          amp_th: float = 0.05) -> float:  # fmt: skip
    """Spectral arc length of a speed profile sampled at ``fs`` Hz.

    The Fourier magnitude spectrum, zero-padded to ``2**(ceil(log2 n) +
    pad_level)`` points and normalised to its peak, is cut at ``fc`` and then
    to the band where it stays at or above ``amp_th``; SPARC is minus the
    arc length of that curve with frequency normalised to the band's width.
    NaN for a profile that is empty, not finite, or all zero."""
    v = np.asarray(speed, dtype=np.float64)
    if v.size < 2 or not np.isfinite(v).all() or not np.any(v):
        return math.nan
    nfft = int(2 ** (math.ceil(math.log2(v.size)) + pad_level))
    f = np.arange(nfft) * (fs / nfft)
    mag = np.abs(np.fft.fft(v, nfft))
    mag = mag / mag.max()
    keep = f <= fc
    f_sel, m_sel = f[keep], mag[keep]
    above = np.nonzero(m_sel >= amp_th)[0]
    f_sel = f_sel[above[0] : above[-1] + 1]
    m_sel = m_sel[above[0] : above[-1] + 1]
    if f_sel.size < 2:
        return 0.0  # all the spectrum's energy in one bin: as smooth as it gets
    df = np.diff(f_sel) / (f_sel[-1] - f_sel[0])
    return -float(np.sum(np.sqrt(df**2 + np.diff(m_sel) ** 2)))


def latest_movement(t_s: FloatArray, x: FloatArray, moving: float = MOVING_DEG_S
                    ) -> tuple[FloatArray, FloatArray] | None:  # fmt: skip
    """The speed profile (times of the speeds, |dx/dt|) of the last stretch in
    which the speed exceeded ``moving``; None if there is none."""
    if t_s.size < 3:
        return None
    dt = np.diff(t_s)
    ok = dt > 0
    speed = np.zeros(dt.size)
    speed[ok] = np.abs(np.diff(x)[ok] / dt[ok])
    mid = (t_s[1:] + t_s[:-1]) / 2
    fast = speed > moving
    if not fast.any():
        return None
    end = int(np.nonzero(fast)[0][-1])
    start = end
    while start > 0 and fast[start - 1]:
        start -= 1
    # a sample of rest on either side, so the profile starts and ends low
    lo, hi = max(start - 1, 0), min(end + 2, speed.size)
    return mid[lo:hi], speed[lo:hi]


def movement_sparc(t_s: FloatArray, x: FloatArray) -> float:
    """SPARC of the latest movement of an angle sampled at times ``t_s`` (s);
    NaN if there is none, or it is shorter than ``MIN_MOVEMENT_S``."""
    found = latest_movement(t_s, x)
    if found is None:
        return math.nan
    tm, speed = found
    if tm[-1] - tm[0] < MIN_MOVEMENT_S:
        return math.nan
    grid = np.arange(tm[0], tm[-1], 1.0 / SPARC_RATE_HZ)
    return sparc(np.interp(grid, tm, speed), SPARC_RATE_HZ)


@dataclass
class DofMetrics:
    """One dof's running numbers."""

    lo: float = math.inf
    hi: float = -math.inf
    samples: int = 0
    repetitions: int = 0
    _phase: str = ""  # "" (before the first sample), "low", "high"
    _t: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    _x: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))

    def add(self, t_s: float, x: float) -> None:
        """One measured value at time ``t_s`` (s, increasing)."""
        if not math.isfinite(x) or not math.isfinite(t_s):
            return
        self.samples += 1
        self.lo, self.hi = min(self.lo, x), max(self.hi, x)
        span = self.hi - self.lo
        if span < MIN_SPAN_DEG:
            self._phase = "low"  # at rest so far: a first movement starts a cycle
        elif x <= self.lo + span / 4:
            if self._phase == "high":
                self.repetitions += 1
            self._phase = "low"
        elif x >= self.hi - span / 4 and self._phase == "low":
            self._phase = "high"
        if self._t:
            step = t_s - self._t[-1]
            if abs(step) > GAP_S:
                self._t.clear()
                self._x.clear()
            elif step <= 0:
                return  # out of order or repeated: not part of a speed profile
        self._t.append(t_s)
        self._x.append(x)

    def smoothness(self) -> float:
        """SPARC of the current (latest) movement; NaN if none."""
        return movement_sparc(np.fromiter(self._t, float), np.fromiter(self._x, float))

    def snapshot(self) -> dict[str, Any]:
        s = self.smoothness()
        return {"min_deg": self.lo, "max_deg": self.hi, "range_deg": self.hi - self.lo,
                "repetitions": self.repetitions, "sparc": None if math.isnan(s) else s,
                "samples": self.samples}  # fmt: skip


class BodyMetrics:
    """The running metrics of every dof of one subject."""

    def __init__(self) -> None:
        self.dofs: dict[str, DofMetrics] = {}
        self.t_ns: int | None = None
        self._t0_ns: int | None = None

    def add(self, t_ns: int, measured: Mapping[str, float]) -> None:
        """One pose: its source time (ns) and the angles measured in it."""
        self.t_ns = t_ns
        if self._t0_ns is None:
            self._t0_ns = t_ns
        t_s = (t_ns - self._t0_ns) * 1e-9  # from the first pose: no precision lost
        for name, value in measured.items():
            dof = self.dofs.get(name)
            if dof is None:
                if len(self.dofs) >= MAX_DOFS:
                    continue
                dof = self.dofs[name] = DofMetrics()
            dof.add(t_s, value)

    def snapshot(self) -> dict[str, Any]:
        """The message of ``body/@metrics`` (JSON-ready): ``t_ns`` of the last
        pose, and per observed dof ``min_deg``, ``max_deg``, ``range_deg``,
        ``repetitions``, ``sparc`` (null without a movement) and ``samples``."""
        dofs = {n: d.snapshot() for n, d in sorted(self.dofs.items()) if d.samples}
        return {"v": 1, "t_ns": self.t_ns, "dofs": dofs}
