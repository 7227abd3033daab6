"""The emulated body: motion routines, sensor models and their physics."""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodynet.core.calibration import default_ole
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import OleAccel, Quat
from bodynet.core.skeleton import CALIBRATION_POSES, build_skeleton, rom
from bodynet.nodes.emulator import (
    BodyEmulator,
    Kind,
    Realism,
    angle_between_deg,
    imu_tags,
    smartsuit_sensors,
)
from bodynet.nodes.motion import PROTOCOL_EASE_S, ROUTINES, heading_protocol, keyframes
from bodynet.nodes.publisher import PeriodicSeq
from bodynet.nodes.sensors import OleModel


def test_elbow_slow_is_0_90_0_at_0_6_hz() -> None:
    angles = ROUTINES["elbow-slow"].angles
    assert angles(0.0)["left_elbow_flexion_deg"] == pytest.approx(0.0)
    assert angles(1 / 1.2)["left_elbow_flexion_deg"] == pytest.approx(90.0)
    assert angles(1 / 0.6)["left_elbow_flexion_deg"] == pytest.approx(0.0, abs=1e-9)


def test_elbow_fast_oscillates_around_45_at_2_hz() -> None:
    values = [ROUTINES["elbow-fast"].angles(t / 100)["right_elbow_flexion_deg"] for t in range(50)]
    assert np.mean(values) == pytest.approx(45.0, abs=0.5)
    assert max(values) - min(values) == pytest.approx(40.0, abs=0.5)


def test_reach_goes_through_the_task_phases() -> None:
    angles = ROUTINES["reach"].angles
    assert angles(1.5)["left_shoulder_flexion_deg"] == pytest.approx(90)  # arm lifted
    assert angles(3.0)["left_elbow_flexion_deg"] == pytest.approx(90)  # elbow bent
    assert angles(7.5)["left_wrist_flexion_deg"] == pytest.approx(60)  # wrist bent
    assert angles(10.5)["left_shoulder_abduction_deg"] == pytest.approx(90)  # arm horizontal
    assert angles(12.0)["left_elbow_pronation_deg"] == pytest.approx(60)  # wrist rolled
    assert all(v == pytest.approx(0) for v in angles(16.5).values())  # back at rest


def test_every_routine_stays_within_range_of_motion() -> None:
    names = set(build_skeleton().angle_names())
    for routine in ROUTINES.values():
        for t in np.linspace(0, 20, 401):
            for name, value in routine.angles(float(t)).items():
                assert name in names, (routine.name, name)
                lo, hi = rom(name)
                assert lo <= value <= hi, (routine.name, name, value)


def test_keyframes_are_smooth_and_loop() -> None:
    motion = keyframes([(0.0, {}), (1.0, {"a": 10.0})])
    assert motion(0.5)["a"] == pytest.approx(5.0)
    assert motion(1.25)["a"] == pytest.approx(motion(0.25)["a"])


def _fastest(angles: Callable[[float], dict[str, float]], times: np.ndarray
             ) -> tuple[float, str, float]:  # fmt: skip
    """The fastest any joint turns between two of ``times`` (deg/s), which, when."""
    fastest, prev = (0.0, "", 0.0), None
    for t0, t1 in itertools.pairwise(times):
        a, prev = prev or angles(float(t0)), angles(float(t1))
        for name in {*a, *prev}:
            speed = abs(prev.get(name, 0.0) - a.get(name, 0.0)) / (t1 - t0)
            fastest = max(fastest, (speed, name, float(t1)))
    return fastest


