"""Sensor models: what each kind of sensor reads while the body moves.

- OLE (000 seed, ch. 2): the joint angle becomes cable travel through the
  inverse of the calibration curve, quantised to 0.1 mm counts; optionally the
  cable buckles at fast onsets and reversals (ch. 5.2.2), modelled as play:
  the reading only follows once the travel has moved past the slack. The count
  is relative, as the node's: its firmware resets the QEI's counter (``POSCNT``)
  at start-up (ch. 3.4.1), so it reads 0 wherever the joint was at power-on
  (:meth:`OleModel.power_on`; by default at the joint's zero).
- Accelerometer (ch. 3.3): specific force (motion acceleration minus gravity)
  in the sensor frame, plus bias and noise, 1024 counts per g, saturating at
  +/-2 g (12 bits). Mounted with x along the segment pointing away from the
  body, y along the joint's flexion axis, z = x cross y.
- IMU tag (003 seed): the segment's orientation through an arbitrary mounting
  rotation, with noise, given in the tag's own reference frame (z up): that
  frame's heading against the body's forward is ``headings_deg`` (one value for
  all tags: a magnetometer-based sensor's earth frame, the subject facing
  anywhere; or one per tag: 6-axis tags each starting with a heading of its
  own), and it drifts about the vertical at ``drift_deg_per_min`` (per tag).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.calibration import MM_PER_COUNT, OleCalibration

GRAVITY = np.array([0.0, 0.0, -9.80665])
COUNTS_PER_G = 1024
ACCEL_MIN, ACCEL_MAX = -2048, 2047  # 12 bits: +/-2 g


class OleModel:
    """An optical linear encoder over one joint dof."""

    def __init__(self, calibration: OleCalibration, slack_mm: float = 0.0) -> None:
        self.calibration = calibration
        self.slack_mm = slack_mm
        r = calibration.radius_mm
        # alpha(D) increases with D, so a dense table inverts it by interpolation
        self._travel = np.linspace(-4 * math.pi * r, 4 * math.pi * r, 20001)
        self._angle = np.asarray(calibration.angle_deg(self._travel / MM_PER_COUNT))
        self._reading: float | None = None
        #: the cable's travel (mm) at which the counter reads 0: where it was at power-on
        self.zero_mm = 0.0

    def power_on(self, angle_deg: float) -> None:
        """The node starts (again) with the joint at ``angle_deg``: its counter
        restarts at 0 there (the firmware's QEI reset)."""
        if self._reading is None or self.slack_mm <= 0:
            self._reading = self.travel_mm(angle_deg)
        self.zero_mm = self._reading

    def travel_mm(self, angle_deg: float) -> float:
        return float(np.interp(angle_deg, self._angle, self._travel))

    def read(self, angle_deg: float) -> int:
        """Encoder count at ``angle_deg`` (with the cable's slack, if any)."""
        travel = self.travel_mm(angle_deg)
        if self._reading is None or self.slack_mm <= 0:
            self._reading = travel
        elif travel > self._reading + self.slack_mm:
            self._reading = travel - self.slack_mm
        elif travel < self._reading - self.slack_mm:
            self._reading = travel + self.slack_mm
        return round((self._reading - self.zero_mm) / MM_PER_COUNT)


@dataclass
class AccelBank:
    """Tri-axis accelerometers on segments, read together (one row per sensor)."""

    mounts: np.ndarray  # (k, 3, 3): sensor axes (columns) in the segment frame
    noise_g: float = 0.0
    bias_g: np.ndarray | None = None  # (k, 3)
    rng: np.random.Generator = field(default_factory=np.random.default_rng)

    def read(self, world_segment: np.ndarray, accel_world: np.ndarray) -> np.ndarray:
        """Counts (k, 3) for segment world rotations (k, 3, 3) and accelerations (k, 3)."""
        world_sensor = world_segment @ self.mounts
        specific = np.einsum("kji,kj->ki", world_sensor, accel_world - GRAVITY)
        g = specific / -GRAVITY[2]
        if self.bias_g is not None:
            g = g + self.bias_g
        if self.noise_g:
            g = g + self.rng.normal(0.0, self.noise_g, g.shape)
        return np.clip(np.round(g * COUNTS_PER_G), ACCEL_MIN, ACCEL_MAX).astype(int)


@dataclass
class QuatBank:
    """Orientation sensors (IMU tags, SmartSuit's trunk-head IMUs), read together."""

    mounts: Rotation  # k mounting rotations, sensor in segment
    noise_deg: float = 0.0
    yaw_drift_deg_per_min: float | np.ndarray = 0.0  # one rate, or one per sensor (k,)
    rng: np.random.Generator = field(default_factory=np.random.default_rng)
    headings_deg: float | np.ndarray = 0.0  # each sensor's reference heading at t = 0

    def read(self, world_segment: np.ndarray, t_s: float) -> np.ndarray:
        """Unit quaternions (k, 4) w, x, y, z of the sensors in their reference
        frames at ``t_s``."""
        rot = Rotation.from_matrix(world_segment) * self.mounts
        heading = np.radians(self.headings_deg + np.asarray(self.yaw_drift_deg_per_min) * t_s / 60)
        if np.any(heading):
            yaw = np.zeros((len(rot), 3))
            yaw[:, 2] = heading
            rot = Rotation.from_rotvec(yaw) * rot
        if self.noise_deg:
            noise = self.rng.normal(0.0, math.radians(self.noise_deg), (len(rot), 3))
            rot = Rotation.from_rotvec(noise) * rot
        return np.roll(rot.as_quat(canonical=True), 1, axis=1)
