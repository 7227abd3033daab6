"""Calibration of orientation sensors on real frames: pose, window, heading.

Frames. A tag reports ``R_s``, its orientation in its own reference frame (z
up: gravity is known; the heading about the vertical is the tag's). The body's
frame is the one the solver works in: +X the way the subject faced during
calibration, +Z up. With ``psi`` the heading of the tag's reference frame
against that forward direction, ``M`` the mount (sensor in segment) and
``R_seg`` the segment in the body's frame::

    R_s(t) = Rz(psi) R_seg(t) M        so   R_seg(t) = Rz(-psi) R_s(t) M^T

A still calibration pose gives ``R_seg`` (the pose's, from the skeleton) and so
``Rz(psi) M`` for each tag, but not ``psi`` and ``M`` apart: whichever way the
subject faced looks the same to one static pose when mountings are arbitrary.
(:func:`calibrate_window` computes the mounts for ``psi = 0`` and says whether
the heading is known: ``fixed`` mode, or a declared reference.)

The motion after the pose gives ``psi`` when tags share one reference
(magnetometer-based sensors, :class:`HingeHeading`): the relative rotation of
the two segments of a hinge joint (knee, elbow) since calibration, seen in the
parent tag's frame, turns about the joint axis, which is the parent segment's
lateral axis (Seel et al. 2014). That axis, in the tag's reference frame at
calibration, against where the pose puts it in the body's frame, is the
heading. A hinge whose axis was vertical in the pose (the elbow in a T-pose)
tells nothing and is skipped; the elbow and wrist as two-dof joints then may
(:class:`SharedTwoDof`: their two axes stay perpendicular). Until the heading
is known the solver flags the dofs it would drive ``uncalibrated``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.keys import Site
from bodynet.core.profile import OLE_DOF, mount
from bodynet.core.skeleton import CALIBRATION_POSES, build_skeleton, rom
from bodynet.core.subject import Profile, QuatWxyz
from bodynet.kinematics.model import BodyModel

POSE_ANGLES = CALIBRATION_POSES


class Fits(Protocol):
    """Where a heading search's fits (a knee's or elbow's pair, a foot or hand:
    a few to a few hundred ms each) run: ``submit(fn, *args)`` gives a Future, as
    a ``concurrent.futures`` executor's does."""

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future[Any]: ...


class InlineFits:
    """Each fit run at once, in the caller: the search takes it in the very tick
    that asked for it (``bodynet process`` and the tests: the same headings at
    the same ticks on any machine)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future[Any]:
        done: Future[Any] = Future()
        done.set_result(fn(*args))
        return done


INLINE = InlineFits()


class _Aside:
    """A finder's fits in flight, by key (a side, a child tag), one at most each:
    started on a copy of the samples, taken by the first update after it is done
    (at once when run inline)."""

    def __init__(self, fits: Fits) -> None:
        self.fits = fits
        self._flying: dict[str, tuple[Future[Any], int]] = {}

    def due(self, key: str, samples: Sequence[Any], first: int, every: int) -> bool:
        """Whether ``key``'s ``samples`` are due a fit: from ``first`` on, at every
        ``every``-th; not while one of its fits is in flight."""
        n = len(samples)
        return n >= first and not (n - first) % every and key not in self._flying

    def start(self, key: str, samples: Sequence[Any], fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn`` for ``key`` on a copy of its ``samples`` (then ``args``)."""
        self._flying[key] = (self.fits.submit(fn, list(samples), *args), len(samples))

    def done(self, key: str) -> tuple[Any, int] | None:
        """The result of ``key``'s fit and how many samples it had, once it is done."""
        flying = self._flying.get(key)
        if flying is None or not flying[0].done():
            return None
        del self._flying[key]
        return flying[0].result(), flying[1]


def _make_way(samples: list[Any], oldest: int, most: int) -> None:
    """A full search's ``oldest`` samples make way (the next ones may tell: a
    drifting tag's old ones say less of its heading now), and as many more as
    came past ``most`` while its fit ran aside."""
    del samples[: max(oldest, len(samples) - most)]


def pose_angles(pose: str) -> Mapping[str, float]:
    """The joint angles (deg) of calibration ``pose``; ValueError naming the
    poses there are when it is none of them."""
    if pose not in POSE_ANGLES:
        raise ValueError(f"unknown calibration pose {pose!r}; one of {', '.join(POSE_ANGLES)}")
    return POSE_ANGLES[pose]


#: A calibration window shorter than this, or with fewer samples of a tag, is refused.
MIN_WINDOW_S = 0.4
MIN_SAMPLES = 5
#: A tag whose orientation, low-passed (the mean of each run of a tenth of its
#: samples, at least 3), turned further than this from its mean in the window, past
#: what its own scatter gives a low-passed mean (three standard deviations): the
#: subject moved, and the window is refused. (The maximum of the raw samples grows
#: with the tags' noise and the samples' count: at 1 deg of noise a still pose of
#: 50 samples went past 3 deg.)
STILL_DEG = 3.0

#: Hinge joints whose motion reveals the heading: (joint, parent, child, the flexion
#: axis in the parent segment's frame, signed so that flexion turns positively).
HINGES = (
    ("knee", "thigh", "shank", (0.0, 1.0, 0.0)),
    ("elbow", "upperarm", "forearm", (0.0, -1.0, 0.0)),
)
#: A hinge's samples count once its relative rotation since calibration passes
#: this; its axis is their mean, weighted by the angle (noise tilts the axis of a
#: small rotation most) ...
HINGE_MIN_DEG = 10.0
#: ... taken once this many have come, turning this far in all, with axes that agree
#: (mean resultant length at least this; a joint turning about two axes does not).
HINGE_SAMPLES = 20
HINGE_TOTAL_DEG = 500.0
HINGE_AGREEMENT = 0.97
#: An axis whose horizontal part (in the calibration pose) is below this gives no heading.
HORIZONTAL_MIN = 0.5
#: A foot's or hand's best heading leaving its joint's axes off perpendicular by more
#: than this (RMS, deg) is not that joint's motion (noise of 2 deg a tag gives about 3)
CHILD_MISFIT_DEG = 6.0
#: the chest tag's headings (deg apart) an arm's twin must be told apart under (:func:`_arm_twin`)
TWIN_CHEST_STEP_DEG = 30.0


class CalibrationRefused(ValueError):
    """A calibration window that cannot be used: the message says why; ``report``
    is the calibration report (what was seen)."""

    def __init__(self, message: str, report: Mapping[str, Any]) -> None:
        super().__init__(message)
        self.report = dict(report)


def rz(deg: float) -> np.ndarray:
    """Rotation about the vertical by ``deg``."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _matrix(q: Sequence[float]) -> np.ndarray:
    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w]).as_matrix()  # type: ignore[no-any-return]


def _quat_matrix(q: Sequence[float]) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def _rotvec(rot: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of a rotation matrix, accurate below 180 deg."""
    vee = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    sin2 = float(np.linalg.norm(vee))  # 2 sin(angle)
    angle = math.atan2(sin2 / 2.0, (float(np.trace(rot)) - 1.0) / 2.0)
    return vee * (0.5 if sin2 < 1e-12 else angle / sin2)  # type: ignore[no-any-return]


def _wxyz(rot: np.ndarray) -> QuatWxyz:
    x, y, z, w = Rotation.from_matrix(rot).as_quat(canonical=True)
    return (float(w), float(x), float(y), float(z))


def pose_segments(profile: Profile, pose: str | None = None) -> dict[str, np.ndarray]:
    """Each segment's orientation (body frame) in the calibration ``pose``."""
    skeleton = build_skeleton(profile.lengths)
    model = BodyModel(skeleton)
    names = list(model.segment_frames)
    rots, _ = model.frame_placements(
        model.q(dict(POSE_ANGLES[pose or profile.pose])), [model.segment_frames[s] for s in names]
    )
    return dict(zip(names, rots, strict=True))


def yaw_deg(rot: np.ndarray) -> float:
    """Heading (deg) of a segment orientation: where its forward (x) axis points
    about the vertical (its lateral axis, turned, when x is near vertical)."""
    x = rot[:, 0]
    if math.hypot(x[0], x[1]) < 0.3:
        y = rot[:, 1]
        return math.degrees(math.atan2(y[1], y[0])) - 90.0
    return math.degrees(math.atan2(x[1], x[0]))


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def declared_heading(orientation: QuatWxyz, axis: str) -> float:
    """The heading of a tag's reference frame when its sensor ``axis`` ("+z",
    "-x", ...) pointed forward at ``orientation`` (a calibration pose)."""
    v = np.zeros(3)
    v["xyz".index(axis[1])] = 1.0 if axis[0] == "+" else -1.0
    u = _matrix(orientation) @ v
    if math.hypot(u[0], u[1]) < HORIZONTAL_MIN:
        raise ValueError(f"the declared axis {axis} was near vertical in calibration, "
                         "not pointing forward")  # fmt: skip
    return math.degrees(math.atan2(u[1], u[0]))


def with_headings(profile: Profile, headings: Mapping[str, float]) -> Profile:
    """``profile`` with tags' headings now known: their mounts, computed for a heading
    of 0 at calibration, turned to match (``M = R_seg0^T Rz(-psi) R_seg0 M_0``)."""
    segments = pose_segments(profile)
    by_key = _segments_of(profile.imu_mounts)
    mounts = dict(profile.imu_mounts)
    known = dict(profile.imu_headings)
    for key, psi in headings.items():
        old = known.get(key, 0.0)
        seg = segments[by_key[key]] if key in by_key else np.eye(3)
        if key in mounts:
            turn = seg.T @ rz(-(psi - old)) @ seg
            mounts[key] = _wxyz(turn @ _matrix(mounts[key]))
        known[key] = _wrap(psi)
    return replace(profile, imu_mounts=MappingProxyType(mounts),
                   imu_headings=MappingProxyType(known))  # fmt: skip


def _tag_by_segment(keys: Iterable[str]) -> dict[str, str]:
    """Segment -> the raw key of its tag (the first of the keys on it)."""
    out: dict[str, str] = {}
    for key, seg in _segments_of(keys).items():
        out.setdefault(seg, key)
    return out


def _segments_of(keys: Iterable[str]) -> dict[str, str]:
    """Raw key -> the segment its sensor rides on (for the keys that name a site)."""
    from bodynet.core import keys as keyspace

    out = {}
    for key in keys:
        try:
            site, _ = keyspace.parse(key)
        except keyspace.KeySpaceError:
            continue
        if isinstance(site, Site):
            out[key] = mount(site).segment
    return out


@dataclass(frozen=True)
class WindowCalibration:
    """What a still window gives: mounts (for a heading of 0 where it is not
    known), the tags' headings where known, and the report for the user."""

    mounts: dict[str, QuatWxyz]
    headings: dict[str, float]
    report: dict[str, Any]

    def apply(self, profile: Profile, pose: str | None = None) -> Profile:
        """``profile`` calibrated: these mounts, the tags' scatter in the window
        (their noise, which their dofs' uncertainty carries), the pose, and the
        headings. The tags recalibrated here lose any heading they had, until it
        is found (the report's ``heading.dropped``, :func:`dropped_note`): a tag's
        heading is its reference frame's turn from where the subject faced in
        *that* calibration's pose, which a new pose does not keep."""
        tags = self.report.get("tags", {})
        scatter = {k: float(tags[k]["scatter_deg"]) for k in self.mounts if k in tags}
        calibrated = replace(
            profile.with_mounts(self.mounts),
            pose=pose or profile.pose,
            imu_scatter_deg=MappingProxyType({**profile.imu_scatter_deg, **scatter}),
            imu_headings=MappingProxyType(
                {k: v for k, v in profile.imu_headings.items() if k not in self.mounts}
            ),
        )
        return with_headings(calibrated, self.headings) if self.headings else calibrated


def dropped_note(report: Mapping[str, Any]) -> str | None:
    """What a calibration report says of the tags' headings it dropped (given in the
    profile, or found after the last calibration), for the user; None if none."""
    dropped = (report.get("heading") or {}).get("dropped")
    if not dropped:
        return None
    return (f"the headings of {len(dropped)} tag(s) in the profile ({', '.join(dropped[:3])}"
            + ("..." if len(dropped) > 3 else "") + ") were the last calibration's and are "
            "dropped: each is found again from the motion, or pass --heading-reference "
            "or --heading fixed")  # fmt: skip


def calibrate_window(
    window: Mapping[Site, Sequence[tuple[float, QuatWxyz]]],
    profile: Profile,
    pose: str | None = None,
    expected: Iterable[Site] = (),
    seconds: float | None = None,
) -> WindowCalibration:
    """Mounts of the orientation sensors from a still window of ``(t_s, wxyz)``
    samples, the subject in ``pose`` (the profile's by default).

    Refused (:class:`CalibrationRefused`) when a tag of ``expected`` has no sample
    in it, when it is shorter than ``MIN_WINDOW_S`` (or than ``seconds``, the
    length asked for, by more than a fifth) or holds fewer than ``MIN_SAMPLES`` of
    a tag, or when a tag turned more than ``STILL_DEG`` in it (low-passed, past
    its own noise). The report gives, per tag, its samples, the time they span,
    how far it turned from its mean, low-passed (``still_deg``), its scatter (RMS,
    ``scatter_deg``), the limit they give (``still_limit_deg``), and its residual
    against the profile's current calibration
    (the angle between where the old mount puts it in the pose and where it was:
    a tag moved on the body, or another pose than before)."""
    pose = pose or profile.pose
    pose_angles(pose)
    segments = pose_segments(profile, pose)
    present = {s: v for s, v in window.items() if v}
    missing = sorted(s.raw_key for s in set(expected) - set(present))
    tags: dict[str, dict[str, Any]] = {}
    mounts: dict[str, QuatWxyz] = {}
    means: dict[str, np.ndarray] = {}
    for site, samples in sorted(present.items(), key=lambda kv: kv[0].raw_key):
        key = site.raw_key
        seg = segments[mount(site).segment]
        means[key], tags[key] = _tag_stats(key, samples, seg, profile)
        mounts[key] = _wxyz(seg.T @ means[key])
    # what the window covers: each of a tag's n samples stands for one sampling
    # interval, n - 1 of which its span holds (a slow sensor's window is not short)
    span_all = max((round(t["span_s"] * t["samples"] / (t["samples"] - 1), 3)
                    for t in tags.values() if t["samples"] > 1), default=0.0)  # fmt: skip
    report: dict[str, Any] = {"pose": pose, "window_s": span_all, "tags": tags,
                              "missing": missing, "still_limit_deg": STILL_DEG}  # fmt: skip
    if not present:
        raise CalibrationRefused("no orientation samples in the window", report)
    if missing:
        raise CalibrationRefused(f"no samples of {len(missing)} tag(s) in the window: "
                                 + ", ".join(missing), report)  # fmt: skip
    short = [k for k, t in tags.items() if t["samples"] < MIN_SAMPLES]
    want = max(MIN_WINDOW_S, 0.8 * seconds if seconds else 0.0)
    if span_all < want or short:
        what = f"{len(short)} tag(s) with fewer than {MIN_SAMPLES} samples" if short else ""
        # of a window asked for (a capture's first seconds, --window), most of it
        asked = f" ({0.8:g} of the {seconds:.3g} s asked)" if want > MIN_WINDOW_S else ""
        raise CalibrationRefused(
            f"the window is too short: {span_all:.3g} s"
            + (f" ({what})" if what else "") + f"; it needs at least {want:.3g} s{asked}",
            report,
        )  # fmt: skip
    moved = {k: t["still_deg"] for k, t in tags.items() if t["still_deg"] > t["still_limit_deg"]}
    if moved:
        worst = sorted(moved, key=moved.__getitem__, reverse=True)
        noisy = [k for k in worst if tags[k]["scatter_deg"] > STILL_DEG]
        raise CalibrationRefused(
            f"the subject moved: {len(moved)} tag(s) turned more than {STILL_DEG:g} deg (past "
            "their noise) in the window (" + ", ".join(f"{k} {moved[k]:.1f} deg" for k in worst[:4])
            + ("..." if len(worst) > 4 else "") + "); stand still in the pose and try again"
            + "".join(f"; tag {k} is noisy (sigma ~ {tags[k]['scatter_deg']:.1f} deg)"
                      for k in noisy[:4]),
            report,
        )  # fmt: skip
    headings = _window_heading(profile, means, report)
    dropped = sorted(k for k in profile.imu_headings if k in mounts and k not in headings)
    if dropped:  # the old calibration's: see WindowCalibration.apply
        report["heading"]["dropped"] = dropped
    report["ok"] = True
    report["calibrated"] = sorted(mounts)
    return WindowCalibration(mounts, headings, report)