@pytest.mark.parametrize(("bow_at_s", "reach_until_s"), [(31.0, math.inf), (11.0, 20.0)])
def test_the_heading_protocol_eases_from_motion_to_motion(
    bow_at_s: float, reach_until_s: float
) -> None:
    """A person does not teleport: from the pose into the walk, into the pose before
    the bow, out of it after and into the walk alone, no joint turns faster than the
    walk's own (its knees: was 90 deg of elbow in one 5 ms step at the bow); the
    bow still starts at ``bow_at_s`` from the pose."""
    step = 0.005
    walk = _fastest(ROUTINES["walk"].angles, np.arange(0.0, 2.0, step))
    protocol = heading_protocol(bow_at_s=bow_at_s, reach_until_s=reach_until_s, pose="npose")
    ends = [1.0, bow_at_s, bow_at_s + 2.9] + ([reach_until_s] if reach_until_s < 60 else [])
    for end in ends:  # every change of motion, and just past the ease
        times = np.arange(end - PROTOCOL_EASE_S - 0.1, end + PROTOCOL_EASE_S + 0.1, step)
        fastest = _fastest(protocol.angles, times)
        assert fastest[0] <= walk[0] * 1.01, (end, fastest, walk)
    still, at_bow = CALIBRATION_POSES["npose"], protocol.angles(bow_at_s)
    assert {n: at_bow.get(n, 0.0) for n in {*at_bow, *still}} == pytest.approx(
        {n: still.get(n, 0.0) for n in {*at_bow, *still}}
    )


def test_ole_model_inverts_the_calibration() -> None:
    cal = default_ole("elbow")
    ole = OleModel(cal)
    for angle in (0.0, 30.0, 60.0, 90.0, 120.0, 140.0, -5.0):
        counts = ole.read(angle)
        # within one count (0.1 mm) of the true travel
        assert abs(cal.angle_deg(counts) - angle) <= cal.angle_deg(1) * 1.3
        assert counts == cal.counts(angle) or abs(counts - cal.counts(angle)) == 1


def test_ole_slack_lags_at_reversals() -> None:
    ole = OleModel(default_ole("knee"), slack_mm=2.0)
    up = [ole.read(a) for a in (0, 10, 20, 30)]
    down = ole.read(29)  # a small reversal stays within the slack: no change
    assert down == up[-1]
    assert ole.read(0) < up[-1]


def test_accelerometer_reads_gravity_at_rest() -> None:
    body = BodyEmulator(ROUTINES["tpose"], smartsuit_sensors([LEFT_ARM]), realism=Realism.ideal())
    readings, _ = body.sample(0.0)
    by_node = {r.node: r for r in readings if isinstance(r, OleAccel)}
    for reading in by_node.values():
        assert math.dist(reading.accel, (0, 0, 0)) == pytest.approx(1024, abs=2)
    # T-pose: arm horizontal, so x (along the segment) feels no gravity
    assert abs(by_node[1].accel[0]) <= 1


def test_accelerometer_hanging_arm_x_reads_minus_one_g() -> None:
    still = keyframes([(0.0, {}), (1.0, {})])
    from bodynet.nodes.motion import Routine

    body = BodyEmulator(
        Routine("still", "", still), smartsuit_sensors([LEFT_ARM]), realism=Realism.ideal()
    )
    readings, _ = body.sample(0.5)
    assert all(isinstance(r, OleAccel) and r.accel == (-1024, 0, 0) for r in readings)


def test_accelerometer_saturates_at_two_g() -> None:
    fast = keyframes([(0.0, {}), (0.05, {"left_elbow_flexion_deg": 120.0})])
    from bodynet.nodes.motion import Routine

    body = BodyEmulator(
        Routine("whip", "", fast), smartsuit_sensors([LEFT_ARM]), realism=Realism.ideal()
    )
    readings, _ = body.sample(0.0)
    counts = [c for r in readings if isinstance(r, OleAccel) for c in r.accel]
    assert min(counts) >= -2048
    assert max(counts) <= 2047
    assert -2048 in counts or 2047 in counts


def test_imu_tags_report_segment_orientation_through_their_mount() -> None:
    sensors = imu_tags([5])  # left forearm
    body = BodyEmulator(
        ROUTINES["elbow-slow"], sensors, realism=Realism(quat_noise_deg=0.0, accel_noise_g=0)
    )
    readings, truths = body.sample(1 / 1.2)  # elbow at 90 degrees
    q = readings[0]
    assert isinstance(q, Quat)
    mount = Rotation.from_quat(body._quat.mounts.as_quat()[0])
    seg = Rotation.from_quat([*truths[0].segment_quat_wxyz[1:], truths[0].segment_quat_wxyz[0]])
    sensor = seg * mount
    x, y, z, w = sensor.as_quat(canonical=True)
    assert angle_between_deg(q.wxyz, (w, x, y, z)) < 1e-6
    assert truths[0].angles_deg["left_elbow_flexion_deg"] == pytest.approx(90)
    # the forearm at 90 degrees of flexion points forward: 90 deg from hanging
    assert angle_between_deg(truths[0].segment_quat_wxyz, (1, 0, 0, 0)) == pytest.approx(90)


