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
Pinocchio's forward kinematics of the assembled configuration, the body set
on the floor: the pelvis above the origin, at the height that puts the
body's lowest point (a heel or a toe, standing) at z = 0.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from bodynet.core.keys import Site
from bodynet.core.messages import OleAccel, Quat, RawSample
from bodynet.core.profile import OLE_DOF, mount
from bodynet.core.skeleton import CALIBRATION_POSES, TPOSE, Joint, build_skeleton, rom
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

    An IMU body splits a dozen relative rotations per tick, and the gateway
    solves several bodies at a time; numpy over the lot costs what one joint
    costs in scalar code. Rows at a gimbal lock go back to the scalar split,
    which holds the first angle there. The joints' axes and ranges of motion
    depend on the skeleton's structure only, not on its lengths, so one batch
    serves every body."""

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
        self.names = [ax.names for ax in axes]
        # where each joint's dofs sit in the skeleton's angle vector; an absent dof
        # points one past the end, a column that takes what nobody reads
        starts = np.cumsum([0, *self.n[:-1]])
        self.angle_index = np.where(self.unused, int(self.n.sum()),
                                    starts[:, None] + np.arange(3)[None, :])  # fmt: skip

    def split(self, rows: np.ndarray, rel: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """Angles (deg, (m, 3), absent dofs 0) of joints ``rows`` for relative
        rotations ``rel`` (m, 3, 3), continuous with ``previous`` (m, 3)."""
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
        lo, hi = self.lo[rows], self.hi[rows]

        def outside(cand: np.ndarray) -> np.ndarray:
            return np.maximum(0.0, np.maximum(lo - cand, cand - hi)).sum(1)  # type: ignore[no-any-return]

        out1, out2 = outside(first), outside(second)
        d1, d2 = np.abs(first - previous).sum(1), np.abs(second - previous).sum(1)
        pick_three = (out2 < out1) | ((out2 == out1) & (d2 < d1))
        chosen = np.where(np.where(n == 3, pick_three, pick_two)[:, None], second, first)
        chosen[unused] = 0.0
        for r in np.flatnonzero((n == 3) & (np.abs(np.cos(b)) < GIMBAL_COS)).tolist():
            chosen[r] = self.axes[rows[r]].split(rel[r], previous[r])
        return chosen  # type: ignore[no-any-return]

    def commit(
        self, rows: np.ndarray, values: np.ndarray, calibration_inv: np.ndarray,
        relative: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What committing a joint does, for many at once: angles (m, 3) clamped to
        the range of motion, which were clamped, the joint rotations (m, 3, 3) and
        each joint's total rotation (deg) from the calibration pose (its rotation
        there inverted: ``calibration_inv``, (m, 3, 3)), taken from the measured
        relative rotations ``relative`` (m, 3, 3), not from the clamped dofs: how a
        rotation splits into dofs is ambiguous at a gimbal lock, the rotation is not."""
        lo, hi = self.lo[rows], self.hi[rows]
        clamped = (values < lo) | (values > hi)
        values = np.clip(values, lo, hi)
        # every dof's rotation in one call, then R = R_dof0 R_dof1 R_dof2 (an absent
        # dof adds nothing)
        dofs = _axis_rotations(self.axis[rows].reshape(-1, 3),
                               np.radians(values).ravel()).reshape(-1, 3, 3, 3)  # fmt: skip
        matrices = dofs[:, 0] @ dofs[:, 1] @ dofs[:, 2]
        total = _angles_deg(calibration_inv @ relative)
        return values, clamped, matrices, total


@dataclass(frozen=True)
class OutputNames:
    """The names of a body's outputs, in the skeleton's order."""

    angles: tuple[str, ...]
    joints: tuple[str, ...]
    segments: tuple[str, ...]
    joint_segment: tuple[int, ...]  # each joint's child segment: its origin is the joint centre


