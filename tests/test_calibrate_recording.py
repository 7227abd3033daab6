"""`bodynet calibrate tpose --from REC --window A:B`: calibration from a recording.

A real MCAP recording (the recorder's raw-sample messages, written by the
project's sink and read back by mcap's reader) of emulated tags: the subject
stands still in the pose for 2 s, then bends a knee.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bodynet.cli.main import main
from bodynet.clients.mcap_store import McapSink
from bodynet.core.messages import RawSample, Source
from bodynet.core.skeleton import CALIBRATION_POSES
from bodynet.core.subject import Profile
from bodynet.gateway.heading import BodyHeading
from bodynet.gateway.solver import BodySolver
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
from bodynet.nodes.motion import Routine, keyframes
from bodynet.session import profile_file

T0_NS = 1_700_000_000_000_000_000


def _record(path: Path, pose: str, facing: float) -> BodyEmulator:
    held = dict(CALIBRATION_POSES[pose])
    bend = {"left_knee_flexion_deg": 70.0, "left_hip_flexion_deg": 20.0}
    motion = Routine("still-then-knee", "", keyframes(
        [(0.0, held), (2.0, held), (3.0, {**held, **bend}), (3.5, held)], loop=False))  # fmt: skip
    body = BodyEmulator(motion, imu_tags(), realism=Realism(facing_deg=facing), seed=3)
    record_tags(path, body, 3.5)
    return body


def record_tags(path: Path, body: BodyEmulator, seconds: float) -> None:
    """A recording of ``body``'s tags at 50 Hz for ``seconds``, as the recorder
    writes the IMU central's raw samples, from ``T0_NS``."""
    sink = McapSink(path)
    try:
        for k, t in enumerate(np.arange(0.0, seconds, 1 / 50)):
            readings, _ = body.sample(float(t))
            t_ns = T0_NS + round(float(t) * 1e9)
            for sensor, reading in zip(body.sensors, readings, strict=True):
                sink.write_raw(sensor.site.raw_key, RawSample(reading, k, t_ns, Source.IMU_CENTRAL),
                               t_ns)  # fmt: skip
    finally:
        sink.close()


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "still.mcap"
    _record(path, "tpose", 40.0)
    return path


def test_calibration_from_a_recordings_still_window(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    profile_path = tmp_path / "subject.toml"
    assert main(["calibrate", "tpose", "--from", str(recording), "--window", "0.2:1.8",
                 "--profile", str(profile_path)]) == 0  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert report["ok"]
    assert len(report["calibrated"]) == 15
    assert report["window_s"] == pytest.approx(1.6, abs=0.05)
    assert all(t["still_deg"] < 2.0 for t in report["tags"].values())
    assert report["heading"]["state"] == "unknown"  # found once a knee moves
    profile = profile_file.load(profile_path)
    assert len(profile.imu_mounts) == 15
    assert profile.pose == "tpose"
    assert not profile.imu_headings


@pytest.mark.parametrize(("window", "why"), [("1.5:3.0", "the subject moved"),
                                             ("0:0.2", "too short")])  # fmt: skip
def test_a_bad_window_is_refused_and_the_profile_kept(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], window: str, why: str
) -> None:
    profile_path = tmp_path / "subject.toml"
    profile_file.save(Profile(subject="kept"), profile_path)
    before = profile_path.read_bytes()
    assert main(["calibrate", "tpose", "--from", str(recording), "--window", window,
                 "--profile", str(profile_path)]) == 1  # fmt: skip
    out, err = capsys.readouterr()
    assert why in err
    assert "unchanged" in err
    assert json.loads(out)["ok"] is False
    assert profile_path.read_bytes() == before


def test_bad_window_arguments_are_refused_by_the_parser(recording: Path) -> None:
    for bad in ("4:2", "x:1", "2", "-1:2", "nan:3"):
        with pytest.raises(SystemExit) as caught:
            main(["calibrate", "tpose", "--from", str(recording), "--window", bad])
        assert caught.value.code == 2


