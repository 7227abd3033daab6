"""`bodynet process` and `bodynet export csv` on captures made by the emulators."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bodynet.clients.mcap_store import read_poses
from bodynet.core.codecs import imu_matrix, smartsuit_can
from bodynet.core.codecs.pose import is_measured
from bodynet.core.errors import Reason
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import Quat
from bodynet.core.profile import mount
from bodynet.core.skeleton import TPOSE
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags, smartsuit_sensors
from bodynet.nodes.motion import ROUTINES, Routine, keyframes
from bodynet.nodes.timing import LinkTiming, Sends, Timers, link_schedule

BODYNET = Path(sys.executable).with_name("bodynet")
IDEAL_RANDOM_MOUNTS = Realism(0.0, 0.0, 0.0, 0.0, 0.0, random_tag_mounts=True)


def run(*args: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BODYNET), *map(str, args)], capture_output=True, text=True,
                          timeout=120, check=False)  # fmt: skip


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


def test_imu_capture_processed_to_the_true_angles(tmp_path: Path) -> None:
    """3 s of T-pose, then the upper-body routine, through the data matrix at 25 Hz."""
    upper = ROUTINES["upper-body"].angles
    motion = Routine("capture", "", lambda t: dict(TPOSE) if t < 3.0 else upper(t - 3.0))
    body = BodyEmulator(motion, imu_tags(), realism=IDEAL_RANDOM_MOUNTS, seed=4)
    capture = tmp_path / "session.txt"
    with capture.open("wb") as f:
        for tick in range(25 * 9):
            readings, _ = body.sample(tick / 25)
            f.write(b"".join(imu_matrix.encode_line(r) for r in readings if isinstance(r, Quat)))
    out = tmp_path / "session.mcap"
    # the emulated subject faces +X of the tags' one frame, and no knee moves: declared
    result = run("process", capture, "--format", "imu-central", "-o", out, "--heading", "fixed")
    assert result.returncode == 0, result.stderr
    assert "calibrated 15 sensors (tpose)" in result.stderr
    assert run("export", "csv", out, "-o", tmp_path / "s.csv").returncode == 0
    table = rows(tmp_path / "s.csv")
    assert len(table) == 25 * 9  # one row per data-matrix frame
    decoded = run("decode", "--format", "imu-central", capture).stdout.splitlines()
    times = sorted({json.loads(line)["t_s"] for line in decoded})
    assert [float(r["t_s"]) for r in table] == times  # the same time base as decode
    for row in table[::10]:
        truth = motion.angles(float(row["t_s"]))
        for name in ("left_shoulder_abduction_deg", "lumbar_rotation_deg", "neck_rotation_deg",
                     "right_shoulder_flexion_deg", "lumbar_lateral_deg"):  # fmt: skip
            assert float(row[name]) == pytest.approx(truth.get(name, 0.0), abs=0.01), (
                row["t_s"],
                name,
            )
    assert float(table[0]["left_wrist_x_m"]) == pytest.approx(0.0, abs=1e-3)  # T-pose: arms out
    assert float(table[0]["left_wrist_y_m"]) == pytest.approx(0.22 + 0.293 + 0.265, abs=1e-3)


def test_can_log_processed_to_the_true_angles(tmp_path: Path) -> None:
    poses = [{}, {"left_shoulder_flexion_deg": 45.0, "left_elbow_flexion_deg": 90.0},
             {"left_shoulder_abduction_deg": 60.0, "left_wrist_flexion_deg": 30.0}]  # fmt: skip
    # each pose from rest and back, as in the reaching task: an accelerometer and an
    # encoder leave two arm poses for one reading, and continuity picks between them
    frames: list[tuple[float, dict[str, float]]] = []
    for i, pose in enumerate(poses):
        frames += [(2.0 * i, pose), (2.0 * i + 1, pose), (2.0 * i + 1.5, {})]
    motion = keyframes(frames, loop=False)
    body = BodyEmulator(Routine("holds", "", motion), smartsuit_sensors([LEFT_ARM]),
                        realism=Realism.ideal())  # fmt: skip
    log = tmp_path / "arm.log"
    with log.open("w") as f:
        for tick in range(500):
            t = tick * 0.01
            readings, _ = body.sample(t)
            for r in readings:
                frame = smartsuit_can.encode_reading(r)
                f.write(
                    f"({1000 + t:.6f}) can0 {frame.arbitration_id:08X}#{frame.data.hex().upper()}\n"
                )
    out = tmp_path / "arm.mcap"
    assert run("process", log, "-o", out).returncode == 0
    assert run("export", "csv", out, "-o", tmp_path / "arm.csv").returncode == 0
    table = {round(float(r["t_s"]) - 1000, 2): r for r in rows(tmp_path / "arm.csv")}
    for t, pose in ((0.5, poses[0]), (2.5, poses[1]), (4.5, poses[2])):
        row = table[t]
        for name in ("left_shoulder_flexion_deg", "left_shoulder_abduction_deg",
                     "left_elbow_flexion_deg", "left_wrist_flexion_deg"):  # fmt: skip
            assert float(row[name]) == pytest.approx(pose.get(name, 0.0), abs=0.3), (t, name)


def test_export_refuses_what_it_cannot_read(tmp_path: Path, data_dir: Path) -> None:
    out = tmp_path / "x.csv"
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + bytes(50))
    result = run("export", "csv", junk, "-o", out)
    assert result.returncode == 2
    assert "not a complete MCAP file" in result.stderr
    assert "Traceback" not in result.stderr
    assert not out.exists()
    # a complete recording cut short at the end
    good = tmp_path / "good.mcap"
    assert run("process", data_dir / "smartsuit_arm.log", "-o", good).returncode == 0
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    result = run("export", "csv", cut, "-o", out)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert not out.exists()
    assert not out.with_name("x.csv.part").exists()


def test_process_holds_drifting_tags_as_the_gateway_does(tmp_path: Path) -> None:
    """A capture of 6-axis tags drifting apart (up to 10 deg/min each), the subject
    walking: `bodynet process` applies the live gateway's drift step
    (BodyHeading.step), so the hips', shoulders', lumbar's and neck's errors
    against the truth stay small where, with ``drift = "off"``, they grow; the
    pose's uncertainty of a joint held by its mean twist is wider than a tag's."""

    from bodynet.bench.drift import measured_errors
    from bodynet.clients.mcap_store import read_poses
    from bodynet.core.subject import Profile
    from bodynet.gateway.solver import UNC_TAG_DEG
    from bodynet.nodes.emulator import Headings
    from bodynet.offline.process import process

    walk = ROUTINES["walk"].angles
    motion = Routine("capture", "", lambda t: dict(TPOSE) if t < 2.0 else walk(t - 2.0))
    realism = Realism(yaw_drift_deg_per_min=10.0, headings=Headings.DRIFTING)
    body = BodyEmulator(motion, imu_tags(), realism=realism, seed=5)
    capture = tmp_path / "walk.txt"
    with capture.open("wb") as f:
        for tick in range(25 * 50):
            readings, _ = body.sample(tick / 25)
            f.write(b"".join(imu_matrix.encode_line(r) for r in readings if isinstance(r, Quat)))
    worst, unc = {}, {}
    for mode in ("joints", "off"):
        out = tmp_path / f"{mode}.mcap"
        profile = Profile(heading="fixed", drift=mode)  # reset together, facing +X
        result = process(capture, "imu-central", out, profile, tpose_s=1.5)
        assert result.calibrated
        worst[mode] = 0.0
        for _, frame in read_poses(out):
            t = frame.t_ns / 1e9
            if t > 35.0:
                errors = measured_errors(frame.angles_deg, frame.flags, motion.angles(t))
                worst[mode] = max(worst[mode], *(e for n, e in errors.items() if n.startswith(
                    ("hip_", "left_hip", "right_hip", "lumbar", "neck", "left_shoulder",
                     "right_shoulder"))))  # fmt: skip
                unc[mode] = dict(frame.unc_deg)
    assert worst["joints"] <= 4.0, worst
    assert worst["off"] > 2 * worst["joints"], worst
    # the tags' own (the capture's noise is below the floor) and what their lines'
    # times leave (STAMP_SPREAD_S), widened where the joint is held by its mean twist
    assert unc["off"]["lumbar_rotation_deg"] >= UNC_TAG_DEG
    assert unc["joints"]["lumbar_rotation_deg"] > unc["off"]["lumbar_rotation_deg"]
    # a hinge: geometric, the same either way
    assert unc["joints"]["left_knee_flexion_deg"] == unc["off"]["left_knee_flexion_deg"]


@pytest.mark.parametrize(
    ("text", "key"),
    [("accel_counts_per_g = 0", "accel_counts_per_g"),  # divided by zero in the solver
     ("[segments]\nthigh = 1e308", "segments.thigh"),  # the poses' pelvis went null
     ("[segments]\nupperam = 0.3", "segments.upperam")],  # dropped without a word
)  # fmt: skip
def test_process_refuses_a_profile_out_of_range(
    tmp_path: Path, data_dir: Path, text: str, key: str
) -> None:
    """A profile's absurd value stops `process` before it starts: exit 2, one line
    naming the file and the key, no traceback, no output."""
    profile = tmp_path / "subject.toml"
    profile.write_text(f"version = 1\n{text}\n")
    out = tmp_path / "p.mcap"
    result = run("process", "--format", "can-log", data_dir / "smartsuit_arm.log", "-o", out,
                 "--profile", profile)  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(f"bodynet process: {profile}: ")
    assert result.stderr.count("\n") == 1
    assert key in result.stderr
    assert not out.exists()


def test_a_sample_before_1970_is_refused_naming_the_capture(tmp_path: Path) -> None:
    """A time decode takes but a recording cannot hold (MCAP's times are from
    1970 on): process says which capture and sample, exit 2, nothing written."""
    csv_file, log = tmp_path / "neg.csv", tmp_path / "neg.log"
    csv_file.write_text("t_s,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n-1,1,0,0,0\n0,1,0,0,0\n")
    log.write_text("(-5.000000) can0 0006FFFF#0100020003000400\n")
    for capture, fmt, site, t in ((csv_file, "orientation-csv", "body/trunk/mid/sacrum/raw", -1),
                                  (log, "can-log", "body/arm/left/shoulder/raw", -5)):  # fmt: skip
        result = run("process", "--format", fmt, capture, "--tpose-s", "0",
                     "-o", tmp_path / "x.mcap")  # fmt: skip
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith(
            f"bodynet process: {capture}: the sample of {site} at {t} s cannot be recorded: "
            f"{Reason.OUT_OF_RANGE}: "), result.stderr  # fmt: skip
        assert result.stderr.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["neg.csv", "neg.log"]


@pytest.mark.parametrize(("end", "least_stale"), [(4.0, 50), (2.3, 10)])
def test_process_flags_a_tag_gone_for_a_stretch_and_one_dead_from_the_start(
    end: float, least_stale: int, tmp_path: Path
) -> None:
    """Segment orientations at 50 Hz (ideal tags, square on their segments): the
    left forearm's tag never sends (no column), the right forearm's sends nothing
    from 2 s to ``end`` (empty cells: 2 s, or a 0.3 s dropout). The left elbow
    and wrist are unobserved throughout; the right ones are flagged stale once
    its last sample is older than three of its 20 ms intervals (not the 0.5 s
    of ``STALE_S``), and the truth again when it is back; everything else is
    the truth all along."""
    from bodynet.cli.main import main
    from bodynet.clients.mcap_store import read_poses
    from bodynet.core.profile import mount
    from bodynet.core.skeleton import build_skeleton
    from bodynet.gateway.solver import STALE_FLOOR_S, STALE_INTERVALS

    motion = ROUTINES["full-body"]
    tags = [t for t in imu_tags() if mount(t.site).segment != "left_forearm"]
    body = BodyEmulator(motion, tags, realism=Realism.ideal(), seed=3)
    header = ["time"] + [f"{mount(t.site).segment}_{c}" for t in tags for c in "wxyz"]
    lines = [",".join(header)]
    for k in range(300):
        readings, _ = body.sample(k / 50)
        gone = 2.0 <= k / 50 < end
        lines.append(",".join([repr(k / 50)] + [
            "nan" if gone and mount(t.site).segment == "right_forearm" else repr(c)
            for t, r in zip(tags, readings, strict=True) for c in r.wxyz  # type: ignore[union-attr]
        ]))  # fmt: skip
    capture = tmp_path / "trial.csv"
    capture.write_text("\n".join(lines) + "\n")
    out = tmp_path / "trial.mcap"
    assert main(["process", str(capture), "--tpose-s", "0", "-o", str(out)]) == 0
    skeleton = build_skeleton()
    dead = set(skeleton.joint("left_elbow").angle_names())
    # (the left wrist, its hand's tag against a forearm nothing measures, is not
    # this test's matter: a capture's topology does not know the dead tag)
    wrist = set(skeleton.joint("left_wrist").angle_names())
    gap = {n for j in ("right_elbow", "right_wrist") for n in skeleton.joint(j).angle_names()}
    poses = list(read_poses(out))
    assert len(poses) == 300
    after = max(STALE_FLOOR_S, STALE_INTERVALS * 0.02)
    stale_poses, frozen_off = 0, 0.0
    for t_ns, frame in poses:
        t, truth = t_ns / 1e9, motion.angles(t_ns / 1e9)
        stale = 1.98 + after < t < end  # its last sample came at 1.98 s
        if abs(t - 1.98 - after) < 1e-6:  # on the edge, to rounding: either
            stale = bool(frame.stale)
        assert frame.stale == (["body/arm/right/forearm/raw"] if stale else []), t
        for name, value in frame.angles_deg.items():
            if name in wrist:
                continue
            if name in dead:
                assert frame.reasons[name] == ("unobserved",), (t, name)
            elif name in gap and stale:
                assert frame.flags[name] == "unobserved", (t, name)
                assert frame.reasons[name][:2] == ("unobserved", "stale"), (t, name)
                assert math.isnan(frame.unc_deg[name]), (t, name)
                frozen_off = max(frozen_off, abs(value - truth.get(name, 0.0)))
            elif name not in gap or not 2.0 <= t < end:
                assert name not in frame.flags, (t, name, frame.reasons.get(name))
                assert value == pytest.approx(truth.get(name, 0.0), abs=1e-3), (t, name)
        stale_poses += stale
    assert stale_poses > least_stale
    assert frozen_off > 10  # the frozen forearm's numbers were far from the truth


def test_a_slow_polled_site_and_a_jittering_tracker_are_not_stale_on_their_rhythm(
    tmp_path: Path,
) -> None:
    """A still body: the pelvis a Wi-Fi tracker at 100 Hz whose times jitter by
    +/-10 ms, the head one at 200 Hz as jittery (its gaps up to five of its
    intervals: the floor), the thorax a concentrator's node asked every 0.33 s.
    None is ever stale while it delivers on its rhythm, and every dof
    they measure is the truth (0); the thorax's node stops at 4 s: it is stale
    once its last sample is older than ``STALE_S`` (three of its intervals are
    more), not before."""
    import numpy as np

    from bodynet.clients.mcap_store import read_poses
    from bodynet.gateway.solver import STALE_S

    rng = np.random.default_rng(5)
    rows = [(0.01 * k + rng.uniform(-0.01, 0.01), "pelvis") for k in range(1, 600)]
    rows += [(0.33 * k, "thorax") for k in range(13)]  # the last at 3.96 s
    rows += [(0.005 * k + rng.uniform(-0.01, 0.01), "head") for k in range(2, 1200)]
    segments = ["pelvis", "thorax", "head"]
    lines = ["time," + ",".join(f"{g}_{c}" for g in segments for c in "wxyz")]
    at: dict[float, set[str]] = {}
    for t, seg in rows:
        at.setdefault(t, set()).add(seg)
    for t, segs in sorted(at.items()):
        lines.append(f"{t!r}," + ",".join("1,0,0,0" if g in segs else ",,," for g in segments))
    path = tmp_path / "trial.csv"
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "trial.mcap"
    result = run("process", path, "--tpose-s", "0", "-o", out)
    assert result.returncode == 0, result.stderr
    poses = list(read_poses(out))
    assert len(poses) > 500
    thorax_last = 0.33 * 12
    for t_ns, frame in poses:
        t = t_ns / 1e9
        if t > thorax_last + STALE_S + 1e-6:
            assert frame.stale == ["body/trunk/mid/chest/raw"], t
            continue
        assert frame.stale == [], t
        if t < 0.02:
            continue  # the trackers have not sent yet
        for name in ("lumbar_flexion_deg", "lumbar_lateral_deg", "neck_flexion_deg"):
            assert name not in frame.flags, (t, name, frame.reasons.get(name))
            assert frame.angles_deg[name] == pytest.approx(0.0, abs=1e-6), (t, name)


@pytest.mark.parametrize(("name", "times"), [
    ("128 Hz", [k / 128 for k in range(256)]),
    ("100 Hz, +-4 ms jitter", [0.01 * k + 0.004 * (-1) ** k for k in range(200)]),
])  # fmt: skip
def test_every_row_of_a_fast_or_jittery_file_is_a_pose(
    name: str, times: list[float], tmp_path: Path
) -> None:
    """Ticks of 1/100 s: a file sampled faster, or whose times jitter across a
    tick's edge, keeps a pose per row (a tick ends where a sensor samples again)."""
    from bodynet.clients.mcap_store import read_poses

    path = tmp_path / "trial.csv"
    lines = ["time,pelvis_w,pelvis_x,pelvis_y,pelvis_z,thorax_w,thorax_x,thorax_y,thorax_z"]
    lines += [f"{t + 0.004!r},1,0,0,0,1,0,0,0" for t in times]
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "trial.mcap"
    result = run("process", path, "--tpose-s", "0", "-o", out)
    assert result.returncode == 0, result.stderr
    poses = [t for t, _ in read_poses(out)]
    assert len(poses) == len(times), name
    assert [t / 1e9 for t in poses] == pytest.approx([t + 0.004 for t in times])


