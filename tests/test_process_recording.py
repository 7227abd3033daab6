"""`bodynet process session.mcap`: a recording's raw samples solved again.

Recordings are real MCAP files (written by the project's sink, read back by
mcap's reader); the captures they come from are the emulators' own, read by
the same `process` a user runs.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from bodynet.cli.main import main
from bodynet.clients.mcap_store import McapSink, read_poses, read_raw
from bodynet.core.codecs import imu_matrix
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import RESUMED, Quat, RawSample, Source
from bodynet.core.skeleton import CALIBRATION_POSES, TPOSE
from bodynet.gateway.solver import UNC_OLE_DEG
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags, smartsuit_sensors
from bodynet.nodes.motion import ROUTINES, Routine, keyframes
from bodynet.offline.process import process
from tests.test_calibrate_recording import T0_NS, record_tags
from tests.test_encoder_reboot import candump_line


def _poses(path: Path) -> list[tuple[int, dict[str, float], dict[str, str]]]:
    return [(t_ns, dict(f.angles_deg), dict(f.flags)) for t_ns, f in read_poses(path)]


def _same_poses(a: Path, b: Path) -> None:
    first, again = _poses(a), _poses(b)
    assert [t for t, _, _ in again] == [t for t, _, _ in first]
    for (t, angles, flags), (_, angles2, flags2) in zip(first, again, strict=True):
        assert flags2 == flags, t
        assert angles2.keys() == angles.keys()
        for name, value in angles.items():
            assert angles2[name] == pytest.approx(value, abs=1e-9, nan_ok=True), (t, name)


def test_a_processed_capture_processed_again_from_its_recording_gives_the_same_poses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The IMU central's data matrix (T-pose, then the upper-body routine) into
    a recording; that recording's raw samples solved again: the same ticks, the
    same angles and flags, each raw sample kept with its source."""
    upper = ROUTINES["upper-body"].angles
    motion = Routine("capture", "", lambda t: dict(TPOSE) if t < 3.0 else upper(t - 3.0))
    body = BodyEmulator(motion, imu_tags(), realism=Realism(random_tag_mounts=True), seed=4)
    capture = tmp_path / "session.txt"
    with capture.open("wb") as f:
        for tick in range(25 * 8):
            readings, _ = body.sample(tick / 25)
            f.write(b"".join(imu_matrix.encode_line(r) for r in readings if isinstance(r, Quat)))
    first, again = tmp_path / "first.mcap", tmp_path / "again.mcap"
    assert main(["process", str(capture), "--format", "imu-central", "-o", str(first),
                 "--heading", "fixed"]) == 0, capsys.readouterr().err  # fmt: skip
    capsys.readouterr()
    assert main(["process", str(first), "-o", str(again), "--heading", "fixed"]) == 0
    err = capsys.readouterr().err
    assert "calibrated 15 sensors (tpose)" in err
    _same_poses(first, again)
    sources = {s.source for _, _, s in read_raw(again)}
    assert sources == {Source.IMU_CENTRAL}
    assert sum(1 for _ in read_raw(again)) == sum(1 for _ in read_raw(first))


def test_a_recording_is_calibrated_again_from_a_window_of_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A live session's recording whose subject moved in its first seconds: solved
    as it is, the tags stay uncalibrated (the default window is refused, said);
    a ``--tpose-s`` asked over the motion is refused, nothing written, as a
    ``--window`` would be; with ``--window`` on the still T-pose later in it, the
    knee bends as the truth's."""
    held = dict(CALIBRATION_POSES["tpose"])
    bend = {"left_knee_flexion_deg": 70.0, "left_hip_flexion_deg": 20.0}
    wave = {"left_shoulder_flexion_deg": 40.0, "right_elbow_flexion_deg": 60.0}
    motion = Routine("move-still-knee", "", keyframes(
        [(0.0, {**held, **wave}), (0.8, held), (1.0, held), (3.0, held),
         (4.0, {**held, **bend}), (4.5, held)], loop=False))  # fmt: skip
    body = BodyEmulator(motion, imu_tags(), realism=Realism(facing_deg=40.0), seed=3)
    session = tmp_path / "session.mcap"
    record_tags(session, body, 4.5)
    as_recorded, again = tmp_path / "as-recorded.mcap", tmp_path / "again.mcap"
    assert main(["process", str(session), "-o", str(as_recorded)]) == 0
    assert "NOT calibrated: the subject moved" in capsys.readouterr().err
    asked = tmp_path / "asked.mcap"
    assert main(["process", str(session), "--tpose-s", "0.8", "-o", str(asked)]) == 1
    err = capsys.readouterr().err
    assert "calibration refused: the subject moved" in err, err
    assert "nothing written" in err
    assert not asked.exists()
    assert all(f["left_knee_flexion_deg"] == "uncalibrated" for _, _, f in _poses(as_recorded))
    assert main(["process", str(session), "--window", "1.2:2.8", "-o", str(again)]) == 0
    err = capsys.readouterr().err
    assert "calibrated 15 sensors (tpose)" in err, err
    assert "heading found" in err, err
    knee = [(t_ns, a["left_knee_flexion_deg"]) for t_ns, a, f in _poses(again)
            if "left_knee_flexion_deg" not in f]  # fmt: skip
    assert max(angle for _, angle in knee) > 60.0
    for t_ns, angle in knee:
        truth = body.angles((t_ns - T0_NS) / 1e9)["left_knee_flexion_deg"]
        assert angle == pytest.approx(truth, abs=3.0), t_ns