def test_n_pose_from_a_recording_then_the_heading_from_the_knee(tmp_path: Path) -> None:
    """The N-pose, remembered in the profile; the profile then finds the heading
    from the knee that bends after the pose, and the angles are the truth's."""
    path = tmp_path / "npose.mcap"
    body = _record(path, "npose", -100.0)
    profile_path = tmp_path / "subject.toml"
    assert main(["calibrate", "tpose", "--from", str(path), "--window", "0.5:1.9",
                 "--pose", "npose", "--profile", str(profile_path)]) == 0  # fmt: skip
    profile = profile_file.load(profile_path)
    assert profile.pose == "npose"
    heading = BodyHeading(profile)
    for t in np.arange(2.0, 3.0, 1 / 50):
        readings, _ = body.sample(float(t))
        samples = {s.site: RawSample(r, 0, 0) for s, r in zip(body.sensors, readings, strict=True)}
        if heading.update(float(t), samples) is not None:
            break
    assert heading.state()["deg"] == pytest.approx(-100.0, abs=1.5)
    readings, _ = body.sample(2.8)
    out = BodySolver(heading.profile).solve(
        {s.site: RawSample(r, 0, 0) for s, r in zip(body.sensors, readings, strict=True)}
    )
    truth = body.angles(2.8)
    assert not out.flags
    for name, value in out.angles_deg.items():
        assert value == pytest.approx(truth.get(name, 0.0), abs=2.0), name