@dataclass(slots=True)
class BodyOutput:
    """One tick of one body: every joint angle and every segment pose, as arrays
    in the order of ``names``; the mappings are views for readers. (Not frozen,
    as the raw samples are not: one is made per body and tick.)"""

    t_ns: int
    names: OutputNames
    angles: np.ndarray  # (angles,) degrees
    rel: np.ndarray  # (joints,) each joint's total rotation (deg) from the calibration pose
    flags: Mapping[str, str]  # angle -> "clamped" or "unobserved"
    positions: np.ndarray  # (segments, 3) metres
    quats: np.ndarray  # (segments, 4) unit quaternions w, x, y, z, w >= 0
    sources: Mapping[str, int]  # raw key -> source t_ns of the sample used

    @property
    def angles_deg(self) -> dict[str, float]:
        return dict(zip(self.names.angles, self.angles.tolist(), strict=True))

    @property
    def rel_deg(self) -> dict[str, float]:
        return dict(zip(self.names.joints, self.rel.tolist(), strict=True))

    @property
    def segments(self) -> dict[str, tuple[tuple[float, float, float], QuatWxyz]]:
        return {s: (tuple(p), tuple(q))  # type: ignore[misc]
                for s, p, q in zip(self.names.segments, self.positions.tolist(),
                                   self.quats.tolist(), strict=True)}  # fmt: skip

    @property
    def joints_m(self) -> dict[str, tuple[float, float, float]]:
        centres = self.positions[list(self.names.joint_segment)].tolist()
        return {j: tuple(p) for j, p in zip(self.names.joints, centres, strict=True)}  # type: ignore[misc]


@dataclass
class _Memory:
    last: np.ndarray | None = None  # the angle vector of the last tick (None before one)
    up: dict[str, np.ndarray] = field(default_factory=dict)  # filtered "up" of each accelerometer
    tilt: dict[str, np.ndarray] = field(default_factory=dict)  # (pronation, deviation) per wrist


class _Tick:
    """One body's working state during one solve: plain data that its
    :class:`BodySolver` fills (:meth:`BodySolver._gather`) and reads."""

    __slots__ = ("angles", "direct_rot", "direct_rows", "flags", "last", "lefts", "measured",
                 "modules", "mounts", "plan", "quats", "rel", "segs", "solver", "sources", "t_ns",
                 "unknown")  # fmt: skip

    def __init__(self, solver: BodySolver, last: np.ndarray | None) -> None:
        self.solver = solver
        self.last = last  # the angle vector of the body's last tick (None before one)
        self.segs: list[str] = []  # segments with an orientation sensor (the first one wins)
        self.quats: list[QuatWxyz] = []
        self.mounts: list[np.ndarray] = []
        self.lefts: list[np.ndarray] = []  # each sensor's turn into the body's heading
        self.unknown: set[str] = set()  # segments whose sensor's heading is not known
        self.modules: dict[str, tuple[Site, OleAccel]] = {}  # SmartSuit modules by segment
        self.sources: dict[str, int] = {}
        self.t_ns = 0
        # the joints between two of ``segs``: rows, parent and child indices (see _direct_plan)
        self.plan: tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros(0, dtype=int),) * 3
        self.measured: dict[str, np.ndarray] = {}  # segment -> world orientation
        # the joints split from two sensors: their rows and rotations
        self.direct_rows: np.ndarray = np.zeros(0, dtype=int)
        self.direct_rot: np.ndarray = np.zeros((0, 3, 3))
        self.angles = np.zeros(0)  # the skeleton's angle vector (+1: see angle_index)
        self.rel = np.zeros(0)
        self.flags: dict[str, str] = {}


def solve_bodies(work: Sequence[tuple[BodySolver, Mapping[Site, RawSample]]]) -> list[BodyOutput]:
    """One tick of each of several bodies: :meth:`BodySolver.solve_many`."""
    return BodySolver.solve_many(work)