def test_yaw_drift_turns_about_the_vertical() -> None:
    body = BodyEmulator(ROUTINES["tpose"], imu_tags([2]),
                        realism=Realism(quat_noise_deg=0.0, yaw_drift_deg_per_min=6.0,
                                        random_tag_mounts=False))  # fmt: skip
    (q0,), _ = body.sample(0.0)
    (q1,), _ = body.sample(60.0)
    assert isinstance(q0, Quat)
    assert isinstance(q1, Quat)
    assert angle_between_deg(q0.wxyz, q1.wxyz) == pytest.approx(6.0, abs=1e-6)


def test_sensor_kinds() -> None:
    kinds = {s.node: s.kind for s in smartsuit_sensors()}
    assert kinds[2] is Kind.MODULE
    assert kinds[13] is Kind.TRUNK_IMU
    assert len(imu_tags()) == 15


def test_periodic_sequence_numbers_show_missed_periods() -> None:
    """0.03 and 0.04 missed: the node's frames run two periods behind from then
    on, which is counted once they have for ``BACKLOG_S``; a silence longer than
    that is counted at the next frame."""
    seq = PeriodicSeq(0.01)
    times = [0.0, 0.0101, 0.0199] + [0.0502 + 0.01 * i for i in range(80)]
    got = [seq.next(1, t) for t in times]
    assert got[:4] == [0, 1, 2, 3]  # late, or two missed: not known yet
    assert got[-1] == 5 + 79  # known: each frame's number is its period's
    assert [b - a for a, b in itertools.pairwise(got)].count(3) == 1  # one gap of two
    assert seq.next(1, 0.0502 + 0.01 * 79 + 1.0) == 5 + 79 + 100  # silent for a second


def _held_back(times: dict[int, float], first: int, periods: int) -> None:
    """Frames ``first``.. held back ``periods`` periods and then handed on at once."""
    end = times[first] + periods * 0.01
    for k, i in enumerate(range(first, first + periods + 1)):
        times[i] = max(times[i], end + k * 1e-4)


def test_periodic_sequence_numbers_take_late_frames_for_late_not_missed() -> None:
    """Frames up to 4 ms late, and frames held back 2, 3.5, 6 and 30 periods and
    then handed on at once (a busy host, an adapter's USB transfer): no period
    missed. Three frames dropped among them are counted, each frame then
    numbered as its period."""
    rng = random.Random(2)
    times = {i: i * 0.01 + rng.uniform(0, 0.004) for i in range(600)}
    for first, periods in ((50, 2), (130, 3), (200, 6), (260, 30)):
        _held_back(times, first, periods)
    dropped = {320, 321, 420}
    seq = PeriodicSeq(0.01)
    got = {i: seq.next(1, t) for i, t in sorted(times.items()) if i not in dropped}
    assert all(got[i] == i for i in range(320))  # nothing counted missed before the drops
    assert [got[i] for i in range(500, 600)] == list(range(500, 600))
    assert sum(b - a - 1 for a, b in itertools.pairwise(got.values())) == len(dropped)


def test_periodic_sequence_numbers_follow_a_slow_node_and_resync() -> None:
    """A node whose clock runs 2 % slow misses nothing; one frame dropped still
    counts. After a reopen (``resync``) a silence is counted at the next frame."""
    seq = PeriodicSeq(0.01)
    got = [seq.next(1, i * 0.0102) for i in range(1000) if i != 500]
    assert got[-1] == 999
    assert sum(b - a - 1 for a, b in itertools.pairwise(got)) == 1
    seq = PeriodicSeq(0.01)
    assert [seq.next(1, i * 0.01) for i in range(10)] == list(range(10))
    seq.resync()
    assert seq.next(1, 0.29) == 29  # 0.2 s silent: 19 missed, counted at once
