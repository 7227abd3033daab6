"""Scripted motion: routines that drive the body model over time.

A routine maps time (s) to joint angles (deg, named as in the skeleton); the
same routine drives every sensor type, and its angles are the ground truth
that downstream accuracy is measured against. Routines follow the movements
of the source documents: the elbow tests of the 000 seed (ch. 5), its
arm-reaching rehabilitation task (ch. 6, Fig. 6-2/6-3), the upper-, lower- and
full-body movements of the 003 seed (ch. 8), a walking gait cycle, and a
smooth random mode for long runs.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from bodynet.core.skeleton import CALIBRATION_POSES, TPOSE, build_skeleton, rom

Pose = Mapping[str, float]

#: Beside the joint angles a routine may give the pelvis' orientation in the world
#: (deg): its forward tilt (about +Y: a bow from the hips), its list (about +X,
#: positive down on the right) and its turn (about +Z), applied turn, tilt, list.
#: Without them the pelvis stays upright, facing +X.
ROOT_ANGLES = ("pelvis_turn_deg", "pelvis_tilt_deg", "pelvis_list_deg")

#: How long the heading protocol takes to go from one motion to the next (s).
PROTOCOL_EASE_S = 0.5


@dataclass(frozen=True)
class Routine:
    """A named motion; ``angles(t)`` gives the true joint angles at ``t`` seconds."""

    name: str
    description: str
    angles: Callable[[float], dict[str, float]]
    period_s: float | None = None  # it repeats after this, if it does


def keyframes(
    frames: Sequence[tuple[float, Pose]], loop: bool = True
) -> Callable[[float], dict[str, float]]:
    """Smooth (cosine-eased) motion through poses at given times.

    Names missing from a pose are 0 there. With ``loop`` the motion repeats
    from the first pose after the last.
    """
    names = sorted({n for _, pose in frames for n in pose})
    times = [t for t, _ in frames]
    if times != sorted(times) or len(frames) < 2:
        raise ValueError("keyframes need two or more poses in time order")
    end = times[-1]

    def angles(t: float) -> dict[str, float]:
        if loop:
            t %= end
        t = min(max(t, times[0]), end)
        i = max(k for k, tk in enumerate(times) if tk <= t)
        if i == len(times) - 1:
            return {n: frames[i][1].get(n, 0.0) for n in names}
        (t0, a), (t1, b) = frames[i], frames[i + 1]
        return eased(a, b, (t - t0) / (t1 - t0), names)

    return angles


def eased(a: Pose, b: Pose, x: float, names: Iterable[str] | None = None) -> dict[str, float]:
    """From pose ``a`` (``x`` = 0) to ``b`` (``x`` = 1), cosine-eased (no jump in
    angle or speed at either end); a name missing from a pose is 0 there."""
    w = 0.5 - 0.5 * math.cos(math.pi * min(max(x, 0.0), 1.0))
    return {n: (1 - w) * a.get(n, 0.0) + w * b.get(n, 0.0) for n in names or {*a, *b}}


def _both(stem: str, value: float) -> dict[str, float]:
    return {f"left_{stem}_deg": value, f"right_{stem}_deg": value}


def _tpose(t: float) -> dict[str, float]:
    return dict(TPOSE)


def _elbow_slow(t: float) -> dict[str, float]:
    return _both("elbow_flexion", 45.0 * (1 - math.cos(2 * math.pi * 0.6 * t)))  # 0-90-0


def _elbow_fast(t: float) -> dict[str, float]:
    return _both("elbow_flexion", 45.0 + 20.0 * math.sin(2 * math.pi * 2.0 * t))


def reach(side: str = "left") -> Callable[[float], dict[str, float]]:
    """The arm-reaching rehabilitation task of the 000 seed (ch. 6, Fig. 6-2/6-3)."""
    j = f"{side}_"
    rest: Pose = {}
    lifted = {j + "shoulder_flexion_deg": 90.0}
    return keyframes([
        (0.0, rest),
        (1.5, lifted),                                            # lift the arm
        (3.0, {**lifted, j + "elbow_flexion_deg": 90.0}),         # bend the elbow
        (4.5, lifted),                                            # return
        (6.0, rest),
        (7.5, {j + "wrist_flexion_deg": 60.0}),                   # bend the wrist
        (9.0, rest),
        (10.5, {j + "shoulder_abduction_deg": 90.0}),             # arm horizontal
        (12.0, {j + "shoulder_abduction_deg": 90.0, j + "elbow_pronation_deg": 60.0}),  # roll
        (13.5, {j + "shoulder_abduction_deg": 90.0, j + "elbow_pronation_deg": -60.0}),
        (15.0, {j + "shoulder_abduction_deg": 90.0}),
        (16.5, rest),                                             # return
    ])  # fmt: skip


def bow(
    depth_deg: float = 40.0, down_s: float = 1.2, hold_s: float = 0.5, **extra: float
) -> Callable[[float], dict[str, float]]:
    """A bow from the hips, once: the pelvis tilts forward ``depth_deg`` (the legs
    straight, so the hips flex as much), the lumbar flexes three quarters of it
    and the neck half (the head follows, looking down), held ``hold_s``, then
    back up; ``extra`` joint angles (or root angles) are added at the bottom."""
    down = {"pelvis_tilt_deg": depth_deg, **_both("hip_flexion", depth_deg),
            "lumbar_flexion_deg": 0.75 * depth_deg, "neck_flexion_deg": 0.5 * depth_deg,
            **extra}  # fmt: skip
    return keyframes([(0.0, {}), (down_s, down), (down_s + hold_s, down),
                      (2 * down_s + hold_s, {})], loop=False)  # fmt: skip


_upper_body = keyframes([
    (0.0, {}),
    (1.5, {**_both("shoulder_abduction", 90.0)}),
    (3.0, {**_both("shoulder_flexion", 150.0)}),
    (4.5, {}),
    (6.0, {"lumbar_flexion_deg": 40.0, "neck_flexion_deg": 20.0}),
    (7.5, {"lumbar_rotation_deg": 35.0, **_both("shoulder_abduction", 60.0)}),
    (9.0, {"lumbar_rotation_deg": -35.0, **_both("shoulder_abduction", 60.0)}),
    (10.5, {"neck_rotation_deg": 60.0}),
    (12.0, {"neck_rotation_deg": -60.0, "lumbar_lateral_deg": 20.0}),
    (13.5, {}),
])  # fmt: skip

_lower_body = keyframes([
    (0.0, {}),
    (2.0, {**_both("hip_flexion", 90.0), **_both("knee_flexion", 110.0),
           **_both("ankle_flexion", 15.0), "lumbar_flexion_deg": 30.0}),  # squat
    (4.0, {}),
    (5.5, {"left_hip_flexion_deg": 60.0, "left_knee_flexion_deg": 10.0}),  # leg raises
    (7.0, {}),
    (8.5, {"right_hip_flexion_deg": 60.0, "right_knee_flexion_deg": 10.0}),
    (10.0, {}),
    (11.5, {"left_hip_abduction_deg": 30.0, "left_ankle_inversion_deg": 15.0}),
    (13.0, {}),
])  # fmt: skip

_full_body = keyframes([
    (0.0, {}),
    (0.8, {**_both("shoulder_abduction", 160.0), **_both("hip_abduction", 25.0)}),  # jacks
    (1.6, {}),
    (2.4, {**_both("shoulder_abduction", 160.0), **_both("hip_abduction", 25.0)}),
    (3.2, {}),
    (5.0, {"lumbar_flexion_deg": 70.0, **_both("shoulder_flexion", 80.0),
           **_both("knee_flexion", 20.0), **_both("hip_flexion", 30.0)}),  # reach the floor
    (7.0, {}),
    (8.5, {"right_hip_flexion_deg": 70.0, "right_knee_flexion_deg": 90.0,
           "left_shoulder_flexion_deg": 90.0, "lumbar_rotation_deg": -20.0}),
    (10.0, {}),
])  # fmt: skip


def _walk(t: float, cadence_hz: float = 1.0) -> dict[str, float]:
    """A simplified gait cycle (heel strike at phase 0), arms swinging opposite."""
    out: dict[str, float] = {}
    for side, shift in (("left", 0.0), ("right", 0.5)):
        ph = 2 * math.pi * (cadence_hz * t + shift)
        out[f"{side}_hip_flexion_deg"] = 10.0 + 20.0 * math.cos(ph)
        out[f"{side}_knee_flexion_deg"] = 5.0 + 55.0 * max(0.0, math.sin(ph - 3.5)) ** 2
        out[f"{side}_ankle_flexion_deg"] = 5.0 * math.sin(ph) - 5.0
        out[f"{side}_shoulder_flexion_deg"] = -15.0 * math.cos(ph)
        out[f"{side}_elbow_flexion_deg"] = 20.0 - 5.0 * math.cos(ph)
    out["lumbar_rotation_deg"] = 5.0 * math.cos(2 * math.pi * cadence_hz * t)
    return out


def smooth_random(seed: int = 0, speed: float = 1.0) -> Callable[[float], dict[str, float]]:
    """Every dof wanders smoothly within the middle of its range of motion."""
    rng = random.Random(seed)
    waves = {}
    for name in build_skeleton().angle_names():
        lo, hi = rom(name)
        mid, half = (lo + hi) / 2, 0.3 * (hi - lo) / 2
        parts = [(rng.uniform(0.05, 0.4) * speed, rng.uniform(0, 2 * math.pi)) for _ in range(3)]
        waves[name] = (mid, half, parts)

    def angles(t: float) -> dict[str, float]:
        return {
            n: mid + half * sum(math.sin(2 * math.pi * f * t + p) for f, p in parts) / 3
            for n, (mid, half, parts) in waves.items()
        }

    return angles


ROUTINES: dict[str, Routine] = {
    r.name: r
    for r in (
        Routine("tpose", "T-pose hold (IMU calibration)", _tpose),
        Routine("elbow-slow", "elbow flexion 0-90-0 deg at 0.6 Hz (000 seed ch. 5)", _elbow_slow,
                1 / 0.6),
        Routine("elbow-fast", "elbow oscillation around 45 deg at 2 Hz (000 seed ch. 5)",
                _elbow_fast, 0.5),
        Routine("reach", "arm-reaching rehabilitation task (000 seed ch. 6)", reach(), 16.5),
        Routine("upper-body", "arms, trunk and head movements (003 seed ch. 8)", _upper_body, 13.5),
        Routine("lower-body", "squat, leg raises, abduction (003 seed ch. 8)", _lower_body, 13.0),
        Routine("full-body", "jumping jacks, floor reach, knee lift (003 seed ch. 8)",
                _full_body, 10.0),
        Routine("walk", "walking gait cycle at 1 Hz", _walk, 1.0),
        Routine("random", "smooth random motion within the range of motion", smooth_random()),
    )
}  # fmt: skip


def heading_protocol(bow_at_s: float = 31.0, reach_until_s: float = math.inf,
                     pose: str = "npose", **bow_extra: float) -> Routine:  # fmt: skip
    """The motions that find 6-axis tags' headings of their own (docs/calibration.md):
    the calibration ``pose`` held for 1 s, then walking with both arms reaching (the
    000 seed's task, every 16.5 s; their tags' headings come from the elbows'
    bending), the walk alone from ``reach_until_s`` (the arms hanging), and a bow
    from the hips at ``bow_at_s`` (the trunk's tags), in the pose, ``bow_extra``
    joint angles added at its bottom (a twist, say). Each change of motion is eased
    over ``PROTOCOL_EASE_S`` (into the walk after the pose, into the pose before
    the bow, out of it after, into the walk alone): no joint jumps."""
    still = dict(CALIBRATION_POSES[pose])
    down, left, right = bow(**bow_extra), reach("left"), reach("right")
    ease = PROTOCOL_EASE_S
    bow_end = bow_at_s + 2 * 1.2 + 0.5  # bow()'s own length

    def moving(t: float) -> dict[str, float]:
        walk = _walk(t)
        if t >= reach_until_s + ease:
            return walk
        reaching = {**walk, **left((t - 1.0) % 16.5), **right((t - 1.0) % 16.5)}
        if t < reach_until_s:
            return reaching
        return eased(reaching, walk, (t - reach_until_s) / ease)

    def angles(t: float) -> dict[str, float]:
        if t < 1.0:
            return dict(still)
        if bow_at_s <= t < bow_end:
            return {**still, **down(t - bow_at_s)}
        if t < 1.0 + ease:
            return eased(still, moving(t), (t - 1.0) / ease)
        if bow_at_s - ease <= t < bow_at_s:
            return eased(moving(t), still, (t - bow_at_s + ease) / ease)
        if bow_end <= t < bow_end + ease:
            return eased(still, moving(t), (t - bow_end) / ease)
        return moving(t)

    return Routine("heading-protocol", "calibration pose, walking and reaching, a bow", angles)