def _tag_stats(key: str, samples: Sequence[tuple[float, QuatWxyz]], seg: np.ndarray,
               profile: Profile) -> tuple[np.ndarray, dict[str, Any]]:  # fmt: skip
    """A tag's mean orientation in a window, and its line of the report."""
    order = np.argsort([t for t, _ in samples], kind="stable")
    times = np.array([samples[i][0] for i in order])
    rots = Rotation.from_quat([[x, y, z, w] for _, (w, x, y, z) in (samples[i] for i in order)])
    mean = rots.mean()
    # the turns from the mean (rotation vectors: small, so they average), low-passed
    dev = (mean.inv() * rots).as_rotvec()
    # its noise (RMS), from the samples' second differences (six times the noise's
    # square for white noise): a smooth turn hardly moves them, even one the whole
    # window long, which the RMS about the mean took for noise and let through
    sq = (dev[2:] - 2.0 * dev[1:-1] + dev[:-2]) ** 2 / 6.0 if len(dev) >= 3 else dev**2
    scatter = math.degrees(math.sqrt(float(sq.sum(axis=1).mean())))
    run = max(3, len(samples) // 10)
    if len(samples) >= run:
        cum = np.cumsum(np.vstack([np.zeros(3), dev]), axis=0)
        smooth = (cum[run:] - cum[:-run]) / run
        spread = math.degrees(float(np.linalg.norm(smooth, axis=1).max()))
    else:
        spread = math.degrees(float(np.linalg.norm(dev, axis=1).max()))
    limit = STILL_DEG + 3.0 * scatter / math.sqrt(run)
    residual = None
    if key in profile.imu_mounts:
        expect = rz(profile.heading_of(key)) @ seg @ _matrix(profile.imu_mounts[key])
        residual = round(math.degrees(Rotation.from_matrix(expect.T @ mean.as_matrix())
                                      .magnitude()), 2)  # fmt: skip
    return mean.as_matrix(), {"samples": len(samples),
                              "span_s": round(float(times.max() - times.min()), 3),
                              "still_deg": round(spread, 2), "scatter_deg": round(scatter, 2),
                              "still_limit_deg": round(limit, 2),
                              "residual_deg": residual}  # fmt: skip


def _window_heading(profile: Profile, means: Mapping[str, np.ndarray],
                    report: dict[str, Any]) -> dict[str, float]:  # fmt: skip
    """The tags' headings a calibration window gives (``fixed`` mode, a declared
    reference) or none (to be found); says which in ``report["heading"]``."""
    if profile.heading == "fixed":
        report["heading"] = {"state": "fixed", "deg": 0.0}
        return dict.fromkeys(means, 0.0)
    if profile.heading_reference is None:
        report["heading"] = {"state": "unknown", "deg": None,
                             "next": "move a knee (or, after an N-pose, an elbow; after a "
                                     "T-pose, flex a wrist or turn a forearm): the heading "
                                     "is found from the joint's axes"}  # fmt: skip
        if profile.heading == "independent":
            report["heading"]["next"] = (
                "walk (the legs' tags), reach (the arms'; after a T-pose, turning the "
                "forearms with the arms out), and bow forward from the hips, the head "
                "following (the pelvis', chest's and head's)"
            )
        return {}
    ref_key, axis = profile.heading_reference
    if ref_key not in means:
        raise CalibrationRefused(f"the declared heading reference {ref_key} has no samples "
                                 "in the window", report)  # fmt: skip
    try:
        psi = declared_heading(_wxyz(means[ref_key]), axis)
    except ValueError as exc:
        raise CalibrationRefused(str(exc), report) from None
    report["heading"] = {"state": "declared", "deg": round(psi, 2),
                         "reference": f"{ref_key} {axis}"}  # fmt: skip
    return dict.fromkeys(means, psi)


@dataclass
class _Hinge:
    parent_key: str
    child_key: str
    parent0: np.ndarray  # parent tag in its reference frame at calibration
    relative0: np.ndarray  # child tag in the parent tag's frame at calibration
    axis_pose: np.ndarray  # the joint axis in the body's frame, in the calibration pose
    sum_axis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sum_unit: np.ndarray = field(default_factory=lambda: np.zeros(3))
    total_deg: float = 0.0
    count: int = 0
    first_move_t: float | None = None


class HingeHeading:
    """Finds the shared heading of a body's tags from its hinge joints' motion.

    Built from a calibrated profile (mounts for a heading of 0); fed each tick's
    tag orientations by raw key (:meth:`update`), it returns the heading once a
    hinge has turned far enough, consistently about one axis, and then stays
    done (``heading``, ``found_t``, ``first_move_t``, ``hinge``)."""

    def __init__(self, profile: Profile) -> None:
        segments = pose_segments(profile)
        by_segment = _tag_by_segment(profile.imu_mounts)
        self.hinges: dict[str, _Hinge] = {}
        for joint, parent, child, axis in HINGES:
            for side in ("left", "right"):
                p, c = by_segment.get(f"{side}_{parent}"), by_segment.get(f"{side}_{child}")
                if p is None or c is None:
                    continue
                seg_p, seg_c = segments[f"{side}_{parent}"], segments[f"{side}_{child}"]
                p0 = seg_p @ _matrix(profile.imu_mounts[p])
                c0 = seg_c @ _matrix(profile.imu_mounts[c])
                self.hinges[f"{side}_{joint}"] = _Hinge(p, c, p0, p0.T @ c0,
                                                        seg_p @ np.array(axis))  # fmt: skip
        self.informative = sorted(
            name for name, h in self.hinges.items()
            if math.hypot(h.axis_pose[0], h.axis_pose[1]) >= HORIZONTAL_MIN
        )  # fmt: skip
        self.heading: float | None = None
        self.found_t: float | None = None
        self.first_move_t: float | None = None
        self.hinge: str | None = None

    @property
    def wanted_keys(self) -> set[str]:
        return {k for name in self.informative
                for k in (self.hinges[name].parent_key, self.hinges[name].child_key)}  # fmt: skip

    def update(self, t_s: float, orientations: Mapping[str, QuatWxyz]) -> float | None:
        """Take one tick's tag orientations; the heading (deg) once found."""
        if self.heading is not None:
            return self.heading
        for name in self.informative:
            h = self.hinges[name]
            p, c = orientations.get(h.parent_key), orientations.get(h.child_key)
            if p is None or c is None:
                continue
            # plain arithmetic: scipy's Rotation costs tens of microseconds a call, and
            # this runs every tick of a body until its heading is found
            change = _quat_matrix(p).T @ _quat_matrix(c) @ h.relative0.T  # in the parent tag
            rotvec = _rotvec(change)
            angle = math.degrees(float(np.linalg.norm(rotvec)))
            if angle > 5.0 and h.first_move_t is None:
                h.first_move_t = t_s
                if self.first_move_t is None:
                    self.first_move_t = t_s
            if angle < HINGE_MIN_DEG:
                continue
            # the axis in the parent tag's frame, taken to the tag's reference frame
            # at calibration (the tag's own motion since then drops out)
            axis = h.parent0 @ rotvec
            h.sum_axis += axis
            h.sum_unit += axis / np.linalg.norm(axis)
            h.total_deg += angle
            h.count += 1
            if h.count >= HINGE_SAMPLES and h.total_deg >= HINGE_TOTAL_DEG:
                agreement = float(np.linalg.norm(h.sum_unit)) / h.count
                if agreement < HINGE_AGREEMENT:  # not a hinge's motion (yet): start again
                    h.sum_axis[:] = 0.0
                    h.sum_unit[:] = 0.0
                    h.total_deg, h.count = 0.0, 0
                    continue
                u, v = h.sum_axis, h.axis_pose
                self.heading = _wrap(math.degrees(math.atan2(u[1], u[0])
                                                  - math.atan2(v[1], v[0])))  # fmt: skip
                self.found_t, self.hinge = t_s, name
                return self.heading
        return None


class KneePairs:
    """Finds the heading of each thigh and shank tag with a reference of its own
    (6-axis tags, ``independent`` mode) from the knees' motion.

    Each tag's rotation since calibration, in its own reference frame, is the
    segment's turned by the tag's unknown heading ``psi`` (``Rz(psi) R Rz(-psi)``).
    For the right pair of headings the thigh-to-shank rotation is a turn about
    the knee's axis alone: the two headings are found by a search over both
    (every 10 deg, then every degree) minimising the rotation off that axis, the
    knee flexing positively (the pair turned by 180 deg fits as well, flexing
    the wrong way). Needs both segments to move (a swing, a walk): samples are
    taken every ``EVERY_S`` while the knee is past 15 deg, each segment past 10;
    from ``PAIR_SAMPLES`` on, every ``TRY_EVERY``, the pair is searched (none
    while a pair far from the best fits nearly as well) and refined, and taken
    once its uncertainty is within ``MAX_UNC_DEG`` (``FULL_UNC_DEG`` once
    ``MAX_SAMPLES`` have come; beyond, the oldest make way), as
    :class:`ChildHeadings` does. The other tags' headings stay unknown (their
    joints have three dofs, or reach no knee), and their dofs stay flagged.
    The searches run on ``fits`` (:class:`Fits`), one per side at a time."""

    PAIR_SAMPLES = 40
    EVERY_S = 0.02
    TRY_EVERY = 20
    MAX_SAMPLES = 200
    MAX_UNC_DEG = 2.0
    FULL_UNC_DEG = 3.0

    def __init__(self, profile: Profile, fits: Fits = INLINE) -> None:
        by_segment = _tag_by_segment(profile.imu_mounts)
        segments = pose_segments(profile)
        self._aside = _Aside(fits)
        self.pairs: dict[str, tuple[str, str, np.ndarray, np.ndarray]] = {}
        for side in ("left", "right"):
            p, c = by_segment.get(f"{side}_thigh"), by_segment.get(f"{side}_shank")
            if p is None or c is None:
                continue
            # the tags' orientations at calibration (mounts computed for a heading of 0)
            p0 = segments[f"{side}_thigh"] @ _quat_matrix(profile.imu_mounts[p])
            c0 = segments[f"{side}_shank"] @ _quat_matrix(profile.imu_mounts[c])
            self.pairs[side] = (p, c, p0, c0)
        self.samples: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {s: [] for s in self.pairs}
        self.found: dict[str, float] = {}
        #: per tag found, the uncertainty (deg) of its pair's headings when taken
        self.unc_deg: dict[str, float] = {}
        self.done: set[str] = set()
        self._last: dict[str, float] = {}

    def update(self, orientations: Mapping[str, QuatWxyz],
               t_s: float | None = None) -> dict[str, float]:  # fmt: skip
        """Take one tick's tag orientations (``t_s``: the tick's time, None taking
        every tick); the headings found at this tick."""
        out: dict[str, float] = {}
        for side, (p, c, p0, c0) in self.pairs.items():
            self._take(side, out)
            if side in self.done or p not in orientations or c not in orientations:
                continue
            if t_s is not None and t_s - self._last.get(side, -math.inf) < self.EVERY_S - 1e-6:
                continue
            a_p = _quat_matrix(orientations[p]) @ p0.T  # each tag's turn since calibration
            a_c = _quat_matrix(orientations[c]) @ c0.T
            moved_p = np.linalg.norm(_rotvec(a_p))
            knee = np.linalg.norm(_rotvec(a_p.T @ a_c))
            if moved_p < math.radians(10) or knee < math.radians(15):
                continue
            if t_s is not None:
                self._last[side] = t_s
            samples = self.samples[side]
            samples.append((a_p, a_c))
            if self._aside.due(side, samples, self.PAIR_SAMPLES, self.TRY_EVERY):
                self._aside.start(side, samples, _knee_pair_headings)
                self._take(side, out)
        self.found.update(out)
        return out

    def _take(self, side: str, out: dict[str, float]) -> None:
        """A side's search, once done: its pair into ``out`` when it is taken."""
        done = self._aside.done(side)
        if done is None:
            return
        fit, n = done
        p, c = self.pairs[side][:2]
        full = n >= self.MAX_SAMPLES
        if fit is not None and fit[2] <= (self.FULL_UNC_DEG if full else self.MAX_UNC_DEG):
            self.done.add(side)
            out[p], out[c] = fit[:2]
            self.unc_deg[p] = self.unc_deg[c] = round(fit[2], 3)
        elif full:  # not telling yet
            _make_way(self.samples[side], self.TRY_EVERY, self.MAX_SAMPLES)


class ChildHeadings:
    """Finds the heading of a tag with a reference of its own (``independent``) whose
    parent's is known, across a two-dof joint (a foot's below its shank, a hand's
    below its forearm).

    As for the knees, the tag's turn since calibration, in its own reference, is
    its segment's turned by its unknown heading; for the right heading the
    joint's second axis (fixed in the child) stays perpendicular to its first
    (fixed in the parent, known). In a swing that holds for four headings 90 deg
    apart (the joint's axes stay perpendicular whichever way the child's turn is
    laid); of those, the one whose joint turns least from the pose wins (the
    others put the segment's swing across its joint: 30-40 deg of ankle against
    5 in a walk), when it beats the runner-up by more than the samples' noise.
    Samples are taken every ``EVERY_S`` once the child has turned past
    ``MOVED_DEG`` since calibration; from ``SAMPLES`` on, every ``TRY_EVERY``,
    the fit is tried and taken once its uncertainty (about two standard
    deviations, :func:`_fit_unc_deg`) is within ``MAX_UNC_DEG`` (within
    ``FULL_UNC_DEG`` once ``MAX_SAMPLES`` have come; beyond, the oldest make
    way): with noisy tags, or tags wobbling on the skin, 40 samples left a foot's
    heading 10-20 deg off. ``unc_deg`` keeps each found tag's uncertainty, which
    the dofs its heading drives carry in the pose's. The fits run on ``fits``
    (:class:`Fits`), one per tag at a time."""

    SAMPLES = 40
    MOVED_DEG = 10.0
    EVERY_S = KneePairs.EVERY_S
    TRY_EVERY = KneePairs.TRY_EVERY
    MAX_SAMPLES = KneePairs.MAX_SAMPLES
    MAX_UNC_DEG = KneePairs.MAX_UNC_DEG
    FULL_UNC_DEG = KneePairs.FULL_UNC_DEG

    def __init__(self, profile: Profile, fits: Fits = INLINE) -> None:
        by_segment = _tag_by_segment(profile.imu_mounts)
        segments = pose_segments(profile)
        self._aside = _Aside(fits)
        #: child key -> (parent key, parent axis, child axis, parent's and child's
        #: segment in the pose, the child tag at calibration for a heading of 0)
        self.joints: dict[str, tuple[str, int, int, np.ndarray, np.ndarray, np.ndarray]] = {}
        for _, parent, child, p_axis, c_axis, kind in DRIFT_JOINTS:
            for side in ("left", "right"):
                p, c = by_segment.get(f"{side}_{parent}"), by_segment.get(f"{side}_{child}")
                if p is None or c is None or kind != "perpendicular":
                    continue
                seg_c = segments[f"{side}_{child}"]
                self.joints[c] = (p, p_axis, c_axis, segments[f"{side}_{parent}"], seg_c,
                                  seg_c @ _quat_matrix(profile.imu_mounts[c]))  # fmt: skip
        self.samples: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {c: [] for c in self.joints}
        self.done: set[str] = set()
        self.found: dict[str, float] = {}
        #: per child key found, the uncertainty (deg) of its heading when taken
        self.unc_deg: dict[str, float] = {}
        self._last: dict[str, float] = {}

    def pending(self, profile: Profile, coming: Iterable[str] = ()) -> bool:
        """Whether a tag may still be found: its heading unknown, not found yet, and
        its parent's known (or among ``coming``, being found)."""
        soon = set(coming)
        return any(c not in self.done and not profile.heading_known(c)
                   and (profile.heading_known(p) or p in soon)
                   for c, (p, *_) in self.joints.items())  # fmt: skip

    def update(self, orientations: Mapping[str, QuatWxyz], profile: Profile,
               t_s: float | None = None) -> dict[str, float]:  # fmt: skip
        """Take one tick's tag orientations (``profile``: the known headings so far;
        ``t_s``: the tick's time, None taking every tick); the headings found at
        this tick."""
        out: dict[str, float] = {}
        for c, (p, p_axis, c_axis, seg_p, seg_c, c0) in self.joints.items():
            self._take(c, out)
            if c in self.done or profile.heading_known(c) or not profile.heading_known(p):
                continue
            if p not in orientations or c not in orientations:
                continue
            if t_s is not None and t_s - self._last.get(c, -math.inf) < self.EVERY_S - 1e-6:
                continue
            a_c = _quat_matrix(orientations[c]) @ c0.T  # the tag's turn since calibration
            if np.linalg.norm(_rotvec(a_c)) < math.radians(self.MOVED_DEG):
                continue
            if t_s is not None:
                self._last[c] = t_s
            parent = JointDrift._segment(profile, p, _quat_matrix(orientations[p]))
            samples = self.samples[c]
            samples.append((parent, a_c))
            if self._aside.due(c, samples, self.SAMPLES, self.TRY_EVERY):
                self._aside.start(c, samples, _child_heading, seg_p, seg_c, p_axis, c_axis)
                self._take(c, out)
        self.found.update(out)
        return out

    def _take(self, c: str, out: dict[str, float]) -> None:
        """A child tag's fit, once done: its heading into ``out`` when it is taken."""
        done = self._aside.done(c)
        if done is None:
            return
        fit, n = done
        full = n >= self.MAX_SAMPLES
        if fit is not None and fit[1] <= (self.FULL_UNC_DEG if full else self.MAX_UNC_DEG):
            self.done.add(c)
            out[c], self.unc_deg[c] = fit[0], round(fit[1], 3)
        elif full:  # not telling yet
            _make_way(self.samples[c], self.TRY_EVERY, self.MAX_SAMPLES)


class ElbowPairs:
    """Finds the heading of each upper arm and forearm tag with a reference of its
    own (``independent``) from the elbow's motion, as :class:`KneePairs` does the
    knees': for the right pair of headings the elbow's axes stay perpendicular
    (its flexion axis, fixed in the upper arm, and its pronation axis, fixed in the
    forearm) and its flexion stays within its range of motion (which settles the
    pair turned by 180 deg). Where the elbow's flexion axis was vertical in the
    calibration pose (a T-pose) the elbow bending tells only the two headings'
    difference, and their common heading shows only as the forearm turns about
    its own axis (pronation); the pair turned by 180 deg then fits as well (its
    flexion the same, the pronation negated) and the shoulder's range of motion
    tells them apart (:func:`_arm_twin`: the chest's tag is needed, ``twins``).
    The samples are taken every ``EVERY_S`` once the
    forearm has turned past ``MOVED_DEG`` since calibration (how far the elbow
    bends cannot be told before the headings are known). From ``MIN_SAMPLES`` on,
    every ``TRY_EVERY`` samples, the pair is searched (every 5 deg; while another
    pair far from the best fits as well, as in a walk with the elbows barely bent,
    there is none) and the best refined (least squares, continuous); it is taken
    once its uncertainty (about two standard deviations, from the misfit's spread
    and the fit's Jacobian: how well the samples constrain the two headings) is
    within ``MAX_UNC_DEG``, or ``MISFIT_SHARE`` of the misfit's RMS (deg; the
    sensors' noise: a fixed 0.3 deg, right for the emulator's 0.3 deg, was never
    reached at 1.5): as soon as the reach has told, not after a fixed count (the
    lift of a straight arm tells only the two headings' difference; the elbow
    bending, both); at ``MAX_SAMPLES`` within ``FULL_UNC_DEG`` or the misfit's
    RMS, never past ``LIMIT_UNC_DEG``. Beyond ``MAX_SAMPLES`` the older half make
    way. ``last_unc_deg`` keeps each side's latest fit's uncertainty (what the
    search waits for). The tries run on ``fits`` (:class:`Fits`), one per side at
    a time."""

    EVERY_S = 0.05
    MOVED_DEG = 10.0
    MIN_SAMPLES = 20
    TRY_EVERY = 4
    MAX_SAMPLES = 120
    MAX_UNC_DEG = 0.3
    FULL_UNC_DEG = 1.0
    MISFIT_SHARE = 0.75
    LIMIT_UNC_DEG = KneePairs.FULL_UNC_DEG

    def __init__(self, profile: Profile, fits: Fits = INLINE) -> None:
        by_segment = _tag_by_segment(profile.imu_mounts)
        segments = pose_segments(profile)
        self._aside = _Aside(fits)
        self.pairs: dict[str, tuple[str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        #: per side whose flexion axis was vertical in the pose (a T-pose): the chest's
        #: tag, at calibration for a heading of 0, and what tells the pair's twin apart
        self.twins: dict[str, tuple[str, np.ndarray, tuple[np.ndarray, str]]] = {}
        chest = by_segment.get("thorax")
        for side in ("left", "right"):
            p, c = by_segment.get(f"{side}_upperarm"), by_segment.get(f"{side}_forearm")
            seg_p, seg_c = segments[f"{side}_upperarm"], segments[f"{side}_forearm"]
            if p is None or c is None:
                continue
            if math.hypot(seg_p[0, 1], seg_p[1, 1]) < HORIZONTAL_MIN:
                if chest is None:  # the twin needs the shoulder
                    continue
                seg_t = segments["thorax"]
                self.twins[side] = (chest, seg_t @ _quat_matrix(profile.imu_mounts[chest]),
                                    (seg_t, side))  # fmt: skip
            p0 = seg_p @ _quat_matrix(profile.imu_mounts[p])
            c0 = seg_c @ _quat_matrix(profile.imu_mounts[c])
            self.pairs[side] = (p, c, p0, c0, seg_p, seg_c)
        #: per side, each sample's tag turns since calibration: the upper arm's, the
        #: forearm's (and the chest's, where the twin is to be told apart)
        self.samples: dict[str, list[tuple[np.ndarray, ...]]] = {s: [] for s in self.pairs}
        self.found: dict[str, float] = {}
        #: per side, the uncertainty (deg) of the pair when taken, and of its latest fit
        self.unc_deg: dict[str, float] = {}
        self.last_unc_deg: dict[str, float] = {}
        self.done: set[str] = set()
        self._last: dict[str, float] = {}
        self._basin: dict[str, tuple[float, float]] = {}  # the grid's best (rad), refined on

    @property
    def coming(self) -> set[str]:
        """The tags whose heading may still be found here."""
        return {k for side, (p, c, *_) in self.pairs.items() if side not in self.done
                for k in (p, c)}  # fmt: skip

    def update(self, t_s: float, orientations: Mapping[str, QuatWxyz]) -> dict[str, float]:
        """Take one tick's tag orientations; the headings found at this tick."""
        out: dict[str, float] = {}
        for side, (p, c, p0, c0, _, _) in self.pairs.items():
            self._take(side, out)
            if side in self.done or p not in orientations or c not in orientations:
                continue
            twin = self.twins.get(side)
            if twin is not None and twin[0] not in orientations:
                continue
            if t_s - self._last.get(side, -math.inf) < self.EVERY_S - 1e-6:
                continue
            a_p = _quat_matrix(orientations[p]) @ p0.T  # each tag's turn since calibration
            a_c = _quat_matrix(orientations[c]) @ c0.T
            if np.linalg.norm(_rotvec(a_c)) < math.radians(self.MOVED_DEG):
                continue
            self._last[side] = t_s
            samples = self.samples[side]
            if twin is None:
                samples.append((a_p, a_c))
            else:
                samples.append((a_p, a_c, _quat_matrix(orientations[twin[0]]) @ twin[1].T))
            if self._aside.due(side, samples, self.MIN_SAMPLES, self.TRY_EVERY):
                limits = (self.MAX_UNC_DEG, self.FULL_UNC_DEG, self.MISFIT_SHARE,
                          self.LIMIT_UNC_DEG)  # fmt: skip
                self._aside.start(side, samples, _elbow_pair_try, *self.pairs[side][4:],
                                  self._basin.get(side), len(samples) >= self.MAX_SAMPLES,
                                  limits, None if twin is None else twin[2])  # fmt: skip
                self._take(side, out)
        self.found.update(out)
        return out

    def _take(self, side: str, out: dict[str, float]) -> None:
        """A side's try (:func:`_elbow_pair_try`), once done: the pair's headings
        into ``out`` when they are taken."""
        done = self._aside.done(side)
        if done is None:
            return
        (unc, basin, found, make_way), n = done
        if unc is not None:
            self.last_unc_deg[side] = unc
        if basin is None:
            self._basin.pop(side, None)
        else:  # refined on from here with the next samples
            self._basin[side] = basin
        if make_way:  # not telling yet: the next samples may (a reach)
            _make_way(self.samples[side], n // 2, self.MAX_SAMPLES)
        if found is not None:
            p, c = self.pairs[side][:2]
            self.done.add(side)
            out[p], out[c], self.unc_deg[side] = found


class SharedTwoDof:
    """Finds the tags' shared heading (``auto``) from an elbow's or wrist's motion as a
    two-dof joint, where no hinge tells (after a T-pose the elbow's flexion axis
    is vertical, and an arm-only session bends no knee).

    The joint's first axis is fixed in the parent (the elbow's flexion axis, the
    wrist's flexion axis), its second in the child (the forearm's long axis, the
    hand's deviation axis), and they stay perpendicular: with one heading for both
    tags, the misfit of :class:`ElbowPairs` searched over one heading instead of
    two. After a T-pose it tells once the joint turns about its second axis, or
    the wrist flexes (an elbow bending alone turns about its vertical axis, which
    every heading keeps: it tells nothing, and nothing is taken). Samples are taken
    every ``EVERY_S`` once the child has turned past ``MOVED_DEG`` since
    calibration; from ``MIN_SAMPLES`` on, every ``TRY_EVERY``, the heading is
    searched (every 2 deg, none while a heading far from the best and from its
    twin fits about as well; then least squares) and taken once its uncertainty
    (:func:`_fit_unc_deg`) is within ``MAX_UNC_DEG`` (``FULL_UNC_DEG`` at
    ``MAX_SAMPLES``; beyond, the oldest make way). Where one of the joint's axes
    was vertical in the pose the heading turned by 180 deg keeps the axes as
    perpendicular (the pronation and the wrist's flexion then come out negated,
    an arm lowered from a T-pose raised): of the two, the one that keeps the
    shoulder inside its range of motion wins, by ``TWIN_MARGIN_DEG`` a sample,
    so the chest's and the upper arm's tags are needed too. The heading found is
    a candidate, checked by :class:`SharedCheck` before it is taken. The tries run
    on ``fits`` (:class:`Fits`), one per joint at a time."""

    JOINTS = ("elbow", "wrist")
    EVERY_S = ElbowPairs.EVERY_S
    MOVED_DEG = ElbowPairs.MOVED_DEG
    MIN_SAMPLES = ElbowPairs.MIN_SAMPLES
    TRY_EVERY = ElbowPairs.TRY_EVERY
    MAX_SAMPLES = ElbowPairs.MAX_SAMPLES
    MAX_UNC_DEG = 0.5
    FULL_UNC_DEG = ElbowPairs.FULL_UNC_DEG
    TWIN_MARGIN_DEG = 2.0

    def __init__(self, profile: Profile, fits: Fits = INLINE) -> None:
        by_segment = _tag_by_segment(profile.imu_mounts)
        segments = pose_segments(profile)
        self._aside = _Aside(fits)
        #: joint -> its tags (parent, child, chest, upper arm), each at calibration
        #: for a heading of 0, and the segments in the pose and axes its try wants
        self.joints: dict[str, tuple[tuple[str, ...], tuple[np.ndarray, ...], tuple[Any, ...]]] = {}
        for joint, parent, child, p_axis, c_axis, _ in DRIFT_JOINTS:
            if joint not in self.JOINTS:
                continue
            for side in ("left", "right"):
                names = (f"{side}_{parent}", f"{side}_{child}", "thorax", f"{side}_upperarm")
                keys = tuple(by_segment.get(n) for n in names)
                if None in keys:
                    continue
                tags0 = tuple(segments[n] @ _quat_matrix(profile.imu_mounts[k])
                              for n, k in zip(names, keys, strict=True))  # fmt: skip
                args = (segments[names[0]], segments[names[1]], (p_axis, c_axis),
                        segments["thorax"], segments[names[3]], side)  # fmt: skip
                self.joints[f"{side}_{joint}"] = (keys, tags0, args)  # type: ignore[assignment]
        self.samples: dict[str, list[tuple[np.ndarray, ...]]] = {j: [] for j in self.joints}
        self.heading: float | None = None
        self.joint: str | None = None  # the joint that gave it
        self.unc_deg: float | None = None
        #: per joint, its latest fit's uncertainty (deg: what the search waits for)
        self.last_unc_deg: dict[str, float] = {}
        self._last: dict[str, float] = {}

    def update(self, t_s: float, orientations: Mapping[str, QuatWxyz]) -> float | None:
        """Take one tick's tag orientations; the heading (deg) once found (a candidate
        for :class:`SharedCheck`), then the same."""
        for joint, (keys, tags0, args) in self.joints.items():
            if self.heading is not None:
                break
            self._take(joint)
            if any(k not in orientations for k in keys):
                continue
            if t_s - self._last.get(joint, -math.inf) < self.EVERY_S - 1e-6:
                continue
            turns = tuple(_quat_matrix(orientations[k]) @ r0.T
                          for k, r0 in zip(keys, tags0, strict=True))  # fmt: skip
            if np.linalg.norm(_rotvec(turns[1])) < math.radians(self.MOVED_DEG):
                continue
            self._last[joint] = t_s
            samples = self.samples[joint]
            samples.append(turns)
            if self._aside.due(joint, samples, self.MIN_SAMPLES, self.TRY_EVERY):
                full = len(samples) >= self.MAX_SAMPLES
                most = self.FULL_UNC_DEG if full else self.MAX_UNC_DEG
                self._aside.start(joint, samples, _shared_two_dof_try, *args, most)
                self._take(joint)
        return self.heading

    def _take(self, joint: str) -> None:
        """A joint's try, once done: the heading when it is taken."""
        done = self._aside.done(joint)
        if done is None or self.heading is not None:
            return
        (unc, found), n = done
        if unc is not None:
            self.last_unc_deg[joint] = unc
        if found is not None:
            self.heading, self.unc_deg = found
            self.joint = joint
        elif n >= self.MAX_SAMPLES:  # not telling yet
            _make_way(self.samples[joint], self.TRY_EVERY, self.MAX_SAMPLES)


class TrunkBow:
    """Finds the heading of the pelvis', chest's and head's tags with references of
    their own (``independent``) from a bow.

    A wrong heading only mis-states which way a tag's segment tilts (a turn about
    the vertical is the same whatever it is), so these tags' headings show when
    their segments tilt. Gravity seen by the tag, in the tag's reference frame at
    calibration (``R_s0 R_s(t)^T z``), moves by ``Rz(psi)`` times where it moves in
    the body's frame (``R_seg0 R_seg(t)^T z``), whatever the drift of the tag's
    reference or the turns of the body since the pose; in a forward bow it moves
    backward. So a bow is waited for: the pelvis tag (the chest's where there is
    none) tilted past ``GATE_DEG`` from the pose, which the hips flexing give and
    a walk, a side bend or a turn of the trunk do not. ``SAMPLES`` samples are
    taken every ``EVERY_S`` while it lasts; then each tag's heading is the one
    that puts the way gravity moved in its frame backward in the body's (the bow
    is forward), over the samples in which its segment tilted past ``TILT_DEG``
    and at least as far as the pelvis (at least half of them), when their ways
    agree (the mean resultant length of their directions at least
    ``AGREEMENT``). A tag not found in one bow is looked for in the next.

    That rule sees the segment's own frame, so a chest or head twisted about its
    long axis in the bow (the trunk or head turned) is taken for a heading. Above
    the pelvis, the joint flexes in its parent's sagittal plane, twisted or not:
    the chest's and head's heading *now* is the one that keeps the axis that was
    vertical in the pose in that plane (:meth:`_level`). The difference between
    the two is the tag's twist in the bow, or its drift against its parent since
    the pose: drift as far as drift can have gone (``SNAP_DEG_PER_MIN``), the rest
    twist; the heading at calibration (the mount's) is the level one less that
    drift.

    The assumptions: the pelvis' first tilt past ``GATE_DEG`` is a forward bow
    (sitting down slumped, which tilts it backward, would be taken for one), and
    in it the chest and the head tilt forward too (a head looking up while the
    chest bows, tilted back as far as the pelvis forward, would be taken turned
    round: the neck near the end of its range); the lumbar and neck do not bend
    sideways in it (their lateral bend goes into the headings)."""

    SEGMENTS = ("pelvis", "thorax", "head")
    GATE_DEG = 20.0
    TILT_DEG = 15.0
    SAMPLES = 20
    EVERY_S = 0.05
    AGREEMENT = 0.97
    #: how fast a 6-axis tag's reference drifts at most (deg/min), and the noise of a
    #: joint's twist in a bow (deg): the bounds of :meth:`snap`
    SNAP_DEG_PER_MIN = 10.0
    SNAP_NOISE_DEG = 1.0
    #: the chest's and head's heading now is searched this far (deg) from the forward
    #: rule's, and taken when the worst fits this much worse (the sine of a tilt)
    LEVEL_DEG = 45.0
    LEVEL_GRIP = 0.2
    #: the drift found at a bow is taken as a rate over the time since the pose, or this
    RATE_SINCE_S = 60.0

    def __init__(self, profile: Profile) -> None:
        by_segment = _tag_by_segment(profile.imu_mounts)
        segments = pose_segments(profile)
        #: segment -> (its tag, the tag at calibration for a heading of 0, the pose's segment)
        self.tags: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}
        for seg in self.SEGMENTS:
            if seg in by_segment:
                key = by_segment[seg]
                tag0 = segments[seg] @ _quat_matrix(profile.imu_mounts[key])
                self.tags[seg] = (key, tag0, segments[seg])
        self._tag0 = {key: tag0 for key, tag0, _ in self.tags.values()}
        gate = next((s for s in ("pelvis", "thorax") if s in self.tags), None)
        self.gate = self.tags[gate][0] if gate is not None else None
        self.samples: list[dict[str, np.ndarray]] = []
        self.bow: list[dict[str, np.ndarray]] = []  # the samples of the last headings found
        self.found: dict[str, float] = {}
        self._last = -math.inf
        self._t0: float | None = None
        self._bow_t = 0.0  # when the last headings were found
        #: per tag placed against its parent at the last find: its heading now less
        #: its heading at calibration (the drift between them since the pose)
        self.drifted: dict[str, float] = {}
        #: per tag turned at the last find by its joint's twist in the bow (deg)
        self.joined: dict[str, float] = {}
        #: the three-dof joints from the root out (parent's segment and tag, child's
        #: segment and tag, the twist in the pose), and each segment's tags and below
        self._joints: list[tuple[str, str, str, str, float]] = []
        for _, parent, child in sorted(TWIST_JOINTS, key=lambda j: TWIST_ORDER.index(j[0])):
            sided = child in ("thigh", "upperarm")
            for name in [f"{side}_{child}" for side in ("left", "right")] if sided else [child]:
                if parent in by_segment and name in by_segment:
                    twist0 = _twist(segments[parent], segments[name]) or 0.0
                    self._joints.append((parent, by_segment[parent], name, by_segment[name],
                                         twist0))  # fmt: skip
        below: dict[str, list[str]] = {}
        for j in build_skeleton(profile.lengths).joints:
            below.setdefault(j.parent, []).append(j.child)

        def subtree(seg: str) -> list[str]:
            return [seg, *(s for c in below.get(seg, []) for s in subtree(c))]

        self._subtree = {seg: [by_segment[s] for s in subtree(seg) if s in by_segment]
                         for seg in by_segment}  # fmt: skip

    def coming(self, profile: Profile) -> set[str]:
        """The tags whose heading may still be found here."""
        if self.gate is None:
            return set()
        return {key for key, _, _ in self.tags.values() if not profile.heading_known(key)}

    def _gravity(self, key: str, rot: np.ndarray) -> np.ndarray:
        """Where gravity is now, seen by the tag (``rot``: its orientation now), in
        the tag's reference frame at calibration (where it was: +z)."""
        return self._tag0[key] @ rot[2]  # type: ignore[no-any-return]

    def update(self, t_s: float, orientations: Mapping[str, QuatWxyz],
               profile: Profile) -> dict[str, float]:  # fmt: skip
        """Take one tick's tag orientations (``profile``: the headings known so far);
        the headings found at this tick."""
        if self._t0 is None:
            self._t0 = t_s  # the first tick after the pose
        if self.gate is None or self.gate not in orientations or not self.coming(profile):
            return {}
        if t_s - self._last < self.EVERY_S - 1e-6:
            return {}
        rots = {key: _quat_matrix(orientations[key]) for key, _, _ in self.tags.values()
                if key in orientations}  # fmt: skip
        if self._gravity(self.gate, rots[self.gate])[2] > math.cos(math.radians(self.GATE_DEG)):
            self.samples.clear()  # not (or no longer) bowing: a bow's samples are its own
            return {}
        self._last = t_s
        rots.update({k: _quat_matrix(q) for k, q in orientations.items() if k not in rots})
        self.samples.append(rots)
        if len(self.samples) < self.SAMPLES:
            return {}
        self.bow, self.samples, self._bow_t = self.samples, [], t_s
        self.joined = {}
        out: dict[str, float] = {}
        self.drifted, now = {}, {}  # heading now - at calibration; headings now
        for seg, (key, _, _) in self.tags.items():
            if profile.heading_known(key):
                continue
            psi = self._forward(key)
            if psi is None:
                continue
            out[key] = now[key] = psi
            parent = {"thorax": "pelvis", "head": "thorax"}.get(seg)
            if parent is None or parent not in self.tags:
                continue
            p_key = self.tags[parent][0]
            if not profile.heading_known(p_key) and p_key not in out:
                continue
            level = self._level(key, parent, profile, out, now, psi)
            if level is None:
                continue
            # what is left of the forward rule's heading is drift since the pose, as
            # far as two tags can have drifted apart; the rest, the bow's twist
            most = self._most_drift()
            drift = max(-most, min(most, _wrap(level - psi)))
            out[key], now[key] = _wrap(level - drift), level
            self.drifted[key] = drift
        self.found.update(out)
        return out

    def _most_drift(self) -> float:
        """How far two tags' references can have drifted apart since the pose (deg)."""
        minutes = (self._bow_t - (self._t0 if self._t0 is not None else self._bow_t)) / 60.0
        return 2.0 * self.SNAP_DEG_PER_MIN * minutes

    def _level(self, key: str, parent: str, profile: Profile, found: Mapping[str, float],
               now: Mapping[str, float], near: float) -> float | None:  # fmt: skip
        """The tag's heading now, within ``LEVEL_DEG`` of ``near``, that keeps its
        segment's axis that was vertical in the pose in its parent's sagittal plane
        (the joint flexing, not bending sideways; a twist of the segment about that
        axis does not move it) over the samples its segment tilted in (``found``,
        ``now``: the headings at calibration and now of the tags found in this bow);
        None without a grip (the two barely tilted)."""
        p_key, p0, seg_p0 = self.tags[parent]
        tag0 = self._tag0[key]
        ups, sides = [], []
        for rots in self.bow:
            if key not in rots or p_key not in rots:
                continue
            g = self._gravity(key, rots[key])
            if g[2] > min(math.cos(math.radians(self.TILT_DEG)),
                          self._gravity(self.gate, rots[self.gate])[2] + 1e-9):  # fmt: skip
                continue
            if p_key in found:
                cal, turn = rz(found[p_key]), rz(now[p_key])
                seg_p = turn.T @ rots[p_key] @ p0.T @ cal @ seg_p0
            else:
                seg_p = JointDrift._segment(profile, p_key, rots[p_key])
            sides.append(seg_p[:, 1])  # the parent's lateral axis, in the body's frame
            ups.append(rots[key] @ tag0[2])  # the pose's vertical axis, in the tag's frame
        if len(ups) < self.SAMPLES // 2:
            return None
        u, y = np.array(ups), np.array(sides)
        psi = np.radians(near + np.arange(-self.LEVEL_DEG, self.LEVEL_DEG + 0.1, 0.1))
        c, s = np.cos(psi)[:, None], np.sin(psi)[:, None]
        # Rz(-psi) u . y, for each heading (rows) and sample (columns)
        off = ((c * u[:, 0] + s * u[:, 1]) * y[:, 0] + (c * u[:, 1] - s * u[:, 0]) * y[:, 1]
               + u[:, 2] * y[:, 2])  # fmt: skip
        cost = (off**2).mean(axis=1)
        k = int(np.argmin(cost))
        if k in (0, len(psi) - 1) or cost.max() - cost[k] < self.LEVEL_GRIP**2:
            return None  # no minimum in the window, or no grip on the heading
        return _wrap(math.degrees(psi[k]))

    def _forward(self, key: str) -> float | None:
        """The tag's heading from the way gravity moved in its frame in the samples
        its segment tilted past ``TILT_DEG`` in, and at least as far as the pelvis
        (backward in a forward bow); None when too few, or their ways do not agree.
        (Above the pelvis, in a bow, the lumbar and neck flex: a chest tilted back
        as far as the pelvis forward is out of the lumbar's range, a head so only
        at the end of the neck's.)"""
        sums, units, n = np.zeros(2), np.zeros(2), 0
        tilt = math.cos(math.radians(self.TILT_DEG))
        for rots in self.bow:
            if key not in rots:
                continue
            g = self._gravity(key, rots[key])
            if g[2] > min(tilt, self._gravity(self.gate, rots[self.gate])[2] + 1e-9):
                continue
            sums += g[:2]
            units += g[:2] / np.linalg.norm(g[:2])
            n += 1
        if n < self.SAMPLES // 2 or np.linalg.norm(units) < self.AGREEMENT * n:
            return None
        return _wrap(math.degrees(math.atan2(sums[1], sums[0])) - 180.0)

    def snap(self, profile: Profile, found: Iterable[str]) -> dict[str, float]:
        """The turns to add to tags' headings once ``found`` (tags just found, their
        headings in ``profile``) join three-dof joints to tags known before.

        A heading found from gravity is the tag's at calibration (its mount's),
        while a tag's reference drifts, each its own way, from the pose on: the
        joints the find joins would show the drift between their two tags since
        then, until the three-dof joints' hold (:class:`JointDrift`) takes it out
        (about 30 s). The bow twists none of them (the hips and lumbar flex, the
        head and arms go with the trunk: the assumption the hold makes too), so
        each joined joint's child, and all below it, is turned at once by the
        joint's mean twist over the bow's samples against the pose's, from the
        root out, as far as two tags can have drifted apart since the pose
        (``SNAP_DEG_PER_MIN`` each, and ``SNAP_NOISE_DEG``): a bow just after the
        pose, twisted, is not taken for drift."""
        new = set(found)
        if not self.bow or not new or not profile.drift_joints[1]:
            return {}
        most = self.SNAP_NOISE_DEG + self._most_drift()
        turns: dict[str, float] = {}
        for _, p_key, child, c_key, twist0 in self._joints:
            if not (profile.heading_known(p_key) and profile.heading_known(c_key)):
                continue
            if (p_key not in new and c_key not in new) or c_key in self.drifted:
                continue  # joined before (the hold has it), or placed against its parent
            offsets = []
            for rots in self.bow:
                if p_key in rots and c_key in rots:
                    twist = _twist(JointDrift._segment(profile, p_key, rots[p_key]),
                                   JointDrift._segment(profile, c_key, rots[c_key]))  # fmt: skip
                    if twist is not None:
                        offsets.append(math.radians(twist - twist0))
            if len(offsets) < len(self.bow) // 2:
                continue
            turn = math.degrees(math.atan2(np.sin(offsets).mean(), np.cos(offsets).mean()))
            turn = max(-most, min(most, turn))
            keys = [k for k in self._subtree[child] if profile.heading_known(k)]
            profile = turned_headings(profile, dict.fromkeys(keys, turn))
            for k in keys:
                turns[k] = turns.get(k, 0.0) + turn
            self.joined[c_key] = turn
        return turns

    def drift_rates(self) -> dict[str, float]:
        """Per tag the last find placed against its parent (``drifted``) or turned by
        its joint's twist (``joined``): the drift between them since the pose, as a
        rate (deg/s) over the time since, at least ``RATE_SINCE_S`` (a bow soon after
        the pose says little of a rate), for the three-dof joints' hold to start from
        (:class:`JointDrift`'s loop would otherwise learn it from zero)."""
        since = self._bow_t - (self._t0 if self._t0 is not None else self._bow_t)
        since = max(since, self.RATE_SINCE_S)
        return {k: v / since for k, v in {**self.drifted, **self.joined}.items()}


def _elbow_pair_segments(samples: Sequence[tuple[np.ndarray, np.ndarray]], seg_p: np.ndarray,
                         seg_c: np.ndarray, psi_p: np.ndarray, psi_c: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The upper arms (body frame; (kp, n, 3, 3)) for each of the ``kp`` headings
    ``psi_p`` (rad) and ``n`` samples (each tag's turn since calibration), and the
    forearms for each of ``psi_c``."""
    a_p = np.array([s[0] for s in samples])[None]
    a_c = np.array([s[1] for s in samples])[None]
    rp, rc = _rz_batch(psi_p)[:, None], _rz_batch(psi_c)[:, None]
    b_p = rp.transpose(0, 1, 3, 2) @ a_p @ rp @ seg_p
    b_c = rc.transpose(0, 1, 3, 2) @ a_c @ rc @ seg_c
    return b_p, b_c


#: the elbow's axes: its flexion axis in the upper arm (y), its pronation axis in the forearm (z)
ELBOW_AXES = (1, 2)


def _axes_dot(b_p: np.ndarray, b_c: np.ndarray, axes: tuple[int, int],
              outer: bool = False) -> np.ndarray:  # fmt: skip
    """A two-dof joint's misfit: the dot product of its axes (``axes``: the parent's,
    fixed in the parent segment, and the child's; 0 when perpendicular) per sample,
    for each parent and child segment of ``b_p`` and ``b_c`` ((k, n, 3, 3), as
    :func:`_elbow_pair_segments` gives): (k, n), each parent with its child
    (``outer``: (kp, kc, n), each parent with each child)."""
    p, c = b_p[..., :, axes[0]], b_c[..., :, axes[1]]
    return np.einsum("pni,cni->pcn" if outer else "kni,kni->kn", p, c)  # type: ignore[no-any-return]


def _elbow_pair_cost(samples: Sequence[tuple[np.ndarray, np.ndarray]], seg_p: np.ndarray,
                     seg_c: np.ndarray, psi_p: np.ndarray, psi_c: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per pair of headings (each of ``psi_p`` with each of ``psi_c``: (kp, kc)): the
    RMS of the elbow's axes' dot product (0: perpendicular), and how far (deg,
    summed over the samples) its flexion falls outside its range."""
    lo, hi = rom("left_elbow_flexion_deg")
    b_p, b_c = _elbow_pair_segments(samples, seg_p, seg_c, psi_p, psi_c)
    perp = np.sqrt((_axes_dot(b_p, b_c, ELBOW_AXES, outer=True) ** 2).mean(-1))
    # the forearm in the upper arm: its flexion about -y
    rel_20 = np.einsum("pni,cni->pcn", b_p[..., :, 2], b_c[..., :, 0])
    rel_00 = np.einsum("pni,cni->pcn", b_p[..., :, 0], b_c[..., :, 0])
    flexion = np.degrees(np.arctan2(rel_20, rel_00))
    outside = np.maximum(0.0, np.maximum(lo - 10 - flexion, flexion - hi - 10)).sum(axis=-1)
    return perp, outside


def _apart_deg(a: tuple[float, float], b: tuple[float, float]) -> float:
    """How far apart (deg) two pairs of headings (rad) are, in the farther one."""
    return max(abs(_wrap(math.degrees(x - y))) for x, y in zip(a, b, strict=True))


def _elbow_pair_grid(samples: Sequence[tuple[np.ndarray, ...]], seg_p: np.ndarray,
                     seg_c: np.ndarray, twin: bool = False
                     ) -> tuple[float, float] | None:  # fmt: skip
    """The upper arm's and forearm's tag headings (rad, every 5 deg) that keep the
    elbow's axes most nearly perpendicular with its flexion in range; None when
    a pair far from it (and from its 180 deg twin, with ``twin``: the flexion axis
    vertical in the pose, where the twin fits as well) fits about as well (the
    motion does not tell)."""
    grid = np.radians(np.arange(0.0, 360.0, 5.0))
    gp, gc = (g.ravel() for g in np.meshgrid(grid, grid, indexing="ij"))
    perp, outside = (v.ravel() for v in _elbow_pair_cost(samples, seg_p, seg_c, grid, grid))
    best = int(np.lexsort((perp, np.round(outside, 0)))[0])
    # a motion that fits a pair far from the best as well (within 20 deg of it in
    # neither heading, as much inside the range) tells nothing: the elbow barely bent
    far = np.maximum(np.abs(_wrap_rad(gp - gp[best])), np.abs(_wrap_rad(gc - gc[best])))
    if twin:
        far = np.minimum(far, np.maximum(np.abs(_wrap_rad(gp - gp[best] - math.pi)),
                                         np.abs(_wrap_rad(gc - gc[best] - math.pi))))  # fmt: skip
    rivals = (far > math.radians(20.0)) & (np.round(outside, 0) <= round(float(outside[best])))
    if rivals.any() and perp[rivals].min() < 2.0 * perp[best]:
        return None
    return float(gp[best]), float(gc[best])


def _elbow_pair_refine(samples: Sequence[tuple[np.ndarray, np.ndarray]], seg_p: np.ndarray,
                       seg_c: np.ndarray, start: tuple[float, float]
                       ) -> tuple[float, float, float, float] | None:  # fmt: skip
    """The pair of headings (rad) near ``start`` that keeps the elbow's axes
    perpendicular (least squares), its uncertainty (deg, about two standard
    deviations: the misfit's spread through the fit's Jacobian) and the misfit's
    RMS (deg off perpendicular); None when it is not an elbow's motion (the axes
    off perpendicular by more than ``CHILD_MISFIT_DEG``, the flexion out of range)
    or the fit left the basin (10 deg)."""
    from scipy.optimize import least_squares

    def residuals(x: np.ndarray) -> np.ndarray:
        b_p, b_c = _elbow_pair_segments(samples, seg_p, seg_c, x[:1], x[1:])
        return _axes_dot(b_p, b_c, ELBOW_AXES)[0]

    fit = least_squares(residuals, np.array(start), method="lm")
    psi_p, psi_c = (float(v) for v in fit.x)
    if _apart_deg((psi_p, psi_c), start) > 10.0:
        return None
    n = len(samples)
    perp, outside = _elbow_pair_cost(samples, seg_p, seg_c, fit.x[:1], fit.x[1:])
    misfit = math.degrees(math.asin(min(1.0, float(perp[0, 0]))))
    if misfit > CHILD_MISFIT_DEG or outside[0, 0] > 5.0 * n:
        return None  # not an elbow's motion
    jtj = fit.jac.T @ fit.jac
    if abs(np.linalg.det(jtj)) < 1e-12:
        return None
    cov = float(fit.fun @ fit.fun) / max(1, n - 2) * np.linalg.inv(jtj)
    unc = 2.0 * math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov).max()), 0.0)))
    return psi_p, psi_c, unc, misfit