def test_a_shared_heading_that_later_breaks_is_not_kept_by_process(tmp_path: Path) -> None:
    """`auto` meeting 6-axis tags whose legs happen to share one reference (their
    own, not the arms'): a walk with the arms still confirms the knees' heading
    (the knees and ankles agree with it; no arm joint has tilted), and the arms'
    reaches later break it. ``bodynet process`` has the whole capture: it does
    not keep the shared heading for the ticks before the break (it switches to
    each tag's own heading in its first pass), so no dof is ever shown measured
    far from the truth; the legs' tags' headings are then found from the walk."""
    from dataclasses import replace

    import numpy as np

    from bodynet.cli.main import main
    from bodynet.clients.mcap_store import read_poses
    from bodynet.core.profile import mount
    from bodynet.core.skeleton import CALIBRATION_POSES
    from bodynet.nodes.emulator import Headings
    from bodynet.nodes.motion import reach

    still, walk = dict(CALIBRATION_POSES["npose"]), ROUTINES["walk"].angles
    left, right = reach("left"), reach("right")

    def angles(t: float) -> dict[str, float]:
        if t < 1.0:
            return still
        legs = {k: v for k, v in walk(t).items() if k.split("_")[1] in ("hip", "knee", "ankle")}
        if t < 6.0:
            return {**still, **legs}
        return {**still, **walk(t), **left(t - 6.0), **right(t - 6.0)}

    tags = imu_tags()
    body = BodyEmulator(Routine("legs, then arms", "", angles), tags,
                        realism=replace(Realism.ideal(), headings=Headings.INDEPENDENT),
                        seed=2)  # fmt: skip
    bank = body._quat
    heads = np.array(bank.headings_deg, dtype=float)
    legs = [j for j, i in enumerate(body._quat_idx) if "/leg/" in body.sensors[i].site.raw_key]
    heads[legs] = heads[legs[0]]  # the legs' tags share a reference, the others' their own
    bank.headings_deg = heads
    header = ["time"] + [f"{mount(t.site).segment}_{c}" for t in tags for c in "wxyz"]
    lines, truths = [",".join(header)], []
    for k in range(700):
        readings, _ = body.sample(k / 50)
        truths.append(angles(k / 50))
        lines.append(",".join([repr(k / 50)] + [repr(c) for r in readings
                                                for c in r.wxyz]))  # type: ignore[union-attr]  # fmt: skip
    capture = tmp_path / "trial.csv"
    capture.write_text("\n".join(lines) + "\n")
    out = tmp_path / "trial.mcap"
    assert main(["process", str(capture), "--tpose-s", "0.9", "--pose", "npose",
                 "-o", str(out)]) == 0  # fmt: skip
    worst = (0.0, "", 0.0)
    for k, (_, frame) in enumerate(read_poses(out)):
        for name, value in frame.angles_deg.items():
            if name not in frame.flags or frame.flags[name] == "clamped":
                worst = max(worst, (abs(value - truths[k].get(name, 0.0)), name, k / 50))
    assert worst[0] < 5.0, worst


