"""Calibration on real frames: the subject facing anywhere, tags of their own heading.

Everything here runs the emulator and the solver directly (no Zenoh): emulated
tags with random mounts and noise report in their own reference frame; the
calibration window, the heading search and the solver are the gateway's own.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pytest

from bodynet.bench.drift import heading_tick, measured_errors
from bodynet.core.keys import Site
from bodynet.core.messages import RawSample
from bodynet.core.skeleton import CALIBRATION_POSES
from bodynet.core.subject import Profile, QuatWxyz
from bodynet.gateway.heading import (
    BodyHeading,
    CalibrationRefused,
    calibrate_window,
    with_headings,
)
from bodynet.gateway.solver import BodySolver
from bodynet.nodes.emulator import BodyEmulator, Headings, Realism, imu_tags
from bodynet.nodes.motion import Routine, keyframes

RATE_HZ = 50.0
STILL_S = 1.0  # the subject holds the calibration pose this long


def _motion(pose: str) -> Routine:
    """The pose held, then a knee bends while everything else moves too (a leg
    swing, arms lowered or raised from the pose, the trunk bending)."""
    held = dict(CALIBRATION_POSES[pose])
    arms = 30.0  # from the T-pose: out of the shoulders' gimbal lock (noise is amplified there)
    return Routine("after-pose", "", keyframes([
        (0.0, held),
        (STILL_S, held),
        (STILL_S + 1.0, {"left_knee_flexion_deg": 60.0, "left_hip_flexion_deg": 30.0,
                         "right_hip_abduction_deg": 10.0, "lumbar_flexion_deg": 15.0,
                         "left_shoulder_abduction_deg": arms, "right_shoulder_abduction_deg": arms,
                         "left_elbow_flexion_deg": 40.0, "right_shoulder_flexion_deg": 30.0,
                         "neck_rotation_deg": 20.0, "right_ankle_flexion_deg": 10.0}),
        (STILL_S + 2.5, {"left_knee_flexion_deg": 20.0, "right_knee_flexion_deg": 30.0,
                         "left_hip_flexion_deg": 10.0, "lumbar_rotation_deg": 15.0,
                         "left_shoulder_abduction_deg": arms + 10,
                         "right_shoulder_abduction_deg": arms,
                         "right_elbow_flexion_deg": 60.0, "left_wrist_flexion_deg": 20.0,
                         "left_ankle_inversion_deg": 10.0}),
    ], loop=False))  # fmt: skip


def _samples(body: BodyEmulator, t: float) -> tuple[dict[Site, RawSample], dict[str, float]]:
    readings, _ = body.sample(t)
    samples = {s.site: RawSample(r, 0, round(t * 1e9))
               for s, r in zip(body.sensors, readings, strict=True)}  # fmt: skip
    return samples, body.angles(t)


def _window(body: BodyEmulator, start: float, end: float
            ) -> dict[Site, list[tuple[float, QuatWxyz]]]:  # fmt: skip
    window: dict[Site, list[tuple[float, QuatWxyz]]] = {}
    for t in np.arange(start, end, 1 / RATE_HZ):
        for site, sample in _samples(body, float(t))[0].items():
            window.setdefault(site, []).append((float(t), sample.reading.wxyz))  # type: ignore[union-attr]
    return window


def _run(realism: Realism, pose: str, profile: Profile, seed: int = 4
         ) -> tuple[BodyHeading, list[tuple[float, dict[str, float], dict[str, str]]]]:  # fmt: skip
    """Calibrate from the still pose, then follow the motion: the heading search and
    the solver, tick by tick; each tick's errors against the truth and its flags."""
    body = BodyEmulator(_motion(pose), imu_tags(), realism=realism, seed=seed)
    calibration = calibrate_window(_window(body, 0.2, STILL_S - 0.05), profile, pose)
    heading = BodyHeading(calibration.apply(profile, pose))
    solver = BodySolver(heading.profile)
    ticks = []
    for t in np.arange(STILL_S, STILL_S + 2.5, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        found = heading.update(float(t), samples)
        if found is not None:
            solver = BodySolver(found)
        out = solver.solve(samples)
        ticks.append((float(t), measured_errors(out.angles_deg, out.flags, truth), dict(out.flags)))
    return heading, ticks


@pytest.mark.parametrize("facing", range(0, 360, 30))
def test_the_subject_may_face_any_direction(facing: int) -> None:
    """Tags share one earth frame (magnetometer-based), the subject faces ``facing``
    in it: until a hinge moves, every tag-driven dof is flagged uncalibrated; within
    3 s of the first hinge movement the heading is found, and from then every joint
    is within 2 deg of the truth."""
    realism = Realism(facing_deg=float(facing))
    heading, ticks = _run(realism, "tpose", Profile())
    state = heading.state()
    assert state["state"] == "found", state
    assert math.isclose((state["deg"] - facing + 180) % 360 - 180, 0.0, abs_tol=2.0), state
    assert state["found_t"] - state["first_move_t"] <= 3.0
    before = [(t, e, f) for t, e, f in ticks if t < state["found_t"]]
    after = [(t, e, f) for t, e, f in ticks if t > state["found_t"]]
    assert before
    assert after
    for _, errors, flags in before:  # never silently wrong
        assert not errors, errors
        assert set(flags.values()) == {"uncalibrated"}
    worst = max(((e, n, t) for t, errs, _ in after for n, e in errs.items()))
    assert worst[0] <= 2.0, worst
    assert not after[-1][2]  # every dof measured


@pytest.mark.parametrize("facing", [75, 200])
def test_n_pose_calibration_finds_the_heading_too(facing: int) -> None:
    heading, ticks = _run(Realism(facing_deg=float(facing)), "npose", Profile())
    assert heading.profile.pose == "npose"
    state = heading.state()
    assert state["state"] == "found", state
    after = [errs for t, errs, _ in ticks if t > state["found_t"]]
    assert max(e for errs in after for e in errs.values()) <= 2.0


def test_fixed_heading_is_right_only_when_the_subject_faced_x() -> None:
    """The old assumption, now a declared mode: exact when true, and the test that
    shows why it is not the default (the same body turned 90 deg is far off)."""
    _, ticks = _run(Realism(), "tpose", Profile(heading="fixed"))
    assert max(e for _, errs, _ in ticks for e in errs.values()) <= 2.0
    _, turned = _run(Realism(facing_deg=90.0), "tpose", Profile(heading="fixed"))
    assert max(e for _, errs, _ in turned for e in errs.values()) > 20.0


def test_a_declared_reference_gives_the_heading_at_once() -> None:
    """ "The sacrum tag's +z pointed forward": the emulated sacrum tag is mounted so."""
    realism = Realism(facing_deg=130.0, random_tag_mounts=False)  # tags' axes = segments'
    profile = Profile(heading_reference=("body/trunk/mid/sacrum/raw", "+x"))
    heading, ticks = _run(realism, "tpose", profile)
    assert heading.state()["state"] == "declared"
    assert heading.state()["deg"] == pytest.approx(130.0, abs=1.0)
    assert all("uncalibrated" not in flags.values() for _, _, flags in ticks)
    assert max(e for _, errs, _ in ticks for e in errs.values()) <= 2.0


def _refusal(window: Mapping[Site, Sequence[tuple[float, QuatWxyz]]], **kw: object) -> str:
    with pytest.raises(CalibrationRefused) as caught:
        calibrate_window(window, Profile(), "tpose", **kw)  # type: ignore[arg-type]
    assert caught.value.report["tags"] or caught.value.report["missing"]
    return str(caught.value)


def test_bad_calibration_windows_are_refused_with_the_reason() -> None:
    body = BodyEmulator(_motion("tpose"), imu_tags(), realism=Realism(facing_deg=30.0), seed=2)
    still = _window(body, 0.1, 0.9)
    ok = calibrate_window(still, Profile(), "tpose", expected=still)
    assert ok.report["ok"]
    assert not ok.report["missing"]
    assert all(t["still_deg"] < 1.5 for t in ok.report["tags"].values())
    moving = _window(body, 0.5, 1.6)  # the knee starts to bend at 1.0 s
    assert "the subject moved" in _refusal(moving)
    with pytest.raises(CalibrationRefused) as caught:
        calibrate_window(moving, Profile(), "tpose")
    assert caught.value.report["tags"]["body/leg/left/shank/raw"]["still_deg"] > 10
    assert "too short" in _refusal(_window(body, 0.1, 0.25))
    # asked for 2 s, got 0.8: "needs at least 1.6 s" said why
    assert "it needs at least 1.6 s (0.8 of the 2 s asked)" in _refusal(still, seconds=2.0)
    lost = {s: v for s, v in still.items() if s.name != "chest"}
    assert "body/trunk/mid/chest/raw" in _refusal(lost, expected=still)
    # 7 samples 56.7 ms apart cover 0.397 s, short of 0.4 s: the message says so (it
    # said "0.40 s; it needs at least 0.40 s" once, on a machine too loaded to sample)
    sparse = {s: [(0.1 + 0.0567 * i, q) for i, (_, q) in enumerate(v[:7])]
              for s, v in still.items()}  # fmt: skip
    assert "too short: 0.397 s; it needs at least 0.4 s" in _refusal(sparse, seconds=0.5)


def test_recalibration_reports_each_tags_residual() -> None:
    """Against the profile's calibration: a tag that slipped on its segment shows."""
    body = BodyEmulator(_motion("tpose"), imu_tags(), realism=Realism(), seed=2)
    still = _window(body, 0.1, 0.9)
    first = calibrate_window(still, Profile(heading="fixed"), "tpose")
    profile = first.apply(Profile(heading="fixed"))
    thigh = "body/leg/left/thigh/raw"
    slipped = {s: [(t, _turned(q, 20.0) if s.raw_key == thigh else q) for t, q in v]
               for s, v in still.items()}  # fmt: skip
    again = calibrate_window(slipped, profile, "tpose").report["tags"]
    assert again["body/leg/left/thigh/raw"]["residual_deg"] == pytest.approx(20.0, abs=0.5)
    assert max(t["residual_deg"] for k, t in again.items() if "left/thigh" not in k) < 1.0


def _turned(q: QuatWxyz, deg: float) -> QuatWxyz:
    half = math.radians(deg) / 2
    w, x, y, z = q  # q * (rotation about the sensor's x)
    c, s = math.cos(half), math.sin(half)
    return (w * c - x * s, x * c + w * s, y * c + z * s, z * c - y * s)


def test_found_heading_turns_the_mounts_not_the_pose() -> None:
    """with_headings keeps the calibration pose exact: the tags' calibration
    orientations, turned into the body's frame, give the pose's segments."""
    body = BodyEmulator(_motion("tpose"), imu_tags(), realism=Realism.ideal(), seed=5)
    turned = Realism(0, 0, 0, 0, 0, True, facing_deg=-60.0)
    body_turned = BodyEmulator(_motion("tpose"), imu_tags(), realism=turned, seed=5)
    cal = calibrate_window(_window(body_turned, 0.1, 0.9), Profile(), "tpose")
    profile = with_headings(cal.apply(Profile()), dict.fromkeys(cal.mounts, -60.0))
    out = BodySolver(profile).solve(_samples(body_turned, 0.5)[0])
    assert not out.flags
    assert max(abs(v) for v in out.rel_deg.values()) < 1e-6
    del body


def test_emulated_tags_report_in_frames_of_their_own() -> None:
    """6-axis tags: each frame has a heading of its own and drifts at its own rate
    (within the bound); a magnetometer-like suit: one frame, the subject turned in it."""
    from scipy.spatial.transform import Rotation

    def readings(realism: Realism, t: float) -> tuple[BodyEmulator, Rotation]:
        body = BodyEmulator(_motion("tpose"), imu_tags(), realism=realism, seed=9)
        quats = [r.wxyz for r in body.sample(t)[0]]  # type: ignore[attr-defined]
        return body, Rotation.from_quat(quats, scalar_first=True)

    plain = Realism(0, 0, 0, 0, 0, True)
    for t in (0.0, 60.0):
        _, base = readings(plain, t)
        six, own = readings(Realism(0, 0, 0, 4.0, 0, True, headings=Headings.INDEPENDENT), t)
        turn = own * base.inv()  # about the vertical only, by the tag's heading and drift
        rotvec = turn.as_rotvec(degrees=True)
        assert np.abs(rotvec[:, :2]).max() < 1e-6
        start = np.array([six.headings_deg[s.node] for s in six.sensors])
        drift = (rotvec[:, 2] - start + 180) % 360 - 180
        assert np.abs(drift).max() <= 4.0 * t / 60 + 1e-6
        if t:
            assert len({round(float(d), 3) for d in drift}) == len(drift)  # rates of their own
        assert np.ptp(start) > 90  # headings of their own
        _, magnetic = readings(Realism(0, 0, 0, 0, 0, True, facing_deg=-110.0), t)
        shared = (magnetic * base.inv()).as_rotvec(degrees=True)
        np.testing.assert_allclose(shared[:, 2], -110.0, atol=1e-6)


def test_joint_constraints_hold_the_shank_and_foot_tags_drift() -> None:
    """6-axis tags reset together, then each drifting at its own rate (up to
    5 deg/min): walking 40 s, the knees' hinge turns each shank tag's heading by
    its drift against the thigh's, the ankles' two dofs each foot tag's against
    the shank's, and the ankles stay within 3 deg; without it they do not."""
    from bodynet.gateway.heading import JointDrift, turned_headings
    from bodynet.nodes.motion import ROUTINES

    realism = Realism(yaw_drift_deg_per_min=5.0, headings=Headings.DRIFTING)
    walk = ROUTINES["walk"].angles
    still = dict(CALIBRATION_POSES["tpose"])
    routine = Routine("pose-then-walk", "", lambda t: still if t < 1.0 else walk(t - 1.0))
    body = BodyEmulator(routine, imu_tags(), realism=realism, seed=5)
    profile = calibrate_window(_window(body, 0.2, 0.95), Profile(heading="fixed"),
                               "tpose").apply(Profile(heading="fixed"))  # fmt: skip
    solvers = {"plain": BodySolver(profile), "held": BodySolver(profile)}
    knees = JointDrift(profile, twist=False)  # the hinge and two-dof joints alone
    worst = {"plain": 0.0, "held": 0.0}
    for t in np.arange(1.0, 41.0, 0.1):
        samples, truth = _samples(body, float(t))
        for name, solver in solvers.items():
            out = solver.solve(samples)
            errors = measured_errors(out.angles_deg, out.flags, truth)
            if t > 20.0:
                worst[name] = max(worst[name], *(e for n, e in errors.items() if "ankle" in n))
        turns = knees.update(float(t), samples, solvers["held"].profile)
        if turns:
            solvers["held"].set_profile(turned_headings(solvers["held"].profile, turns))
    rates = body.drift_deg_per_min
    for side, thigh, shank, foot in (("left", 10, 12, 14), ("right", 11, 13, 15)):
        drifted = (rates[shank] - rates[thigh]) * 40.0 / 60.0
        got = knees.corrected_deg[f"body/leg/{side}/shank/raw"]
        assert got == pytest.approx(drifted, abs=0.6), side
        drifted = (rates[foot] - rates[thigh]) * 40.0 / 60.0  # to the shank, held to the thigh
        got = knees.corrected_deg[f"body/leg/{side}/foot/raw"]
        assert got == pytest.approx(drifted, abs=0.8), side
    assert worst["held"] <= 3.0, worst
    assert worst["plain"] > worst["held"], worst


def test_yaw_reset_turns_the_body_to_face_forward() -> None:
    """Calibrated facing +X, the subject then faces 40 deg away (the same suit in a
    frame turned by 40): the yaw reset turns every tag's heading so the body faces
    +X again, mounts and joint angles unchanged; refused while the heading is unknown."""
    from bodynet.gateway.heading import yaw_deg, yaw_reset

    ideal = Realism(0, 0, 0, 0, 0, True)
    body = BodyEmulator(_motion("tpose"), imu_tags(), realism=ideal, seed=6)
    turned = BodyEmulator(_motion("tpose"), imu_tags(), realism=Realism(
        0, 0, 0, 0, 0, True, facing_deg=40.0), seed=6)  # fmt: skip
    profile = calibrate_window(_window(body, 0.1, 0.9), Profile(heading="fixed"),
                               "tpose").apply(Profile(heading="fixed"))  # fmt: skip
    samples, truth = _samples(turned, 2.0)
    before = BodySolver(profile).solve(samples)
    pelvis = before.segments["pelvis"][1]
    from scipy.spatial.transform import Rotation

    assert yaw_deg(Rotation.from_quat(pelvis, scalar_first=True).as_matrix()) == pytest.approx(
        40.0, abs=1e-3)  # fmt: skip
    reset, turn = yaw_reset(profile, before)
    assert turn == pytest.approx(40.0, abs=1e-3)
    assert reset.imu_mounts == profile.imu_mounts
    after = BodySolver(reset).solve(samples)
    pelvis = Rotation.from_quat(after.segments["pelvis"][1], scalar_first=True).as_matrix()
    assert yaw_deg(pelvis) == pytest.approx(0.0, abs=1e-3)
    assert max(measured_errors(after.angles_deg, after.flags, truth).values()) < 1e-3
    unknown = calibrate_window(_window(body, 0.1, 0.9), Profile(), "tpose").apply(Profile())
    with pytest.raises(ValueError, match="not known yet"):
        yaw_reset(unknown, before)


@pytest.mark.parametrize("seed", [1, 3])
def test_independent_headings_of_the_knee_tags_are_found_from_the_walk(seed: int) -> None:
    """6-axis tags each with a random heading of its own (independent mode): the
    walk after the T-pose gives each thigh and shank tag's heading (within 1 deg),
    and the knees are then within 2 deg of the truth; every dof that a tag of
    unknown heading drives (hips, ankles, trunk, arms) stays flagged uncalibrated."""
    from bodynet.nodes.motion import ROUTINES

    walk = ROUTINES["walk"].angles
    still = dict(CALIBRATION_POSES["tpose"])
    routine = Routine("pose-then-walk", "", lambda t: still if t < 1.0 else walk(t - 1.0))
    body = BodyEmulator(routine, imu_tags(), realism=Realism(headings=Headings.INDEPENDENT),
                        seed=seed)  # fmt: skip
    independent = Profile(heading="independent")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "tpose").apply(independent))  # fmt: skip
    solver = BodySolver(heading.profile)
    found_t, worst = None, 0.0
    for t in np.arange(1.0, 5.0, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        found = heading.update(float(t), samples)
        if found is not None:
            solver, found_t = BodySolver(found), found_t or float(t)
        out = solver.solve(samples)
        measured = measured_errors(out.angles_deg, out.flags, truth)
        if found_t is None:
            assert not measured
        elif len(heading.unknown) == 15 - 4:
            assert set(measured) == {"left_knee_flexion_deg", "right_knee_flexion_deg"}
            worst = max(worst, *measured.values())
    assert heading.state()["state"] == "partly found"
    assert found_t is not None
    assert found_t - 1.0 <= 3.0
    truth_headings = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.pairs is not None
    assert len(heading.pairs.found) == 4
    for key, psi in heading.pairs.found.items():
        assert (psi - truth_headings[key] + 180) % 360 - 180 == pytest.approx(0.0, abs=1.0), key
    assert 0.0 < worst <= 2.0
    # the joints' drift correction holds what is known and makes nothing else "known"
    from bodynet.gateway.heading import JointDrift, turned_headings

    profile, drift = heading.profile, JointDrift(heading.profile)
    for t in np.arange(5.0, 8.0, 0.1):
        profile = turned_headings(profile, drift.update(float(t), _samples(body, float(t))[0],
                                                        profile))  # fmt: skip
    assert set(profile.imu_headings) == set(heading.profile.imu_headings)


#: the three-dof joints' dofs (by name stem) and the tags they hold, by node number
THREE_DOF = ("hip_", "shoulder_", "lumbar_", "neck_")
SACRUM, CHEST, FOREHEAD, R_ARM, L_THIGH = 9, 2, 1, 4, 10


def _drifting_run(routine: Routine, seconds: float, drift_per_min: float,
                  drifts: Mapping[str, object]
                  ) -> tuple[BodyEmulator, dict[str, float], dict[str, BodySolver]]:  # fmt: skip
    """6-axis tags reset together, then drifting apart (each within +/- ``drift_per_min``):
    each of ``drifts`` (name -> a JointDrift, or None) holds its own solver's tags
    after every tick (10 Hz); the worst three-dof joint error after 20 s, by name."""
    from bodynet.gateway.heading import turned_headings

    realism = Realism(yaw_drift_deg_per_min=drift_per_min, headings=Headings.DRIFTING)
    body = BodyEmulator(routine, imu_tags(), realism=realism, seed=5)
    profile = calibrate_window(_window(body, 0.2, 0.95), Profile(heading="fixed"),
                               "tpose").apply(Profile(heading="fixed"))  # fmt: skip
    solvers = {name: BodySolver(profile) for name in drifts}
    worst = dict.fromkeys(drifts, 0.0)
    for t in np.arange(1.0, 1.0 + seconds, 0.1):
        samples, truth = _samples(body, float(t))
        for name, solver in solvers.items():
            out = solver.solve(samples)
            errors = measured_errors(out.angles_deg, out.flags, truth)
            if t > 20.0:
                mine = [e for n, e in errors.items() if n.startswith(THREE_DOF)]
                worst[name] = max(worst[name], *mine)
            drift = drifts[name]
            if drift is not None:
                turns = drift.update(float(t), samples, solver.profile)  # type: ignore[attr-defined]
                if turns:
                    solver.set_profile(turned_headings(solver.profile, turns))
    return body, worst, solvers


def test_three_dof_joints_hold_their_tags_drift_while_walking() -> None:
    """Walking 90 s with 6-axis tags drifting apart (up to 5 deg/min each): the
    hips', shoulders', lumbar's and neck's twist holds each thigh, upper arm,
    chest and head tag to its parent's heading, the loop learning each tag's
    drift rate against its parent (the emulator's truth), and the three-dof
    joints stay within 3 deg; with the hinges alone they do not."""
    from bodynet.gateway.heading import JointDrift
    from bodynet.nodes.motion import ROUTINES

    walk = ROUTINES["walk"].angles
    still = dict(CALIBRATION_POSES["tpose"])
    routine = Routine("pose-then-walk", "", lambda t: still if t < 1.0 else walk(t - 1.0))
    profile = Profile(heading="fixed", drift="joints")
    body = BodyEmulator(routine, imu_tags(), realism=Realism(), seed=5)
    cal = calibrate_window(_window(body, 0.2, 0.95), profile, "tpose").apply(profile)
    held, hinges = JointDrift(cal), JointDrift(cal, twist=False)
    assert {p[0] for p in held.pairs.values()} >= {"left_hip", "right_shoulder", "lumbar", "neck"}
    body, worst, _ = _drifting_run(routine, 90.0, 5.0, {"held": held, "hinges": hinges})
    assert worst["held"] <= 3.0, worst
    assert worst["hinges"] > 2 * worst["held"], worst
    rates = body.drift_deg_per_min
    # each tag is held to its parent's, which is held to its own: to the pelvis' in the end
    for child, key in ((L_THIGH, "body/leg/left/thigh/raw"),
                       (R_ARM, "body/arm/right/upperarm/raw"),
                       (CHEST, "body/trunk/mid/chest/raw"),
                       (FOREHEAD, "body/trunk/mid/forehead/raw")):  # fmt: skip
        relative = rates[child] - rates[SACRUM]  # deg/min, the truth
        # the rate, learnt slowly by design (a 30 s loop): most of it after 90 s
        learnt = held.rate_deg_s[key] * 60.0
        assert learnt == pytest.approx(relative, abs=0.3 + 0.3 * abs(relative)), key
        assert held.corrected_deg[key] == pytest.approx(1.5 * relative, abs=1.0), key  # 90 s
    segments = held.segments(cal)
    assert segments["pelvis"]["how"] == "root"
    assert segments["left_thigh"]["held_by"] == "left_hip"
    assert segments["left_shank"]["held_by"] == "left_knee"
    assert 0.0 < segments["left_thigh"]["unc_deg"] <= segments["left_shank"]["unc_deg"]


def test_a_twist_held_at_rest_is_kept_while_the_tags_drift() -> None:
    """The subject turns the trunk, head and arms and stands still for a minute, the
    6-axis tags drifting at up to 10 deg/min: at rest a three-dof joint does not
    move, so its twist is held as it was and the drift is taken out (within
    3 deg); without that (the mean twist alone) the held twist is taken for drift."""
    from bodynet.gateway.heading import JointDrift

    still = dict(CALIBRATION_POSES["tpose"])
    twisted = {"lumbar_rotation_deg": 25.0, "neck_rotation_deg": 35.0,
               "left_hip_rotation_deg": 15.0, "left_shoulder_rotation_deg": 30.0}  # fmt: skip
    routine = Routine("pose-then-twist", "", keyframes(
        [(0.0, still), (1.0, still), (3.0, twisted)], loop=False))  # fmt: skip
    profile = Profile(heading="fixed", drift="joints")
    body = BodyEmulator(routine, imu_tags(), realism=Realism(), seed=5)
    cal = calibrate_window(_window(body, 0.2, 0.95), profile, "tpose").apply(profile)

    class MeanTwistOnly(JointDrift):
        REST_S = math.inf

    held = JointDrift(cal)
    _, worst, _ = _drifting_run(routine, 60.0, 10.0, {"held": held, "mean": MeanTwistOnly(cal),
                                                      "none": None})  # fmt: skip
    assert worst["held"] <= 3.0, worst
    assert worst["mean"] > 10.0, worst
    assert worst["none"] > 5.0, worst
    assert held.holding["body/trunk/mid/chest/raw"] == "rest"


def test_hybrid_suit_encoders_hold_the_thigh_tags_drift() -> None:
    """The hybrid suit: IMU tags and the legs' SmartSuit modules. Walking toes out
    (each hip turned out 20 deg the whole time) with 6-axis tags drifting (up to
    5 deg/min): the mean twist alone takes the held turn for drift, while the hip
    module's encoder, the hip's absolute rotation, holds each thigh tag's heading
    and the hips within 3 deg of the truth."""
    from bodynet.core.keys import LEFT_LEG, RIGHT_LEG
    from bodynet.gateway.heading import JointDrift
    from bodynet.nodes.emulator import smartsuit_sensors
    from bodynet.nodes.motion import ROUTINES

    walk = ROUTINES["walk"].angles
    still = dict(CALIBRATION_POSES["tpose"])
    out = {"left_hip_rotation_deg": 20.0, "right_hip_rotation_deg": 20.0}
    routine = Routine("toes-out", "", lambda t: still if t < 1.0 else {**walk(t - 1.0), **out})
    tags = imu_tags()
    realism = Realism(yaw_drift_deg_per_min=5.0, headings=Headings.DRIFTING)
    body = BodyEmulator(routine, [*tags, *smartsuit_sensors([LEFT_LEG, RIGHT_LEG])],
                        realism=realism, seed=5)  # fmt: skip
    window: dict[Site, list[tuple[float, QuatWxyz]]] = {}
    for t in np.arange(0.2, 0.95, 1 / RATE_HZ):
        for site, sample in _samples(body, float(t))[0].items():
            if hasattr(sample.reading, "wxyz"):
                window.setdefault(site, []).append((float(t), sample.reading.wxyz))
    profile = Profile(heading="fixed", drift="joints")
    cal = calibrate_window(window, profile, "tpose").apply(profile)
    from bodynet.gateway.heading import turned_headings

    encoder, mean = JointDrift(cal), JointDrift(cal)
    mean.encoders.clear()  # the same loop without the encoders' angle
    solvers = {"encoder": BodySolver(cal), "mean": BodySolver(cal)}
    worst = {"encoder": 0.0, "mean": 0.0}
    tag_only = {s.site for s in tags}
    for t in np.arange(1.0, 61.0, 0.1):
        samples, truth = _samples(body, float(t))
        for name, drift in (("encoder", encoder), ("mean", mean)):
            solver = solvers[name]
            solver.solve(samples)
            if t > 20.0 and round(t * 10) % 10 == 0:  # once a second: a new solver
                # the thigh tags' own hip rotation (the encoder's wins in the pose)
                own = BodySolver(solver.profile).solve(
                    {s: v for s, v in samples.items() if s in tag_only}
                )
                hips = [abs(own.angles_deg[n] - truth.get(n, 0.0))
                        for n in ("left_hip_rotation_deg", "right_hip_rotation_deg")]  # fmt: skip
                worst[name] = max(worst[name], *hips)
            turns = drift.update(float(t), samples, solver.profile)
            if turns:
                solver.set_profile(turned_headings(solver.profile, turns))
    assert encoder.holding["body/leg/left/thigh/raw"] == "encoder"
    assert worst["encoder"] <= 3.0, worst
    assert worst["mean"] > 10.0, worst


@pytest.mark.parametrize("seed", [1, 3])
def test_independent_foot_tags_are_found_below_the_shanks(seed: int) -> None:
    """Independent 6-axis tags, walking: once the knees give each shank tag's
    heading, each foot tag's is found across the ankle (its axes perpendicular,
    the joint turning least), within 1.5 deg of the emulator's truth, and the
    ankles are then measured within 2.5 deg; the trunk's and arms' tags stay
    unknown (flagged), their joints having three dofs and no heading known above."""
    from bodynet.nodes.motion import ROUTINES

    walk = ROUTINES["walk"].angles
    still = dict(CALIBRATION_POSES["tpose"])
    routine = Routine("pose-then-walk", "", lambda t: still if t < 1.0 else walk(t - 1.0))
    body = BodyEmulator(routine, imu_tags(), realism=Realism(headings=Headings.INDEPENDENT),
                        seed=seed)  # fmt: skip
    independent = Profile(heading="independent")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "tpose").apply(independent))  # fmt: skip
    solver = BodySolver(heading.profile)
    worst, measured = 0.0, set()
    for t in np.arange(1.0, 7.0, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        step = heading.step(float(t), samples, solver.profile)
        if step is not None and step[0] == "found":
            solver = BodySolver(step[1])
        out = solver.solve(samples)
        errors = measured_errors(out.angles_deg, out.flags, truth)
        measured |= set(errors)
        feet = heading.children.found if heading.children is not None else {}
        if len(feet) == 2:
            worst = max(worst, *(e for n, e in errors.items() if "ankle" in n))
    truth_headings = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.children is not None
    assert set(heading.children.found) == {"body/leg/left/foot/raw", "body/leg/right/foot/raw"}
    for key, psi in heading.children.found.items():
        assert (psi - truth_headings[key] + 180) % 360 - 180 == pytest.approx(0.0, abs=1.5), key
    assert 0.0 < worst <= 2.5
    assert {"left_ankle_flexion_deg", "right_ankle_inversion_deg"} <= measured
    assert not any(n.startswith(("lumbar", "neck", "left_shoulder", "left_hip")) for n in measured)
    assert heading.state()["state"] == "partly found"


@pytest.mark.parametrize("seed", [1, 3])
def test_independent_arm_tags_are_found_from_a_reach_after_an_n_pose(seed: int) -> None:
    """Independent 6-axis tags, calibrated in an N-pose (the elbows' axes horizontal),
    then reaching with both arms: each elbow's motion gives its upper arm and forearm tags'
    headings (the axes perpendicular, the flexion in range), within 2 deg of the
    emulator's truth, then each hand's below its forearm's; the elbows and wrists
    are then measured within 3 deg, the shoulders stay flagged (the chest's
    heading is not known)."""
    from bodynet.nodes.motion import reach

    left, right = reach("left"), reach("right")
    still = dict(CALIBRATION_POSES["npose"])
    routine = Routine("pose-then-reach", "", lambda t: still if t < 1.0
                      else {**left(t - 1.0), **right(t - 1.0)})  # fmt: skip
    body = BodyEmulator(routine, imu_tags(), realism=Realism(headings=Headings.INDEPENDENT),
                        seed=seed)  # fmt: skip
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    worst, measured = 0.0, set()
    for t in np.arange(1.0, 9.0, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        step = heading.step(float(t), samples, solver.profile)
        if step is not None and step[0] == "found":
            solver = BodySolver(step[1])
        out = solver.solve(samples)
        errors = measured_errors(out.angles_deg, out.flags, truth)
        measured |= set(errors)
        worst = max(worst, *(e for n, e in errors.items() if "elbow" in n or "wrist" in n), 0.0)
    truth_headings = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.elbows is not None
    assert heading.children is not None
    found = {**heading.elbows.found, **heading.children.found}
    arms = {f"body/arm/{side}/{seg}/raw" for side in ("left", "right")
            for seg in ("upperarm", "forearm", "hand")}  # fmt: skip
    assert arms <= set(found), sorted(found)
    for key in arms:
        assert (found[key] - truth_headings[key] + 180) % 360 - 180 == pytest.approx(
            0.0, abs=2.0), key  # fmt: skip
    assert 0.0 < worst <= 3.0
    assert {"left_elbow_flexion_deg", "right_wrist_flexion_deg"} <= measured
    assert not any(n.startswith(("left_shoulder", "right_shoulder", "lumbar")) for n in measured)


@pytest.mark.parametrize("seed", [2, 4, 6])
def test_the_arms_headings_come_within_3_s_of_the_elbows_first_movement(seed: int) -> None:
    """Independent 6-axis tags, the N-pose, then a reach (the arm lifted straight for
    1.5 s, then the elbow bending): each pair's search is refined continuously and
    taken once its uncertainty is low, so both arms' upper arm and forearm
    headings are known within 3 s (emulated) of the elbow's first movement (the
    truth's flexion past 1 deg; a fixed 50 samples every 0.1 s took 3.6 s), within
    1 deg of the truth, and the elbows are measured within 2 deg from then on."""
    from bodynet.nodes.motion import reach

    left, right = reach("left"), reach("right")
    still = dict(CALIBRATION_POSES["npose"])
    routine = Routine("pose-then-reach", "", lambda t: still if t < 1.0
                      else {**left(t - 1.0), **right(t - 1.0)})  # fmt: skip
    body = BodyEmulator(routine, imu_tags(), realism=Realism(headings=Headings.INDEPENDENT),
                        seed=seed)  # fmt: skip
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    moved: dict[str, float] = {}
    known: dict[str, float] = {}
    worst = 0.0
    for t in np.arange(1.0, 6.5, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        for side in ("left", "right"):
            if side not in moved and abs(truth.get(f"{side}_elbow_flexion_deg", 0.0)) > 1.0:
                moved[side] = float(t)
        step = heading.step(float(t), samples, solver.profile)
        if step is not None and step[0] == "found":
            solver = BodySolver(step[1])
        for side in ("left", "right"):
            keys = (f"body/arm/{side}/upperarm/raw", f"body/arm/{side}/forearm/raw")
            if side not in known and all(heading.profile.heading_known(k) for k in keys):
                known[side] = float(t)
        out = solver.solve(samples)
        errors = measured_errors(out.angles_deg, out.flags, truth)
        worst = max(worst, *(e for n, e in errors.items() if "elbow" in n), 0.0)
    assert set(known) == set(moved) == {"left", "right"}
    for side in ("left", "right"):
        assert 0.0 < known[side] - moved[side] <= 3.0, (side, moved, known)
    truth_headings = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.elbows is not None
    assert len(heading.elbows.found) == 4
    for key, psi in heading.elbows.found.items():
        assert (psi - truth_headings[key] + 180) % 360 - 180 == pytest.approx(0.0, abs=1.0), key
    assert 0.0 < worst <= 2.0


def test_a_walk_after_an_n_pose_finds_no_arm_heading_and_holds_the_known_ones() -> None:
    """In a walk the elbows barely bend: every pair of arm headings fits as well as
    another, so none is taken (never a wrong one), the search for them goes on,
    and meanwhile the tags already known (the legs') are held against drift."""
    from bodynet.nodes.motion import ROUTINES

    walk = ROUTINES["walk"].angles
    still = dict(CALIBRATION_POSES["npose"])
    routine = Routine("pose-then-walk", "", lambda t: still if t < 1.0 else walk(t - 1.0))
    realism = Realism(yaw_drift_deg_per_min=10.0, headings=Headings.INDEPENDENT)
    body = BodyEmulator(routine, imu_tags(), realism=realism, seed=1)
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    turned = 0
    for t in np.arange(1.0, 13.0, 1 / RATE_HZ):
        samples, _ = _samples(body, float(t))
        step = heading.step(float(t), samples, solver.profile)
        if step is not None and step[0] == "found":
            solver = BodySolver(step[1])
        elif step is not None:
            heading.hold(solver, step[1])
            turned += 1
    assert heading.elbows is not None
    assert not heading.elbows.found
    assert heading.searching  # the arms' may still come, from a reach
    assert "body/leg/left/foot/raw" in heading.profile.imu_headings
    assert turned > 0
    assert abs(heading.drift.corrected_deg["body/leg/left/shank/raw"]) > 0.0  # type: ignore[union-attr]


TRUNK_TAGS = {"body/trunk/mid/sacrum/raw": "pelvis", "body/trunk/mid/chest/raw": "thorax",
              "body/trunk/mid/forehead/raw": "head"}  # fmt: skip
#: the dofs whose joints a trunk tag's heading drives (the arms' too: the shoulders)
TRUNK_DOFS = ("left_hip", "right_hip", "lumbar", "neck", "left_shoulder", "right_shoulder")


def _bow_protocol(pose: str, turn_deg: float, bow_first: bool = True) -> Routine:
    """The pose held 1 s, the subject turning ``turn_deg`` about the vertical in the
    next second; then a bow (2.9 s) and a walk with both arms reaching (9 s), in
    this order or the other; then a second bow, twisted (the lumbar and neck turned,
    the trunk leaning right a little)."""
    from bodynet.nodes.motion import ROUTINES, bow, reach

    still = dict(CALIBRATION_POSES[pose])
    first, walk = bow(), ROUTINES["walk"].angles
    left, right = reach("left"), reach("right")
    second = bow(35.0, lumbar_rotation_deg=15.0, neck_rotation_deg=25.0, lumbar_lateral_deg=5.0)

    def moving(u: float) -> dict[str, float]:
        return {**walk(u), **left(u), **right(u)}

    def bowing(u: float) -> dict[str, float]:
        return {**still, **first(u)}

    phases = (bowing, moving) if bow_first else (moving, bowing)
    ends = (2.0 + 2.9, 2.0 + 2.9 + 9.0) if bow_first else (2.0 + 9.0, 2.0 + 9.0 + 2.9)

    def angles(t: float) -> dict[str, float]:
        turn = {"pelvis_turn_deg": turn_deg * min(1.0, max(0.0, t - 1.0))}
        if t < 2.0:
            return {**still, **turn}
        if t < ends[0]:
            return {**phases[0](t - 2.0), **turn}
        if t < ends[1]:
            return {**phases[1](t - ends[0]), **turn}
        return {**second(t - ends[1]), **turn}

    return Routine("pose-bow-walk-reach", "", angles)


def _follow(body: BodyEmulator, heading: BodyHeading, end_s: float
            ) -> list[tuple[float, dict[str, float], dict[str, float]]]:  # fmt: skip
    """The gateway's path from 1 s (the pose's end) to ``end_s``: the heading's step
    and the solver, tick by tick; per tick its errors, and the headings known then."""
    solver = BodySolver(heading.profile)
    ticks = []
    for t in np.arange(1.0, end_s, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        solver = heading_tick(heading, solver, float(t), samples)
        out = solver.solve(samples)
        errors = measured_errors(out.angles_deg, out.flags, truth)
        ticks.append((float(t), errors, dict(heading.profile.imu_headings)))
    return ticks


@pytest.mark.parametrize(("seed", "turn"), [(1, 0.0), (3, 120.0), (5, -70.0)])
def test_independent_trunk_tags_are_found_from_a_bow(seed: int, turn: float) -> None:
    """Independent 6-axis tags, arbitrary mountings, the N-pose, the subject turning
    anywhere, then the protocol: a bow, then walking and reaching. The bow gives
    the pelvis', chest's and head's tags' headings (within 1 deg of the emulator's
    truth, within 3 s of the bow's start); until then every hip, lumbar, neck and
    shoulder dof is flagged. Once every tag is known (the legs' from the walk,
    the arms' from the reach) all 32 dofs are measured, every one within 2 deg of
    the truth through the walk, the reach and a second, twisted bow."""
    body = BodyEmulator(_bow_protocol("npose", turn), imu_tags(),
                        realism=Realism(headings=Headings.INDEPENDENT), seed=seed)  # fmt: skip
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    ticks = _follow(body, heading, 17.8)
    truth = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.trunk is not None
    assert set(heading.trunk.found) == set(TRUNK_TAGS)
    for key, psi in heading.trunk.found.items():
        assert (psi - truth[key] + 180) % 360 - 180 == pytest.approx(0.0, abs=1.0), key
    found_t = min(t for t, _, known in ticks if set(TRUNK_TAGS) <= set(known))
    assert found_t - 2.0 <= 3.0  # the bow starts at 2 s
    for t, errors, known in ticks:
        if not set(TRUNK_TAGS) <= set(known):  # never a number that may be wrong
            assert not any(n.startswith(TRUNK_DOFS) for n in errors), (t, errors)
    assert not heading.unknown
    assert "waiting_for" not in heading.state()
    assert not heading.searching
    last = [errors for _, errors, known in ticks if len(known) == 15]
    assert len(last[-1]) == 32  # every dof measured
    worst = max((e, name) for errors in last for name, e in errors.items())
    # the twisted bow's 15 deg of lumbar twist is a posture, not drift: the three-dof
    # joints' hold does not learn from a bowed parent (seed 5's lumbar, learning: 2.04)
    assert worst[0] <= 2.0, worst


def test_a_walk_then_a_bow_after_a_t_pose_measures_the_hips_lumbar_and_neck() -> None:
    """The bow may come after the walk: the T-pose, walking (the legs' tags found),
    then a bow (the trunk's): the hips, lumbar and neck are then measured within
    2 deg; the arms' tags stay unknown after a T-pose (the elbows' flexion axes
    were vertical: bending tells only the difference of their tags' headings, and
    the walk's reach had not turned a forearm yet), so the shoulders stay flagged,
    and ``waiting_for`` says what would tell."""
    body = BodyEmulator(_bow_protocol("tpose", 40.0, bow_first=False), imu_tags(),
                        realism=Realism(headings=Headings.INDEPENDENT), seed=2)  # fmt: skip
    independent = Profile(heading="independent")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "tpose").apply(independent))  # fmt: skip
    ticks = _follow(body, heading, 17.8)
    truth = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.trunk is not None
    assert set(heading.trunk.found) == set(TRUNK_TAGS)
    for key, psi in heading.trunk.found.items():
        assert (psi - truth[key] + 180) % 360 - 180 == pytest.approx(0.0, abs=1.0), key
    found_t = min(t for t, _, known in ticks if set(TRUNK_TAGS) <= set(known))
    assert 11.0 < found_t <= 11.0 + 3.0  # the bow starts at 11 s
    worst, measured = 0.0, set()
    for t, errors, _ in ticks:
        measured |= set(errors)
        if t > found_t:
            worst = max(worst, *(e for n, e in errors.items() if n.startswith(TRUNK_DOFS[:4])))
    assert 0.0 < worst <= 2.0
    assert {"left_hip_rotation_deg", "lumbar_flexion_deg", "neck_lateral_deg"} <= measured
    assert not any(n.startswith(("left_shoulder", "right_shoulder")) for n in measured)
    assert sorted(heading.unknown) == sorted(f"body/arm/{side}/{seg}/raw" for side in (
        "left", "right") for seg in ("upperarm", "forearm", "hand"))  # fmt: skip
    wanted = " ".join(heading.state()["waiting_for"])
    assert "pronation" in wanted, wanted
    assert "bow forward" not in wanted


def test_a_head_looking_up_in_a_shallow_bow_is_not_taken() -> None:
    """A shallow bow (the pelvis 24 deg) looking up (the neck extended 60 deg): the
    head tilts back, which a forward bow's rule would take turned round by 180 deg.
    It tilts less than the pelvis, so it is not taken: the neck stays flagged, and
    the pelvis' and chest's headings are found, the lumbar measured within 2 deg."""
    from bodynet.nodes.motion import bow

    still = dict(CALIBRATION_POSES["npose"])
    looking_up = bow(24.0, down_s=0.6, hold_s=1.5, neck_flexion_deg=-60.0)
    routine = Routine("bow-looking-up", "", lambda t: {**still, **looking_up(max(0.0, t - 1.0))})
    body = BodyEmulator(routine, imu_tags(), realism=Realism(headings=Headings.INDEPENDENT),
                        seed=1)  # fmt: skip
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    ticks = _follow(body, heading, 4.5)
    assert heading.trunk is not None
    assert set(heading.trunk.found) == {"body/trunk/mid/sacrum/raw", "body/trunk/mid/chest/raw"}
    assert any("bow" in wanted for wanted in heading.state()["waiting_for"])  # the head's
    lumbar = [e for _, errors, _ in ticks for n, e in errors.items() if n.startswith("lumbar")]
    assert lumbar
    assert max(lumbar) <= 2.0
    assert not any(n.startswith("neck") for _, errors, _ in ticks for n in errors)


def test_tags_drifting_until_a_late_bow_are_joined_at_once() -> None:
    """Independent 6-axis tags drifting (each within +/- 10 deg/min), the N-pose, then
    30 s of walking and reaching before the bow: a heading found from gravity is
    the tag's at calibration, the drift since then not in it. The bow twists no
    joint, so the find turns each joined tag (and those below it) by its joint's
    twist in the bow: the hips, lumbar, neck and shoulders within 2.5 deg in the 5 s
    after the bow began; left to the three-dof joints' 30 s hold, 5 deg or more."""
    from bodynet.nodes.motion import heading_protocol

    realism = Realism(yaw_drift_deg_per_min=10.0, headings=Headings.INDEPENDENT)
    body = BodyEmulator(heading_protocol(bow_at_s=31.0), imu_tags(), realism=realism, seed=1)
    independent = Profile(heading="independent", pose="npose")
    profile = calibrate_window(_window(body, 0.2, 0.95), independent,
                               "npose").apply(independent, "npose")  # fmt: skip
    worst = {}
    for snap in (True, False):
        heading = BodyHeading(profile)
        if not snap:
            heading.trunk.snap = lambda profile, found: {}  # type: ignore[union-attr,method-assign]
        solver = BodySolver(heading.profile)
        worst[snap] = 0.0
        for t in np.arange(1.0, 36.0, 1 / 25):
            samples, truth = _samples(body, float(t))
            solver = heading_tick(heading, solver, float(t), samples)
            out = solver.solve(samples)
            errors = measured_errors(out.angles_deg, out.flags, truth)
            if t >= 31.0:
                trunk = [e for n, e in errors.items() if n.startswith(TRUNK_DOFS)]
                worst[snap] = max(worst[snap], *trunk, 0.0)
        # every tag but a foot's (one of them, drifting 9 deg/min, fits only 3-5 deg
        # uncertain: ChildHeadings leaves it unknown, flagged, not 3 deg off unflagged)
        assert not [k for k in heading.unknown if "/foot/" not in k], heading.unknown
    assert 0.0 < worst[True] <= 2.5, worst
    assert worst[False] >= 5.0, worst


def test_a_twisted_bow_still_gives_the_chest_and_head() -> None:
    """A bow with the trunk twisted 10 deg and the head turned 20 deg: the way gravity
    moves in the chest's and head's frames turns with them (the forward rule alone
    is 7 deg off), but their axes that were vertical stay in the pelvis' and chest's
    sagittal planes: the headings within 1 deg of the truth, and the lumbar and neck,
    twist included, within 2 deg after."""
    from bodynet.nodes.motion import bow

    still = dict(CALIBRATION_POSES["npose"])
    twisted = bow(lumbar_rotation_deg=10.0, neck_rotation_deg=20.0)
    routine = Routine("twisted-bow", "", lambda t: {**still, **twisted(max(0.0, t - 1.0))})
    body = BodyEmulator(routine, imu_tags(), realism=Realism(headings=Headings.INDEPENDENT),
                        seed=4)  # fmt: skip
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    ticks = _follow(body, heading, 4.5)
    truth = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.trunk is not None
    assert set(heading.trunk.found) == set(TRUNK_TAGS)
    for key, psi in heading.trunk.found.items():
        assert (psi - truth[key] + 180) % 360 - 180 == pytest.approx(0.0, abs=1.0), key
    spine = [e for _, errors, _ in ticks for n, e in errors.items()
             if n.startswith(("lumbar", "neck"))]  # fmt: skip
    assert spine
    assert max(spine) <= 2.0


@pytest.mark.parametrize("seed", [1, 3])
def test_a_bow_a_minute_after_the_pose_starts_the_hold_at_the_drift_rate(seed: int) -> None:
    """Independent 6-axis tags drifting within +/- 5 deg/min, the N-pose, a minute of
    walking and reaching, a bow, a minute more: the drift each join found (the
    joint's twist in the bow, the chest's and head's placing) over the minute since
    the pose is its rate, and the three-dof joints' hold starts from it: the hips,
    lumbar, neck and shoulders within 2.5 deg through the minute after the bow
    (learning the rates from zero, 2.9 and 3.4 deg)."""
    from bodynet.nodes.motion import heading_protocol

    realism = Realism(yaw_drift_deg_per_min=5.0, headings=Headings.INDEPENDENT)
    body = BodyEmulator(heading_protocol(bow_at_s=61.0), imu_tags(), realism=realism, seed=seed)
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    worst, rates = 0.0, {}
    for t in np.arange(1.0, 121.0, 1 / 20):
        samples, truth = _samples(body, float(t))
        step = heading.step(float(t), samples, solver.profile)
        if step is not None and step[0] == "found":
            solver = BodySolver(step[1])
            if heading.trunk is not None and heading.trunk.found and not rates:
                rates = heading.trunk.drift_rates()
        elif step is not None:
            heading.hold(solver, step[1])
        out = solver.solve(samples)
        errors = measured_errors(out.angles_deg, out.flags, truth)
        if t >= 61.0:
            worst = max(worst, *(e for n, e in errors.items() if n.startswith(TRUNK_DOFS)), 0.0)
    assert not heading.unknown
    assert "body/trunk/mid/chest/raw" in rates
    assert any(abs(r) > 0.5 / 60 for r in rates.values())  # deg/s: drift was found
    assert 0.0 < worst <= 2.5


@pytest.mark.parametrize("seed", [2, 3])
def test_a_hanging_forearms_tag_drifts_on_at_the_rate_its_elbow_learnt(seed: int) -> None:
    """Independent 6-axis tags drifting within +/- 5 deg/min: a minute of walking and
    reaching (the elbows' axes grip the forearm tags' headings and their loop learns
    each tag's drift against its upper arm's), then a minute of walking with the arms
    hanging, where an elbow's axes hardly grip (the forearm vertical): the forearm
    tag's heading goes on turning at the rate learnt, so the elbows' pronation, which
    a hanging forearm's heading error is, stays within 2.5 deg (held by the error
    alone, up to 3.2)."""
    from bodynet.nodes.motion import heading_protocol

    realism = Realism(yaw_drift_deg_per_min=5.0, headings=Headings.INDEPENDENT)
    body = BodyEmulator(heading_protocol(bow_at_s=11.0, reach_until_s=60.0), imu_tags(),
                        realism=realism, seed=seed)  # fmt: skip
    independent = Profile(heading="independent", pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "npose").apply(independent, "npose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    worst = 0.0
    for t in np.arange(1.0, 120.0, 1 / 20):
        samples, truth = _samples(body, float(t))
        solver = heading_tick(heading, solver, float(t), samples)
        out = solver.solve(samples)
        if t >= 60.0:
            errors = measured_errors(out.angles_deg, out.flags, truth)
            worst = max(worst, *(e for n, e in errors.items() if "elbow" in n), 0.0)
    assert not heading.unknown
    assert heading.drift is not None
    rates = [heading.drift.rate_deg_s[k] for k in heading.drift.rate_deg_s if "forearm" in k]
    assert any(abs(r) > 0.5 / 60 for r in rates)  # deg/s: a forearm's drift was learnt
    assert 0.0 < worst <= 2.5


@pytest.mark.parametrize(("seed", "facing", "turn"), [(1, 0.0, 0.0), (3, 200.0, 120.0)])
def test_auto_meeting_tags_of_their_own_estimates_each_tags_heading(
    seed: int, facing: float, turn: float
) -> None:
    """The default profile (``auto``: tags assumed to share one reference) fed by
    6-axis tags each with a heading of its own: the heading a knee gives is
    checked against the joints it drives before it is taken; they break their
    constraints, so it is not, and each tag's heading is estimated instead (said
    once, ``switched``). No dof is ever shown measured more than 2.5 deg from the
    truth (the feet's test's bound: an ankle's 2.04 here); after a walk with the
    arms reaching and a bow, all 32 are measured."""
    body = BodyEmulator(_bow_protocol("npose", turn, bow_first=False), imu_tags(),
                        realism=Realism(facing_deg=facing, headings=Headings.INDEPENDENT),
                        seed=seed)  # fmt: skip
    auto = Profile(pose="npose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), auto,
                                           "npose").apply(auto, "npose"))  # fmt: skip
    ticks = _follow(body, heading, 17.8)
    worst = max(((e, n, t) for t, errors, _ in ticks for n, e in errors.items()))
    assert worst[0] <= 2.5, worst
    assert "headings of their own" in heading.state()["switched"]
    assert heading.profile.heading == "independent"
    assert not heading.unknown
    assert len(ticks[-1][1]) == 32  # every dof measured


def _walk_after(pose: str, realism: Realism, seed: int, seconds: float, arms: bool = False
                ) -> tuple[BodyEmulator, BodyHeading, dict[str, tuple[float, float]]]:  # fmt: skip
    """Independent tags: the ``pose`` held 1 s, then walking (``arms``: reaching with
    both arms, not walking), through the gateway's heading step and solver; per
    measured dof, its worst error against the truth and the ``unc_deg`` stated then."""
    from bodynet.nodes.motion import ROUTINES, reach

    walk, left, right = ROUTINES["walk"].angles, reach("left"), reach("right")
    still = dict(CALIBRATION_POSES[pose])

    def angles(t: float) -> dict[str, float]:
        if t < 1.0:
            return still
        return {**still, **left(t - 1.0), **right(t - 1.0)} if arms else walk(t - 1.0)

    body = BodyEmulator(Routine("pose-then-move", "", angles), imu_tags(), realism=realism,
                        seed=seed)  # fmt: skip
    independent = Profile(heading="independent", pose=pose)
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           pose).apply(independent, pose))  # fmt: skip
    solver = BodySolver(heading.profile)
    worst: dict[str, tuple[float, float]] = {}
    for t in np.arange(1.0, 1.0 + seconds, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        solver = heading_tick(heading, solver, float(t), samples)
        out = solver.solve(samples)
        unc = dict(zip(out.names.angles, out.unc.tolist(), strict=True))
        for name, error in measured_errors(out.angles_deg, out.flags, truth).items():
            worst[name] = max(worst.get(name, (0.0, 0.0)), (error, unc[name]))
    return body, heading, worst


def _heading_errors(body: BodyEmulator, heading: BodyHeading, part: str) -> dict[str, float]:
    """The known headings of the tags whose key holds ``part``, against the truth (deg)."""
    truth = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    return {k: abs((heading.profile.heading_of(k) - truth[k] + 180) % 360 - 180)
            for k in truth if part in k and heading.profile.heading_known(k)}  # fmt: skip


def test_a_foot_heading_under_noise_and_soft_tissue_wobble_is_right_or_left_unknown() -> None:
    """Noisier tags (1 deg) wobbling on the skin (3 deg, with the segments' speed),
    walking: 40 samples left the right foot's heading 8 deg off and its ankle
    13 deg off while it stated 2 deg. Now a foot's heading is taken once its fit's
    uncertainty is low: each found within 3 deg of the truth, and the ankles carry
    the fit's uncertainty (above the tags' 2 deg) and keep within twice it."""
    realism = Realism(quat_noise_deg=1.0, tissue_wobble_deg=3.0, headings=Headings.INDEPENDENT)
    body, heading, worst = _walk_after("tpose", realism, seed=3, seconds=11.0)
    feet = _heading_errors(body, heading, "/foot/")
    assert feet, "no foot's heading found"
    assert max(feet.values()) <= 3.0, feet
    ankles = {n: v for n, v in worst.items() if "ankle" in n}
    assert ankles
    assert all(unc > 2.0 and error <= 2.0 * unc for error, unc in ankles.values()), ankles


@pytest.mark.parametrize("noise", [1.0, 2.0])
def test_a_still_pose_of_noisy_tags_is_calibrated_and_a_moved_one_refused(noise: float) -> None:
    """A still N-pose held 1 s (50 samples), the tags' noise 1-2 deg: the largest
    turn of a raw sample from the mean went past 3 deg and the window was refused,
    blaming the subject (10 of 10 seeds at 1 deg). Stillness is now judged on the
    low-passed turn against each tag's own scatter: every seed is calibrated; the
    subject moving (a knee bending 20 deg in the window) is still refused."""
    held = dict(CALIBRATION_POSES["npose"])
    realism = Realism(quat_noise_deg=noise, headings=Headings.INDEPENDENT)
    for seed in range(5):
        body = BodyEmulator(Routine("still", "", lambda t: held), imu_tags(), realism=realism,
                            seed=seed)  # fmt: skip
        report = calibrate_window(_window(body, 0.0, 1.0), Profile(), "npose").report
        assert all(t["scatter_deg"] > noise for t in report["tags"].values())
    bend = Routine("bend", "", keyframes([(0.0, held), (0.5, held),
                                          (1.0, {**held, "left_knee_flexion_deg": 20.0})],
                                         loop=False))  # fmt: skip
    moved = _window(BodyEmulator(bend, imu_tags(), realism=realism, seed=1), 0.0, 1.0)
    with pytest.raises(CalibrationRefused, match="the subject moved") as caught:
        calibrate_window(moved, Profile(), "npose")
    assert "body/leg/left/shank/raw" in str(caught.value)


@pytest.mark.parametrize("noise", [0.3, 2.0])
def test_a_pose_turning_smoothly_through_the_whole_window_is_refused(noise: float) -> None:
    """The arms lowering 20 deg from the pose smoothly through the whole 1 s window
    (a subject settling into it): the tags' scatter about their mean was that
    motion (14 deg), which the stillness limit took for noise, and the window was
    calibrated. The noise is now judged from the samples' second differences: each
    tag's scatter is its noise (within 1.5 times the emulator's), the window refused."""
    held = dict(CALIBRATION_POSES["tpose"])
    lower = {"left_shoulder_abduction_deg": 70.0, "right_shoulder_abduction_deg": 70.0}
    settling = Routine("settling", "", keyframes([(0.0, held), (1.0, {**held, **lower})],
                                                 loop=False))  # fmt: skip
    realism = Realism(quat_noise_deg=noise)
    window = _window(BodyEmulator(settling, imu_tags(), realism=realism, seed=2), 0.0, 1.0)
    with pytest.raises(CalibrationRefused, match="the subject moved") as caught:
        calibrate_window(window, Profile(), "tpose")
    tags = caught.value.report["tags"]
    arm = tags["body/arm/left/upperarm/raw"]
    assert arm["still_deg"] > arm["still_limit_deg"], arm
    # the emulator's noise is about each axis: its turns' RMS is sqrt(3) times it
    assert all(t["scatter_deg"] < 1.5 * math.sqrt(3) * noise for t in tags.values()), tags


def test_the_arms_headings_are_found_with_noisy_tags() -> None:
    """Tags of 1.5 deg noise, the N-pose, then reaching: the elbow pairs' fits never
    came within the fixed 0.3 deg (1 deg at 120 samples) bound, so the arms' tags
    stayed unknown. The bound now scales with the fit's misfit: both arms' upper
    arm and forearm headings are found, within 2 deg of the truth, and the
    elbows state the fit's uncertainty."""
    realism = Realism(quat_noise_deg=1.5, headings=Headings.INDEPENDENT)
    body, heading, worst = _walk_after("npose", realism, seed=2, seconds=9.0, arms=True)
    arms = _heading_errors(body, heading, "/arm/")
    pairs = {k for k in arms if "/upperarm/" in k or "/forearm/" in k}
    assert len(pairs) == 4, sorted(arms)
    assert max(arms[k] for k in pairs) <= 2.0, arms
    assert heading.elbows is not None
    assert all(u > 0.3 for u in heading.elbows.unc_deg.values())
    elbows = {n: v for n, v in worst.items() if "elbow" in n}
    assert elbows
    assert all(unc > 2.0 for _, unc in elbows.values()), elbows


def _after_t_pose(moving: Routine | None = None, side: str = "left") -> Routine:
    """The T-pose held 1 s, then eased over 1 s into ``moving`` (its time from 1 s on;
    by default the reach of the ``side`` arm)."""
    from bodynet.nodes.motion import eased, reach

    still = dict(CALIBRATION_POSES["tpose"])
    angles = moving.angles if moving is not None else reach(side)

    def at(t: float) -> dict[str, float]:
        return still if t < 1.0 else eased(still, angles(t - 1.0), t - 1.0)

    return Routine("tpose-then-move", "", at)


Ticks = list[tuple[float, dict[str, tuple[float, float]]]]


def _shared_run(body: BodyEmulator, end_s: float) -> tuple[BodyHeading, Ticks, bool]:
    """The default profile (``auto``) calibrated in the T-pose, then the gateway's path
    to ``end_s``: per tick, each measured dof's error against the truth and its
    ``unc_deg``; and whether the elbows and wrists proposed a shared heading."""
    auto = Profile(pose="tpose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), auto,
                                           "tpose").apply(auto, "tpose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    ticks, proposed = [], False
    for t in np.arange(1.0, end_s, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        solver = heading_tick(heading, solver, float(t), samples)
        proposed |= heading.two_dof is not None and heading.two_dof.heading is not None
        out = solver.solve(samples)
        unc = dict(zip(out.names.angles, out.unc.tolist(), strict=True))
        errors = measured_errors(out.angles_deg, out.flags, truth)
        ticks.append((float(t), {n: (e, unc[n]) for n, e in errors.items()}))
    return heading, ticks, proposed


@pytest.mark.parametrize(("facing", "seed", "side"), [(37.0, 1, "left"), (250.0, 2, "left"),
                                                     (130.0, 3, "right")])  # fmt: skip
def test_shared_tags_after_a_t_pose_get_their_heading_from_the_reaching_arm(
    facing: float, seed: int, side: str
) -> None:
    """Tags sharing one reference, arbitrary mountings, the subject facing anywhere,
    the default heading ``auto``; the T-pose, then one arm's reach (lowered,
    lifted forward, the elbow bending, then the wrist flexing), nothing else moving:
    no knee bends and the elbow's flexion axis was vertical in the pose, so no
    hinge tells. The wrist, a two-dof joint, does: the heading is found within
    1.5 s (emulated) of its first flexion and within 1 deg of the truth, checked
    by the joints before it is taken; until then every dof is flagged, from then
    the arm's dofs are measured, each within twice its uncertainty."""
    body = BodyEmulator(_after_t_pose(side=side), imu_tags(),
                        realism=Realism(headings=Headings.SHARED, facing_deg=facing),
                        seed=seed)  # fmt: skip
    heading, ticks, _ = _shared_run(body, 10.5)
    state = heading.state()
    assert state["state"] == "found", state
    assert state["hinge"] in (f"{side}_wrist", f"{side}_elbow"), state
    assert abs((state["deg"] - facing + 180) % 360 - 180) <= 1.0, state
    flexed = next(t for t in np.arange(1.0, 10.5, 1 / RATE_HZ)
                  if body.angles(float(t)).get(f"{side}_wrist_flexion_deg", 0.0) > 1.0)  # fmt: skip
    assert 0.0 < state["found_t"] - flexed <= 1.5, (flexed, state)
    before = [errors for t, errors in ticks if t < state["found_t"]]
    after = [errors for t, errors in ticks if t > state["found_t"]]
    assert before
    assert after
    assert not any(before)  # nothing measured before the heading is known
    arm = [(e, u, n, t) for t, errors in ticks if t > state["found_t"]
           for n, (e, u) in errors.items() if n.startswith(side)]  # fmt: skip
    assert {f"{side}_{dof}_deg" for dof in ("elbow_flexion", "wrist_flexion", "shoulder_flexion")
            } <= {n for _, _, n, _ in arm}  # fmt: skip
    worst = max(arm, key=lambda r: r[0] - 2 * r[1])
    assert worst[0] <= 2 * worst[1], worst


def test_tags_of_their_own_reaching_after_a_t_pose_are_not_given_the_arms_heading() -> None:
    """6-axis tags, each with a heading of its own, under the default ``auto``: the
    T-pose, then the same reach. A two-dof joint proposes a shared heading, and
    the joints it drives break their axes under it (:class:`SharedCheck`): it is
    not taken, no dof is shown measured under it, and the gateway goes on
    estimating each tag's heading (``switched``)."""
    body = BodyEmulator(_after_t_pose(), imu_tags(),
                        realism=Realism(headings=Headings.INDEPENDENT, facing_deg=37.0),
                        seed=1)  # fmt: skip
    heading, ticks, proposed = _shared_run(body, 12.0)
    assert proposed
    assert "headings of their own" in heading.state()["switched"]
    assert heading.profile.heading == "independent"
    assert not any(errors for _, errors in ticks)  # nothing shown measured, nothing wrong


def test_an_elbow_bending_alone_after_a_t_pose_tells_no_shared_heading() -> None:
    """The elbow flexing alone after a T-pose turns about its axis that was vertical
    in the pose: every shared heading keeps its axes as perpendicular, so none is
    taken (nothing is guessed), every dof stays flagged, and the state says which
    motion would tell."""
    from bodynet.nodes.motion import ROUTINES

    body = BodyEmulator(_after_t_pose(ROUTINES["elbow-slow"]), imu_tags(),
                        realism=Realism(headings=Headings.SHARED, facing_deg=37.0),
                        seed=3)  # fmt: skip
    heading, ticks, proposed = _shared_run(body, 8.0)
    assert max(abs(body.angles(float(t)).get("left_elbow_flexion_deg", 0.0))
               for t in np.arange(1.0, 8.0, 0.1)) > 60.0  # fmt: skip
    assert not proposed
    state = heading.state()
    assert state["state"] == "unknown", state
    assert not any(errors for _, errors in ticks)
    assert any("pronation" in w and "alone" in w for w in state["waiting_for"]), state


def _reach_bow_reach_after_t_pose() -> Routine:
    """The T-pose held 1 s, then both arms' reach (16.5 s: lifted forward, the elbow
    bending, the wrist flexing, then out to the side and the forearm turning), a
    bow (the trunk's tags: the shoulders then measured), and the reach's first
    4 s again."""
    from bodynet.nodes.motion import bow, eased, reach

    still = dict(CALIBRATION_POSES["tpose"])
    left, right, down = reach("left"), reach("right"), bow()

    def at(t: float) -> dict[str, float]:
        if t < 1.0:
            return still
        if t < 17.5:
            return eased(still, {**left(t - 1.0), **right(t - 1.0)}, t - 1.0)
        if t < 20.4:
            return down(t - 17.5)
        return {**left(t - 20.4), **right(t - 20.4)}

    return Routine("tpose-reach-bow-reach", "", at)


@pytest.mark.parametrize(("seed", "facing"), [(1, 37.0), (2, 250.0)])
def test_independent_arm_tags_are_found_from_a_reach_after_a_t_pose(
    seed: int, facing: float
) -> None:
    """Independent 6-axis tags, arbitrary mountings, the T-pose (the elbows' flexion
    axes vertical: an elbow bending tells only the two tags' headings' difference),
    then both arms reaching: turning the forearm out to the side tells the pair's
    common heading, up to its 180 deg twin, which the shoulder's range tells
    apart. Each arm's tags come within 1 deg of the emulator's truth (the hands'
    then below the forearms'), not before the forearm turned; nothing of an arm
    is measured before; from then each elbow and wrist dof is within twice its
    ``unc_deg``, and, once a bow gave the chest's tag, each shoulder dof too."""
    body = BodyEmulator(_reach_bow_reach_after_t_pose(), imu_tags(),
                        realism=Realism(headings=Headings.INDEPENDENT, facing_deg=facing),
                        seed=seed)  # fmt: skip
    independent = Profile(heading="independent", pose="tpose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "tpose").apply(independent, "tpose"))  # fmt: skip
    solver = BodySolver(heading.profile)
    rows, known = [], {}
    for t in np.arange(1.0, 24.4, 1 / RATE_HZ):
        samples, truth = _samples(body, float(t))
        solver = heading_tick(heading, solver, float(t), samples)
        for side in ("left", "right"):
            if side not in known and heading.profile.heading_known(f"body/arm/{side}/forearm/raw"):
                known[side] = float(t)
        out = solver.solve(samples)
        unc = dict(zip(out.names.angles, out.unc.tolist(), strict=True))
        errors = measured_errors(out.angles_deg, out.flags, truth)
        rows += [(float(t), n, e, unc[n]) for n, e in errors.items()]
    truth_headings = {s.site.raw_key: body.headings_deg[s.node] for s in body.sensors}
    assert heading.elbows is not None
    assert set(heading.elbows.done) == set(known) == {"left", "right"}
    rolled = next(t for t in np.arange(1.0, 24.4, 1 / RATE_HZ)
                  if abs(body.angles(float(t))["left_elbow_pronation_deg"]) > 1.0)  # fmt: skip
    assert all(rolled < t < rolled + 3.0 for t in known.values()), (rolled, known)
    for side in ("left", "right"):
        for seg in ("upperarm", "forearm", "hand"):
            key = f"body/arm/{side}/{seg}/raw"
            error = (heading.profile.imu_headings[key] - truth_headings[key] + 180) % 360 - 180
            assert abs(error) <= 1.0, (key, error)
    arm = [r for r in rows if r[1].startswith(("left", "right"))]
    assert not [r for r in arm if r[0] < min(known.values())]
    measured = {n for _, n, _, _ in arm}
    assert {f"{side}_{dof}_deg" for side in ("left", "right") for dof in (
        "elbow_flexion", "elbow_pronation", "wrist_flexion", "shoulder_flexion",
        "shoulder_rotation")} <= measured  # fmt: skip
    worst = max(arm, key=lambda r: r[2] - 2 * r[3])
    assert worst[2] <= 2 * worst[3], worst


def test_an_elbow_bending_alone_after_a_t_pose_finds_no_independent_arm_tag() -> None:
    """Independent 6-axis tags, the T-pose, then an elbow flexing alone (the arm out
    to the side): it turns about its axis that was vertical in the pose, which
    every pair of headings with the same difference keeps perpendicular to the
    forearm's, so no pair is taken (nothing guessed), every arm dof stays flagged,
    and ``waiting_for`` says which motion would tell (the forearm turning)."""
    from bodynet.nodes.motion import ROUTINES

    body = BodyEmulator(_after_t_pose(ROUTINES["elbow-slow"]), imu_tags(),
                        realism=Realism(headings=Headings.INDEPENDENT, facing_deg=37.0),
                        seed=3)  # fmt: skip
    independent = Profile(heading="independent", pose="tpose")
    heading = BodyHeading(calibrate_window(_window(body, 0.2, 0.95), independent,
                                           "tpose").apply(independent, "tpose"))  # fmt: skip
    assert heading.elbows is not None
    assert set(heading.elbows.twins) == {"left", "right"}  # searched after a T-pose
    ticks = _follow(body, heading, 8.0)
    assert max(abs(body.angles(float(t)).get("left_elbow_flexion_deg", 0.0))
               for t in np.arange(1.0, 8.0, 0.1)) > 60.0  # fmt: skip
    assert len(heading.elbows.samples["left"]) >= heading.elbows.MIN_SAMPLES
    assert not heading.elbows.found
    assert not any(n.startswith(("left", "right")) for _, errors, _ in ticks for n in errors)
    wanted = " ".join(heading.state()["waiting_for"])
    assert "pronation" in wanted, wanted
