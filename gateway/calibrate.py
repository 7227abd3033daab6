"""Fitting encoder calibrations from reference angles (000 seed, ch. 4.2 and 5).

- :func:`radius_from_pair`: eq. 25, ``R = D / alpha * 360 / (2 pi)`` for one
  known rotation (the PowerCube jig: 31.4 mm).
- :func:`fit_radius`: eq. 26, the least-squares slope G of travel against
  reference angle gives ``R = G * 360 / (2 pi)``; with it the correlation
  coefficient the seed reports (eq. 27).
- :func:`fit_scale_factors`: the SF table of Table 4.1: at each reference pose
  the factor that maps the measured travel onto the reference angle, given R.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from bodynet.core.calibration import MM_PER_COUNT, OleCalibration


def radius_from_pair(travel_mm: float, angle_deg: float) -> float:
    """Eq. 25: joint radius (mm) from one travel and the rotation that caused it."""
    return travel_mm / angle_deg * 360.0 / (2 * math.pi)


@dataclass(frozen=True)
class RadiusFit:
    radius_mm: float
    intercept_mm: float
    r: float  # correlation coefficient of travel and angle (eq. 27)
    n: int


def fit_radius(angles_deg: Sequence[float], counts: Sequence[float]) -> RadiusFit:
    """Eq. 26 over (reference angle, encoder count) pairs."""
    if len(angles_deg) != len(counts) or len(angles_deg) < 2:
        raise ValueError("need two or more (angle, counts) pairs")
    travel = [c * MM_PER_COUNT for c in counts]
    with np.errstate(all="ignore"):  # counts of 1e300 overflow: a non-finite fit, refused
        fit = stats.linregress(angles_deg, travel)
    return RadiusFit(fit.slope * 360.0 / (2 * math.pi), fit.intercept, fit.rvalue, len(travel))


def fit_scale_factors(angles_deg: Sequence[float], counts: Sequence[float],
                      radius_mm: float) -> OleCalibration:  # fmt: skip
    """R and the SF table that reproduce each reference angle from its count.

    At zero travel SF is 1; elsewhere ``SF = alpha * R / D``, made
    non-decreasing (as Table 4.1 is) so the curve stays invertible.
    """
    table: dict[float, float] = {0.0: 1.0}
    for angle, c in sorted(zip(angles_deg, counts, strict=True), key=lambda p: p[1]):
        d_mm = c * MM_PER_COUNT
        if d_mm > 0 and angle > 0:
            table[round(d_mm, 6)] = math.radians(angle) * radius_mm / d_mm
    travels = sorted(table)
    sf, best = [], 0.0
    for d in travels:
        best = max(best, table[d])
        sf.append(best)
    return OleCalibration(radius_mm, tuple(travels), tuple(sf))


#: Angles up to this are taken as the linear part of the curve (SF = 1 in Table 4.1).
LINEAR_UP_TO_DEG = 45.0


def fit_calibration(
    angles_deg: Sequence[float], counts: Sequence[float]
) -> tuple[OleCalibration, RadiusFit]:
    """R from the linear part of the curve (eq. 26, through the origin), then the
    SF table that maps every reference pose onto its angle."""
    linear = [(a, c) for a, c in zip(angles_deg, counts, strict=True) if 0 < a <= LINEAR_UP_TO_DEG]
    if len(linear) < 1:
        linear = [(a, c) for a, c in zip(angles_deg, counts, strict=True) if a > 0]
    if not linear:
        raise ValueError("need at least one reference angle above 0")
    # least squares through the origin: D = R * alpha
    radius = sum(c * MM_PER_COUNT * math.radians(a) for a, c in linear) / sum(
        math.radians(a) ** 2 for a, _ in linear
    )
    fit = fit_radius(angles_deg, counts) if len(angles_deg) >= 2 else RadiusFit(radius, 0.0, 1.0, 1)
    return fit_scale_factors(angles_deg, counts, radius), fit