def _elbow_pair_try(samples: Sequence[tuple[np.ndarray, ...]], seg_p: np.ndarray,
                    seg_c: np.ndarray, basin: tuple[float, float] | None, full: bool,
                    limits: tuple[float, float, float, float],
                    twin: tuple[np.ndarray, str] | None = None
                    ) -> tuple[float | None, tuple[float, float] | None,
                               tuple[float, float, float] | None, bool]:  # fmt: skip
    """One try of :class:`ElbowPairs` at a side's pair over its ``samples`` (``full``:
    as many as it keeps), refined from ``basin`` (the last try's, or None: the
    grid's), within ``limits`` (its ``MAX_UNC_DEG``, ``FULL_UNC_DEG``,
    ``MISFIT_SHARE``, ``LIMIT_UNC_DEG``); ``twin``: the chest's segment in the pose
    and the side, where the flexion axis was vertical in it (a T-pose: the pair
    turned by 180 deg fits as well, the pronation negated; the shoulder's range
    tells them apart, :func:`_arm_twin`, each sample holding the chest's tag turn
    last). Returns the fit's uncertainty (deg, None without a fit), the basin to
    refine on from (None: the grid's anew), the pair's headings (deg) and
    uncertainty once taken, and whether the oldest samples make way."""
    most, full_most, share, limit = limits
    start = basin or _elbow_pair_grid(samples, seg_p, seg_c, twin is not None)
    fit = None if start is None else _elbow_pair_refine(samples, seg_p, seg_c, start)
    if fit is None:  # no basin (yet), or a new start
        return None, None, None, full
    psi_p, psi_c, unc, misfit = fit
    bound = min(max(full_most if full else most, misfit if full else share * misfit), limit)
    if unc > bound:
        return round(unc, 2), None if full else (psi_p, psi_c), None, full
    grid = _elbow_pair_grid(samples, seg_p, seg_c, twin is not None)  # still the best basin
    if grid is None or min(_apart_deg(grid, (psi_p + k, psi_c + k))
                           for k in ((0.0, math.pi) if twin else (0.0,))) > 10.0:  # fmt: skip
        return round(unc, 2), None, None, False
    if twin is not None:
        turn = _arm_twin(samples, seg_p, *twin, psi_p)
        if turn is None:  # the shoulder has not told the twins apart yet
            return round(unc, 2), (psi_p, psi_c), None, full
        psi_p, psi_c = psi_p + turn, psi_c + turn
    found = _wrap(math.degrees(psi_p)), _wrap(math.degrees(psi_c)), round(unc, 3)
    return round(unc, 2), None, found, False


