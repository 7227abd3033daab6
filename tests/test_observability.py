"""Honest dofs on emulated SmartSuit arms with truth (issue 22): every dof is
within its stated uncertainty of the truth or flagged, no unflagged dof jumps,
and what gravity cannot see is held, never flipped (000 seed, sections 3.3 and
4.3). The solver is called directly at 50 Hz; a few emulated seconds each."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bodynet.core.codecs import pose
from bodynet.core.keys import LEFT_ARM, RIGHT_ARM
from bodynet.core.messages import RawSample
from bodynet.core.subject import Profile
from bodynet.gateway.service import pose_frame
from bodynet.gateway.solver import BodySolver
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags, smartsuit_sensors
from bodynet.nodes.motion import Routine, keyframes

ARM = ("shoulder_flexion", "shoulder_abduction", "shoulder_rotation", "elbow_flexion",
       "elbow_pronation", "wrist_flexion", "wrist_deviation")  # fmt: skip
JUMP_DEG = 20.0  # a physiological bound for one 10 ms interval (these tests tick every 20 ms)
RATE_HZ = 50
SLACK_DEG = 0.3  # the emulated encoders' quantisation, beyond the stated uncertainty


@dataclass
class Run:
    truth: list[Mapping[str, float]]
    frames: list[pose.PoseFrame]


def run(routine: Routine, seconds: float, side: str = "left", seed: int = 3) -> Run:
    """A SmartSuit arm (shoulder, elbow, wrist modules; realistic accelerometers)
    under ``routine``, solved at ``RATE_HZ``; every pose through the real message."""
    sensors = smartsuit_sensors([LEFT_ARM if side == "left" else RIGHT_ARM])
    body = BodyEmulator(routine, sensors, realism=Realism(), seed=seed)
    solver = BodySolver(Profile())
    out = Run([], [])
    for tick in range(int(seconds * RATE_HZ) + 1):
        t = tick / RATE_HZ
        readings, _ = body.sample(t)
        samples = {s.site: RawSample(r, tick, round(t * 1e9))
                   for s, r in zip(sensors, readings, strict=True)}  # fmt: skip
        frame = pose.decode(pose.encode(pose_frame(solver.solve(samples), tick, [])))
        out.truth.append(routine.angles(t))
        out.frames.append(frame)
    return out


def check_honest(r: Run, side: str = "left") -> dict[str, int]:
    """Every arm dof within its uncertainty of the truth or flagged; no unflagged
    jump; returns how many ticks each dof was flagged after the first second (in
    which the arm's tilt waits for a trunk sensor to show itself)."""
    flagged = dict.fromkeys(ARM, 0)
    for k, (truth, frame) in enumerate(zip(r.truth, r.frames, strict=True)):
        settled = k >= RATE_HZ
        for dof in ARM:
            name = f"{side}_{dof}_deg"
            value, want = frame.angles_deg[name], truth.get(name, 0.0)
            if not pose.is_measured(frame, name):
                flagged[dof] += settled
                assert math.isnan(frame.unc_deg[name]), (k, name)
                continue
            unc = frame.unc_deg[name]
            assert unc > 0, (k, name)
            assert abs(value - want) <= unc + SLACK_DEG, (k / RATE_HZ, name, value, want, unc)
            if k:
                step = abs(value - r.frames[k - 1].angles_deg[name])
                assert step <= JUMP_DEG, (k / RATE_HZ, name, step)
    return flagged


def still(pose_: Mapping[str, float]) -> Routine:
    return Routine("still", "", lambda t: dict(pose_))


def test_a_hanging_arm_keeps_its_pronation_unobserved_and_still() -> None:
    """The demo's right arm: hanging still, forearm and hand along gravity. Their
    rotation about the vertical (pronation) is invisible to every accelerometer:
    flagged ``unobserved``, and its number never moves; every other dof is
    measured within its uncertainty."""
    r = run(still({}), 2.0, side="right")
    flagged = check_honest(r, side="right")
    assert flagged["elbow_pronation"] == len(r.frames) - RATE_HZ
    name = "right_elbow_pronation_deg"
    assert {f.flags[name] for f in r.frames} == {pose.UNOBSERVED}
    assert len({f.angles_deg[name] for f in r.frames}) == 1  # it never moved
    for dof in ("shoulder_flexion", "shoulder_abduction", "shoulder_rotation", "elbow_flexion",
                "wrist_flexion", "wrist_deviation"):  # fmt: skip
        assert flagged[dof] == 0, dof
    assert "gravity" not in r.frames[-1].why(name)  # nothing measured it: why says so
    assert r.frames[-1].why(name) == pose.REASONS[pose.UNOBSERVED]


def test_reaching_up_through_the_vertical() -> None:
    """Lift the straight arm forward and up to 170 deg: abduction is
    invisible where the arm is horizontal (its axis is then the vertical), the
    pronation wherever the forearm hangs or points up; those are held or
    unobserved there and measured elsewhere, never an unflagged jump."""
    up = {"left_shoulder_flexion_deg": 170.0, "left_wrist_flexion_deg": 30.0}
    routine = Routine("reach-up", "", keyframes([
        (0.0, {}), (4.5, up), (5.0, up),
    ], loop=False))  # fmt: skip
    r = run(routine, 5.0)
    flagged = check_honest(r)
    assert flagged["shoulder_abduction"] > 0  # through the horizontal
    assert flagged["shoulder_abduction"] < len(r.frames) // 2  # and only near there
    assert flagged["shoulder_flexion"] == 0  # gravity sees the lift all the way
    reasons = {f.flags.get("left_shoulder_abduction_deg") for f in r.frames}
    assert pose.HELD in reasons


def test_the_seeds_horizontal_sweep_is_held_not_invented() -> None:
    """000 seed, Figure 4-6: the arm horizontal, swept about the vertical from P1
    to P2. No accelerometer and no encoder sees that sweep: abduction is held at
    its last measured value and flagged while the arm is swept horizontal, then
    measured again (back within its uncertainty) once the arm has come down."""
    lifted = {"left_shoulder_flexion_deg": 90.0}
    swept = {"left_shoulder_flexion_deg": 90.0, "left_shoulder_abduction_deg": 40.0}
    routine = Routine("sweep", "", keyframes([
        (0.0, {}), (3.0, lifted), (5.0, swept), (7.5, {}), (8.0, {}),
    ], loop=False))  # fmt: skip
    r = run(routine, 8.0)
    check_honest(r)
    name = "left_shoulder_abduction_deg"
    horizontal = [f for f, t in zip(r.frames, r.truth, strict=True)
                  if t.get(name, 0.0) > 5.0 and t["left_shoulder_flexion_deg"] > 88.0]  # fmt: skip
    assert len(horizontal) > RATE_HZ  # a second and more of sweep
    assert all(not pose.is_measured(f, name) for f in horizontal)
    assert all(f.angles_deg[name] == horizontal[0].angles_deg[name] for f in horizontal)
    assert pose.is_measured(r.frames[-1], name)


def test_uncalibrated_tags_and_the_arms_below_them_are_flagged() -> None:
    """Before the T-pose calibration every dof an IMU tag drives is flagged
    ``uncalibrated``, and so are the tilt dofs of SmartSuit modules below a
    trunk tag (their vertical comes through it).
    A trunk tag the topology announces but that has not delivered leaves the
    arms' tilt ``unobserved`` rather than measured against an assumed trunk."""
    arm = smartsuit_sensors([LEFT_ARM])
    tags = [t for t in imu_tags() if t.site.name in ("chest", "sacrum")]
    body = BodyEmulator(still({}), [*arm, *tags], realism=Realism(), seed=1)
    readings, _ = body.sample(0.0)
    samples = {s.site: RawSample(r, 0, 0) for s, r in zip(body.sensors, readings, strict=True)}
    out = BodySolver(Profile()).solve(samples)
    assert out.flags["lumbar_flexion_deg"] == pose.UNCALIBRATED
    assert out.flags["left_shoulder_flexion_deg"] == pose.UNCALIBRATED
    assert out.flags["left_wrist_deviation_deg"] == pose.UNCALIBRATED
    assert math.isnan(out.unc[list(out.names.angles).index("lumbar_flexion_deg")])
    # the trunk announced, not delivering yet
    solver = BodySolver(Profile())
    solver.expect(t.site.raw_key for t in tags)
    arm_only = {s: v for s, v in samples.items() if s.branch == LEFT_ARM}
    out = solver.solve(arm_only)
    assert out.flags["left_shoulder_flexion_deg"] == pose.UNOBSERVED
    assert "left_shoulder_rotation_deg" not in out.flags  # its encoder
    # nothing announced: an arm on its own is measured against the upright model,
    # once the topology has had a second to show a trunk sensor
    solver = BodySolver(Profile())
    out = solver.solve(arm_only)
    assert out.flags["left_shoulder_flexion_deg"] == pose.UNOBSERVED
    later = {s: RawSample(v.reading, 1, 1_000_000_000) for s, v in arm_only.items()}
    out = solver.solve(later)
    assert "left_shoulder_flexion_deg" not in out.flags


@pytest.mark.parametrize("calibrated", [True, False])
def test_joints_on_a_pelvis_tag_announced_but_silent_are_flagged(calibrated: bool) -> None:
    """Tags everywhere but on the pelvis: the joints between the pelvis and a
    tag (lumbar, hips) are measured against the upright model while no pelvis
    tag is known, and flagged ``unobserved`` once the topology announces one
    that does not deliver (they rest on a pelvis assumed upright); the
    shoulders never rest on it. The same sites deliver throughout, so what
    those joints rest on is worked out for the sites once (``_Sorted``) and
    again when the pelvis's state changes. Uncalibrated, every dof a tag
    drives also says so."""
    tags = imu_tags()
    sacrum = next(t for t in tags if t.site.name == "sacrum")
    body = BodyEmulator(still({}), [t for t in tags if t is not sacrum], realism=Realism(), seed=1)
    solver = BodySolver(Profile(heading="fixed"))
    if calibrated:
        solver.assume_calibrated()
    names = ("left_hip_flexion_deg", "lumbar_flexion_deg", "left_shoulder_flexion_deg")
    seen = []
    for k in range(4):
        if k == 2:  # the pelvis tag's token comes up; it never delivers
            solver.expect([sacrum.site.raw_key])
        readings, _ = body.sample(k / 100)
        out = solver.solve({s.site: RawSample(r, k, k * 10_000_000)
                            for s, r in zip(body.sensors, readings, strict=True)})  # fmt: skip
        seen.append([out.reasons.get(n, ()) for n in names])
    tag = () if calibrated else (pose.UNCALIBRATED,)
    assert seen[:2] == [[tag, tag, tag]] * 2, seen
    pelvis = (*tag, pose.UNOBSERVED)
    assert seen[2:] == [[pelvis, pelvis, tag]] * 2, seen


@pytest.mark.parametrize("version", [1, 2])
def test_pose_versions_decode_and_is_measured(version: int) -> None:
    """Readers of today's (v1) messages keep working; v2 carries every reason
    and each dof's uncertainty."""
    out = BodySolver(Profile()).solve({})
    frame = pose_frame(out, 1, [])
    data = pose.encode(frame)
    if version == 1:
        d = __import__("orjson").loads(data)
        d["v"] = 1
        del d["reasons"], d["unc_deg"]
        data = __import__("orjson").dumps(d)
    back = pose.decode(data)
    assert back.flags == frame.flags
    assert not pose.is_measured(back, "left_elbow_flexion_deg")
    assert back.reasons["left_elbow_flexion_deg"] == ("unobserved",)
    if version == 2:
        assert math.isnan(back.unc_deg["left_elbow_flexion_deg"])
    assert np.isnan(out.unc).all()


def test_report_leaves_unmeasured_samples_out_and_says_so(tmp_path: Path) -> None:
    """``bodynet report``'s figures take measured samples only: a held dof's
    samples are out of its range of motion and counted with their flag; a
    recording with no measured sample at all is refused with the count."""
    from bodynet.clients import report
    from bodynet.clients.mcap_store import McapSink
    from bodynet.core import keys

    out = BodySolver(Profile()).solve({})
    path = tmp_path / "flagged.mcap"
    sink = McapSink(path)
    for k in range(50):
        frame = pose_frame(out, k, [])
        angles = dict(frame.angles_deg, left_elbow_flexion_deg=float(k))
        flags = {} if k < 40 else {"left_elbow_flexion_deg": pose.HELD}
        frame = dataclasses.replace(frame, angles_deg=angles, flags=flags)
        sink.write_pose(keys.pose_key(), frame, (k + 1) * 10_000_000)
    sink.close()
    rec = report.load_recording(path)
    assert rec.left_out["left_elbow_flexion_deg"] == {pose.HELD: 10}
    rom = report.rom_table(rec).set_index("channel")
    assert rom.loc["left_elbow_flexion_deg", "max (deg)"] == 39.0  # the held 40-49 left out
    assert "left out" in report.left_out_table(rec).columns
    everything = tmp_path / "nothing.mcap"
    sink = McapSink(everything)
    for k in range(5):
        sink.write_pose(keys.pose_key(), pose_frame(out, k, []), (k + 1) * 10_000_000)
    sink.close()
    with pytest.raises(report.ReportError, match="no joint angle was measured"):
        report.analyse([everything], with_trials=False)


def test_an_unknown_heading_leaves_the_encoders_measured() -> None:
    """Calibrated tags whose heading is not found yet flag the tilt dofs of the
    SmartSuit arm below the chest (its frame turns with the heading), never the
    dofs its encoders measure: an encoder's angle needs no heading."""
    from bodynet.core.skeleton import TPOSE
    from bodynet.gateway.solver import tpose_mounts

    arm = smartsuit_sensors([LEFT_ARM])
    tags = [t for t in imu_tags() if t.site.name in ("chest", "sacrum")]
    body = BodyEmulator(still(dict(TPOSE)), [*arm, *tags], realism=Realism(), seed=1)
    readings, _ = body.sample(0.0)
    samples = {s.site: RawSample(r, 0, 0) for s, r in zip(body.sensors, readings, strict=True)}
    window = {t.site: [samples[t.site].reading.wxyz] for t in tags}  # type: ignore[union-attr]
    profile = dataclasses.replace(Profile(), heading="auto").with_mounts(tpose_mounts(window))
    out = BodySolver(profile).solve(samples)
    assert out.flags["lumbar_flexion_deg"] == pose.UNCALIBRATED  # heading not found yet
    assert out.flags["left_shoulder_flexion_deg"] == pose.UNCALIBRATED  # a tilt below the chest
    for encoder in ("left_shoulder_rotation_deg", "left_elbow_flexion_deg",
                    "left_wrist_flexion_deg"):  # fmt: skip
        assert pose.UNCALIBRATED not in out.reasons.get(encoder, ()), encoder


@pytest.mark.parametrize(
    ("beside", "encoders_calibrated"), [(False, True), (True, True), (True, False)]
)
def test_encoders_beside_tags_of_unknown_heading_stay_measured(
    beside: bool, encoders_calibrated: bool
) -> None:
    """The IMU suit's 6-axis tags (each a heading of its own, none found yet) with
    a SmartSuit left arm beside its tags (``beside``) or instead of them: the arm's
    encoders (shoulder rotation, elbow and wrist flexion) need no heading, so they
    are measured, within 1 deg of the truth, either way (beside the tags they were
    all flagged, the encoders' data lost); every dof the tags drive is flagged. With
    the encoders not calibrated (no R and SF) neither source is sure: flagged."""
    from bodynet.core.skeleton import TPOSE
    from bodynet.gateway.solver import tpose_mounts
    from bodynet.nodes.emulator import Headings

    tags = [t for t in imu_tags() if beside or t.site.branch != LEFT_ARM]
    held = {**TPOSE, "left_shoulder_rotation_deg": 30.0, "left_elbow_flexion_deg": 60.0,
            "left_wrist_flexion_deg": 20.0, "right_elbow_flexion_deg": 45.0}  # fmt: skip
    body = BodyEmulator(Routine("bent", "", lambda t: dict(TPOSE) if t < 1.0 else dict(held)),
                        [*tags, *smartsuit_sensors([LEFT_ARM])],
                        realism=Realism(headings=Headings.INDEPENDENT), seed=1)  # fmt: skip
    readings, _ = body.sample(0.0)
    window = {s.site: [r.wxyz] for s, r in zip(body.sensors, readings, strict=True)
              if s in tags}  # type: ignore[union-attr]  # fmt: skip
    profile = Profile(heading="auto").with_mounts(tpose_mounts(window))
    solver = BodySolver(profile if encoders_calibrated else dataclasses.replace(profile, ole={}))
    for k, t in enumerate((0.0, 1.5, 2.0)):
        readings, _ = body.sample(t)
        out = solver.solve({s.site: RawSample(r, k, round(t * 1e9))
                            for s, r in zip(body.sensors, readings, strict=True)})  # fmt: skip
    truth = body.angles(2.0)
    encoders = ("left_shoulder_rotation_deg", "left_elbow_flexion_deg", "left_wrist_flexion_deg")
    for encoder in encoders if encoders_calibrated else ():
        assert encoder not in out.flags, (encoder, out.reasons.get(encoder))
        assert out.angles_deg[encoder] == pytest.approx(truth[encoder], abs=1.0), encoder
    tagged = [n for n in out.angles_deg if not n.startswith("left_")
              or (beside and (n not in encoders or not encoders_calibrated))]  # fmt: skip
    assert all(out.flags.get(n) for n in tagged), [n for n in tagged if not out.flags.get(n)]


@pytest.mark.parametrize("pelvis_announced", [False, True])
def test_an_arm_alone_stands_on_the_upright_trunk(pelvis_announced: bool) -> None:
    """The seed's device, a SmartSuit arm with no trunk sensor: its shoulder,
    elbow and wrist are measured against the upright model of the trunk, whose
    lumbar and neck dofs stay not measured (flag ``unobserved``, no angle output)
    with the reason ``upright``; the arm's segments stand on that reference as
    on the pelvis (``unmeasured_segments``, what the exports, LSL and Foxglove
    transforms leave out, does not name them). With a pelvis tag announced but
    silent the trunk is no reference: the arm's chain is unmeasured."""
    from bodynet.clients import lsl
    from bodynet.clients.body_tree import unmeasured_segments
    from bodynet.core.metrics import measured_angles
    from bodynet.core.skeleton import build_skeleton

    # the forearm and hand off the vertical: gravity determines the pronation
    bent = {"left_shoulder_flexion_deg": 40.0, "left_elbow_flexion_deg": 60.0}
    body = BodyEmulator(still(bent), smartsuit_sensors([LEFT_ARM]), realism=Realism(), seed=1)
    solver = BodySolver(Profile())
    if pelvis_announced:
        solver.expect([next(t for t in imu_tags() if t.site.name == "sacrum").site.raw_key])
    for k in range(3):  # past the second the topology has to show a trunk sensor
        readings, _ = body.sample(k * 0.6)
        out = solver.solve({s.site: RawSample(r, k, int(k * 0.6e9))
                            for s, r in zip(body.sensors, readings, strict=True)})  # fmt: skip
    frame = pose_frame(out, 1, [])
    trunk = [n for n in frame.angles_deg if n.startswith(("lumbar_", "neck_"))]
    assert trunk
    want = (pose.UNOBSERVED,) if pelvis_announced else (pose.UNOBSERVED, pose.UPRIGHT)
    got = {n: (frame.flags[n], tuple(frame.reasons[n])) for n in trunk}
    assert got == dict.fromkeys(trunk, (pose.UNOBSERVED, want))
    assert not set(trunk) & set(measured_angles(frame))
    arm = {"left_upperarm", "left_forearm", "left_hand"}
    skeleton = build_skeleton()
    chains = skeleton.segment_chains()
    values = dict(zip([c.label for c in lsl.segment_channels(skeleton)],
                      lsl.segment_values(frame, chains), strict=True))  # fmt: skip
    if pelvis_announced:
        assert arm <= unmeasured_segments(frame)
        assert all(math.isnan(values[f"{s}_qw"]) for s in arm)
    else:
        assert all(pose.is_measured(frame, a) for s in arm for a in chains[s] if a not in trunk)
        assert not arm & unmeasured_segments(frame)
        assert [values[f"{s}_qw"] for s in arm] == [frame.segments[s][1][0] for s in arm]