@pytest.mark.parametrize(("jitter_s", "drop", "bound"), [(0.002, 0.0, 0.01), (0.02, 0.1, 0.01)])
def test_tags_on_timers_of_their_own_give_joints_of_one_time(
    tmp_path: Path, jitter_s: float, drop: float, bound: float
) -> None:
    """Fifteen tags at 50 Hz, each on its own timer (own phase, clock off by up to
    100 ppm, each send late by up to ``jitter_s``, ``drop`` of them lost after the
    calibration pose), a walk, in a CSV whose rows hold each only the tags that
    sampled then: the knees and ankles, whose shanks turn at 350 deg/s, are
    within twice their stated uncertainty but for a small share (``bound``).
    Each joint's two tags' samples are up to a period apart: taken as they are
    (the newest sample's time for all), 6-8 % of these values were off by more
    (12 % with 20 ms of jitter and losses); brought to one time, 0-0.04 % (1.4-2 %,
    0.14 % once a tag's turn too small for its noise to tell states what it may
    have moved since: a sample 35 ms old, 5 ms after the one before it)."""
    walk = ROUTINES["walk"].angles
    motion = Routine("walk", "", lambda t: dict(TPOSE) if t < 3.0 else walk(t - 3.0))
    tags = imu_tags()
    body = BodyEmulator(motion, tags, realism=Realism(), seed=2)
    timing = LinkTiming(Timers.INDEPENDENT, jitter_s=jitter_s, seed=5)
    sends = Sends(link_schedule(len(tags), 0.02, timing), 0.0, jitter_s, timing.draws(), 10.0)
    lost = np.random.default_rng(6)
    due: dict[int, set[int]] = {}  # ms -> the tags sampled then
    while sends:
        t, tag, _ = sends.pop()
        if not (t > 3.0 and lost.random() < drop):
            due.setdefault(round(t * 1000), set()).add(tag)
    columns = [mount(tag.site).segment for tag in tags]
    capture = tmp_path / "walk.csv"
    with capture.open("w") as f:
        f.write(",".join(["time", *(f"{c}_{q}" for c in columns for q in "wxyz")]) + "\n")
        for ms, sampled in sorted(due.items()):
            readings, _ = body.sample(ms / 1000)
            cells = [",".join(f"{v:.9f}" for v in r.wxyz) if k in sampled else ",,,"  # type: ignore[union-attr]
                     for k, r in enumerate(readings)]  # fmt: skip
            f.write(f"{ms / 1000:.3f},{','.join(cells)}\n")
    out = tmp_path / "walk.mcap"
    result = run("process", capture, "--format", "orientation-csv", "-o", out, "--heading", "fixed")
    assert result.returncode == 0, result.stderr
    off, measured = 0, 0
    for t_ns, frame in read_poses(out):
        if t_ns < 4.5e9:  # the calibration pose, and the walk's first step from it
            continue
        truth = motion.angles(t_ns / 1e9)
        for side in ("left", "right"):
            for dof in (f"{side}_knee_flexion_deg", f"{side}_ankle_flexion_deg"):
                if is_measured(frame, dof):
                    measured += 1
                    off += abs(frame.angles_deg[dof] - truth[dof]) > 2 * frame.unc_deg[dof]
    assert measured > 1500  # ~5.5 s of ticks at up to 100 Hz, four dofs: nothing flagged away
    assert off / measured < bound, (off, measured)