def _shoulders_outside(samples: Sequence[tuple[np.ndarray, ...]], seg_t: np.ndarray,
                       seg_u: np.ndarray, side: str, psi: float,
                       psi_t: float | None = None) -> float:  # fmt: skip
    """How far (deg, summed over the ``samples``: each holds the chest's and the upper
    arm's tag turns since calibration last) the ``side`` shoulder falls outside its
    range of motion under the shared heading ``psi`` (rad; ``psi_t``: the chest
    tag's, when it is not ``psi``)."""
    from bodynet.gateway.solver import JointAxes

    shoulder = JointAxes.of(build_skeleton().joint(f"{side}_shoulder"))
    b_t, b_u = _elbow_pair_segments([s[-2:] for s in samples], seg_t, seg_u,
                                    np.array([psi if psi_t is None else psi_t]),
                                    np.array([psi]))  # fmt: skip
    total = 0.0
    for t, u in zip(b_t[0], b_u[0], strict=True):
        angles = shoulder.split(t.T @ u, None)
        total += sum(max(0.0, lo - v, v - hi) for v, (lo, hi)
                     in zip(angles, shoulder.limits, strict=True))  # fmt: skip
    return total


def _twin_turn(here: float, twin: float, n: int) -> float | None:
    """Of a heading and its 180 deg twin, whose shoulders fall ``here`` and ``twin``
    deg outside their range over ``n`` samples: the turn to add (0 or pi, rad) to
    the one that wins by ``SharedTwoDof.TWIN_MARGIN_DEG`` a sample, None if neither."""
    margin = SharedTwoDof.TWIN_MARGIN_DEG * n
    return 0.0 if twin - here >= margin else math.pi if here - twin >= margin else None


