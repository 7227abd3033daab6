"""From raw samples to joint angles and segment poses, for one body.

Per joint, the angles come from the best source at hand:

1. Both segments carry an orientation sensor (IMU tag, SmartSuit trunk IMU):
   the relative rotation ``R_parent^T R_child`` split into the joint's dofs.
   A sensor's segment orientation is ``R_sensor R_mount^T``, the mount coming
   from T-pose calibration (:func:`tpose_mounts`).
2. A SmartSuit module spans the joint: its encoder gives the dof it measures
   (000 seed, eq. 14-15), and at the shoulders and hips its accelerometer's
   tilt gives flexion and abduction (eq. 9-13 and the 7-DOF mapping of ch.
   4.3.2, solved in closed form against the parent segment's vertical).
3. Otherwise the dof is unobserved: it holds 0 and is flagged.

Angles are split with continuity: at a gimbal lock (the middle dof at +/-90
degrees) or where the tilt has no unique answer (the segment along the
vertical), the ambiguous dof holds its last value instead of jumping. Angles
outside the range of motion are clamped and flagged. Positions come from
Pinocchio's forward kinematics of the assembled configuration, the pelvis
fixed at standing height.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from bodynet.core.keys import Site
from bodynet.core.messages import OleAccel, Quat, RawSample
from bodynet.core.profile import OLE_DOF, mount
from bodynet.core.skeleton import TPOSE, Joint, build_skeleton, rom
from bodynet.core.subject import Profile, QuatWxyz
from bodynet.kinematics.model import BodyModel, accel_axes

GIMBAL_COS = 1e-3  # |cos(middle angle)| below this is a gimbal lock
TILT_MIN = 0.05  # |component| below this: the tilt has no unique answer
MISS = 0.05  # a gravity fit further off than this (about 3 degrees) is no fit


# Per-tick maths uses Pinocchio's rotation functions: scipy's Rotation objects cost
# hundreds of microseconds a call, which a solver at 100 Hz per body cannot pay.
def _rot(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    return pin.exp3(axis * angle_rad)  # type: ignore[no-any-return]


def _angle_deg(rot: np.ndarray) -> float:
    """Rotation angle of a rotation matrix (accurate near 0, unlike acos of the trace)."""
    return math.degrees(float(np.linalg.norm(pin.log3(rot))))


# Batches of rotations, in array form: a scipy Rotation call costs some 30-90 us
# whatever the batch (its array-API layer), more than these whole formulas.
def _axis_rotations(axes: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """Rotations (n, 3, 3) about unit ``axes`` (n, 3) by ``angles_rad`` (n,), by
    Rodrigues' formula; a zero axis gives the identity."""
    k = np.zeros((len(axes), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axes[:, 2], axes[:, 1], -axes[:, 0]
    k -= k.transpose(0, 2, 1)
    s, c = np.sin(angles_rad)[:, None, None], np.cos(angles_rad)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)  # type: ignore[no-any-return]


def _angles_deg(rot: np.ndarray) -> np.ndarray:
    """Rotation angles (deg) of rotations (n, 3, 3): atan2 of sine and cosine,
    accurate near 0 (what ``_angle_deg`` gives for one)."""
    vee = np.stack([rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0],
                    rot[:, 1, 0] - rot[:, 0, 1]], axis=1)  # fmt: skip
    cos = (np.trace(rot, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arctan2(np.linalg.norm(vee, axis=1) / 2.0, cos))  # type: ignore[no-any-return]


def _quat_wxyz(rot: np.ndarray) -> QuatWxyz:
    q = pin.Quaternion(rot)
    q.normalize()
    w, x, y, z = q.w, q.x, q.y, q.z
    if w < 0:  # canonical: w >= 0
        w, x, y, z = -w, -x, -y, -z
    return (float(w), float(x), float(y), float(z))


def _matrix(q: QuatWxyz) -> np.ndarray:
    w, x, y, z = q
    return pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()  # type: ignore[no-any-return]


def _euler(rot: np.ndarray, seq: str) -> np.ndarray:
    """Intrinsic Tait-Bryan angles (deg) of ``rot`` for ``seq``, a permutation of XYZ:
    ``rot = R_i(a) R_j(b) R_k(c)``, with b in [-90, 90]."""
    i, j, k = ("XYZ".index(c) for c in seq)
    e = 1.0 if (j - i) % 3 == 1 else -1.0  # cyclic or not
    r = rot.tolist()
    b = math.asin(max(-1.0, min(1.0, e * r[i][k])))
    a = math.atan2(-e * r[j][k], r[k][k])
    c = math.atan2(-e * r[i][j], r[i][i])
    return np.degrees([a, b, c])


@dataclass(frozen=True)
class JointAxes:
    """A joint's dofs as a scipy Euler sequence with signs."""

    joint: Joint
    seq: str
    signs: np.ndarray
    axes: tuple[np.ndarray, ...]
    names: tuple[str, ...]  # the dofs' angle names
    limits: tuple[tuple[float, float], ...]  # their ranges of motion

    @classmethod
    def of(cls, joint: Joint) -> JointAxes:
        letters, signs = [], []
        for dof in joint.dofs:
            k = int(np.argmax(np.abs(dof.axis)))
            letters.append("XYZ"[k])
            signs.append(float(np.sign(dof.axis[k])))
        seq = "".join(letters) + "".join(c for c in "XYZ" if c not in letters)
        names = joint.angle_names()
        return cls(joint, seq[:3], np.array(signs), tuple(np.array(d.axis) for d in joint.dofs),
                   names, tuple(map(rom, names)))  # fmt: skip

    def matrix(self, angles_deg: np.ndarray) -> np.ndarray:
        out = _rot(self.axes[0], math.radians(angles_deg[0]))
        for axis, angle in zip(self.axes[1:], angles_deg[1:], strict=True):
            out = out @ _rot(axis, math.radians(angle))
        return out

    def dof(self, i: int, angle_deg: float) -> np.ndarray:
        """The rotation of dof ``i`` alone."""
        return _rot(self.axes[i], math.radians(angle_deg))

    def split(self, rel: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
        """Angles (deg) of the joint's dofs for a relative rotation.

        A three-angle split has two solutions, ``(a, b, c)`` and
        ``(a + 180, 180 - b, c + 180)``: the one inside the range of motion and
        nearest the previous angles wins. At a gimbal lock (``b`` at +/-90) the
        first angle holds its previous value (0 at first) and the third takes the rest.
        """
        euler = _euler(rel, self.seq)
        n = len(self.axes)
        if n == 3 and abs(math.cos(math.radians(euler[1]))) < GIMBAL_COS:
            first = previous[0] * self.signs[0] if previous is not None else 0.0
            head = _rot(np.eye(3)["XYZ".index(self.seq[0])], math.radians(first))
            head = head @ _rot(np.eye(3)["XYZ".index(self.seq[1])], math.radians(euler[1]))
            rest = pin.log3(head.T @ rel)
            euler = np.array([first, euler[1], math.degrees(rest["XYZ".index(self.seq[2])])])
            return euler * self.signs  # type: ignore[no-any-return]
        other = np.array([_wrap(euler[0] + 180), _wrap(180 - euler[1]), _wrap(euler[2] + 180)])
        signs = np.concatenate([self.signs, np.ones(3 - n)])
        candidates = [euler * signs, other * signs]
        if n < 3:  # the unused angles must vanish: only one candidate can be exact
            best = min(candidates, key=lambda c: float(np.abs(c[n:]).sum()))
            return best[:n]  # type: ignore[no-any-return]
        return _nearest([c[:n] for c in candidates], previous, self.names)


def _nearest(
    candidates: list[np.ndarray], previous: np.ndarray | None, names: tuple[str, ...]
) -> np.ndarray:
    """The candidate inside the range of motion (if any) nearest ``previous`` (or 0)."""

    def outside(c: np.ndarray) -> float:
        return sum(max(0.0, lo - v, v - hi) for v, (lo, hi) in zip(c, map(rom, names), strict=True))

    ref = previous if previous is not None else np.zeros(len(names))
    return min(candidates, key=lambda c: (outside(c), float(np.abs(c - ref).sum())))


class _SplitBatch:
    """:meth:`JointAxes.split` for many joints at once, in array form.

    An IMU body splits a dozen relative rotations per tick; numpy over the
    lot costs what one joint costs in scalar code. Rows at a gimbal lock go
    back to the scalar split, which holds the first angle there."""

    def __init__(self, axes: list[JointAxes]) -> None:
        self.axes = axes
        self.index = {ax.joint.name: r for r, ax in enumerate(axes)}
        ijk = np.array([["XYZ".index(c) for c in ax.seq] for ax in axes]).reshape(-1, 3)
        self.i, self.j, self.k = ijk.T
        self.e = np.where((self.j - self.i) % 3 == 1, 1.0, -1.0)
        self.n = np.array([len(ax.axes) for ax in axes])
        self.signs = np.ones((len(axes), 3))
        self.lo = np.full((len(axes), 3), -np.inf)
        self.hi = np.full((len(axes), 3), np.inf)
        for r, ax in enumerate(axes):
            self.signs[r, : self.n[r]] = ax.signs
            for d, name in enumerate(ax.joint.angle_names()):
                self.lo[r, d], self.hi[r, d] = rom(name)
        self.unused = np.arange(3)[None, :] >= self.n[:, None]
        self.axis = np.zeros((len(axes), 3, 3))  # per joint, each dof's axis (0: no dof)
        for r, ax in enumerate(axes):
            self.axis[r, : self.n[r]] = ax.axes

    def split(
        self, rows: np.ndarray, rel: np.ndarray, previous: list[np.ndarray | None]
    ) -> list[np.ndarray]:
        """Angles (deg) of joints ``rows`` for relative rotations ``rel`` (m, 3, 3)."""
        m = np.arange(len(rows))
        i, j, k, e = self.i[rows], self.j[rows], self.k[rows], self.e[rows]
        b = np.arcsin(np.clip(e * rel[m, i, k], -1.0, 1.0))
        a = np.arctan2(-e * rel[m, j, k], rel[m, k, k])
        c = np.arctan2(-e * rel[m, i, j], rel[m, i, i])
        euler = np.degrees(np.column_stack([a, b, c]))
        other = (np.column_stack([euler[:, 0] + 180, 180 - euler[:, 1], euler[:, 2] + 180])
                 + 180.0) % 360.0 - 180.0  # fmt: skip
        signs = self.signs[rows]
        first, second = euler * signs, other * signs
        n = self.n[rows]
        unused = self.unused[rows]
        # fewer than three dofs: the candidate whose unused angles vanish
        pick_two = np.abs(second * unused).sum(1) < np.abs(first * unused).sum(1)
        # three dofs: inside the range of motion, then nearest the previous angles
        ref = np.array([p if p is not None and len(p) == 3 else np.zeros(3) for p in previous])
        lo, hi = self.lo[rows], self.hi[rows]

        def outside(cand: np.ndarray) -> np.ndarray:
            return np.maximum(0.0, np.maximum(lo - cand, cand - hi)).sum(1)  # type: ignore[no-any-return]

        out1, out2 = outside(first), outside(second)
        d1, d2 = np.abs(first - ref).sum(1), np.abs(second - ref).sum(1)
        pick_three = (out2 < out1) | ((out2 == out1) & (d2 < d1))
        chosen = np.where(np.where(n == 3, pick_three, pick_two)[:, None], second, first)
        gimbal = (n == 3) & (np.abs(np.cos(b)) < GIMBAL_COS)
        result = []
        for r, row in enumerate(rows):
            if gimbal[r]:
                result.append(self.axes[row].split(rel[r], previous[r]))
            else:
                result.append(chosen[r, : n[r]].copy())
        return result


@dataclass(frozen=True)
class BodyOutput:
    """One tick of one body: every joint angle and every segment pose."""

    t_ns: int
    angles_deg: Mapping[str, float]
    rel_deg: Mapping[str, float]  # joint -> total rotation from the calibration pose
    flags: Mapping[str, str]  # angle -> "clamped" or "unobserved"
    segments: Mapping[str, tuple[tuple[float, float, float], QuatWxyz]]  # position, orientation
    joints_m: Mapping[str, tuple[float, float, float]]  # joint centres
    sources: Mapping[str, int]  # raw key -> source t_ns of the sample used


@dataclass
class _Memory:
    angles: dict[str, np.ndarray] = field(default_factory=dict)
    up: dict[str, np.ndarray] = field(default_factory=dict)
    tilt: dict[str, np.ndarray] = field(
        default_factory=dict
    )  # (pronation, deviation) per wrist  # filtered "up" of each accelerometer


class BodySolver:
    """Joint angles and poses of one body from its latest raw samples."""

    def __init__(self, profile: Profile | None = None) -> None:
        self.profile = profile or Profile()
        self.skeleton = build_skeleton(self.profile.lengths)
        self.model = BodyModel(self.skeleton)
        self.axes = {j.name: JointAxes.of(j) for j in self.skeleton.joints}
        self._calibration = {
            j.name: self.axes[j.name].matrix(np.array([TPOSE.get(n, 0.0) for n in j.angle_names()]))
            for j in self.skeleton.joints
        }
        self._frames = [self.model.segment_frames[s] for s in self.skeleton.segments]
        self._batch = _SplitBatch([self.axes[j.name] for j in self.skeleton.joints])
        self._calibration_inv = np.array(
            [self._calibration[j.name].T for j in self.skeleton.joints]
        )
        self._angle_order = self.skeleton.angle_names()
        self._memory = _Memory()
        self._sites: dict[Site, tuple[str, np.ndarray]] = {}

    def _site(self, site: Site) -> tuple[str, np.ndarray]:
        """The segment a sensor rides on, and its mount's inverse (for orientation sensors)."""
        known = self._sites.get(site)
        if known is None:
            w, x, y, z = self.profile.imu_mounts.get(site.raw_key, (1.0, 0.0, 0.0, 0.0))
            known = self._sites[site] = (mount(site).segment, _matrix((w, x, y, z)).T)
        return known

    def solve(self, samples: Mapping[Site, RawSample]) -> BodyOutput:
        """Angles and poses from the latest sample of each site."""
        measured, modules = self._by_segment(samples)
        world: dict[str, np.ndarray] = {"pelvis": measured.get("pelvis", np.eye(3))}
        angles: dict[str, float] = {}
        flags: dict[str, str] = {}
        rel: dict[str, float] = {}

        def commit(joint: Joint, values: np.ndarray) -> None:
            """Clamp to the range of motion, record, and carry the chain on."""
            ax = self.axes[joint.name]
            for i, (name, (lo, hi)) in enumerate(zip(ax.names, ax.limits, strict=True)):
                if not lo <= values[i] <= hi:
                    values[i] = min(max(values[i], lo), hi)
                    flags[name] = "clamped"
                angles[name] = float(values[i])
            self._memory.angles[joint.name] = values
            joint_rot = ax.matrix(values)
            world[joint.child] = world[joint.parent] @ joint_rot
            rel[joint.name] = _angle_deg(self._calibration[joint.name].T @ joint_rot)

        by_child = {j.child: j for j in self.skeleton.joints}
        direct = self._commit_direct(self._split_direct(measured, world["pelvis"]),
                                     angles, flags, rel)  # fmt: skip
        for joint in self.skeleton.joints:
            if joint.name in direct:
                world[joint.child] = world[joint.parent] @ direct[joint.name]
                continue
            ax = self.axes[joint.name]
            parent = world[joint.parent]
            previous = self._memory.angles.get(joint.name)
            names = ax.names
            if joint.child in measured:
                values = ax.split(parent.T @ measured[joint.child], previous)
            elif joint.child in modules:
                site, reading = modules[joint.child]
                values = self._from_module(joint, ax, parent, site, reading, previous, flags)
                if len(names) == 2 and reading is not None:  # wrist, ankle: the distal tilt
                    upstream = by_child[joint.parent]
                    chained = (
                        joint.parent not in measured
                        and joint.parent in modules
                        and len(upstream.dofs) == 2  # the elbow: its pronation is unknown too
                    )
                    values = self._distal_tilt(joint, values, upstream if chained else None,
                                               world, site, reading, flags, commit)  # fmt: skip
            else:
                values = np.zeros(len(names))
                flags.update(dict.fromkeys(names, "unobserved"))
            commit(joint, values)
        angles = {n: angles[n] for n in self._angle_order}  # the skeleton's order, always
        rel = {j.name: rel[j.name] for j in self.skeleton.joints}
        w, x, y, z = _quat_wxyz(world["pelvis"])
        root = (x, y, z, w)
        rotations, positions = self.model.frame_placements(
            self.model.q(angles, None, root), self._frames
        )
        xyzw = np.array([pin.Quaternion(r).coeffs() for r in rotations])
        xyzw /= np.linalg.norm(xyzw, axis=1, keepdims=True)
        xyzw *= np.where(xyzw[:, 3:] < 0, -1.0, 1.0)  # canonical: w >= 0
        segments = {
            s: (tuple(p), (q[3], q[0], q[1], q[2]))
            for s, p, q in zip(self.skeleton.segments, positions.tolist(), xyzw.tolist(),
                               strict=True)
        }  # fmt: skip
        joints = {j.name: segments[j.child][0] for j in self.skeleton.joints}
        return BodyOutput(
            t_ns=max((s.t_ns for s in samples.values()), default=0),
            angles_deg=angles,
            rel_deg=rel,
            flags=flags,
            segments=segments,
            joints_m=joints,  # type: ignore[arg-type]
            sources={site.raw_key: s.t_ns for site, s in samples.items()},
        )

    def _by_segment(
        self, samples: Mapping[Site, RawSample]
    ) -> tuple[dict[str, np.ndarray], dict[str, tuple[Site, OleAccel]]]:
        """Segment orientations of the orientation sensors, and the SmartSuit
        modules by the segment they ride on."""
        quats: dict[str, tuple[QuatWxyz, np.ndarray]] = {}  # the first sensor of a segment
        modules: dict[str, tuple[Site, OleAccel]] = {}
        for site, sample in samples.items():
            seg, mount_inv = self._site(site)
            r = sample.reading
            if isinstance(r, Quat):
                if seg not in quats:
                    quats[seg] = (r.wxyz, mount_inv)
            elif site.name in OLE_DOF:
                modules[seg] = (site, r)
        if not quats:
            return {}, modules
        sensor = Rotation.from_quat([q for q, _ in quats.values()], scalar_first=True)
        segment = sensor.as_matrix() @ np.array([m for _, m in quats.values()])
        return dict(zip(quats, segment, strict=True)), modules

    def _commit_direct(
        self,
        split: Mapping[str, np.ndarray],
        angles: dict[str, float],
        flags: dict[str, str],
        rel: dict[str, float],
    ) -> dict[str, np.ndarray]:
        """What ``commit`` does for one joint, for the joints split from two
        orientation sensors, all at once: clamp to the range of motion, record
        angles, flags and total rotation; their joint rotations."""
        if not split:
            return {}
        batch = self._batch
        rows = np.array([batch.index[name] for name in split])
        values = np.zeros((len(rows), 3))
        for r, v in enumerate(split.values()):
            values[r, : len(v)] = v
        lo, hi = batch.lo[rows], batch.hi[rows]
        clamped = (values < lo) | (values > hi)
        values = np.clip(values, lo, hi)
        radians = np.radians(values)
        matrices = _axis_rotations(batch.axis[rows, 0], radians[:, 0])
        for d in (1, 2):  # R = R_dof0 R_dof1 R_dof2, an absent dof adding nothing
            matrices = matrices @ _axis_rotations(batch.axis[rows, d], radians[:, d])
        total = _angles_deg(self._calibration_inv[rows] @ matrices).tolist()
        out = {}
        for r, (name, row) in enumerate(zip(split, rows.tolist(), strict=True)):
            ax = batch.axes[row]
            n = len(ax.names)
            v = values[r, :n]
            self._memory.angles[name] = v
            angles.update(zip(ax.names, v.tolist(), strict=True))
            if clamped[r, :n].any():
                flags.update((ax.names[i], "clamped") for i in np.flatnonzero(clamped[r, :n]))
            rel[name] = total[r]
            out[name] = matrices[r]
        return out

    def _split_direct(
        self, measured: Mapping[str, np.ndarray], pelvis: np.ndarray
    ) -> dict[str, np.ndarray]:
        """Angles of the joints between two orientation sensors (or the root and
        one), all at once. Each comes from its two segments' measured orientations,
        so a parent joint clamped to its range of motion does not move its child's."""
        direct = [
            j for j in self.skeleton.joints
            if j.child in measured and (j.parent in measured or j.parent == "pelvis")
        ]  # fmt: skip
        if not direct:
            return {}
        parents = [pelvis if j.parent == "pelvis" else measured[j.parent] for j in direct]
        rel = np.einsum(
            "nji,njk->nik", np.array(parents), np.array([measured[j.child] for j in direct])
        )
        rows = np.array([self._batch.index[j.name] for j in direct])
        previous = [self._memory.angles.get(j.name) for j in direct]
        values = self._batch.split(rows, rel, previous)
        return {j.name: v for j, v in zip(direct, values, strict=True)}

    def _from_module(
        self,
        joint: Joint,
        ax: JointAxes,
        parent: np.ndarray,
        site: Site,
        reading: OleAccel,
        previous: np.ndarray | None,
        flags: dict[str, str],
    ) -> np.ndarray:
        names = self.axes[joint.name].names
        values = previous.copy() if previous is not None else np.zeros(len(names))
        ole_name = f"{site.branch.side}_{site.name}_{OLE_DOF[site.name]}_deg"
        ole_index = names.index(ole_name)
        cal = self.profile.ole.get(ole_name)
        if cal is not None:
            values[ole_index] = float(cal.angle_deg(reading.encoder))
        if len(names) == 3 and ole_index == 2:  # shoulder, hip: flexion and abduction from tilt
            up_sensor = np.array(reading.accel, dtype=float)
            norm = np.linalg.norm(up_sensor)
            if norm > 0.1 * self.profile.accel_counts_per_g:  # not in free fall
                up = self._filtered_up(site.raw_key, up_sensor / norm)
                values[:2] = self._tilt(ax, parent, up, values, joint)
        else:
            for i, name in enumerate(names):
                if i != ole_index:
                    flags[name] = "unobserved"
                    values[i] = 0.0
        return values

    def _distal_tilt(
        self,
        joint: Joint,
        values: np.ndarray,
        upstream: Joint | None,
        world: dict[str, np.ndarray],
        site: Site,
        reading: OleAccel,
        flags: dict[str, str],
        commit: Any,
    ) -> np.ndarray:
        """The second dof of a wrist or ankle (deviation, inversion) from the
        accelerometer on the hand or foot, and with ``upstream`` (an elbow
        measured by its encoder only) that joint's second dof too (pronation):
        the angles that put the sensor's measured "up" on the world vertical,
        found by Gauss-Newton from the last values, so a direction gravity
        cannot see keeps its value instead of jumping (000 seed, eq. 21-23)."""
        up_sensor = np.array(reading.accel, dtype=float)
        norm = float(np.linalg.norm(up_sensor))
        if norm <= 0.1 * self.profile.accel_counts_per_g:
            return values
        ax = self.axes[joint.name]
        seg = joint.child
        mount_axes = accel_axes(np.array(self.skeleton.directions[seg]), ax.axes[0])
        target = mount_axes @ self._filtered_up(site.raw_key, up_sensor / norm)
        up_world = np.array([0.0, 0.0, 1.0])
        if upstream is None:
            fixed = world[joint.parent] @ ax.dof(0, values[0])

            def predict(x: np.ndarray) -> np.ndarray:
                return (fixed @ ax.dof(1, x[0])).T @ up_world  # type: ignore[no-any-return]

            (values[1],) = _gauss_newton(predict, np.array([values[1]]), target)
            flags.pop(self.axes[joint.name].names[1], None)
            return values
        up_ax = self.axes[upstream.name]
        up_values = self._memory.angles[upstream.name].copy()
        fixed = world[upstream.parent] @ up_ax.dof(0, up_values[0])
        wrist_flexion = ax.dof(0, values[0])

        def predict2(x: np.ndarray) -> np.ndarray:
            chain = fixed @ up_ax.dof(1, x[0]) @ wrist_flexion @ ax.dof(1, x[1])
            return chain.T @ up_world  # type: ignore[no-any-return]

        prev = self._memory.tilt.get(joint.name, np.zeros(2))
        names = (self.axes[upstream.name].names[1], self.axes[joint.name].names[1])

        def rank(x: np.ndarray) -> tuple[bool, float, float]:
            miss = float(np.linalg.norm(predict2(x) - target)) > MISS
            outside = sum(
                max(0.0, lo - v, v - hi) for v, (lo, hi) in zip(x, map(rom, names), strict=True)
            )
            return miss, outside, float(np.abs(x - prev).sum())

        fits = [_gauss_newton(predict2, prev, target)]
        if rank(fits[0])[:2] != (False, 0.0):  # no good fit near the last answer: try neutral
            fits.append(_gauss_newton(predict2, np.zeros(2), target))

        solution = min(fits, key=rank)
        self._memory.tilt[joint.name] = solution
        up_values[1], values[1] = solution
        flags.pop(self.axes[upstream.name].names[1], None)
        flags.pop(self.axes[joint.name].names[1], None)
        commit(upstream, up_values)
        return values

    def _filtered_up(self, key: str, up: np.ndarray) -> np.ndarray:
        """Light low-pass filtering of an accelerometer's direction (exponential,
        ``accel_filter`` of the new sample each time), against vibration."""
        last = self._memory.up.get(key)
        if last is not None:
            up = last + self.profile.accel_filter * (up - last)
            up /= np.linalg.norm(up)
        self._memory.up[key] = up
        return up

    def _tilt(
        self,
        ax: JointAxes,
        parent: np.ndarray,
        up_sensor: np.ndarray,
        values: np.ndarray,
        joint: Joint,
    ) -> np.ndarray:
        """Flexion and abduction putting the sensor's measured "up" on the parent's vertical.

        Solves ``R_a1(f) R_a2(a) R_a3(rot) u_seg = u_parent`` with a1 = +/-Y and
        a2 = +/-X: the X component fixes f (two candidates: the one nearer the
        last value wins), then the Y-Z plane gives a.
        """
        seg = joint.child
        m = accel_axes(np.array(self.skeleton.directions[seg]), ax.axes[0])
        u_seg = m @ up_sensor
        v = _rot(ax.axes[2], math.radians(values[2])) @ u_seg
        u_p = parent.T @ np.array([0.0, 0.0, 1.0])
        s1, s2 = ax.signs[0], ax.signs[1]
        a, b, c = u_p[0], -u_p[2], v[0]
        r = math.hypot(a, b)
        prev = values[:2].copy()
        if r < TILT_MIN:  # the parent's vertical gives no grip on flexion: hold it
            phis = [math.radians(prev[0] * s1)]
        else:
            base, spread = math.atan2(b, a), math.acos(max(-1.0, min(1.0, c / r)))
            phis = [base + spread, base - spread]
        candidates = []
        for phi1 in phis:
            w = _rot(np.array([0.0, 1.0, 0.0]), -phi1) @ u_p
            if math.hypot(v[1], v[2]) < TILT_MIN or math.hypot(w[1], w[2]) < TILT_MIN:
                phi2 = math.radians(prev[1] * s2)  # along the vertical: abduction is free, hold it
            else:
                phi2 = math.atan2(w[2], w[1]) - math.atan2(v[2], v[1])
            candidates.append(
                np.array([_wrap(math.degrees(phi1)) * s1, _wrap(math.degrees(phi2)) * s2])
            )
        return _nearest(candidates, prev, self.axes[joint.name].names[:2])


def _gauss_newton(predict: Any, x0: np.ndarray, target: np.ndarray, iters: int = 5) -> np.ndarray:
    """Angles (deg) near ``x0`` with ``predict(x)`` closest to ``target``.

    Least-squares steps (minimum norm), so a direction the target cannot
    see is left where it was."""
    x = x0.astype(float).copy()
    h = 1e-3
    eye = np.eye(len(x))
    for _ in range(iters):
        y = predict(x)
        r = y - target
        jac = np.column_stack([(predict(x + h * e) - y) / h for e in eye])
        # damped normal equations: a direction gravity cannot see gets no step
        jtj = jac.T @ jac
        step = np.linalg.solve(jtj + 1e-6 * np.trace(jtj) * eye + 1e-12 * eye, -jac.T @ r)
        x += np.clip(step, -30.0, 30.0)
        if float(np.abs(step).max()) < 1e-3:  # degrees: far below the sensors' resolution
            break
    return np.array([_wrap(v) for v in x])


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def tpose_mounts(
    window: Mapping[Site, list[QuatWxyz]], profile: Profile | None = None
) -> dict[str, QuatWxyz]:
    """Sensor-to-segment mounts from a still T-pose window of orientation samples.

    Assumes every tag shares one heading reference and that the subject faces
    +X of it during the T-pose.
    """
    skeleton = build_skeleton((profile or Profile()).lengths)
    model = BodyModel(skeleton)
    out: dict[str, QuatWxyz] = {}
    for site, quats in window.items():
        if not quats:
            continue
        seg = mount(site).segment
        seg_rot, _ = model.frame_placements(model.q(dict(TPOSE)), [model.segment_frames[seg]])
        mean = Rotation.from_quat([[x, y, z, w] for w, x, y, z in quats]).mean()
        x, y, z, w = Rotation.from_matrix(seg_rot[0].T @ mean.as_matrix()).as_quat(canonical=True)
        out[site.raw_key] = (float(w), float(x), float(y), float(z))
    return out
