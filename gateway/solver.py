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

A joint is measured only where both its segments' orientations are: from a
sensor on the segment, or through joints that are measured themselves (a
SmartSuit module's). A segment nothing measures (a dead tag) leaves the joint
above it unobserved, and the joints below it too: a hand's tag against a
forearm placed at the elbow's rest value gives no wrist angle. The trunk of a
body with no pelvis sensor is the exception: it stands on the upright model,
and the trunk dofs nothing measures say so (``unobserved`` with ``upright``:
what hangs below them stands on that reference, as on the pelvis).

Every dof comes with an uncertainty (degrees, about two standard deviations)
and, where its number is no plain measurement, its reasons (the pose
message's vocabulary, :mod:`bodynet.core.codecs.pose`): ``uncalibrated`` (an
orientation sensor it rests on has no T-pose mount yet), ``unobserved``
(nothing measures it, or an expected sensor above it has not delivered; with
``stale`` where a sensor it rests on stopped delivering, :meth:`BodySolver.set_stale`),
``held`` (gravity does not determine this tilt dof in this posture: its last
measured value, held) and ``clamped``. How well gravity determines a tilt dof
is geometric: how far the accelerometers' "up" moves per radian of that dof,
the others free (000 seed, section 3.3: an accelerometer cannot see rotation
about the vertical); the encoders and the chain model decide which dofs that
leaves to gravity (the seed's compensation, section 4.3). See
docs/observability.md.

Angles are split with continuity: at a gimbal lock (the middle dof at +/-90
degrees) or where the tilt has no unique answer (the segment along the
vertical), the ambiguous dof holds its last value instead of jumping. Angles
outside the range of motion are clamped and flagged. Positions come from
forward kinematics of the assembled configuration on the Pinocchio model's
chain (one compiled pass over every body of a solve, held to Pinocchio's own
in the tests), the body set on the floor: the pelvis above the origin, at
the height that puts the body's lowest point (a heel or a toe, standing) at
z = 0.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from bodynet.core import keys
from bodynet.core.calibration import OleCalibration
from bodynet.core.codecs.pose import (
    CLAMPED,
    HELD,
    REASONS,
    STALE,
    UNCALIBRATED,
    UNOBSERVED,
    UPRIGHT,
    WholeBodyEncoder,
    primary,
)
from bodynet.core.keys import Site
from bodynet.core.messages import STAMP_SPREAD_S, OleAccel, Quat, RawSample
from bodynet.core.profile import OLE_DOF, mount
from bodynet.core.skeleton import CALIBRATION_POSES, TPOSE, Joint, build_skeleton, part, rom
from bodynet.core.subject import Profile, QuatWxyz
from bodynet.gateway import kernels
from bodynet.gateway.columns import Frame
from bodynet.gateway.encoders import EncoderZero
from bodynet.kinematics.model import BodyModel, accel_axes

_REASON_ORDER = {r: i for i, r in enumerate(REASONS)}
#: a dof's reasons -> (in order, its flag): the few sets that occur, each worked out once
#: (every dof of an uncalibrated body has some, every tick)
_ORDERED: dict[frozenset[str], tuple[tuple[str, ...], str]] = {}


def _ole_name(site: Site) -> str:
    """The angle a SmartSuit module's encoder measures (``left_elbow_flexion_deg``)."""
    return f"{site.branch.side}_{site.name}_{OLE_DOF[site.name]}_deg"


def _order(reasons: frozenset[str]) -> tuple[tuple[str, ...], str]:
    """A dof's reasons in order, and its flag (the first); remembered (``_ORDERED``).
    ``stale`` comes with ``unobserved`` (the flag), also where a step of the solve
    took that reason away from the dof's others (:meth:`BodySolver._wrist_and_elbow`)."""
    order = _REASON_ORDER
    every = reasons | _UNOBS if STALE in reasons else reasons
    ordered = tuple(sorted(every, key=lambda x: (order.get(x, len(order)), x)))
    if len(_ORDERED) < 256:  # reasons are a handful of names: a few combinations
        _ORDERED[reasons] = (ordered, primary(ordered))
    return ordered, primary(ordered)


GIMBAL_COS = 1e-3  # |cos(middle angle)| below this is a gimbal lock
TILT_MIN = 0.05  # |component| below this: the tilt has no unique answer
MISS = 0.05  # a gravity fit further off than this (about 3 degrees) is no fit

#: Stated uncertainties (deg, about two standard deviations) of each kind of source.
#: a dof split from orientation sensors: at least what good IMUs claim, more for tags that
#: scattered more in their calibration window (``Profile.imu_scatter_deg``, :func:`tag_unc`)
UNC_TAG_DEG = 2.0
#: A three-dof joint's outer dofs near its gimbal lock: the tags' uncertainty over
#: ``|cos|`` of the middle dof (the split's Jacobian), at most this: any angle at all.
UNC_SPLIT_MAX_DEG = 180.0
UNC_OLE_DEG = 0.5  # an encoder's dof: 0.1 mm of travel is at most 0.23 deg, plus slack
#: an encoder's noise (rad, each sample's): a turn from its sample before not well above
#: it gives no rate (``kernels.ahead``): under 0.28 deg none, so a count (0.23 deg at
#: most) flickering at rest turns nothing
OLE_NOISE_RAD = math.radians(0.1)
#: a module's filtered "up": the accelerometer's bias and noise (about 0.03), and the
#: body's own acceleration up to about 0.07 g (a 90 degree lift of the arm in 3 s, at the
#: hand); faster movement errs by more where its acceleration is across gravity, which an
#: accelerometer cannot tell from tilt (see docs/observability.md)
UP_UNC_RAD = 0.1
DYN_FREE, DYN_GAIN = 0.05, 2.0  # beyond 5 % off 1 g, the body's own acceleration adds this much
#: A swinging limb (:class:`_Swing`): the time constants (s) of the tilt's smoothing
#: (each of three stages: angle, rate, acceleration) and of its running mean and sizes
SWING_TAU_S, SWING_SPAN_S = 0.06, 0.5
#: a shoulder's or hip's "up" turning slower than this (rad/s; a realistic sensor's noise
#: at 100 Hz is below 0.1) for this long (s) is at rest: its swing is over
SWING_STILL_RAD_S, SWING_STILL_S = 0.15, 0.1
#: a swing the accelerometer hardly saw is forgotten too once the "up" has been still
#: this long (s): longer than a walking thigh's still moments mid-swing (about 0.2 s)
SWING_BLIND_STILL_S = 1.0
SWING_GAIN_MIN = 0.35  # the accelerometer sees at least this share of a swing (see _Swing)
G = 9.81
UNC_MAX_DEG = 20.0  # a tilt dof gravity determines less well than this is not measured
SLEW_DEG = 5.0  # a held dof goes back to its measurement at most this far a tick
#: A body with no trunk sensor known is measured against the upright model only
#: after this long (source time): its other nodes announce themselves first.
SETTLE_NS = 1_000_000_000
HARM_FLOOR_RAD = 0.02  # a held dof's pull below this (the sensors' noise) tilts nothing below
#: Gauss-Newton's damping, (rad^-1)^2 in degree units: a dof whose "up" moves less
#: than about 0.1 per radian barely steps.
DAMPING = 0.01 * (math.pi / 180.0) ** 2

#: Raw keys :meth:`BodySolver.expect` remembers having taken (then it starts over).
MAX_TOLD = 4096
#: A site is stale once its latest sample is older than ``STALE_INTERVALS`` of its
#: usual intervals (:class:`Rhythm`), ``STALE_FLOOR_S`` at least (a Wi-Fi tracker's
#: jitter) and ``STALE_S`` at most (also until its interval is known): what rests on
#: its last sample is flagged (:meth:`BodySolver.set_stale`; the gateway's and
#: ``bodynet process``'s one rule). Frozen values are shown measured for that long.
STALE_S = 0.5
STALE_INTERVALS, STALE_FLOOR_S = 3.0, 0.05
#: A site's usual interval: the median of the mean intervals of its last
#: ``RHYTHM_SPANS`` runs of ``RHYTHM_RUN`` samples (a run's mean, not each interval:
#: the gateway takes samples in rounds, several of a site at one arrival time).
RHYTHM_RUN, RHYTHM_SPANS = 32, 5
#: A tick's orientations (and encoders' angles) are brought to its time (its newest
#: sample's) on each sensor's rate between its last two samples
#: (:func:`kernels.align_quats`, :meth:`BodySolver._encoder_now`): at most
#: ``ALIGN_AHEAD_NS`` (and twice that span) ahead, from a span of at most ``ALIGN_SPAN_NS``.
ALIGN_AHEAD_NS = round(STALE_FLOOR_S * 1e9)
ALIGN_SPAN_NS = 100_000_000
#: How fast a limb's rate changes, relative to itself (1/s, about 2 pi times the
#: motion's frequency): what an orientation brought forward states it may be off
#: by, over the time from its rate's span's middle to the tick's (kernels.align_quats).
ALIGN_CHANGE_PER_S = 12.0
#: What a turn left out states, as a rate, at most (deg/s): a foot's or hand's
#: fastest; two samples stamped a hair apart (a burst) give no rate.
ALIGN_RATE_MAX_DEG_S = 1000.0
#: ``STAMP_SPREAD_S`` by source id, in ns: what a sample stamped on its arrival
#: states for the time it may have been taken before (kernels.align_quats)
_SPREAD_BY_SOURCE = np.zeros(256)  # by source id (a byte)
for _source, _spread in STAMP_SPREAD_S.items():
    _SPREAD_BY_SOURCE[_source] = _spread * 1e9
#: A sample with no rate of its own (a sensor's first, or the first after a gap
#: over ``ALIGN_SPAN_NS``) states its age at the sensor's recent rate: the fastest
#: of its turns, each forgotten over this long (s; a gait cycle), else
#: ``ALIGN_RATE_MAX_DEG_S`` (:func:`kernels.recent_rate`).
ALIGN_RATE_MEMORY_S = 1.0


class Rhythm:
    """A site's usual interval between samples, learnt from their times (arrival
    live, the capture's offline), and ``after_s``: the age past which its latest
    sample is stale. :meth:`seen` costs a subtraction and a comparison per
    sample; the median is taken once a run (:meth:`end_run`)."""

    __slots__ = ("_next", "_spans", "_start", "after_s", "left")

    def __init__(self) -> None:
        self.after_s = STALE_S
        self.left = 0  # samples until this run ends (the first sample starts one)
        self._start = math.nan
        self._spans: list[float] = []
        self._next = 0  # where the next run's mean goes in ``_spans`` once full

    def seen(self, t: float) -> None:
        """A sample came at ``t`` (s)."""
        self.left -= 1
        if self.left < 0:
            self.end_run(t)

    def end_run(self, t: float) -> None:
        """A run of ``RHYTHM_RUN`` intervals ended at ``t`` and the next starts (the
        first sample only starts one, as one whose time went back does)."""
        mean = (t - self._start) / RHYTHM_RUN
        if mean >= 0.0:  # not NaN
            spans = self._spans
            if len(spans) < RHYTHM_SPANS:
                spans.append(mean)
            else:
                spans[self._next] = mean
                self._next = (self._next + 1) % RHYTHM_SPANS
            usual = sorted(spans)[len(spans) // 2]
            self.after_s = min(STALE_S, max(STALE_FLOOR_S, STALE_INTERVALS * usual))
        self._start, self.left = t, RHYTHM_RUN - 1


def fresh_samples(samples: Mapping[Site, Any], stale: Iterable[str]) -> Mapping[Site, Any]:
    """``samples`` (site -> sample) without the stale sites' (raw keys): what a
    heading's search or hold may feed on (a frozen sample is no motion)."""
    gone = set(stale)
    return {s: v for s, v in samples.items() if s.raw_key not in gone} if gone else samples


_UP = np.array([0.0, 0.0, 1.0])
_TRUNK = frozenset(part("trunk", "mid")[1])  # pelvis, thorax, head
_NOTHING: frozenset[str] = frozenset()
_UNCAL = frozenset({UNCALIBRATED})
_UNOBS = frozenset({UNOBSERVED})
_UPRIGHT = frozenset({UNOBSERVED, UPRIGHT})
_CLAMPED = frozenset({CLAMPED})
_STALE = frozenset({UNOBSERVED, STALE})
_UNCAL_STALE = _UNCAL | _STALE
#: a dof's reasons -> the same and uncalibrated, one shared set each (worked out once)
_PLUS_UNCAL: dict[frozenset[str], frozenset[str]] = {}


# Per-tick maths uses Pinocchio's rotation functions: scipy's Rotation objects cost
# hundreds of microseconds a call, which a solver at 100 Hz per body cannot pay.
def tag_unc(scatter_deg: Iterable[float]) -> float:
    """The stated uncertainty (deg, about two standard deviations) of a dof split
    from the relative rotation of tags whose calibration windows scattered this
    much (RMS of their turns, deg; 0 where not known): each tag's noise is
    about ``scatter / sqrt(3)`` about each axis, the two tags' add, and
    ``UNC_TAG_DEG`` is the floor (what a still window does not show: bias,
    soft tissue)."""
    var = sum(s * s for s in scatter_deg) / 3.0
    return max(UNC_TAG_DEG, 2.0 * math.sqrt(var))


def _rot(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    return pin.exp3(axis * angle_rad)  # type: ignore[no-any-return]


def _angle_deg(rot: np.ndarray) -> float:
    """Rotation angle of a rotation matrix (accurate near 0, unlike acos of the trace)."""
    return math.degrees(float(np.linalg.norm(pin.log3(rot))))


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


def _two_dofs(rot: np.ndarray, seq: str) -> np.ndarray:
    """The two angles (deg) of a two-dof joint, ``rot ~ R_i(a) R_j(b)``: ``a`` from
    where the child's own axis ``j`` points (about the parent's ``i``, to which
    it is perpendicular), then ``b`` about it. A measured rotation is never
    exactly of that form (noise, soft tissue); the Euler split took both angles
    from the third axis instead, and its first angle then carried the misfit
    times ``1 / cos b`` (an elbow pronated 60 deg: twice the tags' noise into its
    flexion)."""
    i, j, k = ("XYZ".index(c) for c in seq)
    e = 1.0 if (j - i) % 3 == 1 else -1.0
    a = math.atan2(e * rot[k, j], rot[j, j])
    ca, sa = math.cos(a), math.sin(a)
    # b from (R_i(a)^T rot) e_k: its i and k components
    col_i = rot[i, k]
    col_k = -e * sa * rot[j, k] + ca * rot[k, k]
    b = math.atan2(e * col_i, col_k)
    return np.degrees([a, b])


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

    def unc(self, rel: np.ndarray, unc_deg: float) -> np.ndarray:
        """The uncertainty (deg) of each dof :meth:`split` gives for ``rel``, a
        relative rotation known within ``unc_deg`` about each axis: that, but a
        three-dof joint's outer dofs carry it over ``|cos b|`` (the split's
        Jacobian: near the gimbal lock, ``b`` at +/-90, the two outer axes nearly
        coincide and only their sum is known), ``b`` taken ``unc_deg`` nearer the
        lock (where the truth may be: a measured ``b`` a few degrees off the lock
        stated a tenth of the outer dofs' error), at most ``UNC_SPLIT_MAX_DEG``."""
        out = np.full(len(self.axes), unc_deg)
        if len(self.axes) == 3:
            i, k = "XYZ".index(self.seq[0]), "XYZ".index(self.seq[2])
            b = math.asin(min(1.0, abs(float(rel[i, k]))))
            near = math.pi / 2 - b - math.radians(unc_deg)
            out[[0, 2]] = (min(UNC_SPLIT_MAX_DEG, unc_deg / math.sin(near)) if near > 0.0
                           else UNC_SPLIT_MAX_DEG)  # fmt: skip
        return out

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
        if n == 2:
            return _two_dofs(rel, self.seq) * self.signs  # type: ignore[no-any-return]
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
    """:meth:`JointAxes.split` for many joints at once, and their commit.

    An IMU body splits a dozen relative rotations per tick, and the gateway
    solves several bodies at a time: one compiled loop over the lot
    (gateway/kernels.py), a few microseconds a call and a quarter of one a
    joint. Rows at a gimbal lock go back to the scalar split, which holds the
    first angle there. The joints' axes and ranges of motion depend on the
    skeleton's structure only, not on its lengths, so one batch serves every
    body."""

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
        # the layouts of the sets of bodies solved together (BodySolver._solve_direct)
        self.layouts: dict[tuple[tuple[int | bytes, ...], ...], _Layout] = {}

    def prepare(self, rows: np.ndarray) -> _Rows:
        """What :meth:`split` and :meth:`commit` take of the batch for joints
        ``rows``: worked out once for a set of rows that comes back tick after tick."""
        return _Rows(self, rows)

    def split(self, rows: np.ndarray, rel: np.ndarray, previous: np.ndarray,
              prep: _Rows | None = None, unc: np.ndarray | None = None,
              ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """Angles (deg, (m, 3), absent dofs 0) of joints ``rows`` for relative
        rotations ``rel`` (m, 3, 3), continuous with ``previous`` (m, 3), and
        their uncertainties (:meth:`JointAxes.unc`) for relative rotations known
        within ``unc`` (m, 3: per dof, the same across a row; None: 1 deg)."""
        p = prep or self.prepare(rows)
        base = unc if unc is not None else np.ones((len(rows), 3))
        chosen, gimbal, stated = kernels.split_rows(rel, previous, p.i, p.j, p.k, p.e, p.signs,
                                                    p.n, p.lo, p.hi, GIMBAL_COS, base,
                                                    UNC_SPLIT_MAX_DEG)  # fmt: skip
        self.unlock(rows, gimbal, chosen, rel, previous)
        return chosen, stated

    def unlock(self, rows: np.ndarray, gimbal: np.ndarray, chosen: np.ndarray, rel: np.ndarray,
               previous: np.ndarray) -> None:  # fmt: skip
        """The rows at a gimbal lock (``gimbal``) of a split ``chosen`` split again
        by the scalar code, which holds the first angle there."""
        for r in np.flatnonzero(gimbal).tolist():
            chosen[r] = self.axes[rows[r]].split(rel[r], previous[r])

    def commit(
        self,
        rows: np.ndarray,
        values: np.ndarray,
        calibration_inv: np.ndarray,
        relative: np.ndarray,
        prep: _Rows | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What committing a joint does, for many at once: angles (m, 3) clamped to
        the range of motion, which were clamped, the joint rotations (m, 3, 3) and
        each joint's total rotation (deg) from the calibration pose (its rotation
        there inverted: ``calibration_inv``, (m, 3, 3)), taken from the measured
        relative rotations ``relative`` (m, 3, 3), not from the clamped dofs: how a
        rotation splits into dofs is ambiguous at a gimbal lock, the rotation is not."""
        p = prep or self.prepare(rows)
        return kernels.commit_rows(values, p.lo, p.hi, p.axis, calibration_inv, relative)  # type: ignore[no-any-return]


class _Rows:
    """The batch's constants gathered for some joint rows (:meth:`_SplitBatch.prepare`)."""

    __slots__ = ("axis", "e", "hi", "i", "j", "k", "lo", "n", "signs", "unused")

    def __init__(self, batch: _SplitBatch, rows: np.ndarray) -> None:
        self.i, self.j, self.k, self.e = batch.i[rows], batch.j[rows], batch.k[rows], batch.e[rows]
        self.signs, self.n, self.unused = batch.signs[rows], batch.n[rows], batch.unused[rows]
        self.lo, self.hi = batch.lo[rows], batch.hi[rows]
        self.axis = batch.axis[rows]  # (rows, 3 dofs, xyz)


class _Plan:
    """One body's joints between two of its measured segments (or the root and
    one), for :meth:`BodySolver._solve_direct`: their ``rows`` in the batch
    arrays, the indices in the measured segments of each one's ``parents`` (-1:
    the unmeasured pelvis) and ``children``, where its dofs sit in the angle
    vector (``index``) and its calibration pose's rotation inverted
    (``cal_inv``, (rows, 3, 3)), and how well its two tags give its relative
    rotation (``unc``, deg, (rows, 3): :func:`tag_unc`). What a batch of bodies
    gathers from each (:class:`_Layout`), worked out once per set of measured
    segments and their tags' scatter."""

    __slots__ = ("cal_inv", "children", "index", "parents", "rows", "shape", "unc")

    def __init__(self, rows: np.ndarray, parents: np.ndarray, children: np.ndarray,
                 index: np.ndarray, cal_inv: np.ndarray, unc: np.ndarray,
                 segments: int = 0) -> None:  # fmt: skip
        self.rows, self.parents, self.children = rows, parents, children
        self.index, self.cal_inv, self.unc = index, cal_inv, unc
        # which joints the plan has, of its ``segments`` measured: one object for every
        # plan of the same joints (bodies of one kind), which a batch's layout is kept
        # by; not their numbers (each body's tags scatter by their own calibration)
        key = (segments, *(a.tobytes() for a in (rows, parents, children)))
        if len(_SHAPES) >= 1024:
            _SHAPES.clear()
        self.shape = _SHAPES.setdefault(key, key)


#: every plan's shape (:class:`_Plan`), one object each
_SHAPES: dict[tuple[int | bytes, ...], tuple[int | bytes, ...]] = {}
_NO_PLAN = _Plan(*(np.zeros(0, dtype=int),) * 3, np.zeros((0, 3), dtype=int),
                 np.zeros((0, 3, 3)), np.zeros((0, 3)))  # fmt: skip


class _Layout:
    """Where the direct joints of a set of bodies' ticks sit in the batch arrays
    (:meth:`BodySolver._solve_direct`), joined from the bodies' plans: kept by
    their shapes (which sensors deliver changes rarely, and bodies of one kind
    share a shape), so that unsynchronised bodies, which come due in ever other
    sets, find theirs: joining the plans took some 220 us of a round of twenty
    bodies' 1,700 (2026-12-07). The batch keeps them (``_SplitBatch.layouts``),
    for every solver of its skeleton. The plans' numbers (``cal_inv``, ``unc``)
    are each body's, joined each round."""

    __slots__ = ("children", "index", "owner", "parents", "prep", "rows", "spans", "unc_index")

    def __init__(self, ticks: Sequence[_Tick], batch: _SplitBatch) -> None:
        plans = [t.plan for t in ticks]
        counts = [len(p.rows) for p in plans]
        sizes = [len(t.segs) for t in ticks]
        owner = np.repeat(np.arange(len(ticks)), counts)
        offsets = np.repeat(np.cumsum([0, *sizes[:-1]]), counts)
        rows = np.concatenate([p.rows for p in plans])
        parents = np.concatenate([p.parents for p in plans])
        self.children = np.concatenate([p.children for p in plans]) + offsets
        # an unmeasured pelvis (-1) is the identity, put after every measured segment
        self.parents = np.where(parents >= 0, parents + offsets, sum(sizes))
        self.owner, self.rows = owner, rows
        self.index = np.concatenate([p.index for p in plans])
        self.prep = batch.prepare(rows)
        self.unc_index = [p.index for p in plans]
        ends = np.cumsum(counts).tolist()
        self.spans = [slice(end - c, end) for end, c in zip(ends, counts, strict=True)]


@dataclass(frozen=True)
class OutputNames:
    """The names of a body's outputs, in the skeleton's order."""

    angles: tuple[str, ...]
    joints: tuple[str, ...]
    segments: tuple[str, ...]
    joint_segment: tuple[int, ...]  # each joint's child segment: its origin is the joint centre

    @cached_property
    def encoder(self) -> WholeBodyEncoder:
        """The whole-body message's encoder for these names (worked out once)."""
        return WholeBodyEncoder(self.angles, self.joints, self.segments, self.joint_segment)


@dataclass(slots=True)
class BodyOutput:
    """One tick of one body: every joint angle and every segment pose, as arrays
    in the order of ``names``; the mappings are views for readers. (Not frozen,
    as the raw samples are not: one is made per body and tick.)"""

    t_ns: int
    names: OutputNames
    angles: np.ndarray  # (angles,) degrees
    rel: np.ndarray  # (joints,) each joint's total rotation (deg) from the calibration pose
    flags: Mapping[str, str]  # angle -> its first reason (pose.primary)
    positions: np.ndarray  # (segments, 3) metres
    quats: np.ndarray  # (segments, 4) unit quaternions w, x, y, z, w >= 0
    sources: Mapping[str, int]  # raw key -> source t_ns of the sample used
    reasons: Mapping[str, tuple[str, ...]]  # angle -> every reason, in pose.REASONS order
    unc: np.ndarray  # (angles,) uncertainty (deg), NaN where no measurement stands behind it

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


class _EncoderHistory(NamedTuple):
    """An encoder's last two samples (:meth:`BodySolver._encoder_now`): their times
    (``kernels.NO_TIME``: none) and angles (deg), the calibration and zero they
    were read with, and its recent rate (rad/s, :func:`kernels.recent_rate`)."""

    previous_ns: int
    previous: float
    latest_ns: int
    latest: float
    cal: OleCalibration
    counts: int
    recent: float


@dataclass
class _Memory:
    last: np.ndarray | None = None  # the angle vector of the last tick (None before one)
    up: dict[str, np.ndarray] = field(default_factory=dict)  # filtered "up" of each accelerometer
    held: set[str] = field(default_factory=set)  # tilt dofs held (or unobserved) last tick
    seen: set[str] = field(default_factory=set)  # tilt dofs gravity has determined at least once
    swing: dict[str, _Swing] = field(default_factory=dict)  # each shoulder or hip module's
    expected: set[str] = field(default_factory=set)  # segments an orientation sensor is on
    first_t_ns: int = -1  # the body's first tick (source time)
    encoders: dict[str, _EncoderHistory] = field(default_factory=dict)  # by raw key


_NO_FRAMES = np.zeros((0, 3, 3))
_NO_QUATS = np.zeros((0, 4))
_NO_RESIDUAL = np.zeros(0)
_NO_ROWS = np.zeros(0, dtype=int)


def _carry_history(old: _Sorted | None, new: _Sorted) -> None:
    """A new sorting's orientation sensors keep the last two samples the old one
    had of them (:func:`kernels.align_quats`): a site that joins or goes stale
    re-sorts the body, and its others' rates go on."""
    n = len(new.used)
    new.times = np.full((n, 2), kernels.NO_TIME, dtype=np.int64)
    new.held = np.zeros((n, 2, 4))
    new.recent = np.full(n, math.inf)
    if old is not None and len(old.used):
        was = {site: i for i, site in enumerate(old.used)}
        for i, site in enumerate(new.used):
            j = was.get(site)
            if j is not None:
                new.times[i], new.held[i], new.recent[i] = old.times[j], old.held[j], old.recent[j]


class _Swing:
    """How fast a module's measured "up" swings (in its sensor frame, so across
    the limb: the tilt gravity sees), and how far the swing's own acceleration
    may tilt that "up" (:meth:`error_rad`).

    An accelerometer ``r`` from the joint of a limb swinging at angular
    acceleration ``alpha`` feels ``r alpha`` across the limb besides gravity: the
    seed's tilt (eq. 4-7) holds for a static sensor only. At the ends of a swing
    that acceleration opposes gravity's own across the limb, so the measured tilt
    is the true one shrunk by ``1 - r W^2 / g`` (a swing of angular frequency
    ``W``; 0.15 m down the upper arm in a 1 Hz walk: 0.41, 0.21 m down the
    thigh: 0.16). Subtracting the acceleration is no cure: the true tilt from
    the measured one solves ``x = m + r x'' / g``, unstable (a root at
    ``sqrt(g/r)``). So the swing's size is estimated instead: ``W^2`` from the
    measured tilt's acceleration against its rate (their ratio does not shrink),
    the acceleration corrected by that gain. Three exponential stages smooth
    direction, rate and acceleration (``SWING_TAU_S``); the sizes are running
    mean squares (``SWING_SPAN_S``), forgotten once the "up" has been still
    (its rate below ``SWING_STILL_RAD_S``, the sensor's noise, for
    ``SWING_STILL_S``): a limb at rest has no swing, however fast its last was."""

    __slots__ = ("acc", "acc2", "quiet", "r", "rate", "rate2", "smooth", "still", "t")

    def __init__(self, t: float, up: list[float], r: float) -> None:
        self.t, self.r = t, r  # r: the module's distance (m) from the joint
        self.smooth = list(up)
        self.rate, self.acc = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        self.acc2 = self.rate2 = self.still = self.quiet = 0.0

    def update(self, t: float, up: list[float], steady: bool) -> None:
        """Take this tick's "up" (a unit vector) at source time ``t`` (s);
        ``steady``: the acceleration's size showed no motion of the body's own."""
        dt = t - self.t
        if dt <= 0.0:
            return
        if dt > SWING_SPAN_S:  # a gap: start over
            self.__init__(t, up, self.r)  # type: ignore[misc]
            return
        self.t = t
        b = 1.0 - math.exp(-dt / SWING_TAU_S)
        acc2 = rate2 = 0.0
        for i in (0, 1, 2):
            smooth = self.smooth[i] + b * (up[i] - self.smooth[i])
            rate = self.rate[i] + b * ((smooth - self.smooth[i]) / dt - self.rate[i])
            acc = self.acc[i] + b * ((rate - self.rate[i]) / dt - self.acc[i])
            self.smooth[i], self.rate[i], self.acc[i] = smooth, rate, acc
            acc2 += acc * acc
            rate2 += rate * rate
        # a swing the accelerometer hardly sees (its gain near 0) can leave the "up"
        # still while the limb moves: no rest then
        still = steady and rate2 < SWING_STILL_RAD_S**2 and self.error_rad() < math.inf
        self.still = self.still + dt if still else 0.0
        # blind or not, an "up" still for long is a limb at rest (else a swing too fast
        # to see would hold its dofs for ever after: a sudden move, then rest)
        quiet = steady and rate2 < SWING_STILL_RAD_S**2
        self.quiet = self.quiet + dt if quiet else 0.0
        if self.still >= SWING_STILL_S or self.quiet >= SWING_BLIND_STILL_S:  # at rest: no
            # swing (and the smoothing's ringing gone)
            self.acc = [0.0, 0.0, 0.0]
            self.acc2 = self.rate2 = 0.0
            return
        m = 1.0 - math.exp(-dt / SWING_SPAN_S)
        self.acc2 += m * (acc2 - self.acc2)
        self.rate2 += m * (rate2 - self.rate2)

    def error_rad(self) -> float:
        """How far (rad, a swing's peak) the swing's acceleration may tilt the
        module's "up"; ``inf`` where the accelerometer sees less than
        ``SWING_GAIN_MIN`` of the swing."""
        acc2, rate2, r = self.acc2, self.rate2, self.r
        if acc2 <= 0.0:
            return 0.0
        w2 = acc2 / rate2 if rate2 > 0.0 else math.inf
        gain = abs(1.0 - r * w2 / G)
        if gain < SWING_GAIN_MIN:
            return math.inf
        # peaks of a sine: sqrt(2) its root mean square
        return r * (math.sqrt(2 * acc2) / gain + 2 * rate2 / gain**2) / G


class _Tick:
    """One body's working state during one solve: plain data that its
    :class:`BodySolver` fills (:meth:`BodySolver._gather`) and reads."""

    __slots__ = ("_measured", "angles", "direct_rot", "direct_rows", "harm", "held_tilt", "last",
                 "modules", "plan", "quats", "reasons", "rel", "residual", "rests", "segments",
                 "segs", "solver", "sort", "sources", "stale", "stale_modules", "t_ns", "unc",
                 "uncal", "unknown")  # fmt: skip

    def __init__(self, solver: BodySolver, last: np.ndarray | None, sort: _Sorted) -> None:
        self.solver = solver
        self.last = last  # the angle vector of the body's last tick (None before one)
        self.sort = sort  # how its samples sort (BodySolver._sort): these are its
        self.segs, self.plan = sort.segs, sort.plan
        self.unknown, self.uncal = sort.unknown, sort.uncal
        self.stale, self.stale_modules = sort.stale_segs, sort.stale_modules
        self.quats = _NO_QUATS  # the quaternions of ``sort.used``, at the tick's time (n, 4)
        self.residual = _NO_RESIDUAL  # how far each may be off for that (deg, n)
        self.segments = _NO_FRAMES  # their segments' world rotations (n, 3, 3)
        self.modules: dict[str, tuple[Site, OleAccel]] = {}  # SmartSuit modules by segment
        self.sources: dict[str, int] = {}  # raw key -> the source time of its sample
        self.t_ns = 0
        self._measured: dict[str, np.ndarray] | None = None
        # the joints split from two sensors: their rows and rotations
        self.direct_rows: np.ndarray = _NO_ROWS
        self.direct_rot: np.ndarray = _NO_FRAMES
        self.angles = _NO_RESIDUAL  # the skeleton's angle vector (+1: see angle_index)
        self.rel = _NO_RESIDUAL
        self.unc = _NO_RESIDUAL  # each angle's uncertainty (deg), NaN: none
        # angle -> why it is no plain measurement (frozen: the same sets serve tick after tick)
        self.reasons: dict[str, frozenset[str]] = {}
        self.rests: dict[str, frozenset[str]] = {}  # segment -> what its orientation rests on
        # segment -> how far (rad) held dofs above it may tilt it from what gravity says
        self.harm: dict[str, float] = {}
        self.held_tilt = 0.0  # the harm of the dofs held in the joint being solved

    @property
    def measured(self) -> dict[str, np.ndarray]:
        """Segment -> its world orientation, where a sensor measures it: made when
        first read (a body whose joints are all between two sensors never does)."""
        if self._measured is None:
            self._measured = dict(zip(self.segs, self.segments, strict=True))
        return self._measured


class _Sorted:
    """How a body's tick sorts its samples, worked out from which sites deliver
    which kind of reading (:meth:`BodySolver._sort`): the same tick after tick,
    so a tick only takes the numbers (sorting fifteen samples cost more than a
    tenth of a hot solve)."""

    __slots__ = ("flagged", "held", "keys", "kinds", "lefts", "modules", "mounts", "pelvis",
                 "plan", "reasons", "recent", "rows", "scatter", "scatter_rad", "seen", "segs",
                 "sites", "stale", "stale_modules", "stale_segs", "tainted", "times", "uncal",
                 "unknown", "upright", "used")  # fmt: skip

    def __init__(self, sites: tuple[Site, ...], kinds: tuple[type, ...],
                 stale: frozenset[str]) -> None:  # fmt: skip
        self.sites, self.kinds = sites, kinds
        self.stale = stale  # the stale raw keys it was sorted with (BodySolver.set_stale)
        self.stale_segs: set[str] = set()  # segments of ``segs`` whose sensor is stale
        self.stale_modules: set[str] = set()  # segments whose SmartSuit module is stale
        self.keys: list[str] = []  # each site's raw key
        self.segs: list[str] = []  # segments with an orientation sensor (the first key wins)
        self.seen: frozenset[str] = _NOTHING  # and as a set
        self.used: list[Site] = []  # the orientation sensors of ``segs``, in that order
        self.scatter: list[float] = []  # and each one's in calibration (deg, 0: not known)
        self.rows = _NO_ROWS  # where their samples are among the tick's
        self.unknown: set[str] = set()  # segments whose sensor's heading is not known
        self.uncal: set[str] = set()  # segments whose orientation sensor has no mount yet
        self.modules: list[tuple[str, int]] = []  # SmartSuit modules: segment, sample
        # the used sensors' turns into the body's heading and mounts' inverses, stacked
        self.lefts, self.mounts = _NO_FRAMES, _NO_FRAMES
        # the joints between two of ``segs`` (see _direct_plan)
        self.plan = _NO_PLAN
        self.flagged: list[str] | None = None  # BodySolver._flag_uncalibrated's dofs
        self.tainted: frozenset[str] | None = None  # BodySolver._tainted's segments
        self.pelvis = -1  # where the pelvis is in ``segs`` (-1: no sensor on it)
        # the trunk's segments below an unmeasured pelvis that nothing measures either:
        # the upright model, as the pelvis (BodySolver._rests); see BodySolver._sort
        self.upright: frozenset[str] = _NOTHING
        # what the pelvis rests on -> the reasons of the joints of ``plan``
        # (BodySolver._direct_reasons)
        self.reasons: dict[frozenset[str], dict[str, frozenset[str]]] = {}
        # each of ``used``'s last two samples: times (n, 2) and quaternions (n, 2, 4),
        # what kernels.align_quats brings a tick's orientations to one time with
        self.times = np.full((0, 2), kernels.NO_TIME, dtype=np.int64)
        self.held = np.zeros((0, 2, 4))
        self.recent = np.zeros(0)  # and each one's recent rate (rad/s, kernels.recent_rate)
        self.scatter_rad = np.zeros(0)  # ``scatter`` in radians


def solve_bodies(work: Sequence[tuple[BodySolver, Mapping[Site, RawSample]]]) -> list[BodyOutput]:
    """One tick of each of several bodies: :meth:`BodySolver.solve_many`."""
    return BodySolver.solve_many(work)


class _Shape:
    """What a solver works out from its profile's segment lengths and calibration
    pose alone, and never changes: the skeleton, its Pinocchio model, the joints'
    axes and their batch, the calibration pose's rotations, the outputs' names.
    Solvers of the same lengths and pose share one (:func:`_shape`): building
    them cost a new body's solver 2.5 ms, and a gateway meeting twenty suits at
    once some 130 ms more before its first pose. Shared: nothing may write to them."""

    __slots__ = ("accel_axes", "angle_at", "axes", "batch", "by_child", "calibration",
                 "calibration_inv", "lengths", "model", "names", "skeleton", "slices")  # fmt: skip

    def __init__(self, lengths: Mapping[str, float], pose: str) -> None:
        self.skeleton = skeleton = build_skeleton(lengths)
        self.model = BodyModel(skeleton)
        chain = self.model.chain
        #: the lengths as a batch of one body (``BodySolver._outputs``)
        self.lengths = (np.array([chain.root_z]), chain.offsets[None], chain.floor_points[None])
        self.axes = {j.name: JointAxes.of(j) for j in skeleton.joints}
        angles = CALIBRATION_POSES[pose]
        self.calibration = {
            j.name: self.axes[j.name].matrix(np.array([angles.get(n, 0.0)
                                                       for n in j.angle_names()]))
            for j in skeleton.joints
        }  # fmt: skip
        self.batch = _SplitBatch([self.axes[j.name] for j in skeleton.joints])
        self.calibration_inv = np.array([self.calibration[j.name].T for j in skeleton.joints])
        segments = skeleton.segments
        self.names = OutputNames(
            skeleton.angle_names(),
            tuple(j.name for j in skeleton.joints),
            segments,
            tuple(segments.index(j.child) for j in skeleton.joints),
        )
        self.slices = {
            joint.name: slice(start, start + len(joint.dofs))
            for joint, start in zip(skeleton.joints, self.batch.angle_index[:, 0].tolist(),
                                    strict=True)
        }  # fmt: skip
        self.angle_at = {n: i for i, n in enumerate(self.names.angles)}
        self.by_child = {j.child: j for j in skeleton.joints}
        # a SmartSuit accelerometer's axes on each segment (its joint's flexion axis)
        self.accel_axes = {j.child: accel_axes(np.array(skeleton.directions[j.child]),
                                               self.axes[j.name].axes[0])
                           for j in skeleton.joints}  # fmt: skip


@lru_cache(maxsize=64)
def _shape(lengths: tuple[tuple[str, float], ...], pose: str) -> _Shape:
    """The shared :class:`_Shape` of these lengths (over the defaults) and pose."""
    return _Shape(dict(lengths), pose)


class BodySolver:
    """Joint angles and poses of one body from its latest raw samples.

    It is the one owner of the body's state between ticks (the last angles, the
    accelerometers' filtered "up", the wrists' tilt, the sites and plans it has
    worked out); a tick's working state (:class:`_Tick`) is plain data it fills.
    ``solve`` does one tick of this body; :meth:`solve_many` does one tick of
    many, with the array work shared. Both run the same code."""

    def __init__(self, profile: Profile | None = None) -> None:
        self.profile = profile or Profile()
        shape = _shape(tuple(sorted(self.profile.lengths.items())), self.profile.pose)
        self.skeleton, self.model, self.axes, self.names = (shape.skeleton, shape.model,
                                                            shape.axes, shape.names)  # fmt: skip
        self._calibration, self._calibration_inv = shape.calibration, shape.calibration_inv
        self._batch, self._slices, self._angle_at = shape.batch, shape.slices, shape.angle_at
        self._by_child, self._accel_axes = shape.by_child, shape.accel_axes
        self._lengths = shape.lengths
        #: per angle (and the absent column), how well the tags' headings are known
        #: where a three-dof joint's assumption holds them (deg; None: nowhere)
        self._heading_unc: np.ndarray | None = None
        self._memory = _Memory()
        self._all_mounted = False  # assume_calibrated
        self._sites: dict[Site, tuple[str, np.ndarray, str, bool, np.ndarray, bool, bool]] = {}
        self._plans: dict[tuple[tuple[str, ...], tuple[float, ...]], _Plan] = {}
        # the sensors' stacked frames (turns, mounts) by the sensors used, see _frames
        self._stacked: dict[tuple[Site, ...], tuple[np.ndarray, np.ndarray]] = {}
        self._told: set[str] = set()  # raw keys ``expect`` has taken (parsing 15 cost 15 us)
        self._sorted: _Sorted | None = None  # how the last tick's samples sorted
        self._resort = False  # the profile changed: sort again (the samples' history kept)
        self._stale: frozenset[str] = frozenset()  # see set_stale
        #: each SmartSuit encoder's zero by raw key (gateway/encoders.py; absent: its
        #: node's power-on), shared with the gateway, which finds a zero lost
        self.encoder_zeros: Mapping[str, EncoderZero] = {}

    def _site(self, site: Site) -> tuple[str, np.ndarray, str, bool, np.ndarray, bool, bool]:
        """The segment a sensor rides on, its mount's inverse (for orientation
        sensors), its raw key, whether it is a SmartSuit module, the turn from its
        reference frame to the body's (``Rz(-heading)``, see gateway/heading.py),
        whether that heading is known, and whether its mount is calibrated (an
        orientation sensor's T-pose mount exists)."""
        known = self._sites.get(site)
        if known is None:
            key = site.raw_key
            mounts = self.profile.imu_mounts
            w, x, y, z = mounts.get(key, (1.0, 0.0, 0.0, 0.0))
            known = self._sites[site] = (
                mount(site).segment, _matrix((w, x, y, z)).T, key, site.name in OLE_DOF,
                _rot(np.array([0.0, 0.0, 1.0]), -math.radians(self.profile.heading_of(key))),
                self.profile.heading_known(key), self._all_mounted or key in mounts,
            )  # fmt: skip
        return known

    def _flag_uncalibrated(self, tick: _Tick) -> None:
        """Flag ``uncalibrated`` every dof that a sensor of unknown heading drives:
        the joints next to its segment, and down the chain while the segments'
        orientations come from their parents (SmartSuit modules). Which dofs
        those are follows from the sites that deliver (worked out once for them),
        except an unobserved dof, which keeps that flag alone."""
        sort = tick.sort
        if sort.flagged is None:
            sort.flagged = self._driven_by_unknown(tick)
        reasons, plus = tick.reasons, _PLUS_UNCAL
        for name in sort.flagged:
            why = reasons.get(name)
            if why is None:
                reasons[name] = _UNCAL
            elif UNOBSERVED not in why:
                flagged = plus.get(why)
                if flagged is None:
                    flagged = why | _UNCAL
                    if len(plus) < 256:  # a handful of names: a few combinations
                        plus[why] = flagged
                reasons[name] = flagged

    def _driven_by_unknown(self, tick: _Tick) -> list[str]:
        """The dofs that the tick's sensors of unknown heading drive (see
        :meth:`_flag_uncalibrated`), but an encoder's: it measures its dof whatever
        the heading of the segments around it (where a tag beside it gives that dof
        too, :meth:`_merge_module` takes the tag's for uncalibrated)."""
        tainted = self._tainted(tick)
        names = []
        for joint in self.skeleton.joints:
            if joint.parent in tainted or joint.child in tick.unknown:
                module = tick.modules.get(joint.child)
                absolute = _ole_name(module[0]) if module is not None else None
                names += [name for name in self.axes[joint.name].names if name != absolute]
        return names

    def _tainted(self, tick: _Tick) -> frozenset[str]:
        """The segments whose orientation rests on a tag of unknown heading: those
        tags' own and the unmeasured ones below them (worked out once per sort)."""
        sort = tick.sort
        if sort.tainted is None:
            tainted = set(tick.unknown)
            for joint in self.skeleton.joints:
                if joint.parent in tainted and joint.child not in tick.sort.seen:
                    tainted.add(joint.child)
            sort.tainted = frozenset(tainted)
        return sort.tainted

    def set_profile(self, profile: Profile) -> None:
        """Take a profile of the same body (lengths, calibration pose) whose mounts or
        headings changed, keeping the body's memory (the last angles...): a heading
        that drifts is corrected tick by tick without starting the body again."""
        if profile.lengths != self.profile.lengths or profile.pose != self.profile.pose:
            raise ValueError("set_profile keeps the body: new lengths or pose need a new solver")
        self.profile = profile
        self._sites.clear()
        self._stacked.clear()
        self._resort = True

    def set_heading_unc(self, by_segment: Mapping[str, float]) -> None:
        """How well each segment's tag heading is known against its parent's (deg,
        about two standard deviations; ``JointDrift.link_unc``): the dofs of the
        joint above each such segment carry it, with the tags' own, in ``unc``."""
        if not by_segment:
            self._heading_unc = None
            return
        extra = np.zeros(len(self.names.angles) + 1)
        for joint in self.skeleton.joints:
            if joint.child in by_segment:
                for name in self.axes[joint.name].names:
                    extra[self._angle_at[name]] = by_segment[joint.child]
        self._heading_unc = extra

    def solve(self, samples: Mapping[Site, RawSample]) -> BodyOutput:
        """Angles and poses from the latest sample of each site."""
        return BodySolver.solve_many([(self, samples)])[0]

    @staticmethod
    def solve_many(work: Sequence[tuple[BodySolver, Mapping[Site, RawSample]]]) -> list[BodyOutput]:
        """One tick of each of several bodies: angles and poses from the latest
        sample of each site.

        The array work of every body is done together: sensor orientations, the
        relative rotations of the joints between two sensors, their split into
        dofs, clamping and total rotations (one compiled loop), and forward
        kinematics with the floor and the canonical quaternions (another).
        What is left per body is gathering its samples, the joints that SmartSuit
        modules measure (scalar code) and its output's flags. The solvers must
        share one skeleton structure (any segment lengths)."""
        if not work:
            return []
        ticks = [solver._gather(samples) for solver, samples in work]
        first = work[0][0]
        angles = np.zeros((len(ticks), len(first.names.angles) + 1))
        rel = np.zeros((len(ticks), len(first.names.joints)))
        unc = np.full((len(ticks), len(first.names.angles) + 1), math.nan)
        for b, tick in enumerate(ticks):
            tick.angles, tick.rel, tick.unc = angles[b], rel[b], unc[b]
        roots = np.full(len(ticks), -1)  # each body's pelvis in ``segments`` (-1: upright)
        if any(len(t.quats) for t in ticks):
            if len(ticks) > 1:
                segments = np.concatenate([t.segments for t in ticks])
                residual = np.concatenate([t.residual for t in ticks])
            else:
                segments, residual = ticks[0].segments, ticks[0].residual
            start = 0
            for b, tick in enumerate(ticks):
                if tick.sort.pelvis >= 0:
                    roots[b] = start + tick.sort.pelvis
                start += len(tick.segs)
            first._solve_direct(ticks, segments, residual, angles, rel, unc)
        else:
            segments = _NO_FRAMES
        for tick in ticks:
            tick.solver._solve_rest(tick)
            if tick.unknown:
                tick.solver._flag_uncalibrated(tick)
        return first._outputs(ticks, angles, segments, roots)

    def _gather(self, samples: Mapping[Site, RawSample]) -> _Tick:
        """A new tick of this body: its samples sorted by kind, against its last
        angles. The gateway's are a :class:`Frame` already (arrays, no sample
        read); other mappings are made one."""
        frame = Frame.of(samples)
        sites, kinds = frame.sites, frame.kinds
        sort = self._sorted
        if sort is None or (sort.sites is not sites and sort.sites != sites) or \
                sort.kinds != kinds or sort.stale is not self._stale or self._resort:  # fmt: skip
            sort = self._sorted = self._sort(sites, kinds)
            self._resort = False
        tick = _Tick(self, self._memory.last, sort)
        stamps = frame.t_ns.tolist()
        tick.sources = dict(zip(sort.keys, stamps, strict=True))
        tick.t_ns = t_ns = max(max(stamps, default=0), 0)
        if self._memory.first_t_ns == -1:
            self._memory.first_t_ns = t_ns
        tick.modules = {seg: (sites[i], frame.reading(i).reading)  # type: ignore[misc]
                        for seg, i in sort.modules}  # fmt: skip
        if sort.segs:
            # each orientation turned on at its own rate to the tick's time: tags on
            # timers of their own sample up to a period apart, and a shank turning at
            # 350 deg/s against its thigh's sample 15 ms older is 5 deg off
            tick.quats, tick.residual, tick.segments = kernels.aligned_segments(
                frame.floats, frame.ints, sort.rows, _SPREAD_BY_SOURCE, t_ns, sort.times,
                sort.held, sort.recent, sort.scatter_rad, ALIGN_SPAN_NS, ALIGN_AHEAD_NS,
                ALIGN_CHANGE_PER_S, ALIGN_RATE_MAX_DEG_S, ALIGN_RATE_MEMORY_S, sort.lefts,
                sort.mounts,
            )  # fmt: skip
            self._memory.expected.update(sort.segs)
        return tick

    def _sort(self, sites: tuple[Site, ...], kinds: tuple[type, ...]) -> _Sorted:
        """How a tick of samples from ``sites``, of readings ``kinds``, sorts (see
        :class:`_Sorted`): each segment's orientation sensor of the first raw key
        measures it, SmartSuit modules by segment.

        The sensors are taken in the order of their raw keys, not of ``sites``
        (the order their first samples came in): bodies of one kind then sort
        alike, and a batch of them finds its layout kept (``_solve_direct``),
        however their nodes' phases fell when they started."""
        stale = self._stale
        sorted_ = _Sorted(sites, kinds, stale)
        seen: set[str] = set()
        rows: list[int] = []  # the used sensors' samples among the tick's
        known = [self._site(site) for site in sites]
        sorted_.keys = [k[2] for k in known]
        for i in sorted(range(len(sites)), key=sorted_.keys.__getitem__):
            site, kind = sites[i], kinds[i]
            seg, _, key, module, _, heading_known, calibrated = known[i]
            if kind is Quat:
                if seg not in seen:
                    seen.add(seg)
                    sorted_.segs.append(seg)
                    rows.append(i)
                    sorted_.used.append(site)
                    sorted_.scatter.append(self.profile.imu_scatter_deg.get(key, 0.0))
                    if not heading_known:
                        sorted_.unknown.add(seg)
                    if not calibrated:
                        sorted_.uncal.add(seg)
                    if key in stale:
                        sorted_.stale_segs.add(seg)
            elif module:
                sorted_.modules.append((seg, i))
                if key in stale:
                    sorted_.stale_modules.add(seg)
        sorted_.seen = frozenset(seen)
        if "pelvis" not in seen:
            # no sensor on the pelvis: the trunk stands on the upright model as far
            # up as nothing measures it (what the lumbar and neck are taken against)
            upright = {"pelvis"}
            unsensed = _TRUNK - seen - {seg for seg, _ in sorted_.modules}
            for joint in self.skeleton.joints:
                if joint.parent in upright and joint.child in unsensed:
                    upright.add(joint.child)
            sorted_.upright = frozenset(upright)
        if sorted_.segs:
            sorted_.rows = np.array(rows, dtype=np.int64)
            _carry_history(self._sorted, sorted_)
            sorted_.scatter_rad = np.radians(sorted_.scatter)
            if "pelvis" in seen:
                sorted_.pelvis = sorted_.segs.index("pelvis")
            sorted_.lefts, sorted_.mounts = self._frames(tuple(sorted_.used))
            sorted_.plan = self._direct_plan(tuple(sorted_.segs), tuple(sorted_.scatter))
        return sorted_

    def assume_calibrated(self) -> None:
        """Take every orientation sensor's orientation as its segment's, calibrated
        (the profile's mount, else none): for orientations given per segment, such
        as OpenSense files processed without a T-pose. Call before the first solve."""
        self._all_mounted = True
        self._sites.clear()
        self._stacked.clear()
        self._resort = True

    def expect(self, raw_keys: Iterable[str], complete: bool = False) -> None:
        """Orientation sensors this body has (the gateway's topology: nodes whose
        liveliness token is up), delivering or not. Until one delivers, what rests
        on its segment is flagged rather than taken from an assumed upright pose.
        ``complete``: these are all the body's sensors (a capture's), so a body
        with no trunk sensor is measured against the upright model at once."""
        if complete:
            self._memory.first_t_ns = -(2**62)
        told = self._told
        for key in raw_keys:
            if key in told:  # the gateway tells its live nodes every tick
                continue
            if len(told) >= MAX_TOLD:
                told.clear()
            told.add(key)
            try:
                site, _ = keys.parse(key)
            except keys.KeySpaceError:
                continue
            if site.name not in OLE_DOF:
                self._memory.expected.add(mount(site).segment)

    def set_stale(self, raw_keys: Iterable[str]) -> None:
        """The sites (raw keys) whose latest sample is stale: they stopped
        delivering (for a few of their usual intervals, :class:`Rhythm`, or their
        node is gone). Until
        they are no longer named here, every dof resting on such a sample is
        flagged ``unobserved`` with reason ``stale``; one another source
        determines (a SmartSuit module beside a stale tag, dof by dof) stays
        measured. The set changes rarely: what it flags is worked out once per set."""
        stale = frozenset(raw_keys)
        if stale != self._stale:
            self._forget_rates(self._stale - stale)
            self._stale = stale

    def _forget_rates(self, back: frozenset[str]) -> None:
        """Sites back from stale start their samples' history over (their recent
        rate kept): what they did while stale is unknown, and a rate across it is
        none (a node stopped and another started: an elbow held at 40 deg and then
        at 100 was brought forward 7 deg past 100, stating 2)."""
        encoders = self._memory.encoders
        for key in back:
            had = encoders.get(key)
            if had is not None:
                encoders[key] = had._replace(previous_ns=kernels.NO_TIME, latest_ns=kernels.NO_TIME)
        sort = self._sorted
        if sort is not None:
            for i, site in enumerate(sort.used):
                if site.raw_key in back:
                    sort.times[i] = kernels.NO_TIME

    def _solve_direct(self, ticks: Sequence[_Tick], segments: np.ndarray, residual: np.ndarray,
                      angles: np.ndarray, rel: np.ndarray, unc: np.ndarray) -> None:  # fmt: skip
        """The joints between two orientation sensors (or the root and one), of every
        body at once (this solver's structure, which they share), into ``angles``
        ``rel`` and ``unc`` (one row a body). Each comes from its two segments' measured
        orientations (``segments``, every body's in turn, brought to the tick's time
        with ``residual`` deg left each), so a parent joint
        clamped to its range of motion does not move its child's."""
        batch = self._batch
        plans = [tick.plan for tick in ticks]
        if not any(len(p.rows) for p in plans):
            return
        # kept by the shapes of the plans: bodies of one kind come due in ever other
        # sets, each set of m of them laid out as any other
        key = tuple([t.plan.shape for t in ticks])
        layout = batch.layouts.get(key)
        if layout is None:
            if len(batch.layouts) >= 256:  # bodies of several kinds in ever other orders
                batch.layouts.clear()
            layout = batch.layouts[key] = _Layout(ticks, batch)
        owner, rows, index = layout.owner, layout.rows, layout.index
        if len(ticks) == 1 and ticks[0].last is not None:
            last = ticks[0].last[None]
        else:
            nothing = np.zeros(angles.shape[1])  # a body's first tick: no previous angles
            last = np.stack([t.last if t.last is not None else nothing for t in ticks])
        p = layout.prep
        # how well the tags give each relative rotation (deg), and each body's own
        # calibration pose (T or N), which the total rotations are from
        if len(plans) == 1:
            known, cal_inv = plans[0].unc, plans[0].cal_inv
        else:
            known = np.concatenate([plan.unc for plan in plans])
            cal_inv = np.concatenate([plan.cal_inv for plan in plans])
        for tick, at, span in zip(ticks, layout.unc_index, layout.spans, strict=True):
            extra = tick.solver._heading_unc
            if extra is not None:  # a tag whose heading a three-dof joint holds widens them
                known = known.copy() if known is plans[0].unc else known
                known[span] = np.hypot(known[span], extra[at])  # (gateway/heading.py)
        # in two compiled calls: relative rotations, widened by the two segments'
        # residual turns (brought to the tick's time), split; then committed and
        # written into each body's rows (gateway/kernels.py)
        relative, previous, split, gimbal, locked, stated = kernels.direct_split(
            segments, residual, layout.parents, layout.children, last, owner, index, known,
            p.i, p.j, p.k, p.e, p.signs, p.n, p.lo, p.hi, GIMBAL_COS, UNC_SPLIT_MAX_DEG,
        )  # fmt: skip
        if locked:
            batch.unlock(rows, gimbal, split, relative, previous)
        matrices, clamped, n_clamped = kernels.direct_commit(
            split, stated, relative, owner, index, rows, p.lo, p.hi, p.axis, p.unused,
            cal_inv, angles, unc, rel,
        )  # fmt: skip
        start = 0
        for tick, plan in zip(ticks, plans, strict=True):
            mine = plan.rows
            tick.direct_rows, tick.direct_rot = mine, matrices[start : start + len(mine)]
            start += len(mine)
            # what an unmeasured pelvis rests on changes with the topology, not the sorting
            pelvis = tick.solver._rests("pelvis", tick)
            known = tick.sort.reasons.get(pelvis)
            if known is None:
                known = tick.sort.reasons[pelvis] = tick.solver._direct_reasons(tick, pelvis)
            tick.reasons.update(known)
        if not n_clamped:
            return
        at, dof = np.nonzero(clamped & ~p.unused)
        names = batch.names
        for b, row, d in zip(owner[at].tolist(), rows[at].tolist(), dof.tolist(), strict=True):
            reasons, name = ticks[b].reasons, names[row][d]
            reasons[name] = reasons.get(name, _NOTHING) | _CLAMPED

    def _direct_reasons(self, tick: _Tick, pelvis: frozenset[str]) -> dict[str, frozenset[str]]:
        """What the dofs of the tick's joints between two orientation sensors rest
        on besides their measurement (an uncalibrated sensor; ``pelvis``, what the
        pelvis rests on, where it is not measured): the same for every tick of
        the same sorting and pelvis (:class:`_Sorted`)."""
        plan = tick.plan
        mine, parent_at, child_at = plan.rows, plan.parents, plan.children
        names = self._batch.names
        out: dict[str, frozenset[str]] = {}
        if not tick.uncal and not tick.stale:  # each measured segment rests on its measurement
            if pelvis:
                for row in mine[parent_at < 0].tolist():
                    out.update(dict.fromkeys(names[row], pelvis))
            return out
        for row, p, c in zip(mine.tolist(), parent_at.tolist(), child_at.tolist(), strict=True):
            why = (self._rests(tick.segs[p], tick) if p >= 0 else pelvis) | self._rests(
                tick.segs[c], tick
            )
            if why:
                out.update(dict.fromkeys(names[row], why))
        return out

    def _outputs(self, ticks: Sequence[_Tick], angles: np.ndarray, segments: np.ndarray,
                 roots: np.ndarray) -> list[BodyOutput]:  # fmt: skip
        """Forward kinematics of every body at once (this solver's structure, which
        they share; one compiled pass over the Pinocchio model's chain): the
        segments' poses with each body's lowest point on the floor (z = 0) and
        canonical quaternions (w >= 0). Each body's pelvis is turned as its
        sensor measured it (``segments[roots[b]]``), else upright."""
        chain = self.model.chain
        if len(ticks) == 1:  # the body's lengths, as a batch of one (worked out once)
            root_z, offsets, floor = ticks[0].solver._lengths
        else:
            chains = [t.solver.model.chain for t in ticks]  # the lengths are each body's
            root_z, offsets, floor = (np.array([c.root_z for c in chains]),
                                      np.array([c.offsets for c in chains]),
                                      np.array([c.floor_points for c in chains]))  # fmt: skip
        positions, quats = kernels.forward_poses(
            angles, segments, roots, root_z, chain.parents, chain.axes, offsets,
            chain.segment_joints, chain.floor_joints, floor,
        )  # fmt: skip
        for tick in ticks:  # what the next tick's angles are continuous with
            tick.solver._memory.last = tick.angles
        return [t.solver._output(t, p, q) for t, p, q in zip(ticks, positions, quats, strict=True)]

    def _output(self, tick: _Tick, positions: np.ndarray, quats: np.ndarray) -> BodyOutput:
        """One body's output: flags (each dof's first reason) and uncertainties
        (none where a reason other than ``clamped`` says no measurement)."""
        reasons: dict[str, tuple[str, ...]] = {}
        flags: dict[str, str] = {}
        ordered = _ORDERED
        for n, r in tick.reasons.items():
            if r:
                known = ordered.get(r) or _order(r)
                reasons[n], flags[n] = known
        unc = tick.unc[:-1]
        at = self._angle_at
        if none := [at[n] for n, f in flags.items() if f != CLAMPED]:
            unc[none] = math.nan
        return BodyOutput(tick.t_ns, self.names, tick.angles[:-1], tick.rel, flags, positions,
                          quats, tick.sources, reasons, unc)  # fmt: skip

    def _frames(self, used: tuple[Site, ...]) -> tuple[np.ndarray, np.ndarray]:
        """The turns into the body's heading and the mounts' inverses of the
        orientation sensors ``used``, stacked (n, 3, 3): the same sensors deliver
        tick after tick, and stacking thirty small matrices each tick cost more
        than the rotations they take part in."""
        stacked = self._stacked.get(used)
        if stacked is None:
            sites = [self._sites.get(site) or self._site(site) for site in used]
            stacked = (np.array([k[4] for k in sites]), np.array([k[1] for k in sites]))
            if len(self._stacked) >= 64:  # which sensors deliver changes rarely
                self._stacked.clear()
            self._stacked[used] = stacked
        return stacked

    def _direct_plan(self, measured: tuple[str, ...], scatter: tuple[float, ...]) -> _Plan:
        """For segments ``measured`` (in this order) whose tags scattered ``scatter``
        in calibration, the joints between two of them (or the root and one): see
        :class:`_Plan`."""
        plan = self._plans.get((measured, scatter))
        if plan is None:
            at = {s: i for i, s in enumerate(measured)}
            direct = [
                (self._batch.index[j.name], at.get(j.parent, -1), at[j.child])
                for j in self.skeleton.joints
                if j.child in at and (j.parent in at or j.parent == "pelvis")
            ]  # fmt: skip
            rows, parents, children = (np.array([d[k] for d in direct], dtype=int)
                                       for k in range(3))  # fmt: skip
            own = (*scatter, 0.0)  # an unmeasured pelvis (-1) adds nothing
            pairs = zip(parents.tolist(), children.tolist(), strict=True)
            unc = np.array([[tag_unc((own[p], own[c]))] * 3 for p, c in pairs]).reshape(-1, 3)
            plan = _Plan(rows, parents, children, self._batch.angle_index[rows],
                         self._calibration_inv[rows], unc, len(measured))  # fmt: skip
            if len(self._plans) >= 64:  # which sensors deliver changes rarely: a small cache
                self._plans.clear()
            self._plans[measured, scatter] = plan
        return plan

    def _solve_rest(self, tick: _Tick) -> None:
        """The joints not split from two orientation sensors: from one sensor and
        the chain above it, from SmartSuit modules (scalar code, in chain order,
        each from its parent's world orientation), or unobserved; and where a
        module rides a segment an orientation sensor measures, the better
        determined of the two gives each dof.

        Each segment's world orientation carries what it rests on besides
        measurements (``rests``): an uncalibrated sensor, or an expected sensor
        that has not delivered (the pelvis or trunk assumed upright). The tilt
        dofs of modules below it inherit those reasons."""
        modules = tick.modules
        if len(tick.direct_rows) == len(self.skeleton.joints) and not modules:
            return
        direct = dict(zip([self.names.joints[r] for r in tick.direct_rows.tolist()],
                          tick.direct_rot, strict=True))  # fmt: skip
        measured, expected = tick.measured, self._memory.expected
        world: dict[str, np.ndarray] = {"pelvis": measured.get("pelvis", np.eye(3))}
        rests, harm, last = tick.rests, tick.harm, tick.last
        rests["pelvis"], harm["pelvis"] = self._rests("pelvis", tick), 0.0
        for joint in self.skeleton.joints:
            child = joint.child
            ax = self.axes[joint.name]
            names = ax.names
            parent = world[joint.parent]
            previous = last[self._slices[joint.name]] if last is not None else None
            inherited = rests[joint.parent]
            harm[child] = 0.0 if child in measured else harm[joint.parent]
            if joint.name in direct:
                # the measured orientation, not the clamped dofs': what hangs below
                # (a module's tilt) is fitted against where the segment really is
                world[child] = measured[child] if child in measured else parent @ direct[joint.name]
                rests[child] = self._rests(child, tick)
                if child in modules:  # a module on the same segment: dof by dof
                    self._merge_module(tick, world, joint, parent, previous, inherited)
                continue
            if child in measured:
                relative = parent.T @ measured[child]
                values = ax.split(relative, previous)
                known, chain = self._one_sensor(joint, tick)
                unc = ax.unc(relative, known)
                own = self._rests(child, tick)
                why = [set(inherited | own | chain) for _ in names]
                rests[child] = own
                self._commit(tick, world, joint, values, unc, why, relative)
                if child in modules:
                    self._merge_module(tick, world, joint, parent, previous, inherited)
                continue
            if child in modules:
                site, reading = modules[child]
                tick.held_tilt = 0.0
                values, unc, why = self._from_module(joint, parent, site, reading, previous,
                                                     inherited, tick)  # fmt: skip
                # a segment turned by an encoder that does not measure rests on that
                rests[child] = (inherited | self._module_stale(child, tick)
                                | (why[names.index(_ole_name(site))] & _UNCAL))  # fmt: skip
                if len(names) == 2:  # elbow, wrist, ankle: the second dof from gravity
                    self._distal_tilt(joint, values, unc, why, world, site, reading, tick)
                harm[child] += tick.held_tilt
                if len(names) == 2:
                    continue
            else:
                values = np.zeros(len(names))
                unc = np.full(len(names), math.nan)
                # nothing measures this segment: the model's rest pose, and no joint
                # below is measured against it, but for the trunk on the upright model
                # with no sensor expected on it (a body with no pelvis sensor): the
                # reference, as the pelvis is (what a chain of segments may stand on)
                upright = child in tick.sort.upright and child not in expected
                why = [set(_UPRIGHT if upright and not inherited else _UNOBS) for _ in names]
                rests[child] = inherited if upright else inherited | _UNOBS
            self._commit(tick, world, joint, values, unc, why)

    def _one_sensor(self, joint: Joint, tick: _Tick) -> tuple[float, frozenset[str]]:
        """How well (deg) a joint whose child alone an orientation sensor measures
        knows its relative rotation: the sensor's noise, what its sample's age
        may hold (``tick.residual``) and how far its parent's orientation, solved
        this tick, may be off (its joints' stated uncertainties up to an
        orientation sensor's segment, the pelvis or the trunk's upright model, the
        reference of a body with no trunk sensor); and what those joints' dofs
        rest on besides measurement (``held``: a forearm's roll an elbow module
        does not give), which the joint's dofs rest on too."""
        at = tick.segs.index(joint.child)
        var = tag_unc((tick.sort.scatter[at],)) ** 2 + float(tick.residual[at]) ** 2
        why, by_child, reasons = _NOTHING, self._by_child, tick.reasons
        segment = joint.parent
        upright = tick.sort.upright
        while segment not in tick.sort.seen and segment not in upright and segment in by_child:
            above = by_child[segment]
            stated = tick.unc[self._slices[above.name]]
            var += float(np.sum(stated[np.isfinite(stated)] ** 2))
            for name in self.axes[above.name].names:
                why = why | (reasons.get(name, _NOTHING) - _CLAMPED)
            segment = above.parent
        return math.sqrt(var), why

    def _rests(self, segment: str, tick: _Tick) -> frozenset[str]:
        """What a segment's own orientation rests on besides measurement: its
        sensor uncalibrated, or (the pelvis) expected but not delivering."""
        if segment in tick.sort.seen:
            if segment in tick.stale:
                return _UNCAL_STALE if segment in tick.uncal else _STALE
            return _UNCAL if segment in tick.uncal else _NOTHING
        if segment == "pelvis":
            memory = self._memory
            if segment in memory.expected:
                return _UNOBS
            # no trunk sensor known: the upright model, once the topology has had
            # time to show one (the nodes of a suit announce themselves within it)
            if not memory.expected and tick.t_ns - memory.first_t_ns < SETTLE_NS:
                return _UNOBS
        return _NOTHING

    def _merge_module(self, tick: _Tick, world: dict[str, np.ndarray], joint: Joint,
                      parent: np.ndarray, previous: np.ndarray | None,
                      inherited: frozenset[str]) -> None:  # fmt: skip
        """A joint an orientation sensor gave, whose child also carries a SmartSuit
        module: each dof from the source that determines it better (the smaller
        uncertainty, a measured value before a flagged one). The segment's world
        orientation stays the orientation sensor's."""
        site, reading = tick.modules[joint.child]
        sl = self._slices[joint.name]
        values, unc, why = self._from_module(joint, parent, site, reading, previous, inherited,
                                             tick)  # fmt: skip
        if len(values) == 2:
            values[1], unc[1], why[1] = self._gravity_dof(joint, values, world, site, reading,
                                                          previous, tick)  # fmt: skip
            # from gravity through the encoder's dof: uncalibrated where that is
            why[1] |= inherited | self._module_stale(joint.child, tick) | (why[0] & _UNCAL)
        ax = self.axes[joint.name]
        have = tick.angles[sl].copy()
        have_unc = tick.unc[sl].copy()
        have_why = [set(tick.reasons.get(n, ())) - {CLAMPED} for n in ax.names]
        if tick.unknown and (joint.child in tick.unknown or joint.parent in self._tainted(tick)):
            for w in have_why:  # the tags' relative rotation, one of unknown heading
                w.add(UNCALIBRATED)
        for i, name in enumerate(ax.names):
            mine_ok = not (why[i] - {CLAMPED})
            have_ok = not have_why[i]
            if (mine_ok, -unc[i] if mine_ok else 0.0) > (have_ok, -have_unc[i] if have_ok else 0.0):
                have[i], have_unc[i], have_why[i] = values[i], unc[i], why[i] - {CLAMPED}
            tick.reasons.pop(name, None)
        saved = world[joint.child]
        self._commit(tick, world, joint, have, have_unc, have_why)
        world[joint.child] = saved

    def _commit(self, tick: _Tick, world: dict[str, np.ndarray], joint: Joint,
                values: np.ndarray, unc: np.ndarray, why: Sequence[set[str] | frozenset[str]],
                relative: np.ndarray | None = None) -> None:  # fmt: skip
        """Clamp to the range of motion, record with each dof's uncertainty and
        reasons, and carry the chain on. The total rotation from the calibration
        pose is the measured ``relative`` rotation's when there is one (see
        :meth:`_SplitBatch.commit`)."""
        ax = self.axes[joint.name]
        for i, (name, (lo, hi)) in enumerate(zip(ax.names, ax.limits, strict=True)):
            reasons = why[i]
            if not lo <= values[i] <= hi:
                values[i] = min(max(values[i], lo), hi)
                reasons = reasons | _CLAMPED
            if reasons:
                tick.reasons[name] = frozenset(reasons)  # a copy of a set the caller keeps
            else:
                tick.reasons.pop(name, None)
        sl = self._slices[joint.name]
        tick.angles[sl] = values
        tick.unc[sl] = unc
        joint_rot = ax.matrix(values)
        world[joint.child] = world[joint.parent] @ joint_rot
        tick.rel[self._batch.index[joint.name]] = _angle_deg(
            self._calibration[joint.name].T @ (joint_rot if relative is None else relative)
        )

    def _from_module(
        self,
        joint: Joint,
        parent: np.ndarray,
        site: Site,
        reading: OleAccel,
        previous: np.ndarray | None,
        inherited: frozenset[str],
        tick: _Tick,
    ) -> tuple[np.ndarray, np.ndarray, list[set[str]]]:
        """A module's joint: the encoder's dof, and at the shoulders and hips
        flexion and abduction from the accelerometer's tilt; the second dof of
        an elbow, wrist or ankle is left to :meth:`_distal_tilt` (its last value
        until then). Values, uncertainties (deg) and reasons."""
        ax = self.axes[joint.name]
        names = ax.names
        values = previous.copy() if previous is not None else np.zeros(len(names))
        unc = np.full(len(names), math.nan)
        why: list[set[str]] = [set() for _ in names]
        ole_name = _ole_name(site)
        ole_index = names.index(ole_name)
        cal = self.profile.ole.get(ole_name)
        zero = self.encoder_zeros.get(site.raw_key)
        counts = reading.encoder if zero is None else zero.angle_counts(reading.encoder)
        if cal is not None and counts is not None:
            values[ole_index], late = self._encoder_now(site.raw_key, float(cal.angle_deg(counts)),
                                                        cal, zero, tick)  # fmt: skip
            unc[ole_index] = math.hypot(UNC_OLE_DEG, late)  # as a tag's residual widens its joints'
        else:
            why[ole_index].add(UNCALIBRATED)
        if len(names) == 3 and ole_index == 2:  # shoulder, hip: flexion and abduction from tilt
            up = self._up(site, reading)
            prev = previous[:2] if previous is not None else None
            if up is None:  # in free fall: nothing to see
                values[:2], unc[:2], why[:2] = self._settle(names[:2], values[:2],
                                                            np.zeros(2), prev, 1.0)  # fmt: skip
            else:
                fit = values.copy()
                fit[:2] = self._tilt(ax, parent, up[0], values, joint)
                rot = values[2]
                swing = self._swing(site, joint.child, up, tick)

                def predict(x: np.ndarray) -> np.ndarray:
                    return (parent @ ax.matrix(np.array([x[0], x[1], rot]))).T @ _UP  # type: ignore[no-any-return]

                strength = _strengths(predict, fit[:2])
                noise = up[1] + tick.harm[joint.parent] + swing
                values[:2], unc[:2], why[:2] = self._settle(names[:2], fit[:2], strength, prev,
                                                            noise, tick)  # fmt: skip
                seg_axes = self._accel_axes[joint.child]
                values[:2] = _refit(predict, values[:2], why[:2], seg_axes @ up[0])
            for i in (0, 1):  # fitted with the encoder's rotation: uncalibrated where it is
                why[i] |= inherited | (why[2] & _UNCAL)
        else:
            for i in range(len(names)):
                if i != ole_index:  # decided by _distal_tilt
                    why[i].add(UNOBSERVED)
        if joint.child in tick.stale_modules:
            for w in why:
                w.update(_STALE)
        return values, unc, why

    def _encoder_now(self, key: str, angle_deg: float, cal: OleCalibration,
                     zero: EncoderZero | None,
                     tick: _Tick) -> tuple[float, float]:  # fmt: skip
        """An encoder's angle (deg) from its sample, brought to the tick's time on its
        rate between its last two samples as the tags' orientations are
        (:func:`kernels.ahead`), and how far (deg) that may be off: a module on a
        timer of its own samples up to a period before the tick, an elbow at 100
        deg/s turning 2 deg meanwhile; with no rate (its first sample, after a gap)
        its age at its recent rate (:func:`kernels.recent_rate`). A calibration or
        zero that changed starts its history over (its angles jumped), not its rate."""
        t_ns = tick.sources[key]
        history = self._memory.encoders
        counts = zero.counts if zero is not None else 0
        had = history.get(key)
        recent = had.recent if had is not None else math.inf
        if had is None or had.cal is not cal or had.counts != counts or t_ns < had.latest_ns:
            before_ns, before = kernels.NO_TIME, angle_deg
        elif t_ns == had.latest_ns:  # the same sample again: the same two
            before_ns, before = had.previous_ns, had.previous
        else:
            before_ns, before = had.latest_ns, had.latest
        turned = math.radians(angle_deg - before)
        if had is None or t_ns != had.latest_ns:
            recent = kernels.recent_rate(
                recent, before_ns, t_ns, abs(turned), ALIGN_RATE_MAX_DEG_S, ALIGN_RATE_MEMORY_S
            )
        history[key] = _EncoderHistory(before_ns, before, t_ns, angle_deg, cal, counts, recent)
        more, late = kernels.ahead(t_ns, before_ns, tick.t_ns, abs(turned), OLE_NOISE_RAD,
                                   ALIGN_SPAN_NS, ALIGN_AHEAD_NS, ALIGN_CHANGE_PER_S,
                                   ALIGN_RATE_MAX_DEG_S, recent)  # fmt: skip
        return angle_deg + math.copysign(math.degrees(more), turned), late

    def _swing(self, site: Site, segment: str, up: tuple[np.ndarray, float], tick: _Tick) -> float:
        """Take a shoulder or hip module's "up" into its swing's history; how far
        (rad) the swing may tilt it (:class:`_Swing`)."""
        t = tick.t_ns * 1e-9
        values = up[0].tolist()
        swings = self._memory.swing
        swing = swings.get(site.raw_key)
        if swing is None:
            r = self.skeleton.segment_length(segment) * mount(site).fraction
            swings[site.raw_key] = _Swing(t, values, r)
            return 0.0
        swing.update(t, values, up[1] <= UP_UNC_RAD)
        return swing.error_rad()

    def _up(self, site: Site, reading: OleAccel) -> tuple[np.ndarray, float] | None:
        """A module's filtered "up" in its sensor frame and that direction's
        uncertainty (rad): the sensor's own, growing with how far the
        acceleration's size is from 1 g (the body's own acceleration adds to
        gravity). ``None`` in free fall."""
        a = np.array(reading.accel, dtype=float)
        norm = float(np.linalg.norm(a))
        g = self.profile.accel_counts_per_g
        if norm <= 0.1 * g:
            return None
        dynamic = DYN_GAIN * max(0.0, abs(norm / g - 1.0) - DYN_FREE)
        return self._filtered_up(site.raw_key, a / norm), UP_UNC_RAD + dynamic

    def _distal_tilt(
        self,
        joint: Joint,
        values: np.ndarray,
        unc: np.ndarray,
        why: list[set[str]],
        world: dict[str, np.ndarray],
        site: Site,
        reading: OleAccel,
        tick: _Tick,
    ) -> None:
        """The second dof of an elbow, wrist or ankle (pronation, deviation,
        inversion) from the accelerometer on the forearm, hand or foot, and at a
        wrist whose elbow a module measures (encoder only) that elbow's pronation
        too, from both accelerometers: the angles that put the sensors' measured
        "up" on the world vertical, found by Gauss-Newton from the last values
        (000 seed, eq. 21-23). Then committed. An elbow whose wrist carries a
        module leaves its pronation to the wrist (committed as it was for now)."""
        by_child = self._by_child
        modules, measured = tick.modules, tick.measured
        hand = next((j.child for j in self.skeleton.joints if j.parent == joint.child), None)
        if (len(self.axes[joint.name].names) == 2 and hand is not None and hand in modules
                and hand not in measured and OLE_DOF.get(site.name) == "flexion"
                and site.name == "elbow"):  # fmt: skip
            self._commit(tick, world, joint, values, unc, why)  # the wrist decides pronation
            return
        upstream = by_child.get(joint.parent)
        chained = (
            upstream is not None
            and joint.parent not in measured
            and joint.parent in modules
            and len(upstream.dofs) == 2  # the elbow: its pronation is unknown too
        )
        if not chained or upstream is None:
            last = tick.last[self._slices[joint.name]] if tick.last is not None else None
            values[1], unc[1], why[1] = self._gravity_dof(joint, values, world, site, reading,
                                                          last, tick)  # fmt: skip
            # found from gravity through the encoder's dof: uncalibrated where that is
            why[1] |= (self._inherited(joint.parent, tick) | self._module_stale(joint.child, tick)
                       | (why[0] & _UNCAL))  # fmt: skip
            self._commit(tick, world, joint, values, unc, why)
            return
        self._wrist_and_elbow(joint, upstream, values, unc, why, world, site, reading, tick)

    def _wrist_and_elbow(
        self,
        joint: Joint,
        upstream: Joint,
        values: np.ndarray,
        unc: np.ndarray,
        why: list[set[str]],
        world: dict[str, np.ndarray],
        site: Site,
        reading: OleAccel,
        tick: _Tick,
    ) -> None:
        """A wrist's deviation and its elbow's pronation together, from the hand's
        and the forearm's accelerometers (the elbow measured by its encoder only),
        both committed."""
        modules = tick.modules
        ax, up_ax = self.axes[joint.name], self.axes[upstream.name]
        up_sl = self._slices[upstream.name]
        up_values = tick.angles[up_sl].copy()  # committed this tick, pronation as it was
        up_unc = tick.unc[up_sl].copy()
        up_why = [set(tick.reasons.get(n, ())) - {CLAMPED, UNOBSERVED} for n in up_ax.names]
        fixed = world[upstream.parent] @ up_ax.dof(0, up_values[0])
        wrist_flexion = ax.dof(0, values[0])
        hand_up = self._up(site, reading)
        fore_site, fore_reading = modules[joint.parent]
        fore_up = self._up(fore_site, fore_reading)
        preds, targets, noise = [], [], []
        if hand_up is not None:
            hand_axes = self._accel_axes[joint.child]

            def hand_pred(x: np.ndarray) -> np.ndarray:
                chain = fixed @ up_ax.dof(1, x[0]) @ wrist_flexion @ ax.dof(1, x[1])
                return chain.T @ _UP  # type: ignore[no-any-return]

            preds.append(hand_pred)
            targets.append(hand_axes @ hand_up[0])
            noise.append(hand_up[1])
        if fore_up is not None:
            fore_axes = self._accel_axes[joint.parent]

            def fore_pred(x: np.ndarray) -> np.ndarray:
                return (fixed @ up_ax.dof(1, x[0])).T @ _UP  # type: ignore[no-any-return]

            preds.append(fore_pred)
            targets.append(fore_axes @ fore_up[0])
            noise.append(fore_up[1])
        names = (up_ax.names[1], ax.names[1])
        prev = np.array([up_values[1], values[1]])
        if tick.last is None:
            prev = np.zeros(2)
        if preds:

            def predict(x: np.ndarray) -> np.ndarray:
                return np.concatenate([p(x) for p in preds])

            target = np.concatenate(targets)
            fit, strength = _gravity_fit(predict, prev, target, names)
            sol, sol_unc, sol_why = self._settle(names, fit, strength,
                                                 prev if tick.last is not None else None,
                                                 max(noise) + tick.harm[upstream.parent]
                                                 + _miss(predict, fit, target),
                                                 tick)  # fmt: skip
            sol = _refit(predict, sol, sol_why, target)
        else:
            sol, sol_unc, sol_why = self._settle(names, prev, np.zeros(2), prev, 1.0)
        # both accelerometers', and both encoders' dofs: uncalibrated where either is
        inherited_up = (self._inherited(upstream.parent, tick)
                        | self._module_stale(joint.child, tick)
                        | self._module_stale(joint.parent, tick)
                        | ((up_why[0] | why[0]) & _UNCAL))  # fmt: skip
        up_values[1], up_unc[1], up_why[1] = sol[0], sol_unc[0], sol_why[0] | inherited_up
        values[1], unc[1], why[1] = sol[1], sol_unc[1], sol_why[1] | inherited_up
        self._commit(tick, world, upstream, up_values, up_unc, up_why)
        self._commit(tick, world, joint, values, unc, why)

    def _inherited(self, segment: str, tick: _Tick) -> frozenset[str]:
        return tick.rests.get(segment, _NOTHING)

    @staticmethod
    def _module_stale(segment: str, tick: _Tick) -> frozenset[str]:
        """The reasons of what rests on the SmartSuit module on ``segment``: ``stale``
        if it is."""
        return _STALE if segment in tick.stale_modules else _NOTHING

    def _gravity_dof(self, joint: Joint, values: np.ndarray, world: dict[str, np.ndarray],
                     site: Site, reading: OleAccel, previous: np.ndarray | None,
                     tick: _Tick) -> tuple[float, float, set[str]]:  # fmt: skip
        """The second dof of a two-dof joint from its child's accelerometer alone,
        with its uncertainty and reasons."""
        ax = self.axes[joint.name]
        name = ax.names[1]
        prev = None if previous is None else np.array([previous[1]])
        up = self._up(site, reading)
        if up is None:
            v, u, w = self._settle((name,), np.array([values[1]]), np.zeros(1), prev, 1.0)
            return float(v[0]), float(u[0]), w[0]
        seg_axes = self._accel_axes[joint.child]
        target = seg_axes @ up[0]
        fixed = world[joint.parent] @ ax.dof(0, values[0])

        def predict(x: np.ndarray) -> np.ndarray:
            return (fixed @ ax.dof(1, x[0])).T @ _UP  # type: ignore[no-any-return]

        start = prev if prev is not None else np.zeros(1)
        fit, strength = _gravity_fit(predict, start, target, (name,))
        noise = up[1] + tick.harm[joint.parent] + _miss(predict, fit, target)
        v, u, w = self._settle((name,), fit, strength, prev, noise, tick)
        return float(v[0]), float(u[0]), w[0]

    def _settle(
        self,
        names: Sequence[str],
        fit: np.ndarray,
        strength: np.ndarray,
        previous: np.ndarray | None,
        up_unc_rad: float,
        tick: _Tick | None = None,
    ) -> tuple[np.ndarray, np.ndarray, list[set[str]]]:
        """Tilt dofs from a gravity fit and how strongly gravity determines each
        (``strength``: how far the sensors' "up" moves per radian of the dof, the
        others free). Uncertainty = the "up"'s uncertainty / strength. A dof
        determined within ``UNC_MAX_DEG`` takes the fit; one that is not keeps its
        last value, flagged ``held`` (``unobserved`` if it never was determined),
        and when it is determined again it moves back to the fit at most
        ``SLEW_DEG`` a tick, still flagged, so it never jumps."""
        memory = self._memory
        out = fit.astype(float).copy()
        unc = np.full(len(names), math.nan)
        why: list[set[str]] = [set() for _ in names]
        for i, name in enumerate(names):
            s = float(strength[i])
            u = math.degrees(up_unc_rad / s) if s > 1e-9 else math.inf
            if u <= UNC_MAX_DEG:
                if previous is not None and name in memory.held and \
                        abs(fit[i] - previous[i]) > max(u, SLEW_DEG):  # fmt: skip
                    step = min(max(fit[i] - previous[i], -SLEW_DEG), SLEW_DEG)
                    out[i] = previous[i] + step
                    why[i].add(HELD)
                    if tick is not None:  # how far this may tilt what lies below
                        tick.held_tilt += self._harm(fit[i], out[i], s)
                    continue
                memory.held.discard(name)
                memory.seen.add(name)
                unc[i] = u
            else:  # its last value, or the model's rest value if it never had one
                out[i] = previous[i] if previous is not None else 0.0
                why[i].add(HELD if name in memory.seen else UNOBSERVED)
                if tick is not None:
                    tick.held_tilt += self._harm(fit[i], out[i], s)
                memory.held.add(name)
        return out, unc, why

    @staticmethod
    def _harm(fit: float, held: float, strength: float) -> float:
        """How far (rad) a dof held at ``held`` while gravity, with ``strength``,
        puts it at ``fit`` may tilt the segments below it (beyond the noise)."""
        return max(0.0, math.radians(abs(fit - held)) * strength - HARM_FLOOR_RAD)

    def _filtered_up(self, key: str, up: np.ndarray) -> np.ndarray:
        """Light low-pass filtering of an accelerometer's direction (exponential,
        ``accel_filter`` of the new sample each time), against vibration."""
        last = self._memory.up.get(key)
        if last is not None:
            blend = last + self.profile.accel_filter * (up - last)
            norm = np.linalg.norm(blend)
            if norm > 1e-6:  # a sample opposite the last blends to nothing: start over
                up = blend / norm
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
        m = self._accel_axes[seg]
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
        # damped normal equations (an absolute damping, per radian): a direction
        # gravity cannot see gets no step, instead of a huge one that its noise sets
        jtj = jac.T @ jac
        step = np.linalg.solve(jtj + DAMPING * eye, -jac.T @ r)
        x += np.clip(step, -30.0, 30.0)
        if float(np.abs(step).max()) < 1e-3:  # degrees: far below the sensors' resolution
            break
    return np.array([_wrap(v) for v in x])


def _jacobian(predict: Any, x: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """d predict / dx (per degree), by forward differences."""
    y = predict(x)
    return np.column_stack([(predict(x + h * e) - y) / h for e in np.eye(len(x))])


def _strengths(predict: Any, x: np.ndarray) -> np.ndarray:
    """How far the predicted "up"s move per radian of each dof, the other dofs
    free to make up for it: 1 / sqrt of the diagonal of (J^T J)^-1. 0 for a dof
    gravity cannot see (about the vertical, or one another dof already covers)."""
    jac = _jacobian(predict, x) * (180.0 / math.pi)
    jtj = jac.T @ jac
    try:
        inv = np.linalg.inv(jtj + 1e-12 * np.eye(len(x)))
    except np.linalg.LinAlgError:
        return np.zeros(len(x))
    return 1.0 / np.sqrt(np.maximum(np.diag(inv), 1e-300))  # type: ignore[no-any-return]


def _gravity_fit(predict: Any, x0: np.ndarray, target: np.ndarray,
                 names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Angles (deg) near ``x0`` that put the predicted "up"s on ``target``, and
    each dof's strength there (:func:`_strengths`). Damped steps that a dof
    gravity cannot see does not take, so it stays where it was; if no good fit
    is near ``x0``, one from neutral is tried too (inside the range of motion
    and nearest ``x0`` wins among good fits)."""

    def rank(x: np.ndarray) -> tuple[bool, float, float]:
        miss = float(np.linalg.norm(predict(x) - target)) > MISS * math.sqrt(len(target) / 3)
        outside = sum(
            max(0.0, lo - v, v - hi) for v, (lo, hi) in zip(x, map(rom, names), strict=True)
        )
        return miss, outside, float(np.abs(x - x0).sum())

    fits = [_gauss_newton(predict, x0, target)]
    if rank(fits[0])[:2] != (False, 0.0):  # no good fit near the last answer: try neutral
        fits.append(_gauss_newton(predict, np.zeros(len(x0)), target))
    best = min(fits, key=rank)
    return best, _strengths(predict, best)


def _miss(predict: Any, x: np.ndarray, target: np.ndarray) -> float:
    """How far (rad) the best fit leaves a measured "up" off its predicted one:
    the largest miss over the fit's accelerometers. The chain above and the
    encoders fix more of each segment's tilt than the fit's dofs can change, so
    what they cannot explain is the limb's own acceleration across gravity (or a
    model error), and a dof fitted through it is as far off (the hand's deviation
    swings as the lifted arm's reach accelerates)."""
    return float(np.linalg.norm((predict(x) - target).reshape(-1, 3), axis=1).max())


def _refit(predict: Any, values: np.ndarray, why: Sequence[set[str]],
           target: np.ndarray) -> np.ndarray:  # fmt: skip
    """With some of a fit's dofs held, the others fitted again around them (a
    held dof's value is not the fit's, and the others must agree with it)."""
    held = np.array([bool(w & {HELD, UNOBSERVED}) for w in why])
    if not held.any() or held.all():
        return values
    free = np.flatnonzero(~held)
    base = values.astype(float).copy()

    def partial(x: np.ndarray) -> np.ndarray:
        full = base.copy()
        full[free] = x
        return predict(full)  # type: ignore[no-any-return]

    base[free] = _gauss_newton(partial, base[free], target)
    return base


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