class BodySolver:
    """Joint angles and poses of one body from its latest raw samples.

    It is the one owner of the body's state between ticks (the last angles, the
    accelerometers' filtered "up", the wrists' tilt, the sites and plans it has
    worked out); a tick's working state (:class:`_Tick`) is plain data it fills.
    ``solve`` does one tick of this body; :meth:`solve_many` does one tick of
    many, with the array work shared. Both run the same code."""

    def __init__(self, profile: Profile | None = None) -> None:
        self.profile = profile or Profile()
        self.skeleton = build_skeleton(self.profile.lengths)
        self.model = BodyModel(self.skeleton)
        self.axes = {j.name: JointAxes.of(j) for j in self.skeleton.joints}
        pose = CALIBRATION_POSES[self.profile.pose]
        self._calibration = {
            j.name: self.axes[j.name].matrix(np.array([pose.get(n, 0.0) for n in j.angle_names()]))
            for j in self.skeleton.joints
        }
        self._batch = _SplitBatch([self.axes[j.name] for j in self.skeleton.joints])
        self._calibration_inv = np.array(
            [self._calibration[j.name].T for j in self.skeleton.joints]
        )
        segments = self.skeleton.segments
        self.names = OutputNames(
            self.skeleton.angle_names(),
            tuple(j.name for j in self.skeleton.joints),
            segments,
            tuple(segments.index(j.child) for j in self.skeleton.joints),
        )
        self._slices: dict[str, slice] = {}
        for joint, start in zip(self.skeleton.joints, self._batch.angle_index[:, 0].tolist(),
                                strict=True):  # fmt: skip
            self._slices[joint.name] = slice(start, start + len(joint.dofs))
        self._memory = _Memory()
        self._sites: dict[Site, tuple[str, np.ndarray, str, bool, np.ndarray, bool]] = {}
        self._plans: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _site(self, site: Site) -> tuple[str, np.ndarray, str, bool, np.ndarray, bool]:
        """The segment a sensor rides on, its mount's inverse (for orientation
        sensors), its raw key, whether it is a SmartSuit module, the turn from its
        reference frame to the body's (``Rz(-heading)``, see gateway/heading.py) and
        whether that heading is known."""
        known = self._sites.get(site)
        if known is None:
            key = site.raw_key
            w, x, y, z = self.profile.imu_mounts.get(key, (1.0, 0.0, 0.0, 0.0))
            known = self._sites[site] = (
                mount(site).segment, _matrix((w, x, y, z)).T, key, site.name in OLE_DOF,
                _rot(np.array([0.0, 0.0, 1.0]), -math.radians(self.profile.heading_of(key))),
                self.profile.heading_known(key),
            )  # fmt: skip
        return known

    def _flag_uncalibrated(self, tick: _Tick) -> None:
        """Flag ``uncalibrated`` every dof that a sensor of unknown heading drives:
        the joints next to its segment, and down the chain while the segments'
        orientations come from their parents (SmartSuit modules)."""
        unknown, tainted, measured = tick.unknown, set(tick.unknown), tick.measured
        for joint in self.skeleton.joints:
            if joint.parent in tainted or joint.child in unknown:
                if joint.child not in measured:
                    tainted.add(joint.child)
                for name in self.axes[joint.name].names:
                    if tick.flags.get(name) != "unobserved":
                        tick.flags[name] = "uncalibrated"

    def set_profile(self, profile: Profile) -> None:
        """Take a profile of the same body (lengths, calibration pose) whose mounts or
        headings changed, keeping the body's memory (the last angles...): a heading
        that drifts is corrected tick by tick without starting the body again."""
        if profile.lengths != self.profile.lengths or profile.pose != self.profile.pose:
            raise ValueError("set_profile keeps the body: new lengths or pose need a new solver")
        self.profile = profile
        self._sites.clear()

    def solve(self, samples: Mapping[Site, RawSample]) -> BodyOutput:
        """Angles and poses from the latest sample of each site."""
        return BodySolver.solve_many([(self, samples)])[0]

    @staticmethod
    def solve_many(work: Sequence[tuple[BodySolver, Mapping[Site, RawSample]]]) -> list[BodyOutput]:
        """One tick of each of several bodies: angles and poses from the latest
        sample of each site.

        The array work of every body is done together: sensor orientations, the
        relative rotations of the joints between two sensors, their split into
        dofs, clamping and total rotations, and after forward kinematics the floor
        and the canonical quaternions are each one numpy pass over all the bodies.
        What is left per body is gathering its samples, the joints that SmartSuit
        modules measure (scalar code) and Pinocchio's forward kinematics. The
        solvers must share one skeleton structure (any segment lengths)."""
        if not work:
            return []
        ticks = [solver._gather(samples) for solver, samples in work]
        first = work[0][0]
        angles = np.zeros((len(ticks), len(first.names.angles) + 1))
        rel = np.zeros((len(ticks), len(first.names.joints)))
        for b, tick in enumerate(ticks):
            tick.angles, tick.rel = angles[b], rel[b]
        quats = [q for t in ticks for q in t.quats]
        if quats:
            sensors = Rotation.from_quat(np.array(quats), scalar_first=True).as_matrix()
            segments = (np.array([m for t in ticks for m in t.lefts]) @ sensors
                        @ np.array([m for t in ticks for m in t.mounts]))  # fmt: skip
            start = 0
            for tick in ticks:
                tick.measured = dict(zip(tick.segs, segments[start : start + len(tick.segs)],
                                         strict=True))  # fmt: skip
                start += len(tick.segs)
            first._solve_direct(ticks, segments, angles, rel)
        for tick in ticks:
            tick.solver._solve_rest(tick)
            if tick.unknown:
                tick.solver._flag_uncalibrated(tick)
        return first._outputs(ticks)

    def _gather(self, samples: Mapping[Site, RawSample]) -> _Tick:
        """A new tick of this body: its samples sorted by kind, against its last angles."""
        tick = _Tick(self, self._memory.last)
        sources = tick.sources
        seen: set[str] = set()
        known, t_ns = self._sites, 0
        for site, sample in samples.items():
            seg, mount_inv, key, module, left, heading_known = known.get(site) or self._site(site)
            sources[key] = t = sample.t_ns
            t_ns = max(t_ns, t)
            r = sample.reading
            if type(r) is Quat:
                if seg not in seen:
                    seen.add(seg)
                    tick.segs.append(seg)
                    tick.quats.append(r.wxyz)
                    tick.mounts.append(mount_inv)
                    tick.lefts.append(left)
                    if not heading_known:
                        tick.unknown.add(seg)
            elif module:
                tick.modules[seg] = (site, r)  # type: ignore[assignment]
        tick.t_ns = t_ns
        if tick.segs:
            tick.plan = self._direct_plan(tuple(tick.segs))
        return tick

    def _solve_direct(self, ticks: Sequence[_Tick], segments: np.ndarray, angles: np.ndarray,
                      rel: np.ndarray) -> None:  # fmt: skip
        """The joints between two orientation sensors (or the root and one), of every
        body at once (this solver's structure, which they share), into ``angles``
        and ``rel`` (one row a body). Each comes from its two segments' measured
        orientations (``segments``, every body's in turn), so a parent joint
        clamped to its range of motion does not move its child's."""
        batch = self._batch
        plans = [tick.plan for tick in ticks]
        counts = [len(p[0]) for p in plans]
        if not sum(counts):
            return
        owner = np.repeat(np.arange(len(ticks)), counts)
        offsets = np.repeat(np.cumsum([0, *(len(t.segs) for t in ticks[:-1])]), counts)
        rows = np.concatenate([p[0] for p in plans])
        parents = np.concatenate([p[1] for p in plans])
        children = np.concatenate([p[2] for p in plans]) + offsets
        # an unmeasured pelvis (-1) is the identity, put after every measured segment
        segments = np.concatenate([segments, np.eye(3)[None]])
        parents = np.where(parents >= 0, parents + offsets, len(segments) - 1)
        relative = np.einsum("nji,njk->nik", segments[parents], segments[children])
        index = batch.angle_index[rows]
        nothing = np.zeros(angles.shape[1])  # a body's first tick: no previous angles
        last = np.stack([t.last if t.last is not None else nothing for t in ticks])
        # each body's own calibration pose (T or N): the total rotations are from it
        calibration_inv = np.stack([t.solver._calibration_inv for t in ticks])[owner, rows]
        values, clamped, matrices, total = batch.commit(
            rows, batch.split(rows, relative, last[owner[:, None], index]), calibration_inv,
            relative,
        )
        angles[owner[:, None], index] = values
        angles[:, -1] = 0.0  # the absent dofs' column
        rel[owner, rows] = total
        start = 0
        for tick, (mine, _, _) in zip(ticks, plans, strict=True):
            tick.direct_rows, tick.direct_rot = mine, matrices[start : start + len(mine)]
            start += len(mine)
        clamped &= ~batch.unused[rows]
        for r, d in zip(*np.nonzero(clamped), strict=True):
            ticks[owner[r]].flags[batch.names[rows[r]][d]] = "clamped"

    def _outputs(self, ticks: Sequence[_Tick]) -> list[BodyOutput]:
        """Forward kinematics of each body's angles (Pinocchio), then, for every body
        at once (this solver's structure, which they share), the pelvis height that
        puts the lowest point on the floor (z = 0) and the segments' quaternions,
        canonical (w >= 0)."""
        poses, floor = zip(*(tick.solver._forward(tick) for tick in ticks), strict=True)
        for tick in ticks:  # what the next tick's angles are continuous with
            tick.solver._memory.last = tick.angles
        poses = np.array(poses)  # (bodies, segments, xyz + quaternion x, y, z, w)
        points = np.array([tick.solver.model.floor_points for tick in ticks])  # lengths differ
        floor_z = self.model.floor_heights(np.array(floor), points).min(axis=1)
        lowest = np.minimum(floor_z, poses[:, :, 2].min(axis=1))  # or a joint centre
        poses[:, :, 2] -= lowest[:, None]
        quats = poses[:, :, [6, 3, 4, 5]]  # x, y, z, w -> w, x, y, z
        quats /= np.linalg.norm(quats, axis=2, keepdims=True)
        quats *= np.where(quats[:, :, :1] < 0, -1.0, 1.0)
        return [BodyOutput(t.t_ns, t.solver.names, t.angles[:-1], t.rel, t.flags, p[:, :3], q,
                           t.sources)
                for t, p, q in zip(ticks, poses, quats, strict=True)]  # fmt: skip

    def _direct_plan(self, measured: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For segments ``measured`` (in this order), the joints between two of them
        (or the root and one): their rows, and the indices in ``measured`` of their
        parent (-1: the unmeasured pelvis) and child segments."""
        plan = self._plans.get(measured)
        if plan is None:
            at = {s: i for i, s in enumerate(measured)}
            direct = [
                (self._batch.index[j.name], at.get(j.parent, -1), at[j.child])
                for j in self.skeleton.joints
                if j.child in at and (j.parent in at or j.parent == "pelvis")
            ]  # fmt: skip
            plan = tuple(np.array([d[k] for d in direct], dtype=int) for k in range(3))  # type: ignore[assignment]
            if len(self._plans) >= 64:  # which sensors deliver changes rarely: a small cache
                self._plans.clear()
            self._plans[measured] = plan  # type: ignore[assignment]
        return plan  # type: ignore[return-value]

    def _solve_rest(self, tick: _Tick) -> None:
        """The joints not split from two orientation sensors: SmartSuit modules
        (scalar code, in chain order, each from its parent's world orientation),
        or unobserved."""
        if len(tick.direct_rows) == len(self.skeleton.joints):
            return
        direct = dict(zip([self.names.joints[r] for r in tick.direct_rows.tolist()],
                          tick.direct_rot, strict=True))  # fmt: skip
        world: dict[str, np.ndarray] = {"pelvis": tick.measured.get("pelvis", np.eye(3))}
        by_child = {j.child: j for j in self.skeleton.joints}
        measured, modules = tick.measured, tick.modules
        last = tick.last
        for joint in self.skeleton.joints:
            if joint.name in direct:
                world[joint.child] = world[joint.parent] @ direct[joint.name]
                continue
            ax = self.axes[joint.name]
            parent = world[joint.parent]
            previous = last[self._slices[joint.name]] if last is not None else None
            names = ax.names
            relative = None
            if joint.child in measured:
                relative = parent.T @ measured[joint.child]
                values = ax.split(relative, previous)
            elif joint.child in modules:
                site, reading = modules[joint.child]
                values = self._from_module(joint, ax, parent, site, reading, previous, tick.flags)
                if len(names) == 2 and reading is not None:  # wrist, ankle: the distal tilt
                    upstream = by_child[joint.parent]
                    chained = (
                        joint.parent not in measured
                        and joint.parent in modules
                        and len(upstream.dofs) == 2  # the elbow: its pronation is unknown too
                    )
                    values = self._distal_tilt(joint, values, upstream if chained else None,
                                               world, site, reading, tick)  # fmt: skip
            else:
                values = np.zeros(len(names))
                tick.flags.update(dict.fromkeys(names, "unobserved"))
            self._commit(tick, world, joint, values, relative)

    def _commit(self, tick: _Tick, world: dict[str, np.ndarray], joint: Joint,
                values: np.ndarray, relative: np.ndarray | None = None) -> None:  # fmt: skip
        """Clamp to the range of motion, record, and carry the chain on. The total
        rotation from the calibration pose is the measured ``relative`` rotation's
        when there is one (see :meth:`_SplitBatch.commit`)."""
        ax = self.axes[joint.name]
        for i, (name, (lo, hi)) in enumerate(zip(ax.names, ax.limits, strict=True)):
            if not lo <= values[i] <= hi:
                values[i] = min(max(values[i], lo), hi)
                tick.flags[name] = "clamped"
        tick.angles[self._slices[joint.name]] = values
        joint_rot = ax.matrix(values)
        world[joint.child] = world[joint.parent] @ joint_rot
        tick.rel[self._batch.index[joint.name]] = _angle_deg(
            self._calibration[joint.name].T @ (joint_rot if relative is None else relative)
        )

    def _forward(self, tick: _Tick) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics of the tick's angles (Pinocchio): the segments' poses
        with the pelvis at standing height, and the model's floor rows."""
        w, x, y, z = _quat_wxyz(tick.measured.get("pelvis", np.eye(3)))
        poses = self.model.segment_poses(self.model.q_of(tick.angles[:-1], (x, y, z, w)))
        return poses, self.model.floor_rows()

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
        tick: _Tick,
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
            tick.flags.pop(self.axes[joint.name].names[1], None)
            return values
        up_ax = self.axes[upstream.name]
        up_values = tick.angles[self._slices[upstream.name]].copy()  # committed this tick
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
        tick.flags.pop(self.axes[upstream.name].names[1], None)
        tick.flags.pop(self.axes[joint.name].names[1], None)
        self._commit(tick, world, upstream, up_values)
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