def test_a_recordings_reboot_flags_are_the_bridges_verdict(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A SmartSuit arm's CAN log with the whole suit switched off and on: its
    recording keeps each node's ``RESUMED`` sample, and solved again from it every
    encoder dof after the swap is flagged as the first solve flagged it (the
    recording's times alone would not say: its samples are read as recorded)."""
    elbow = "left_elbow_flexion_deg"
    angles = {elbow: 0.0}
    body = BodyEmulator(Routine("held", "", lambda t: dict(angles)), smartsuit_sensors([LEFT_ARM]),
                        realism=Realism.ideal())  # fmt: skip
    log = tmp_path / "arm.log"
    with log.open("w") as f:
        for tick in range(400):
            t = tick * 0.01
            angles[elbow] = 60.0 if tick >= 80 else 0.0
            if 100 <= tick < 250:
                continue  # the suit off
            if tick == 250:
                for node in body.module_nodes:
                    body.power_on(node, t)
            f.writelines(candump_line(t, r) for r in body.sample(t)[0])
    first, again = tmp_path / "first.mcap", tmp_path / "again.mcap"
    assert main(["process", str(log), "--tpose-s", "0", "-o", str(first)]) == 0
    assert main(["process", str(first), "--tpose-s", "0", "-o", str(again)]) == 0, (
        capsys.readouterr().err
    )
    flagged = [f.get(elbow) for t_ns, _, f in _poses(again) if t_ns >= (1000 + 2.5) * 1e9]
    assert flagged
    assert set(flagged) == {"uncalibrated"}
    resumed = sorted(s.reading.node for _, _, s in read_raw(again) if s.flags & RESUMED)
    assert resumed == sorted(body.module_nodes)
    _same_poses(first, again)


def test_a_recording_of_several_subjects_and_one_that_is_not_mcap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Raw samples on another subject's keys (``alice/body/...``, a recorder
    without a namespace) are counted and left out; a file named .mcap that is
    not one is refused in a line, nothing written."""
    body = BodyEmulator(Routine("still", "", lambda t: dict(TPOSE)), imu_tags(),
                        realism=Realism.ideal(), seed=1)  # fmt: skip
    mixed = tmp_path / "mixed.mcap"
    sink = McapSink(mixed)
    try:
        for k in range(100):
            t_ns = T0_NS + k * 20_000_000
            for sensor, reading in zip(body.sensors, body.sample(k / 50)[0], strict=True):
                sample = RawSample(reading, k, t_ns, Source.IMU_CENTRAL)
                sink.write_raw(sensor.site.raw_key, sample, t_ns)
                sink.write_raw(f"alice/{sensor.site.raw_key}", sample, t_ns)
    finally:
        sink.close()
    out = tmp_path / "out.mcap"
    assert main(["process", str(mixed), "--heading", "fixed", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "unknown_node: 1500" in err, err
    assert len(_poses(out)) == 100
    assert not math.isnan(_poses(out)[-1][1]["left_knee_flexion_deg"])
    broken = tmp_path / "broken.mcap"
    broken.write_text("time,a,b\n0,1,2\n")
    assert main(["process", str(broken), "-o", str(tmp_path / "b-out.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bodynet process: "), err
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "b-out.mcap").exists()


def test_a_smartsuit_elbow_on_its_own_timer_states_its_samples_age(tmp_path: Path) -> None:
    """The SmartSuit left arm's modules instead of the arm's tags, every sensor on
    its own timer at 50 Hz (the truth benchmark's session, recorded and processed):
    the encoder's sample is up to a period older than the pose, and the elbow
    reaching at up to 95 deg/s turns 2 deg meanwhile. Brought to the pose's time
    with what that leaves stated, its flexion is within twice its ``unc_deg`` of
    the truth in nearly every tick of the reach (taken as sampled, with 0.5 deg:
    a quarter beyond it); still, after the reach, its uncertainty is the encoder's
    own (nothing moved, nothing added)."""
    from bodynet.bench import truth

    sc = truth.Scenario("instead-reach", motion="reach", hybrid="instead", seconds=9.0)
    angles = truth.motion(sc.motion, sc.pose)
    body = BodyEmulator(Routine(sc.name, "", angles), truth.sensors_of(sc),
                        realism=Realism(quat_noise_deg=sc.noise), seed=sc.seed)  # fmt: skip
    recording, poses = tmp_path / "reach.mcap", tmp_path / "poses.mcap"
    truth.record(sc, body, recording)
    process(recording, "mcap", poses, truth.profile_of(sc, body, recording), tpose_s=truth.HOLD_S,
            pose=sc.pose)  # fmt: skip
    dof = "left_elbow_flexion_deg"
    moving, beyond, still = 0, 0, []
    for t_ns, frame in read_poses(poses):
        t = t_ns / 1e9
        if t < truth.HOLD_S or dof in frame.flags:
            continue
        error = abs(frame.angles_deg[dof] - angles(t).get(dof, 0.0))
        if 4.5 < t < 7.5:  # the reach: the elbow bends to 90 deg and back
            moving += 1
            beyond += error > 2 * frame.unc_deg[dof]
        elif t > 7.6:  # the elbow still (the shoulder and wrist go on)
            still.append(frame.unc_deg[dof])
    assert moving > 250  # ~3 s of ticks, and 1.4 s still: nothing flagged away
    assert len(still) > 100
    assert beyond / moving < 0.005, (beyond, moving)
    assert set(still) == {UNC_OLE_DEG}