def _arm_twin(samples: Sequence[tuple[np.ndarray, ...]], seg_u: np.ndarray, seg_t: np.ndarray,
              side: str, psi_u: float) -> float | None:  # fmt: skip
    """Which of an upper arm's tag heading ``psi_u`` (rad) and its 180 deg twin keeps
    the ``side`` shoulder inside its range of motion, by ``SharedTwoDof.TWIN_MARGIN_DEG``
    a sample (``samples``: the upper arm's tag turn first, the chest's last): the
    turn to add (0 or pi, rad), or None when they are not told apart. The chest's
    tag heading is not known yet (a bow gives it): the verdict must hold for each
    of its headings every ``TWIN_CHEST_STEP_DEG`` (where the chest keeps upright,
    its heading hardly moves the shoulder)."""
    pairs = [(s[-1], s[0]) for s in samples]
    verdict = None
    for psi_t in np.radians(np.arange(0.0, 360.0, TWIN_CHEST_STEP_DEG)):
        here, twin = (_shoulders_outside(pairs, seg_t, seg_u, side, x, float(psi_t))
                      for x in (psi_u, psi_u + math.pi))  # fmt: skip
        this = _twin_turn(here, twin, len(samples))
        if this is None or (verdict is not None and this != verdict):
            return None  # not told apart under this chest heading (the rest not computed)
        verdict = this
    return verdict


def _shared_two_dof_try(samples: Sequence[tuple[np.ndarray, ...]], seg_p: np.ndarray,
                        seg_c: np.ndarray, axes: tuple[int, int], seg_t: np.ndarray,
                        seg_u: np.ndarray, side: str, most: float
                        ) -> tuple[float | None, tuple[float, float] | None]:  # fmt: skip
    """One try of :class:`SharedTwoDof` at a joint: the shared heading (rad) that keeps
    the joint's axes perpendicular over the ``samples`` (each the parent's and
    child's tag turns since calibration, then the chest's and upper arm's), the
    same misfit as :class:`ElbowPairs`' with one heading for both tags. Returns
    the fit's uncertainty (deg; None without a fit) and, once it is within
    ``most``, the heading (deg) and its uncertainty, its 180 deg twin (which keeps
    the axes as perpendicular when one of them was vertical in the pose: the
    T-pose's elbow and wrist) told apart by the shoulder's range of motion."""
    from scipy.optimize import least_squares

    pairs = [s[:2] for s in samples]

    def dots(psi: np.ndarray) -> np.ndarray:
        b_p, b_c = _elbow_pair_segments(pairs, seg_p, seg_c, psi, psi)
        return _axes_dot(b_p, b_c, axes)

    grid = np.radians(np.arange(0.0, 360.0, 2.0))
    rms = np.sqrt((dots(grid) ** 2).mean(axis=1))
    best = int(np.argmin(rms))
    # a heading far from the best and from its twin that fits about as well: the
    # joint has not moved the way that tells (an elbow bending alone after a T-pose)
    far = np.minimum(np.abs(_wrap_rad(grid - grid[best])),
                     np.abs(_wrap_rad(grid - grid[best] - math.pi)))  # fmt: skip
    rivals = far > math.radians(20.0)
    if rivals.any() and rms[rivals].min() < 2.0 * rms[best]:
        return None, None
    fit = least_squares(lambda x: dots(x)[0], grid[best : best + 1], method="lm")
    psi = float(fit.x[0])
    if abs(_wrap(math.degrees(psi - grid[best]))) > 10.0:
        return None, None  # left the basin
    misfit = math.degrees(math.asin(min(1.0, math.sqrt(float(np.mean(fit.fun**2))))))
    if misfit > CHILD_MISFIT_DEG:
        return None, None  # not this joint's motion (tags with headings of their own)
    unc = _fit_unc_deg(fit.fun, fit.jac)
    if unc > most:
        return round(unc, 2), None
    here, twin = (_shoulders_outside(samples, seg_t, seg_u, side, x)
                  for x in (psi, psi + math.pi))  # fmt: skip
    turn = _twin_turn(here, twin, len(samples))
    if turn is None:
        return round(unc, 2), None  # the shoulder's range does not tell the twins apart
    return round(unc, 2), (_wrap(math.degrees(psi + turn)), round(unc, 3))


def _fit_unc_deg(residuals: np.ndarray, jacobian: np.ndarray) -> float:
    """A least-squares fit's uncertainty (deg, about two standard deviations of its
    worst-known direction): the misfit's spread through the fit's Jacobian
    (``jacobian``: (n, parameters), per rad), the samples counted as independent
    only as far as their misfits are (a wobble of the tags on the skin lasts many
    samples: the lag-one autocorrelation of the misfit, in time order, shrinks n)."""
    n, k = jacobian.shape
    jtj = jacobian.T @ jacobian
    if n <= k or abs(np.linalg.det(jtj)) < 1e-12:
        return math.inf
    r = residuals - residuals.mean()
    rho = float(r[1:] @ r[:-1]) / max(float(r @ r), 1e-300) if n > 2 else 0.0
    rho = max(0.0, min(0.95, rho))
    cov = float(residuals @ residuals) / (n - k) * np.linalg.inv(jtj) * (1 + rho) / (1 - rho)
    return 2.0 * math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(cov).max()), 0.0)))


