"""OLE calibration: encoder travel to joint angle (000 seed, eq. 3 and 14-15).

An optical linear encoder reads the travel D of a cable laid over a joint of
radius R; the joint turns by ``alpha = SF(D) * D / R`` radians, where the scale
factor SF compensates for skin and bone (Table 4.1). SF is interpolated
linearly in D from a table and held constant beyond its ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The largest radius an OLE calibration may have: a joint's bend radius is
#: tens of mm; a fit far above this is a failed fit, not a joint.
MAX_RADIUS_MM = 1000.0

#: Millimetres of cable travel per encoder count.
MM_PER_COUNT = 0.1

#: Table 4.1 of the 000 seed: elbow travel D (cm) and the scale factor SF(D).
ELBOW_SF_D_CM = (0.0, 1.41, 2.80, 3.91, 4.86, 5.22)
ELBOW_SF = (1.0, 1.0, 1.007, 1.084, 1.161, 1.261)
ELBOW_RADIUS_MM = 26.93

#: Joint radii (mm) of the default profile; SF = 1 except at the elbows.
DEFAULT_RADIUS_MM = {
    "shoulder": 45.0,
    "elbow": ELBOW_RADIUS_MM,
    "wrist": 25.0,
    "hip": 50.0,
    "knee": 30.0,
    "ankle": 25.0,
}


@dataclass(frozen=True, slots=True)
class OleCalibration:
    """R and the SF table of one joint's encoder."""

    radius_mm: float
    sf_d_mm: tuple[float, ...] = (0.0,)
    sf: tuple[float, ...] = (1.0,)

    def __post_init__(self) -> None:
        if not 0 < self.radius_mm <= MAX_RADIUS_MM:  # also refuses NaN
            raise ValueError(f"radius must be above 0 and at most {MAX_RADIUS_MM:g} mm (a "
                             f"joint's), not {self.radius_mm}")  # fmt: skip
        if not all(math.isfinite(v) for v in (*self.sf_d_mm, *self.sf)):
            raise ValueError("SF table holds a number that is not finite")
        if len(self.sf_d_mm) != len(self.sf) or not self.sf:
            raise ValueError("SF table needs one factor per travel")
        if any(b <= a for a, b in zip(self.sf_d_mm, self.sf_d_mm[1:], strict=False)):
            raise ValueError("SF table travels must increase")
        if any(b < a for a, b in zip(self.sf, self.sf[1:], strict=False)) or min(self.sf) <= 0:
            raise ValueError("SF must be positive and never decrease with travel")

    def scale(self, d_mm: float | np.ndarray) -> float | np.ndarray:
        """SF at travel ``d_mm`` (by magnitude; constant beyond the table)."""
        return np.interp(np.abs(d_mm), self.sf_d_mm, self.sf)

    def angle_deg(self, counts: float | np.ndarray) -> float | np.ndarray:
        """Joint angle for an encoder reading: eq. 14-15."""
        d_mm = np.asarray(counts, dtype=float) * MM_PER_COUNT
        alpha = self.scale(d_mm) * d_mm / self.radius_mm * (180.0 / math.pi)
        return float(alpha) if np.ndim(alpha) == 0 else alpha

    def travel_mm(self, angle_deg: float) -> float:
        """Cable travel that reads as ``angle_deg``: the inverse of :meth:`angle_deg`.

        ``alpha(D)`` increases with D because SF never decreases, so a bisection
        on D converges to the one answer.
        """
        target = math.radians(angle_deg)
        lo, hi = -4 * math.pi * self.radius_mm, 4 * math.pi * self.radius_mm
        for _ in range(60):
            mid = (lo + hi) / 2
            if float(self.scale(mid)) * mid / self.radius_mm < target:
                lo = mid
            else:
                hi = mid
        return (lo + hi) / 2

    def counts(self, angle_deg: float) -> int:
        """The encoder count a perfect sensor reads at ``angle_deg``."""
        return round(self.travel_mm(angle_deg) / MM_PER_COUNT)


def default_ole(joint: str) -> OleCalibration:
    """Default calibration of a joint type (``"elbow"``, ``"knee"``...)."""
    if joint == "elbow":
        return OleCalibration(
            ELBOW_RADIUS_MM, tuple(round(10 * d, 6) for d in ELBOW_SF_D_CM), ELBOW_SF
        )
    return OleCalibration(DEFAULT_RADIUS_MM[joint])