def test_live_calibration_refuses_heading_options_it_cannot_apply(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The live gateway solves with its own profile: `--drift` or `--heading`
    without `--from` is refused with the reason (exit 2), never ignored."""
    assert main(["calibrate", "tpose", "--drift", "joints", "--heading", "fixed"]) == 2
    err = capsys.readouterr().err
    assert "--heading, --drift go with --from" in err
    assert "Traceback" not in err


def test_a_recording_that_is_no_mcap_is_one_line_naming_it(
    recording: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An empty, cut or foreign file given as the recording: the store's reason
    on one line (exit 2), no profile written."""
    empty, cut, foreign = tmp_path / "empty.mcap", tmp_path / "cut.mcap", tmp_path / "x.mcap"
    empty.write_bytes(b"")
    cut.write_bytes(recording.read_bytes()[:2000])
    foreign.write_bytes(bytes(range(256)) * 8)
    profile_path = tmp_path / "subject.toml"
    for path, why in ((empty, "not a complete MCAP file"), (cut, "not a complete MCAP file"),
                      (foreign, "not an MCAP recording")):  # fmt: skip
        assert main(["calibrate", "tpose", "--from", str(path), "--profile",
                     str(profile_path)]) == 2  # fmt: skip
        err = capsys.readouterr().err
        assert err.startswith(f"bodynet calibrate tpose: {path}: {why}"), err
        assert err.count("\n") == 1, err
        assert not profile_path.exists()


def test_a_capture_recording_takes_its_format_from_its_suffix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--from still.sto` needs no `--format` (as `process still.sto` does not); a
    suffix that names no format is one line saying so, no profile written."""
    from bodynet.core.messages import Quat
    from bodynet.core.opensim import imu_label
    from bodynet.core.profile import mount

    tags = imu_tags()
    body = BodyEmulator(Routine("still", "", lambda t: dict(CALIBRATION_POSES["tpose"])), tags,
                        realism=Realism(facing_deg=30.0), seed=4)  # fmt: skip
    lines = ["DataType=Quaternion", "endheader",
             "\t".join(["time"] + [imu_label(mount(t.site).segment) for t in tags])]  # fmt: skip
    for k in range(60):
        quats = {r.node: r.wxyz for r in body.sample(0.02 * k)[0] if isinstance(r, Quat)}
        lines.append("\t".join([f"{0.02 * k:.2f}"]
                               + [",".join(map(repr, quats[t.node])) for t in tags]))  # fmt: skip
    sto = tmp_path / "still.sto"
    sto.write_text("\n".join(lines) + "\n")
    profile_path = tmp_path / "subject.toml"
    assert main(["calibrate", "tpose", "--from", str(sto), "--window", "0:1",
                 "--profile", str(profile_path)]) == 0, capsys.readouterr().err  # fmt: skip
    assert len(profile_file.load(profile_path).imu_mounts) == len(tags)
    capsys.readouterr()
    unknown, profile_path = tmp_path / "still.quat", tmp_path / "other.toml"
    unknown.write_bytes(sto.read_bytes())
    assert main(["calibrate", "tpose", "--from", str(unknown), "--profile",
                 str(profile_path)]) == 2  # fmt: skip
    err = capsys.readouterr().err
    # a .sto by its content: which --format reads it is said
    assert err == (f"bodynet calibrate tpose: {unknown}: say which --format the recording is "
                   "in (its suffix '.quat' names none; it looks like an OpenSense orientation "
                   "file (--format sto, named .sto))\n")  # fmt: skip
    assert not profile_path.exists()


def test_process_takes_its_calibration_from_a_recording_by_its_suffix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`process trial.csv --calibration still.mcap`: the MCAP is read as the
    recording it is (not as a CSV, the trial's format): its still window
    calibrates the trial, whose knee then bends as the truth's."""
    from bodynet.clients.mcap_store import read_poses

    still = tmp_path / "still.mcap"
    body = _record(still, "tpose", 0.0)
    trial = _trial_csv(body, tmp_path / "trial.csv")
    out = tmp_path / "trial.mcap"
    assert main(["process", str(trial), "--calibration", str(still), "--window", "0.2:1.8",
                 "--heading", "fixed", "-o", str(out)]) == 0, capsys.readouterr().err  # fmt: skip
    knee = [(t_ns / 1e9, frame.angles_deg["left_knee_flexion_deg"]) for t_ns, frame
            in read_poses(out)]  # fmt: skip
    assert max(angle for _, angle in knee) > 60.0
    for t, angle in knee:
        assert angle == pytest.approx(body.angles(t)["left_knee_flexion_deg"], abs=3.0), t


def test_a_recalibration_drops_the_last_calibrations_headings_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A heading is a tag's reference frame's turn from where the subject faced in
    the calibration's pose: a session's headings, found from the knee (the subject
    facing -100 deg), saved in the profile; the subject calibrates again facing 40
    deg. The new calibration drops them, and says so (the report's
    ``heading.dropped``, a line on stderr, `bodynet process`'s too); kept, the
    knee's bend would be shown tens of degrees off the truth. Found again from
    the knee: the truth."""
    from bodynet.gateway.heading import with_headings

    first, again = tmp_path / "first.mcap", tmp_path / "again.mcap"
    before = _record(first, "npose", -100.0)
    body = _record(again, "npose", 40.0)
    profile_path = tmp_path / "subject.toml"
    args = ["calibrate", "tpose", "--window", "0.5:1.9", "--pose", "npose",
            "--profile", str(profile_path)]  # fmt: skip
    assert main([*args, "--from", str(first)]) == 0
    found = _found(before, BodyHeading(profile_file.load(profile_path)))
    assert found.state()["deg"] == pytest.approx(-100.0, abs=1.5)
    old = dict(found.profile.imu_headings)
    assert len(old) == 15
    profile_file.save(found.profile, profile_path)
    capsys.readouterr()
    assert main(["process", str(_trial_csv(body, tmp_path / "trial.csv")), "--calibration",
                 str(again), "--window", "0.5:1.9", "--pose", "npose", "--profile",
                 str(profile_path), "-o", str(tmp_path / "trial.mcap")]) == 0  # fmt: skip
    assert "headings of 15 tag(s) in the profile" in capsys.readouterr().err
    assert main([*args, "--from", str(again)]) == 0
    out, err = capsys.readouterr()
    assert sorted(json.loads(out)["heading"]["dropped"]) == sorted(old)
    assert "headings of 15 tag(s) in the profile" in err
    assert "dropped" in err
    recalibrated = profile_file.load(profile_path)
    assert not recalibrated.imu_headings
    readings, _ = body.sample(2.8)
    samples = {s.site: RawSample(r, 0, 0) for s, r in zip(body.sensors, readings, strict=True)}
    truth = body.angles(2.8)
    kept = BodySolver(with_headings(recalibrated, old)).solve(samples)
    assert max(abs(v - truth.get(n, 0.0)) for n, v in kept.angles_deg.items()) > 20.0
    heading = _found(body, BodyHeading(recalibrated))
    out_found = BodySolver(heading.profile).solve(samples)
    assert not out_found.flags
    for name, value in out_found.angles_deg.items():
        assert value == pytest.approx(truth.get(name, 0.0), abs=2.0), name


def _found(body: BodyEmulator, heading: BodyHeading) -> BodyHeading:
    """``heading`` after the knee's bend (the recording's 2 to 3.5 s)."""
    for t in np.arange(2.0, 3.5, 1 / 50):
        readings, _ = body.sample(float(t))
        samples = {s.site: RawSample(r, 0, 0) for s, r in zip(body.sensors, readings, strict=True)}
        if heading.update(float(t), samples) is not None:
            break
    return heading


def _trial_csv(body: BodyEmulator, path: Path) -> Path:
    """The tags' orientations from 2 to 3.5 s (the knee's bend) as an orientation CSV."""
    from bodynet.core.messages import Quat
    from bodynet.core.profile import mount

    header = ["time"] + [f"{mount(s.site).segment}_{c}" for s in body.sensors for c in "wxyz"]
    rows = [header]
    for t in np.arange(2.0, 3.5, 1 / 50):
        quats = {r.node: r.wxyz for r in body.sample(float(t))[0] if isinstance(r, Quat)}
        rows.append([repr(float(t))] + [repr(c) for s in body.sensors for c in quats[s.node]])
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")
    return path