def _child_heading(samples: Sequence[tuple[np.ndarray, np.ndarray]], seg_p: np.ndarray,
                   seg_c: np.ndarray, p_axis: int, c_axis: int
                   ) -> tuple[float, float] | None:  # fmt: skip
    """The child tag's heading (deg) that keeps the joint's axes perpendicular and
    turns the joint least from the pose, and its uncertainty (deg,
    :func:`_fit_unc_deg`); None when no heading keeps them so (the misfit past
    ``CHILD_MISFIT_DEG``), or the runner-up (the next perpendicular fit) does not
    turn the joint more by more than the samples' noise."""
    parents = np.array([p for p, _ in samples])  # the parent segment, body frame
    turns = np.array([a for _, a in samples])
    p_axes, c_axis0 = parents[:, :, p_axis], seg_c[:, c_axis]
    pose_rel = seg_p.T @ seg_c

    def perp(psi: np.ndarray) -> np.ndarray:
        """Per heading and sample (k, n): the axes' dot product (0: perpendicular)."""
        rc = _rz_batch(psi)
        axis = np.einsum("kji,njl,kl->kni", rc, turns, rc @ c_axis0)  # Rz(-psi) A Rz(psi) c
        return np.einsum("ni,kni->kn", p_axes, axis)  # type: ignore[no-any-return]

    def turn(psi: np.ndarray) -> np.ndarray:
        """Per heading and sample (k, n): the joint's turn (deg) from the pose."""
        rc = _rz_batch(psi)
        child = np.einsum("kji,njl,klm->knim", rc, turns, rc) @ seg_c  # (k, n, 3, 3)
        rel = np.einsum("nji,knjl->knil", parents, child)  # parent^T child
        off = np.einsum("ji,knjl->knil", pose_rel, rel)
        cos = (np.trace(off, axis1=-2, axis2=-1) - 1) / 2
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))  # type: ignore[no-any-return]

    grid = np.radians(np.arange(0.0, 360.0, 5.0))
    rms = np.sqrt((perp(grid) ** 2).mean(axis=1))
    # each local minimum of the misfit, refined (on the coarse grid alone a true fit
    # between two of its points can look worse than a rival's falling on one) ...
    minima = np.flatnonzero((rms <= np.roll(rms, 1)) & (rms <= np.roll(rms, -1)))
    step = np.radians(np.arange(-5.0, 5.25, 0.25))
    fine = (grid[minima][:, None] + step[None, :]).ravel()
    rms = np.sqrt((perp(fine) ** 2).mean(axis=1)).reshape(len(minima), len(step))
    at = np.argmin(rms, axis=1)
    rows = np.arange(len(minima))
    rms, fine = rms[rows, at], fine.reshape(len(minima), len(step))[rows, at]
    # ... the perpendicular fits (within twice the best), then the least turned joint
    fits = np.flatnonzero(rms <= 2 * rms.min() + 1e-3)
    turns_fit = turn(fine[fits])
    order = np.argsort(turns_fit.mean(axis=1))
    k = int(fits[order[0]])
    if math.degrees(math.asin(min(1.0, rms[k]))) > CHILD_MISFIT_DEG:  # not this joint's motion
        return None
    if len(order) > 1:  # the runner-up turns the joint more, beyond the samples' noise
        diff = turns_fit[order[1]] - turns_fit[order[0]]
        noise = _fit_unc_deg(np.radians(diff - diff.mean()), np.ones((len(diff), 1)))
        if diff.mean() <= noise:
            return None
    h = math.radians(0.1)
    around = perp(np.array([fine[k] - h, fine[k], fine[k] + h]))
    unc = _fit_unc_deg(around[1], ((around[2] - around[0]) / (2 * h))[:, None])
    return _wrap(math.degrees(fine[k])), unc


