"""The emulated body: a routine drives the body model, sensor models read it.

:class:`BodyEmulator` gives, for any time, the readings of a set of emulated
sensors (SmartSuit modules, SmartSuit trunk IMUs, IMU tags) and the ground
truth they came from. It does no I/O: the hardware emulators put its readings
on real transports.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.calibration import OleCalibration, default_ole
from bodynet.core.keys import Branch, Site
from bodynet.core.messages import OleAccel, Quat, Reading
from bodynet.core.profile import IMU_SITES, SMARTSUIT_QUAT_NODES, SMARTSUIT_SITES, mount
from bodynet.core.skeleton import build_skeleton
from bodynet.kinematics.model import BodyModel, SiteMount, accel_axes
from bodynet.nodes.motion import ROOT_ANGLES, Routine
from bodynet.nodes.sensors import AccelBank, OleModel, QuatBank


class Kind(StrEnum):
    MODULE = "module"  # SmartSuit OLE + accelerometer
    TRUNK_IMU = "trunk-imu"  # SmartSuit trunk-head IMU (Q14 quaternion on CAN)
    TAG = "tag"  # IMU suit BLE tag


@dataclass(frozen=True, slots=True)
class EmulatedSensor:
    node: int
    site: Site
    kind: Kind


def smartsuit_sensors(branches: Iterable[Branch] | None = None) -> list[EmulatedSensor]:
    """SmartSuit nodes of the given branches (all five by default)."""
    wanted = set(branches) if branches is not None else None
    return [
        EmulatedSensor(n, s, Kind.TRUNK_IMU if n in SMARTSUIT_QUAT_NODES else Kind.MODULE)
        for n, s in SMARTSUIT_SITES.items()
        if wanted is None or s.branch in wanted
    ]


def imu_tags(
    sensors: Iterable[int] | None = None, branches: Iterable[Branch] | None = None
) -> list[EmulatedSensor]:
    """IMU tags by sensor number and/or branch (all fifteen by default)."""
    numbers = set(sensors) if sensors is not None else set(IMU_SITES)
    wanted = set(branches) if branches is not None else None
    return [
        EmulatedSensor(n, s, Kind.TAG)
        for n, s in IMU_SITES.items()
        if n in numbers and (wanted is None or s.branch in wanted)
    ]


@dataclass(frozen=True, slots=True)
class Truth:
    """What a sensor's segment really did: its joint's angles and orientation."""

    angles_deg: Mapping[str, float]
    segment: str
    segment_quat_wxyz: tuple[float, float, float, float]


class Headings(StrEnum):
    """The heading references of emulated orientation sensors."""

    SHARED = "shared"  # one earth frame (magnetometer-based sensors): z up, x to north
    INDEPENDENT = "independent"  # 6-axis tags: each its own heading, drawn at random
    DRIFTING = "drifting"  # 6-axis tags reset together: one heading at first, then their own


@dataclass(frozen=True, slots=True)
class Realism:
    """How far emulated sensors fall short of ideal ones.

    Orientation sensors report in their reference frame, z up. With ``SHARED``
    headings that frame is one for all, and the subject faces ``facing_deg`` in
    it (0: +X, as the solver's ``fixed`` heading assumes); the whole frame drifts
    at ``yaw_drift_deg_per_min``. With ``INDEPENDENT`` headings each sensor's
    frame has a random heading of its own and drifts at a rate drawn within
    +/- ``yaw_drift_deg_per_min``; ``DRIFTING`` tags start as ``SHARED`` ones and
    drift as ``INDEPENDENT`` ones. The truth stays in the body's frame.

    ``tissue_wobble_deg``: soft tissue under the tags (orientation sensors) lets
    each turn on its segment, up to this far: a smooth oscillation (0.5-3 Hz about
    each axis, random per tag) whose amplitude grows with the segment's angular
    speed (all of it from 100 deg/s on), as a tag on the skin shakes in a walk."""

    accel_noise_g: float = 0.01
    accel_bias_g: float = 0.02  # bias of each axis drawn within +/- this
    quat_noise_deg: float = 0.3
    yaw_drift_deg_per_min: float = 0.0
    ole_slack_mm: float = 0.0
    random_tag_mounts: bool = True
    facing_deg: float = 0.0
    headings: Headings = Headings.SHARED
    tissue_wobble_deg: float = 0.0

    @classmethod
    def ideal(cls) -> Realism:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, False)


class BodyEmulator:
    """Readings and ground truth of emulated sensors on a body under a routine."""

    def __init__(
        self,
        routine: Routine,
        sensors: Sequence[EmulatedSensor],
        *,
        realism: Realism | None = None,
        lengths: Mapping[str, float] | None = None,
        ole: Mapping[str, OleCalibration] | None = None,
        seed: int = 0,
        accel_step_s: float = 0.005,
    ) -> None:
        self.routine = routine
        self.sensors = list(sensors)
        self.realism = realism or Realism()
        self.skeleton = build_skeleton(lengths)
        self._h = accel_step_s
        rng = np.random.default_rng(seed)
        mounts = {s: mount(s.site) for s in self.sensors}
        self.model = BodyModel(
            self.skeleton,
            [SiteMount(f"n{s.node}-{s.kind}", m.segment, m.fraction) for s, m in mounts.items()],
        )
        self._frames = [self.model.site_frames[f"n{s.node}-{s.kind}"] for s in self.sensors]
        self._segment_frames = [self.model.segment_frames[mounts[s].segment] for s in self.sensors]
        self._mounts = [mounts[s] for s in self.sensors]
        self._joint_angles = [self._angles_of(m.segment) for m in self._mounts]
        r = self.realism
        self._ole: dict[int, tuple[OleModel, str]] = {}
        accel_idx, accel_mounts, quat_idx, quat_mounts = [], [], [], []
        for i, (s, m) in enumerate(zip(self.sensors, self._mounts, strict=True)):
            if s.kind is Kind.MODULE:
                assert m.ole_angle is not None
                cal = (ole or {}).get(m.ole_angle) or default_ole(s.site.name)
                self._ole[i] = (OleModel(cal, r.ole_slack_mm), m.ole_angle)
                joint = next(j for j in self.skeleton.joints if j.child == m.segment)
                direction = np.array(self.skeleton.directions[m.segment])
                accel_idx.append(i)
                accel_mounts.append(accel_axes(direction, np.array(joint.dofs[0].axis)))
            else:
                quat_idx.append(i)
                random_mount = s.kind is Kind.TAG and r.random_tag_mounts
                quat_mounts.append(
                    Rotation.random(random_state=int(rng.integers(1 << 31))).as_quat()
                    if random_mount
                    else np.array([0.0, 0.0, 0.0, 1.0])
                )
        self._accel_idx, self._quat_idx = np.array(accel_idx, int), np.array(quat_idx, int)
        bias = rng.uniform(-r.accel_bias_g, r.accel_bias_g, (len(accel_idx), 3))
        self._accel = AccelBank(
            np.array(accel_mounts).reshape(-1, 3, 3), r.accel_noise_g, bias, rng
        )
        k = len(quat_idx)
        if r.headings is Headings.INDEPENDENT:
            headings = rng.uniform(-180.0, 180.0, k)
            drift: float | np.ndarray = rng.uniform(-1.0, 1.0, k) * r.yaw_drift_deg_per_min
        elif r.headings is Headings.DRIFTING:
            headings = np.full(k, r.facing_deg)
            drift = rng.uniform(-1.0, 1.0, k) * r.yaw_drift_deg_per_min
        else:
            headings, drift = np.full(k, r.facing_deg), r.yaw_drift_deg_per_min
        #: each orientation sensor's reference heading (deg) at t = 0, by node number
        self.headings_deg = {self.sensors[i].node: float(h)
                             for i, h in zip(quat_idx, headings, strict=True)}  # fmt: skip
        #: and how fast it drifts (deg/min), by node number
        rates = np.broadcast_to(drift, (k,))
        self.drift_deg_per_min = {self.sensors[i].node: float(d)
                                  for i, d in zip(quat_idx, rates, strict=True)}  # fmt: skip
        self._quat = QuatBank(
            Rotation.from_quat(np.array(quat_mounts).reshape(-1, 4)),
            r.quat_noise_deg,
            drift,
            rng,
            headings,
        )

        # the wobble's own draws (the noise's stream stays the same without it)
        wobble = np.random.default_rng(seed + 7919)
        self._wobble_freq = wobble.uniform(0.5, 3.0, (k, 3))
        self._wobble_phase = wobble.uniform(0.0, 2 * math.pi, (k, 3))

    def _wobbled(self, t_s: float, seg_rot: np.ndarray) -> np.ndarray:
        """The orientation sensors' segments (``seg_rot``, at ``t_s``) turned by the
        soft tissue under their tags (``Realism.tissue_wobble_deg``)."""
        dt = 0.01
        frames = [self._segment_frames[i] for i in self._quat_idx]
        before, _ = self.model.frame_placements(self._q(self.angles(t_s - dt)), frames)
        cos = (np.trace(before.transpose(0, 2, 1) @ seg_rot, axis1=1, axis2=2) - 1) / 2
        speed = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) / dt
        amp = self.realism.tissue_wobble_deg * np.minimum(1.0, speed / 100.0)
        turn = np.sin(2 * math.pi * self._wobble_freq * t_s + self._wobble_phase)
        rotvec = np.radians(amp[:, None] * turn / math.sqrt(3))
        return seg_rot @ Rotation.from_rotvec(rotvec).as_matrix()  # type: ignore[no-any-return]

    @property
    def module_nodes(self) -> set[int]:
        """The node numbers of the SmartSuit modules (an encoder each)."""
        return {self.sensors[i].node for i in self._ole}

    def power_on(self, node: int, t_s: float) -> None:
        """SmartSuit module ``node`` starts (again) at ``t_s``: its encoder's count
        restarts at 0 where its joint is then (``OleModel.power_on``); its other
        sensors are absolute. ``KeyError`` if ``node`` is no module here."""
        for i, sensor in enumerate(self.sensors):
            if sensor.node == node and i in self._ole:
                ole, angle = self._ole[i]
                ole.power_on(self.angles(t_s).get(angle, 0.0))
                return
        raise KeyError(f"node {node} is no SmartSuit module of this body")

    def _angles_of(self, segment: str) -> tuple[str, ...]:
        for joint in self.skeleton.joints:
            if joint.child == segment:
                return joint.angle_names()
        return ()

    def angles(self, t_s: float) -> dict[str, float]:
        return self.routine.angles(t_s)

    def _q(self, angles: Mapping[str, float]) -> np.ndarray:
        """The model's configuration: the joint angles, and the pelvis' orientation
        where the routine gives it (``ROOT_ANGLES``)."""
        if not any(n in angles for n in ROOT_ANGLES):
            return self.model.q(angles)
        turn, tilt, lean = (angles.get(n, 0.0) for n in ROOT_ANGLES)
        root = Rotation.from_euler("ZYX", [turn, tilt, lean], degrees=True).as_quat()
        joints = {n: v for n, v in angles.items() if n not in ROOT_ANGLES}
        return self.model.q(joints, root_quat_xyzw=root)

    def sample(self, t_s: float) -> tuple[list[Reading], list[Truth]]:
        """Every sensor's reading at ``t_s``, and the truth behind each."""
        angles = self.angles(t_s)
        n = len(self._frames)
        rot, pos = self.model.frame_placements(self._q(angles), self._frames + self._segment_frames)
        seg_rot = rot[n:]
        readings: list[Reading | None] = [None] * n
        if len(self._accel_idx):
            sites = [self._frames[i] for i in self._accel_idx]
            _, before = self.model.frame_placements(self._q(self.angles(t_s - self._h)), sites)
            _, after = self.model.frame_placements(self._q(self.angles(t_s + self._h)), sites)
            accel = (after - 2 * pos[self._accel_idx] + before) / (self._h * self._h)
            counts = self._accel.read(seg_rot[self._accel_idx], accel)
            for row, i in enumerate(self._accel_idx):
                ole, ole_angle = self._ole[int(i)]
                x, y, z = (int(c) for c in counts[row])
                readings[i] = OleAccel(
                    self.sensors[i].node, ole.read(angles.get(ole_angle, 0.0)), (x, y, z)
                )
        if len(self._quat_idx):
            on = seg_rot[self._quat_idx]
            if self.realism.tissue_wobble_deg:
                on = self._wobbled(t_s, on)
            quats = self._quat.read(on, t_s)
            for row, i in enumerate(self._quat_idx):
                w, x, y, z = (float(c) for c in quats[row])
                readings[i] = Quat(self.sensors[i].node, (w, x, y, z))
        true_quats = np.roll(Rotation.from_matrix(seg_rot).as_quat(canonical=True), 1, axis=1)
        truths = [
            Truth({a: angles.get(a, 0.0) for a in names}, m.segment, tuple(float(c) for c in q))  # type: ignore[arg-type]
            for names, m, q in zip(self._joint_angles, self._mounts, true_quats, strict=True)
        ]
        return [r for r in readings if r is not None], truths


def angle_between_deg(q1: Sequence[float], q2: Sequence[float]) -> float:
    """Rotation angle (deg) between two unit quaternions w, x, y, z."""
    dot = abs(sum(a * b for a, b in zip(q1, q2, strict=True)))
    return math.degrees(2 * math.acos(min(1.0, dot)))