def _knee_pair_headings(samples: Sequence[tuple[np.ndarray, np.ndarray]]
                        ) -> tuple[float, float, float] | None:  # fmt: skip
    """The thigh's and shank's tag headings (deg) that make every sample's knee a
    positive turn about the thighs' lateral axis, and their uncertainty (deg,
    :func:`_fit_unc_deg`); None when no pair fits, or a pair far from it (20 deg
    or more in either heading, as much in the knee's range) fits nearly as well
    (within twice its misfit: the motion does not tell them apart)."""
    from scipy.optimize import least_squares

    a_p = np.array([a for a, _ in samples])
    a_c = np.array([b for _, b in samples])

    lo, hi = rom("left_knee_flexion_deg")

    def parts(psi_p: np.ndarray, psi_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per candidate and sample: the knee's rotation vector's parts off its axis
        (x, z: twice the sine of the turn off it), and the knee's angle (deg)."""
        rp, rc = _rz_batch(psi_p), _rz_batch(psi_c)  # (k, 3, 3)
        # segments' turns in the body's frame: Rz(-psi) A Rz(psi)
        b_p = np.einsum("kji,njl,klm->knim", rp, a_p, rp)
        b_c = np.einsum("kji,njl,klm->knim", rc, a_c, rc)
        rel = np.einsum("knji,knjl->knil", b_p, b_c)
        vee = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 1, 0] - rel[..., 0, 1],
                        rel[..., 0, 2] - rel[..., 2, 0]], axis=-1)  # fmt: skip
        knee = np.degrees(np.arctan2(vee[..., 2] / 2, (np.trace(rel, axis1=-2, axis2=-1) - 1) / 2))
        return vee[..., :2], knee

    def cost(psi_p: np.ndarray, psi_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per candidate: the rotation off the knee's axis, and how far its knee
        angles fall outside the knee's range of motion (both summed over samples)."""
        off, knee = parts(psi_p, psi_c)
        outside = np.maximum(0.0, np.maximum(lo - knee, knee - hi)).sum(axis=1)
        return (off**2).sum(axis=(1, 2)), outside

    # in a plane motion each tag's heading fits turned by 180 deg too (its turns'
    # axis is a line): the knee's range of motion picks the pair, then the hinge
    grid = np.radians(np.arange(0.0, 360.0, 10.0))
    gp, gc = (g.ravel() for g in np.meshgrid(grid, grid, indexing="ij"))
    off, outside = cost(gp, gc)
    inside = np.round(outside, 0)
    best = int(np.lexsort((off, inside))[0])
    far = np.maximum(np.abs(_wrap_rad(gp - gp[best])), np.abs(_wrap_rad(gc - gc[best])))
    rivals = (far > math.radians(20.0)) & (inside <= inside[best])
    if rivals.any() and off[rivals].min() < 2.0 * off[best]:
        return None  # the motion does not tell (the knee barely bent, or noise)

    def residuals(x: np.ndarray) -> np.ndarray:
        return parts(x[:1], x[1:])[0][0].T.ravel()  # type: ignore[no-any-return]

    start = np.array([gp[best], gc[best]])
    fit = least_squares(residuals, start, method="lm")
    if _apart_deg(tuple(fit.x), tuple(start)) > 10.0:
        return None  # left the basin
    off, outside = cost(fit.x[:1], fit.x[1:])
    off_deg = math.degrees(math.sqrt(off[0] / len(samples)) / 2)  # mean turn off the axis
    if off_deg > 5.0 or outside[0] > 5.0 * len(samples):  # not a knee's motion
        return None
    unc = _fit_unc_deg(fit.fun, fit.jac)
    return _wrap(math.degrees(fit.x[0])), _wrap(math.degrees(fit.x[1])), unc


def _wrap_rad(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped into [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi  # type: ignore[no-any-return]


def _rz_batch(psi: np.ndarray) -> np.ndarray:
    """Rotations (k, 3, 3) about the vertical by ``psi`` (rad, (k,))."""
    c, s = np.cos(psi), np.sin(psi)
    out = np.zeros((len(psi), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 2, 2] = 1.0
    return out


class SharedCheck:
    """Checks, in ``auto`` mode, that the tags share one heading reference, as the
    heading a hinge gives (:class:`HingeHeading`) assumes.

    Under the heading a hinge gave, every hinge and two-dof joint (knees, ankles,
    elbows, wrists: ``DRIFT_JOINTS``) must keep its constraint (a knee's axes the
    same line, the others' perpendicular). With tags sharing a reference they do,
    to the tags' noise; with tags of their own (6-axis: the 003 seed's, SlimeVR
    trackers) a tag's heading error leaves its segment right only while it does
    not tilt, and once it tilts the constraint breaks by up to the heading error
    (measured on the emulator, 0.3 deg noise: 0.1-1.9 deg sharing a reference,
    a joint at 9 to 130 deg with references of their own, in every motion tried).
    Each joint is judged on the median of its constraint's error (deg) over
    ``SAMPLES`` samples in which one of its tags has tilted past ``TILT_DEG``
    since calibration (a tag that has not tilted says nothing): beyond
    ``FAIL_DEG`` the tags have references of their own (``"own"``); the heading is
    taken (``"shared"``) once ``MIN_JOINTS`` joints have been judged and every
    joint that tilted has been, all within it. Once taken, the joints are watched
    on (every ``EVERY_S``): a joint breaking its constraint later is ``"own"``
    too (the backstop of a check that saw few joints)."""

    TILT_DEG = 10.0
    SAMPLES = 10
    FAIL_DEG = 6.0
    MIN_JOINTS = 2
    EVERY_S = 0.05

    def __init__(self, profile: Profile) -> None:
        """``profile``: calibrated, the tags' headings unknown (mounts for 0)."""
        by_segment = _tag_by_segment(profile.imu_mounts)
        segments = pose_segments(profile)
        #: joint -> (parent key, child key, parent axis, child axis, kind)
        self.joints: dict[str, tuple[str, str, int, int, str]] = {}
        for joint, parent, child, p_axis, c_axis, kind in DRIFT_JOINTS:
            for side in ("left", "right"):
                p, c = by_segment.get(f"{side}_{parent}"), by_segment.get(f"{side}_{child}")
                if p is not None and c is not None:
                    self.joints[f"{side}_{joint}"] = (p, c, p_axis, c_axis, kind)
        #: each tag in its reference frame at calibration
        self._tag0 = {k: segments[seg] @ _quat_matrix(profile.imu_mounts[k])
                      for k, seg in _segments_of(profile.imu_mounts).items()}  # fmt: skip
        self.errors: dict[str, list[float]] = {j: [] for j in self.joints}
        self.verdict: str | None = None
        self.failed: tuple[str, float] | None = None  # the joint that broke, its error
        self._last = -math.inf

    def _tilted(self, key: str, rot: np.ndarray) -> bool:
        rotvec = _rotvec(rot @ self._tag0[key].T)  # the tag's turn since calibration
        return math.hypot(rotvec[0], rotvec[1]) >= math.radians(self.TILT_DEG)

    def medians(self) -> dict[str, float]:
        """Per joint judged so far, its constraint's median error (deg)."""
        return {j: round(float(np.median(e)), 2) for j, e in self.errors.items()
                if len(e) >= self.SAMPLES}  # fmt: skip

    def update(self, t_s: float, orientations: Mapping[str, QuatWxyz],
               profile: Profile) -> str | None:  # fmt: skip
        """One tick's tag orientations, judged under ``profile`` (the tags'
        headings as the hinge gave them); the verdict once there is one."""
        if self.verdict == "own":
            return self.verdict
        if self.verdict == "shared":
            if t_s - self._last < self.EVERY_S - 1e-6:
                return self.verdict
            self._last = t_s
        rots: dict[str, np.ndarray] = {}
        for joint, (p, c, p_axis, c_axis, kind) in self.joints.items():
            if p not in orientations or c not in orientations or p not in self._tag0:
                continue
            for k in (p, c):
                if k not in rots:
                    rots[k] = _quat_matrix(orientations[k])
            if not (self._tilted(p, rots[p]) or self._tilted(c, rots[c])):
                continue
            a = JointDrift._segment(profile, p, rots[p])[:, p_axis]
            b = JointDrift._segment(profile, c, rots[c])[:, c_axis]
            error = _parallel_error(a, b) if kind == "parallel" else _perpendicular_error(a, b)
            if error is None:  # no grip on the heading at this pose
                continue
            errors = self.errors[joint]
            errors.append(abs(error))
            del errors[: -self.SAMPLES]
        judged = self.medians()
        broken = [(e, j) for j, e in judged.items() if e > self.FAIL_DEG]
        if broken:
            error, joint = max(broken)
            self.verdict, self.failed = "own", (joint, error)
        elif (
            self.verdict is None
            and len(judged) >= self.MIN_JOINTS
            and all(len(e) >= self.SAMPLES or not e for e in self.errors.values())
        ):
            self.verdict = "shared"
        return self.verdict


class BodyHeading:
    """A body's heading between calibration and the solver.

    With tags of unknown heading (``auto`` mode, nothing declared) it feeds each
    tick to a :class:`HingeHeading` and a :class:`SharedTwoDof` (the elbows and
    wrists), and once one finds the heading and the joints it drives confirm
    that the tags share it (:class:`SharedCheck`), returns the profile with it
    (:meth:`update`); when they do not, the tags have headings of their own,
    and it estimates each tag's as ``independent`` mode does, from the
    calibration on (the profile's ``heading`` becomes ``independent``;
    :meth:`step` says so once, ``switched``). :meth:`state` says where it
    stands, for the pose's health and the user. The searches' fits run on
    ``fits`` (:class:`Fits`): inline by default, where a result is taken in
    the tick that asked for it; the live gateway's run aside
    (gateway/aside.py), and each result is taken at a later tick."""

    #: what the user is told when ``auto`` finds tags with headings of their own
    SWITCHED = (
        "tags have headings of their own (6-axis tags): estimating each tag's heading "
        "(walk, reach, bow; --heading independent says so at once)"
    )

    #: what the elbows and wrists want to tell the shared heading (:class:`SharedTwoDof`)
    TWO_DOF_WANTED = (
        "the elbows and wrists: turn the forearm (pronation) with the elbow bent, or "
        "flex a wrist (after a T-pose an elbow bending alone does not tell the heading)"
    )

    def __init__(self, profile: Profile, fits: Fits = INLINE) -> None:
        self.profile = profile
        self.fits = fits
        #: the joints' hold on drifting tags' headings, once they are known
        self.drift: JointDrift | None = JointDrift(profile) if profile.imu_mounts else None
        self.unknown = sorted(k for k in profile.imu_mounts if not profile.heading_known(k))
        independent = profile.heading == "independent"
        self.ended = False  # the search was ended (end_search)
        self.finder = HingeHeading(profile) if self.unknown and not independent else None
        self.pairs = KneePairs(profile, fits) if self.unknown and independent else None
        self.children = ChildHeadings(profile, fits) if self.unknown and independent else None
        self.elbows = ElbowPairs(profile, fits) if self.unknown and independent else None
        self.trunk = TrunkBow(profile) if self.unknown and independent else None
        #: auto: the check that the tags share the heading a hinge gives, the profile
        #: with that heading while it is checked, and the calibration to go back to
        self.check = SharedCheck(profile) if self.finder is not None else None
        #: auto: the elbows and wrists as two-dof joints, where no hinge tells
        self.two_dof = SharedTwoDof(profile, fits) if self.finder is not None else None
        self.candidate: Profile | None = None
        self.calibrated = profile
        self.switched: str | None = None  # why auto went on as independent
        self._announce = False  # the switch not reported by step yet
        if profile.heading == "fixed":
            self.how = "fixed"
        elif not profile.imu_mounts:
            self.how = "uncalibrated"
        elif self.unknown:
            self.how = "unknown"
        else:
            self.how = "declared" if profile.heading_reference is not None else "found"

    @property
    def searching(self) -> bool:
        """Whether a heading may still be found (the search has not ended)."""
        if not self.unknown or self.ended:
            return False
        if self.pairs is not None:
            knees = {k for side, (p, c, _, _) in self.pairs.pairs.items()
                     if side not in self.pairs.done for k in (p, c)}  # fmt: skip
            if self.elbows is not None:
                knees |= self.elbows.coming
            if self.trunk is not None and self.trunk.coming(self.profile):
                return True
            return bool(knees) or (self.children is not None
                                   and self.children.pending(self.profile, knees))  # fmt: skip
        return self.finder is not None

    def update(self, t_s: float, samples: Mapping[Site, Any]) -> Profile | None:
        """Take one tick's samples (site -> RawSample); the profile with the heading
        once it is found (then never again; in ``independent`` mode, once per knee
        or elbow, once per foot or hand whose parent's is known, and once per bow
        that gives trunk tags' headings: :class:`TrunkBow`)."""
        if not self.searching:
            return None  # nothing more to find
        orientations = {site.raw_key: s.reading.wxyz for site, s in samples.items()
                        if hasattr(s.reading, "wxyz")}  # fmt: skip
        if self.pairs is not None:  # each tag its own: the knees' tags, pair by pair,
            found = self.pairs.update(orientations, t_s)
            if self.elbows is not None:  # and the arms' from the elbows'
                found.update(self.elbows.update(t_s, orientations))
            if self.children is not None:  # then the feet's and hands' below them
                found.update(self.children.update(orientations, self.profile, t_s))
            trunk: dict[str, float] = {}
            if self.trunk is not None:  # and the pelvis', chest's and head's from a bow
                trunk = self.trunk.update(t_s, orientations, self.profile)
                found.update(trunk)
            if not found:
                return None
            self.profile = with_headings(self.profile, found)
            if trunk and self.trunk is not None:  # the drift since the pose, at once
                self.profile = turned_headings(self.profile, self.trunk.drifted)
                self.profile = turned_headings(self.profile, self.trunk.snap(self.profile, trunk))
                if self.drift is not None:  # and the rate of that drift, to hold on with
                    for key, rate in self.trunk.drift_rates().items():
                        if key in self.drift.rate_deg_s:
                            self.drift.rate_deg_s[key] = rate
            self.unknown = [k for k in self.unknown if k not in found]
            self.how = "partly found" if self.unknown else "found"
            return self.profile
        if self.candidate is None:
            psi = self.finder.update(t_s, orientations)
            if psi is None and self.two_dof is not None:
                psi = self.two_dof.update(t_s, orientations)
            if psi is None:
                return None
            self.candidate = with_headings(self.profile, dict.fromkeys(self.unknown, psi))
        assert self.check is not None
        verdict = self.check.update(t_s, orientations, self.candidate)
        if verdict == "own":
            self._switch()
            return None
        if verdict != "shared":
            return None  # not taken before the joints it drives confirm it
        self.profile, self.candidate = self.candidate, None
        self.finder.found_t = t_s
        self.unknown = []
        self.how = "found"
        return self.profile

    def _switch(self) -> None:
        """``auto`` met tags with headings of their own: each tag's heading is
        estimated from the calibration on, as ``independent`` mode does."""
        assert self.check is not None
        assert self.check.failed is not None
        joint, error = self.check.failed
        ended = self.ended
        self.__init__(replace(self.calibrated, heading="independent"), self.fits)  # type: ignore[misc]
        self.ended = ended
        self.switched = f"{self.SWITCHED}; {joint} was {error:.0f} deg off its axes"
        self._announce = True

    def step(self, t_s: float, samples: Mapping[Site, Any], current: Profile,
             encoder_zeros: Mapping[str, Any] | None = None
             ) -> tuple[str, Profile] | None:  # fmt: skip
        """One solved tick (site -> RawSample; ``current``: the profile it was solved
        with; ``encoder_zeros``: the SmartSuit encoders' zeros by raw key, see
        gateway/encoders.py), the same for the live gateway and ``bodynet process``: while the
        heading is searched, ``("found", profile)`` once it is (a new calibration:
        a new solver, the profile saved); ``("switched", profile)`` once, when
        ``auto`` found tags with headings of their own (the calibration with
        ``independent`` headings, none known: a new solver, flagged); once known,
        ``("turned", profile)`` when the joints' constraints turn drifting tags'
        headings (the same body: ``BodySolver.set_profile``); else None."""
        if self.searching:
            self.profile = current  # the known tags' headings as held so far
            found = self.update(t_s, samples)
            if found is not None:
                return "found", found
            if self._announce:
                self._announce = False
                return "switched", self.profile
            if self.pairs is None:  # one shared heading: nothing is known until found
                return None
        elif self.watch(t_s, samples, current):
            return "switched", self.profile
        # tags of their own: the known ones are held while others' are still searched
        if self.drift is not None and self.drift.pairs:
            turns = self.drift.update(t_s, samples, current, encoder_zeros)
            if turns:
                return "turned", turned_headings(current, turns)
        return None

    def watch(self, t_s: float, samples: Mapping[Site, Any], current: Profile) -> bool:
        """``auto``'s heading, once taken, checked on by the joints it drives (a check
        that saw few joints may be broken by one that tilts later): True when they
        break it, and each tag's heading is then searched (``independent``)."""
        if self.ended or self.check is None or self.check.verdict != "shared":
            return False
        orientations = {site.raw_key: s.reading.wxyz for site, s in samples.items()
                        if hasattr(s.reading, "wxyz")}  # fmt: skip
        if self.check.update(t_s, orientations, current) != "own":
            return False
        self._switch()
        self._announce = False
        return True

    def end_search(self) -> None:
        """No heading is searched any more (``bodynet process``: its first pass had
        the whole capture); the tags still unknown stay so, and flagged."""
        self.ended = True

    def hold(self, solver: Any, profile: Profile) -> None:
        """A step applied to the body's ``solver`` (a ``BodySolver``: kept for a
        ``("turned", profile)``, the new one for a ``("found", profile)``): the
        tags' headings, and how well they are known (:meth:`heading_unc`)."""
        solver.set_profile(profile)
        solver.set_heading_unc(self.heading_unc())

    def heading_unc(self) -> dict[str, float]:
        """Per segment, how well its tag's heading is known against its parent's
        (deg, about two standard deviations), for the joint above it to carry in
        the pose's ``unc_deg``: the fits that found it (a knee's or elbow's pair,
        a foot or hand below its parent) and the three-dof joints' holds
        (``JointDrift.link_unc``), in quadrature."""
        by_key = _segments_of(self.profile.imu_mounts)
        out: dict[str, float] = {}
        for finder in (self.pairs, self.children):
            for key, unc in (finder.unc_deg if finder is not None else {}).items():
                out[by_key[key]] = unc
        if self.elbows is not None:
            for side, unc in self.elbows.unc_deg.items():
                out[f"{side}_upperarm"] = out[f"{side}_forearm"] = unc
        if self.drift is not None and self.drift.twist0:
            for seg, unc in self.drift.link_unc().items():
                out[seg] = round(math.hypot(out.get(seg, 0.0), unc), 2)
        return out

    def state(self) -> dict[str, Any]:
        """Where the heading stands: ``state`` (fixed, declared, found, unknown or
        uncalibrated), ``deg`` (the tags' shared heading against the body's
        forward), and how it was or will be found (``switched``: why ``auto``
        went on estimating each tag's heading)."""
        out: dict[str, Any] = {"state": self.how, "deg": None}
        values = [self.profile.heading_of(k) for k in self.profile.imu_mounts
                  if self.profile.heading_known(k)]  # fmt: skip
        if values and not self.unknown:
            out["deg"] = round(values[0], 2)
        finder = self.finder
        if finder is not None:
            out["hinge"] = finder.hinge or (self.two_dof.joint if self.two_dof else None)
            out["first_move_t"] = finder.first_move_t
            out["found_t"] = finder.found_t
            if self.unknown:
                wanted = list(finder.informative)
                if self.two_dof is not None and self.two_dof.joints:
                    wanted.append(self.TWO_DOF_WANTED)
                out["waiting_for"] = (
                    wanted or "no hinge with both tags: declare a heading reference"
                )
            if self.candidate is not None:
                out["waiting_for"] = [
                    "move the arms and legs (knees, ankles, elbows, wrists "
                    "bending): they check that the tags share one heading"
                ]
        if self.check is not None and self.check.errors:
            # per hinge and two-dof joint, how far off its axes under the heading found
            out["shared_check_deg"] = self.check.medians()
        if self.switched is not None:
            out["switched"] = self.switched
        if self.pairs is not None and self.unknown:
            out["waiting_for"] = self._motions_wanted()
        return out

    def _motions_wanted(self) -> list[str]:
        """The motions that would find the tags still unknown (``independent``)."""
        segments = {seg.partition("_")[2] or seg for seg in _segments_of(self.unknown).values()}
        want = []
        if segments & {"thigh", "shank"}:
            want.append("walk or swing a leg: the thighs' and shanks' tags")
        if segments & {"upperarm", "forearm"}:
            elbows = self.elbows
            pending = {s: u for s, u in elbows.last_unc_deg.items()
                       if s not in elbows.done} if elbows is not None else {}  # fmt: skip
            if pending:  # the reach tells; the fit's uncertainty is what waits
                uncs = ", ".join(f"{s} {u:.1f} deg" for s, u in sorted(pending.items()))
                want.append(f"the arms' tags: the elbows' fit is still {uncs} uncertain "
                            "(sensor noise): keep reaching, the elbows bending")  # fmt: skip
            elif elbows is not None and set(elbows.twins) - elbows.done:
                want.append("reach, the elbows bending, and with the arm out to the side turn "
                            "the forearm (pronation): the arms' tags (after a T-pose an elbow "
                            "bending alone does not tell)")  # fmt: skip
            else:
                want.append("reach, the elbows bending: the arms' tags"
                            if elbows is not None and elbows.pairs
                            else "the arms' tags: calibrate in an N-pose, then reach")  # fmt: skip
        if segments & {"foot", "hand"}:
            want.append("move the feet and hands: their tags, once the legs' and arms' are known")
        if segments & {"pelvis", "thorax", "head"}:
            want.append("bow forward from the hips, the head following: the pelvis', chest's "
                        "and head's tags")  # fmt: skip
        return want


#: Where the body faces, for the yaw reset: the first of these segments with a tag.
FACING_SEGMENTS = ("pelvis", "thorax", "head")


def yaw_reset(profile: Profile, output: Any) -> tuple[Profile, float]:
    """The yaw reset: the subject faces forward now. Every tag's heading turns by
    the heading the body's trunk has in ``output`` (a solved tick), so that the
    body faces +X from now on; the mounts stay. Returns the profile and the turn
    (deg). Refused (``ValueError``) while the tags' heading is unknown: facing
    forward says nothing about which way round a tag sits on its segment."""
    if not profile.imu_mounts:
        raise ValueError("no orientation sensor is calibrated: calibrate a pose first")
    unknown = [k for k in profile.imu_mounts if not profile.heading_known(k)]
    if unknown:
        raise ValueError("the tags' heading is not known yet: bend a knee (or declare a "
                         "heading reference) before a yaw reset")  # fmt: skip
    by_segment = set(_segments_of(profile.imu_mounts).values())
    facing = next((s for s in FACING_SEGMENTS if s in by_segment), None)
    if facing is None:
        raise ValueError("no tag on the pelvis, thorax or head to say where the body faces")
    turn = yaw_deg(_matrix(output.segments[facing][1]))
    headings = {k: _wrap(profile.heading_of(k) + turn) for k in profile.imu_mounts}
    return replace(profile, imu_headings=MappingProxyType(headings)), turn


#: The joints whose constraint shows a child tag's heading drift against its
#: parent's: (joint, parent, child, parent axis, child axis, how they relate).
#: A hinge (knee): the axes are the same line. Two dofs (ankle, elbow, wrist):
#: the second dof's axis, fixed in the child, stays perpendicular to the first,
#: fixed in the parent (Laidig et al. 2017's 1D and 2D joints).
DRIFT_JOINTS = (
    ("knee", "thigh", "shank", 1, 1, "parallel"),
    ("ankle", "shank", "foot", 1, 0, "perpendicular"),
    ("elbow", "upperarm", "forearm", 1, 2, "perpendicular"),
    ("wrist", "forearm", "hand", 0, 1, "perpendicular"),
)
#: The three-dof joints (joint, parent segment, child segment; "left_"/"right_" are
#: put before the sided ones), each child tag held to its parent's by the joint's
#: twist about the vertical (:class:`JointDrift`). The pelvis is the root: its tag's
#: drift turns the whole body about the vertical, which no joint angle sees.
TWIST_JOINTS = (
    ("hip", "pelvis", "thigh"),
    ("lumbar", "pelvis", "thorax"),
    ("neck", "thorax", "head"),
    ("shoulder", "thorax", "upperarm"),
)
#: the three-dof joints from the root out (a parent's before its children's)
TWIST_ORDER = ("lumbar", "hip", "neck", "shoulder")
#: a perpendicular constraint's grip on the heading (|d(c.p)/d heading| at the
#: answer) below this: the child's heading is not seen at that instant
PERPENDICULAR_MIN = 0.3
#: how each kind of constraint holds a child tag's heading (health's words)
HOLD_WORDS = {
    "parallel": "hinge axis",
    "perpendicular": "two-dof joint's axes",
    "twist": "three-dof joint's mean twist",
    "rest": "three-dof joint held at rest",
    "encoder": "SmartSuit encoder's absolute angle",
}


class JointDrift:
    """Heading drift of tags, held by the joints' constraints.

    6-axis tags drift about the vertical, each its own way. Where a joint allows
    fewer than three dofs its axes are bound to the two segments: a knee turns
    about one axis, the thigh's lateral axis, which is the shank's too; an ankle,
    elbow or wrist turns about an axis fixed in the parent and one fixed in the
    child that stay perpendicular. In the body's frame a child tag whose
    heading drifted turns its axis about the vertical away from where the
    constraint wants it, at every instant (no movement needed) when the axes
    are not vertical: the angle that puts it back is the child tag's heading
    error against its parent's. Chained (thigh, shank, foot; upper arm,
    forearm, hand), each tag is held to its parent.

    A three-dof joint (hip, shoulder, lumbar, neck) allows every relative
    orientation, so at one instant nothing tells its twist about the vertical
    from the child tag's drift. Two things do over time (``TWIST_JOINTS``):

    - **at rest** (both tags still for ``REST_S``), the joint does not move, so
      whatever its twist, it stays: the twist at the start of the rest is held
      (what turns it is drift), as qmt's heading correction does in stillness;
    - **while moving**, the joint's twist about the vertical (the turn about the
      vertical that best lays the child's axes onto the parent's, against that
      in the calibration pose) averages out to the pose's: a gait, reaching or
      bending swings the joints about horizontal axes and twists them both
      ways. The child tag's heading follows that mean through a second-order
      loop (``TWIST_TAU_S``) that also learns the tag's drift rate, so a steady
      drift leaves no lag. What it cannot tell: a twist held while moving for
      longer than about ``TWIST_TAU_S`` (walking with the head turned), which
      it slowly takes for drift; health says which tags rest on this
      assumption.

    :meth:`update` takes a tick's samples and returns the small turns to add to
    the child tags' headings."""

    #: it looks at most this often (drift is slow; a gateway solves 100 ticks a second)
    INTERVAL_S = 0.1
    #: and turns a tag's heading once the turn due to it has grown to this (each turn
    #: costs the solver its sites' set-up)
    MIN_TURN_DEG = 0.05
    #: the three-dof joints' loop: its time constant (1 / natural frequency, critically
    #: damped), and the low-pass of the twist it follows (a gait's twists average out)
    TWIST_TAU_S = 30.0
    TWIST_FILTER_S = 2.0
    REST_FILTER_S = 0.5  # at rest: nothing to average out but the tags' noise
    HINGE_FILTER_S = 0.5  # a hinge's error is geometric, at every instant: only noise
    #: a three-dof joint whose parent segment is tilted past this (deg) from its pose's
    #: vertical, moving, does not learn from its twist (a bow is a posture, not a gait)
    BOWED_COS = math.cos(math.radians(20.0))
    #: a learnt drift rate is bounded by this (deg/s: 20 deg/min, twice the worst
    #: 6-axis tag's drift the emulator gives)
    MAX_RATE_DEG_S = 20.0 / 60.0
    #: a tag that turned less than this in ``REST_S`` is at rest
    REST_DEG = 2.0
    REST_S = 1.0
    #: the twist of a joint whose axes are this close to one another across the
    #: vertical (|best-fit grip| below) is not seen
    TWIST_GRIP_MIN = 0.5
    #: an encoder's dof turning less than this a degree of the child tag's heading
    #: (the joint's rotation axis near horizontal) does not say the heading
    ENCODER_GRIP_MIN = 0.3

    def __init__(self, profile: Profile, tau_s: float = 5.0, twist: bool | None = None) -> None:
        """Which joints hold which tags: the profile's ``drift`` says (``twist``, when
        given, whether the three-dof joints do, whatever it says)."""
        by_segment = _tag_by_segment(profile.imu_mounts)
        hinges, twists = profile.drift_joints
        twist = twists if twist is None else twist
        self.tau_s = tau_s
        self.pending = dict[str, float]()
        #: child key -> (joint name, parent key, parent axis, child axis, kind)
        self.pairs: dict[str, tuple[str, str, int, int, str]] = {}
        for joint, parent, child, p_axis, c_axis, kind in DRIFT_JOINTS if hinges else ():
            for side in ("left", "right"):
                p, c = by_segment.get(f"{side}_{parent}"), by_segment.get(f"{side}_{child}")
                if p is not None and c is not None:
                    self.pairs[c] = (f"{side}_{joint}", p, p_axis, c_axis, kind)
        #: child key -> the joint's twist (deg) in the calibration pose
        self.twist0: dict[str, float] = {}
        if twist and profile.imu_mounts:
            segments = pose_segments(profile)
            for joint, parent, child in TWIST_JOINTS:
                sided = child in ("thigh", "upperarm")
                for side in ("left", "right") if sided else ("",):
                    name = f"{side}_{child}" if sided else child
                    p, c = by_segment.get(parent), by_segment.get(name)
                    if p is None or c is None or c in self.pairs:
                        continue
                    self.pairs[c] = (f"{side}_{joint}" if sided else joint, p, -1, -1, "twist")
                    self.twist0[c] = _twist(segments[parent], segments[name]) or 0.0
        #: child key -> (the SmartSuit module's site name, its encoder's angle name, the
        #: joint's axes, the encoder dof's index): the hybrid suit's absolute angle
        self.encoders: dict[str, tuple[str, str, Any, int]] = {}
        if self.twist0:
            from bodynet.gateway.solver import JointAxes  # the solver's own split

            joints = {j.name: j for j in build_skeleton(profile.lengths).joints}
            for key, (joint, _, _, _, _) in self.pairs.items():
                side, _, name = joint.partition("_")
                if name in OLE_DOF and joint in joints:
                    axes = JointAxes.of(joints[joint])
                    angle = f"{joint}_{OLE_DOF[name]}_deg"
                    self.encoders[key] = (f"{side}/{name}", angle, axes, axes.names.index(angle))
        self.error_deg = dict.fromkeys(self.pairs, 0.0)  # filtered, per child tag
        self.corrected_deg = dict.fromkeys(self.pairs, 0.0)  # in all
        self.spread_deg = dict.fromkeys(self.pairs, 0.0)  # RMS of the error seen (filtered)
        self.rate_deg_s = dict.fromkeys(self.pairs, 0.0)  # each held tag's drift, learnt
        self.holding = {k: kind for k, (_, _, _, _, kind) in self.pairs.items()}
        self._rest_ref: dict[str, float] = {}  # child key -> the twist held at rest
        #: tag -> (since, its orientation then, at rest)
        self._anchor: dict[str, tuple[float, np.ndarray, bool]] = {}
        self._last_t: float | None = None

    def _still(self, key: str, t_s: float, rot: np.ndarray) -> bool:
        """Whether the tag ``key`` (its orientation ``rot`` in its own frame) is at
        rest: it took ``REST_S`` or longer to turn its last ``REST_DEG`` (a drift of
        its reference is no movement)."""
        since, anchor, still = self._anchor.get(key, (t_s, rot, False))
        if float(np.trace(anchor.T @ rot)) < 1 + 2 * math.cos(math.radians(self.REST_DEG)):
            still = t_s - since >= self.REST_S - 1e-6
            since, anchor = t_s, rot
        elif t_s - since >= self.REST_S - 1e-6:
            still = True
        self._anchor[key] = (since, anchor, still)
        return still

    def update(self, t_s: float, samples: Mapping[Site, Any], profile: Profile,
               encoder_zeros: Mapping[str, Any] | None = None) -> dict[str, float]:  # fmt: skip
        """The turns (deg) to add to child tags' headings after the tick at ``t_s``
        whose samples (site -> RawSample) are ``samples``, solved with ``profile``
        (the segments as the tags measure them: the solver's output has the
        joints' dofs already imposed); an encoder whose zero ``encoder_zeros``
        says is lost holds nothing."""
        if self._last_t is not None and t_s - self._last_t < self.INTERVAL_S - 1e-6:
            return {}
        dt = 0.0 if self._last_t is None else t_s - self._last_t
        self._last_t = t_s
        gain = min(1.0, dt / self.tau_s)
        tags = {site.raw_key: s.reading.wxyz for site, s in samples.items()
                if hasattr(s.reading, "wxyz")}  # fmt: skip
        encoders: dict[str, int] = {}
        if self.encoders:
            zeros = encoder_zeros or {}
            for site, s in samples.items():
                if hasattr(s.reading, "encoder"):
                    zero = zeros.get(site.raw_key)
                    counts = (s.reading.encoder if zero is None
                              else zero.angle_counts(s.reading.encoder))  # fmt: skip
                    if counts is not None:
                        encoders[f"{site.branch.side}/{site.name}"] = counts
        rots = {k: _quat_matrix(q) for k, q in tags.items()}
        still = {k: self._still(k, t_s, r) for k, r in rots.items()} if self.twist0 else {}
        turns: dict[str, float] = {}
        for key, (_, parent_key, p_axis, c_axis, kind) in self.pairs.items():
            if key not in tags or parent_key not in tags:
                continue
            if not (profile.heading_known(key) and profile.heading_known(parent_key)):
                continue  # a heading not known yet is found, not held
            p = self._segment(profile, parent_key, rots[parent_key])
            c = self._segment(profile, key, rots[key])
            if kind == "twist":
                target = self._encoder_twist(key, p, c, encoders, profile)
                turn = self._twist_turn(key, p, c, still[key] and still[parent_key], dt, target)
                turn += self.pending.get(key, 0.0)
            else:
                if kind == "parallel":
                    error = _parallel_error(p[:, p_axis], c[:, c_axis])
                else:
                    error = _perpendicular_error(p[:, p_axis], c[:, c_axis])
                if error is None and self.twist0 and still[key] and still[parent_key]:
                    # the axes vertical: no grip; but at rest the joint holds its twist
                    error = self._rest_error(key, p, c)
                else:
                    self._rest_ref.pop(key, None)
                turn = self.pending.get(key, 0.0) + self._hinge_turn(key, error, dt, gain)
            if abs(turn) >= self.MIN_TURN_DEG:
                turns[key] = turn
                self.corrected_deg[key] += turn
                turn = 0.0
            self.pending[key] = turn
        return turns

    def _hinge_turn(self, key: str, error: float | None, dt: float, gain: float) -> float:
        """A hinge or two-dof joint's turn of its child tag's heading over ``dt``:
        its constraint's ``error`` (deg; None where the axes give no grip, the
        forearm hanging, say) through a critically damped loop (``tau_s``) that
        also learns the tag's drift against its parent's, so a steady drift leaves
        no lag, and goes on turning the tag at that rate while nothing grips it
        (a gyroscope's bias does not stop when its axis turns vertical)."""
        w = 1.0 / self.tau_s
        if error is None:
            return self.rate_deg_s[key] * dt
        self.error_deg[key] += min(1.0, dt / self.HINGE_FILTER_S) * (error - self.error_deg[key])
        self.spread_deg[key] += gain * (error**2 - self.spread_deg[key])
        rate = self.rate_deg_s[key] + w * w * self.error_deg[key] * dt
        self.rate_deg_s[key] = max(-self.MAX_RATE_DEG_S, min(self.MAX_RATE_DEG_S, rate))
        return (2.0 * w * self.error_deg[key] + self.rate_deg_s[key]) * dt

    def _rest_error(self, key: str, p: np.ndarray, c: np.ndarray) -> float | None:
        """A joint at rest: its twist's turn since the rest began (drift)."""
        twist = _twist(p, c)
        if twist is None:
            return None
        return _wrap(twist - self._rest_ref.setdefault(key, twist))

    def _encoder_twist(self, key: str, p: np.ndarray, c: np.ndarray,
                       encoders: Mapping[str, int], profile: Profile) -> float | None:  # fmt: skip
        """The hybrid suit: where a SmartSuit encoder spans the joint (a hip's or a
        shoulder's rotation), the twist the joint has when the tags' rotation dof is
        the encoder's absolute angle (None: no encoder, or its dof has no grip on
        the child tag's heading at this pose)."""
        spec = self.encoders.get(key)
        if spec is None or spec[0] not in encoders:
            return None
        _, angle, axes, index = spec
        cal = profile.ole.get(angle)
        if cal is None:
            return None
        want = float(cal.angle_deg(encoders[spec[0]]))

        def dof(turn: float) -> float:
            return float(axes.split(p.T @ rz(-turn) @ c, None)[index])

        now, grip = dof(0.0), (dof(1.0) - dof(-1.0)) / 2.0  # its change a degree of turn
        twist = _twist(p, c)
        if abs(grip) < self.ENCODER_GRIP_MIN or twist is None:
            return None
        return twist - max(-30.0, min(30.0, _wrap(want - now) / grip))

    def _twist_turn(self, key: str, p: np.ndarray, c: np.ndarray, rest: bool,
                    dt: float, target: float | None = None) -> float:  # fmt: skip
        """A three-dof joint's turn of its child tag's heading over ``dt``: its
        twist against ``target`` (where an encoder measures the joint), the one
        held at rest, or (moving) the calibration pose's, low-passed, through
        the loop that also learns the tag's drift rate; the rate learnt alone
        where the twist is not seen or the parent is bowed."""
        twist = _twist(p, c)
        if twist is None:  # nothing seen: the drift learnt goes on
            return self.rate_deg_s[key] * dt
        if target is None and not rest and p[2, 2] < self.BOWED_COS:
            # the parent bowed (a bow, a reach to the floor): a posture held, whose
            # twist is not a gait's that averages out; the drift learnt goes on
            return self.rate_deg_s[key] * dt
        if target is not None:  # measured: followed as fast as at rest
            self._rest_ref.pop(key, None)
            ref, rest = target, True
            self.holding[key] = "encoder"
        elif rest:
            ref = self._rest_ref.setdefault(key, twist)
            self.holding[key] = "rest"
        else:
            self._rest_ref.pop(key, None)
            ref = self.twist0[key]
            self.holding[key] = "twist"
        error = _wrap(twist - ref)
        a = min(1.0, dt / (self.REST_FILTER_S if rest else self.TWIST_FILTER_S))
        self.error_deg[key] += a * (error - self.error_deg[key])
        self.spread_deg[key] += min(1.0, dt / self.TWIST_TAU_S) * (error**2 - self.spread_deg[key])
        # critically damped: 2 w on the error, w^2 on its sum; at rest what it follows
        # is no assumption, and it follows faster
        w = 1.0 / (self.tau_s if rest else self.TWIST_TAU_S)
        self.rate_deg_s[key] += w * w * self.error_deg[key] * dt
        return (2.0 * w * self.error_deg[key] + self.rate_deg_s[key]) * dt

    @staticmethod
    def _segment(profile: Profile, key: str, rot: np.ndarray) -> np.ndarray:
        """The segment's orientation (body frame) as its tag measures it (plain
        arithmetic: a scipy Rotation costs tens of microseconds a call)."""
        mount = _quat_matrix(profile.imu_mounts[key])
        return rz(-profile.heading_of(key)) @ rot @ mount.T  # type: ignore[no-any-return]

    def link_unc(self) -> dict[str, float]:
        """Per segment whose tag a three-dof joint holds (its mean twist, at rest, or
        an encoder), how well its heading is known against its parent's (deg, about
        two standard deviations: the spread of the twist around what it is held
        to); the joints above these segments carry it in the pose's ``unc_deg``.
        The hinge and two-dof joints' holds are geometric, and left out."""
        by_key = _segments_of(self.pairs)
        return {by_key[k]: round(max(2.0 * math.sqrt(max(self.spread_deg[k], 0.0)), 0.5), 2)
                for k, (_, _, _, _, kind) in self.pairs.items()
                if kind == "twist" and k in by_key}  # fmt: skip

    def segments(self, profile: Profile) -> dict[str, dict[str, Any]]:
        """How well each tag's heading is known against the body's, by segment: the
        joint and constraint that hold it (``held_by``, ``how``), ``unc_deg`` (about
        two standard deviations: the error seen around the constraint, summed in
        quadrature up the chain to the root) and ``corrected_deg``. The root is the
        pelvis' tag, or every tag no joint holds where the tags share a reference
        that does not drift (the profile's ``drift`` holds no three-dof joint):
        known to 0 against the body's frame they define. Where tags drift (6-axis),
        a tag no joint holds drifts freely since calibration: ``unc_deg`` None; and
        None for a tag whose heading is not known yet."""
        by_key = _segments_of(profile.imu_mounts)
        shared = not profile.drift_joints[1]
        unc: dict[str, float | None] = {}

        def chain(key: str, depth: int = 0) -> float | None:
            if key in unc:
                return unc[key]
            pair = self.pairs.get(key)
            if not profile.heading_known(key):
                unc[key] = None
            elif pair is None or depth > 8:
                unc[key] = 0.0 if shared or by_key.get(key) == "pelvis" else None
            else:
                up = chain(pair[1], depth + 1)
                own = 2.0 * math.sqrt(max(self.spread_deg[key], 0.0))
                unc[key] = None if up is None else round(math.hypot(up, max(own, 0.5)), 2)
            return unc[key]

        out: dict[str, dict[str, Any]] = {}
        for key, seg in sorted(by_key.items(), key=lambda kv: kv[1]):
            pair = self.pairs.get(key)
            if not profile.heading_known(key):
                how = "heading unknown"
            elif pair is not None:
                how = HOLD_WORDS[self.holding[key]]
            elif seg == "pelvis":
                how = "root"
            else:
                how = "shared reference" if shared else "not held"
            out[seg] = {"tag": key, "held_by": pair[0] if pair else None, "how": how,
                        "unc_deg": chain(key),
                        "corrected_deg": round(self.corrected_deg.get(key, 0.0), 2)}  # fmt: skip
        return out


def _twist(p: np.ndarray, c: np.ndarray) -> float | None:
    """The twist (deg) about the vertical between two segment orientations: the
    turn about the vertical that best lays ``c``'s axes onto ``p``'s (the
    rotation nearest the horizontal block of ``c p^T``); None where that block
    is near singular (the segments' axes across the vertical from one another)."""
    m = c @ p.T
    num, den = m[1, 0] - m[0, 1], m[0, 0] + m[1, 1]
    if math.hypot(num, den) < JointDrift.TWIST_GRIP_MIN:
        return None
    return math.degrees(math.atan2(num, den))


def _parallel_error(p: np.ndarray, c: np.ndarray) -> float | None:
    """The child's heading error (deg) when its axis ``c`` should lie along ``p``."""
    if math.hypot(p[0], p[1]) * math.hypot(c[0], c[1]) < HORIZONTAL_MIN:
        return None  # the axis near vertical: nothing to see
    return _wrap(math.degrees(math.atan2(c[1], c[0]) - math.atan2(p[1], p[0])))


def _perpendicular_error(p: np.ndarray, c: np.ndarray) -> float | None:
    """The child's heading error (deg) when its axis ``c`` should stay perpendicular
    to ``p``: the turn ``e`` about the vertical with ``(Rz(-e) c) . p = 0``,
    nearest 0, when the constraint has a grip on it."""
    a = c[0] * p[0] + c[1] * p[1]
    b = c[1] * p[0] - c[0] * p[1]
    r = math.hypot(a, b)
    if r < 1e-9:
        return None
    base = math.atan2(b, a)
    spread = math.acos(max(-1.0, min(1.0, -c[2] * p[2] / r)))
    e = min((_wrap(math.degrees(base + sign * spread)) for sign in (1, -1)), key=abs)
    grip = abs(-a * math.sin(math.radians(e)) + b * math.cos(math.radians(e)))
    return e if grip >= PERPENDICULAR_MIN else None


def turned_headings(profile: Profile, turns: Mapping[str, float]) -> Profile:
    """``profile`` with these tags' heading references turned by ``turns`` (deg),
    their mounts kept (a drift of the reference, not of the tag on the segment)."""
    headings = dict(profile.imu_headings)
    for key, turn in turns.items():
        if profile.heading_known(key):  # turning an unknown heading would make it "known"
            headings[key] = _wrap(profile.heading_of(key) + turn)
    return replace(profile, imu_headings=MappingProxyType(headings))
