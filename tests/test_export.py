"""`bodynet export bvh|c3d` and the Foxglove transforms of recordings, read back
by independent readers (bvhio, ezc3d, mcap + Foxglove's protobuf classes) and compared with the
recording's own poses."""

from __future__ import annotations

import fcntl
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
import time
import warnings
from pathlib import Path

import ezc3d
import numpy as np
import pytest
from export_recordings import tf_message
from mcap.reader import make_reader
from mcap.writer import Writer
from pyglm import glm
from scipy.spatial.transform import Rotation

from bodynet.cli.main import main
from bodynet.clients.mcap_store import McapSink, count_messages, read_poses, read_raw
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.keys import BRANCHES
from bodynet.core.skeleton import build_skeleton
from bodynet.gateway.frames import branch_views

with warnings.catch_warnings():
    warnings.simplefilter("ignore", PendingDeprecationWarning)  # bvhio imports glm the old way
    import bvhio

BODYNET = Path(sys.executable).with_name("bodynet")
# bodynet (+X forward, +Y left, +Z up) -> the BVH file's axes
TO_Y_UP = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def run(*args: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BODYNET), *map(str, args)], capture_output=True, text=True,
                          timeout=120, check=False)  # fmt: skip


def poses(path: Path) -> list[pose.PoseFrame]:
    return [frame for _, frame in read_poses(path)]


def segment_rotation(frame: pose.PoseFrame, segment: str) -> Rotation:
    return Rotation.from_quat(frame.segments[segment][1], scalar_first=True)


def joint_centres(frame: pose.PoseFrame) -> dict[str, np.ndarray]:
    """Where each BVH joint (a segment) sits: the recording's joint centres, and
    the pelvis (the root) at its segment origin."""
    skeleton = build_skeleton()
    out = {j.child: np.array(frame.joints_m[j.name]) for j in skeleton.joints}
    out["pelvis"] = np.array(frame.segments["pelvis"][0])
    return out


def check_bvh_against_poses(
    bvh: Path, frames: list[pose.PoseFrame], m: np.ndarray, scale: float
) -> None:
    """bvhio's forward kinematics of every frame against the recording: each
    segment whose chain from the pelvis the pose measures (BVH holds the last
    measured value of a held or uncalibrated angle, the pose its own: issue 22)."""
    root = bvhio.readAsHierarchy(str(bvh))
    joints = [j for j, _, _ in root.layout()]
    assert {j.Name for j in joints} == set(build_skeleton().segments)
    chains = build_skeleton().segment_chains()
    root.loadRestPose()
    # rest pose = bodynet's zero pose, where every segment frame is the world's
    rest = {j.Name: glm.quat(j.RotationWorld) for j in joints}
    to_file = Rotation.from_matrix(m)
    worst_m, worst_deg, compared = 0.0, 0.0, 0
    for index, frame in enumerate(frames):
        held = {a for a, f in frame.flags.items() if f in ("held", "uncalibrated")}
        measured = [j for j in joints if held.isdisjoint(chains[j.Name])]
        if len(measured) < len(joints) // 2:
            continue
        compared += 1
        root.loadPose(index)
        centres = joint_centres(frame)
        for j in measured:
            got_p = np.array(j.PositionWorld) / scale
            worst_m = max(worst_m, float(np.abs(got_p - m @ centres[j.Name]).max()))
            q = j.RotationWorld * glm.inverse(rest[j.Name])
            got = Rotation.from_quat([q.x, q.y, q.z, q.w])
            want = to_file * segment_rotation(frame, j.Name) * to_file.inv()
            worst_deg = max(worst_deg, float(np.degrees((got * want.inv()).magnitude())))
    assert compared >= 10, compared  # the check bites
    assert worst_m < 2e-5, worst_m  # metres: the pose messages carry 1 µm
    assert worst_deg < 0.01, worst_deg


def bvh_channels(bvh: Path) -> tuple[dict[str, list[str]], np.ndarray, float]:
    """Channel names per joint, the motion table and the frame time, read as
    text (the layout every BVH reader expects)."""
    text = bvh.read_text().split("MOTION\n", 1)
    channels: dict[str, list[str]] = {}
    name = ""
    for line in text[0].splitlines():
        words = line.split()
        if words[:1] in (["ROOT"], ["JOINT"]):
            name = words[1]
        elif words[:1] == ["CHANNELS"]:
            channels[name] = words[2:]
    lines = text[1].splitlines()
    assert lines[0].startswith("Frames:")
    frame_time = float(lines[1].split(":")[1])
    return channels, np.loadtxt(lines[2:], ndmin=2), frame_time


@pytest.mark.parametrize(("up", "units"), [("y", "m"), ("z", "cm")])
def test_bvh_read_by_bvhio_matches_the_poses(
    body_mcap: Path, tmp_path: Path, up: str, units: str
) -> None:
    out = tmp_path / "session.bvh"
    result = run("export", "bvh", body_mcap, "-o", out, "--up", up, "--units", units)
    assert result.returncode == 0, result.stderr
    frames = poses(body_mcap)
    assert len(frames) == 25 * 7
    m = TO_Y_UP if up == "y" else np.eye(3)
    check_bvh_against_poses(out, frames, m, 1.0 if units == "m" else 100.0)
    channels, motion, frame_time = bvh_channels(out)
    assert frame_time == pytest.approx(0.04)
    assert motion.shape == (len(frames), 6 + 3 * (len(channels) - 1))
    assert channels["pelvis"][:3] == ["Xposition", "Yposition", "Zposition"]


def test_bvh_channels_read_as_joint_angles(body_mcap: Path, tmp_path: Path) -> None:
    """Each joint's channels come in the order of its dofs, so the first one of
    the forearm is the elbow's flexion (about -X of a Y-up file) and the
    thigh's the hip's flexion."""
    out = tmp_path / "s.bvh"
    assert run("export", "bvh", body_mcap, "-o", out, "-q").returncode == 0
    channels, motion, _ = bvh_channels(out)
    assert channels["left_forearm"] == ["Xrotation", "Yrotation", "Zrotation"]
    column = 0
    for name, names in channels.items():
        if name == "left_forearm":
            break
        column += len(names)
    flexion = np.array([f.angles_deg["left_elbow_flexion_deg"] for f in poses(body_mcap)])
    assert np.ptp(flexion) > 20  # the elbow did move
    np.testing.assert_allclose(motion[:, column], -flexion, atol=0.01)


def test_bvh_at_another_rate(arm_mcap: Path, tmp_path: Path) -> None:
    """A 100 Hz recording exported at 50 Hz: every other pose, by bvhio."""
    out = tmp_path / "arm.bvh"
    result = run("export", "bvh", arm_mcap, "-o", out, "--rate-hz", 50)
    assert result.returncode == 0, result.stderr
    assert "at 50 Hz" in result.stderr
    frames = poses(arm_mcap)
    every_other = frames[::2]
    _, motion, frame_time = bvh_channels(out)
    assert frame_time == pytest.approx(0.02)
    assert len(motion) == len(every_other)
    check_bvh_against_poses(out, every_other, TO_Y_UP, 1.0)
    assert out.stat().st_mode & 0o077 == 0  # health data: the owner's only


def test_c3d_read_by_ezc3d_matches_the_poses(body_mcap: Path, tmp_path: Path) -> None:
    out = tmp_path / "session.c3d"
    result = run("export", "c3d", body_mcap, "-o", out)
    assert result.returncode == 0, result.stderr
    c3d = ezc3d.c3d(str(out))
    point = c3d["parameters"]["POINT"]
    labels = list(point["LABELS"]["value"])
    skeleton = build_skeleton()
    joints = [j.name for j in skeleton.joints]
    assert labels == [*joints, "pelvis", *(f"{j}_angles" for j in joints)]
    assert point["UNITS"]["value"] == ["mm"]
    assert float(point["RATE"]["value"][0]) == pytest.approx(25.0)
    assert list(point["ANGLES"]["value"]) == [f"{j}_angles" for j in joints]
    assert point["ANGLE_UNITS"]["value"] == ["deg"]
    frames = poses(body_mcap)
    data = c3d["data"]["points"]
    assert data.shape == (4, len(labels), len(frames))
    for f, frame in enumerate(frames):
        for j in joints:
            got = data[:3, labels.index(j), f]
            np.testing.assert_allclose(got, np.array(frame.joints_m[j]) * 1000, atol=1e-3)
        pelvis = data[:3, labels.index("pelvis"), f]
        np.testing.assert_allclose(pelvis, np.array(frame.segments["pelvis"][0]) * 1000, atol=1e-3)
        for joint in skeleton.joints:
            got = data[:3, labels.index(f"{joint.name}_angles"), f]
            want = [frame.angles_deg[n] for n in joint.angle_names()]
            want += [0.0] * (3 - len(want))
            np.testing.assert_allclose(got, want, atol=1e-3)
    description = point["DESCRIPTIONS"]["value"][labels.index("left_shoulder_angles")]
    assert "x flexion, y abduction, z rotation" in description


def test_c3d_keeps_the_first_frame_s_absolute_time(body_mcap: Path, tmp_path: Path) -> None:
    """The first frame's time (the first pose's source time, ns since the Unix
    epoch) is ``BODYNET:START_NS``, a string exact to the nanosecond, resampled or not."""
    first_ns = next(read_poses(body_mcap))[1].t_ns
    for rate in ([], ["--rate-hz", "60"]):
        out = tmp_path / f"start{len(rate)}.c3d"
        result = run("export", "c3d", body_mcap, "-o", out, *rate)
        assert result.returncode == 0, result.stderr
        bodynet = ezc3d.c3d(str(out))["parameters"]["BODYNET"]
        assert bodynet["START_NS"]["value"] == [str(first_ns)]
        assert int(bodynet["START_NS"]["value"][0]) == first_ns


def test_recordings_carry_foxglove_transforms(body_mcap: Path) -> None:
    """`bodynet process` (McapSink) writes foxglove.FrameTransforms beside the
    poses; composing each frame's chain from `world` gives the pose's segments."""
    parents = {j.child: j.parent for j in build_skeleton().joints}
    with body_mcap.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        by_topic = {ch.topic: ch for ch in summary.channels.values()}
        tf = by_topic[keys.TRANSFORMS]
        schema = summary.schemas[tf.schema_id]
        assert (schema.name, schema.encoding, tf.message_encoding) == (
            "foxglove.FrameTransforms", "protobuf", "protobuf")  # fmt: skip
        # the raw and pose channels are as they were
        assert summary.schemas[by_topic[keys.pose_key()].schema_id].name == "bodynet.PoseFrame"
        raw_topics = [t for t in by_topic if t.endswith("/raw")]
        assert len(raw_topics) == 15
        counts = summary.statistics.channel_message_counts
        transforms = [(m.publish_time, tf_message(m.data))
                      for _, _, m in reader.iter_messages(topics=[keys.TRANSFORMS])]  # fmt: skip
    frames = list(read_poses(body_mcap))
    assert counts[tf.id] == len(frames) == len(transforms)
    assert sum(1 for _ in read_raw(body_mcap)) == sum(counts[by_topic[t].id] for t in raw_topics)
    for (log_time, frame), (tf_time, message) in zip(frames, transforms, strict=True):
        assert tf_time == log_time
        world: dict[str, tuple[np.ndarray, Rotation]] = {}
        for t in message["transforms"]:  # parents come first
            child, parent = t["child_frame_id"], t["parent_frame_id"]
            assert parent == parents.get(child, "world")
            stamp = t["timestamp"]
            assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == log_time
            local_p = np.array([t["translation"][a] for a in "xyz"])
            local_r = Rotation.from_quat([t["rotation"][a] for a in "xyzw"])
            if parent == "world":
                world[child] = (local_p, local_r)
            else:
                pp, pr = world[parent]
                world[child] = (pp + pr.apply(local_p), pr * local_r)
        assert set(world) == set(frame.segments)
        for segment, (p, r) in world.items():
            want_p, _ = frame.segments[segment]
            np.testing.assert_allclose(p, want_p, atol=1e-5)
            error = (r * segment_rotation(frame, segment).inv()).magnitude()
            assert np.degrees(error) < 1e-3, segment


def test_only_the_whole_body_pose_gives_transforms(arm_mcap: Path, tmp_path: Path) -> None:
    """Branch views (as the recorder receives them) add no transforms."""
    out = tmp_path / "sink.mcap"
    sink = McapSink(out, tf_min_gap_ns=0)  # each whole-body pose its transforms
    frames = list(read_poses(arm_mcap))[:5]
    for log_time, frame in frames:
        for branch, view in branch_views(frame, BRANCHES).items():
            sink.write_pose(keys.pose_key(branch), view, log_time)
        sink.write_pose(keys.pose_key(), frame, log_time)
    sink.close()
    with out.open("rb") as f:
        reader = make_reader(f)
        topics = [ch.topic for _, ch, _ in reader.iter_messages()]
    assert topics.count(keys.TRANSFORMS) == len(frames)
    assert topics.count(keys.pose_key()) == len(frames)


def foreign_mcap(path: Path) -> None:
    """A valid MCAP file from some other tool: no bodynet topic at all."""
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="other")
        schema = writer.register_schema("x.Temperature", "jsonschema", b"{}")
        channel = writer.register_channel("/sensors/temperature", "json", schema)
        writer.add_message(channel, 1, b'{"celsius": 21.5}', 1)
        writer.finish()


def garbage_pose_mcap(path: Path) -> None:
    """Something else than a bodynet pose on body/pose."""
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="other")
        schema = writer.register_schema("x.Pose", "jsonschema", b"{}")
        channel = writer.register_channel(keys.pose_key(), "json", schema)
        writer.add_message(channel, 1, b'{"x": 1}', 1)
        writer.finish()


def raw_only_mcap(path: Path, source: Path) -> None:
    """A recording of raw samples only (``bodynet record 'body/*/*/*/raw'``)."""
    sink = McapSink(path)
    for topic, log_time, sample in read_raw(source):
        sink.write_raw(topic, sample, log_time)
    sink.close()


def export(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str]:
    """``bodynet export ...`` in this process (fast); an exception escaping it
    fails the test as a traceback would."""
    try:
        code = main(["export", *map(str, args)])
    except SystemExit as exc:  # argparse's refusal of an option
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


@pytest.mark.parametrize("kind", ["bvh", "c3d"])
def test_export_refuses_bad_input(
    kind: str, arm_mcap: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + bytes(50))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(arm_mcap.read_bytes()[: arm_mcap.stat().st_size // 2])
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    foreign, garbage, raw_only = (tmp_path / n for n in ("foreign.mcap", "g.mcap", "raw.mcap"))
    foreign_mcap(foreign)
    garbage_pose_mcap(garbage)
    raw_only_mcap(raw_only, arm_mcap)
    cases = [
        (junk, "not a complete MCAP file"),
        (cut, "not a complete MCAP file"),
        (text, "not an MCAP recording (it does not start as MCAP files do)"),
        (foreign, "no poses"),
        (raw_only, "no poses"),
        (garbage, "is not a bodynet pose"),
    ]
    out = tmp_path / f"out.{kind}"
    for recording, message in cases:
        code, err = export(capsys, kind, recording, "-o", out)
        assert code == 2, (recording, err)
        assert err.startswith("bodynet export: "), err
        assert message in err, (recording, err)
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith("out")] == []
    # a missing recording: argparse's refusal of the argument, naming it
    code, err = export(capsys, kind, tmp_path / "missing.mcap", "-o", out)
    assert code == 2
    assert f"argument recording: cannot read '{tmp_path / 'missing.mcap'}': no such file" in err
    # a failed export leaves an earlier file of that name alone
    out.write_text("an earlier export\n")
    assert export(capsys, kind, raw_only, "-o", out)[0] == 2
    assert out.read_text() == "an earlier export\n"
    code, err = export(capsys, kind, arm_mcap, "-o", out, "--rate-hz", 0)
    assert code == 2
    assert "argument --rate-hz: '0' is outside" in err  # argparse's refusal, with the bounds
    # and the command line as a user runs it: a message, no traceback
    result = run("export", kind, garbage, "-o", out)
    assert result.returncode == 2
    assert "is not a bodynet pose" in result.stderr
    assert "Traceback" not in result.stderr
    assert out.read_text() == "an earlier export\n"


def on_a_terminal(*args: object, timeout: float = 120) -> tuple[int, str]:
    """``bodynet ...`` with its stderr on a pseudo-terminal (where a progress bar
    shows, as for a user); its exit code and what the terminal got."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))
    proc = subprocess.Popen([str(BODYNET), *map(str, args)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=slave)  # fmt: skip
    os.close(slave)
    got = bytearray()
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            if not select.select([master], [], [], 0.5)[0]:
                if proc.poll() is not None:
                    break
                continue
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the process closed the terminal
                break
            if not data:
                break
            got += data
    finally:
        os.close(master)
    return proc.wait(timeout=10), got.decode(errors="replace")


@pytest.mark.parametrize("kind", ["csv", "bvh", "c3d"])
def test_export_shows_its_progress_on_a_terminal_unless_quiet(
    kind: str, arm_mcap: Path, tmp_path: Path
) -> None:
    poses_in_file = count_messages(arm_mcap, keys.pose_key())
    bar = re.compile(rf"\d+/{poses_in_file} \[.*pose/s")
    out = tmp_path / f"out.{kind}"
    code, terminal = on_a_terminal("export", kind, arm_mcap, "-o", out)
    assert code == 0, terminal
    assert bar.search(terminal), terminal
    assert out.exists()
    out.unlink()
    code, terminal = on_a_terminal("export", kind, arm_mcap, "-o", out, "-q")
    assert code == 0, terminal
    assert not bar.search(terminal), terminal
    assert "pose/s" not in terminal
    assert out.exists()


def test_amc_skeleton_beside_it_is_checked_as_the_output_is(
    arm_mcap: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The .asf written beside the .amc is never an input, the .amc itself or a
    read-only file; neither file is written when one is refused."""
    recording = tmp_path / "rec.asf"  # a recording named like the skeleton
    recording.write_bytes(arm_mcap.read_bytes())
    code, err = export(capsys, "amc", recording, "-o", tmp_path / "rec.amc")
    assert code == 2, err
    assert err == (f"bodynet export: refusing to write {recording}: it is an input of this "
                   "command; choose another output\n")  # fmt: skip
    assert recording.read_bytes() == arm_mcap.read_bytes()
    both = tmp_path / "w.asf"  # the motion and the skeleton in one file: the motion lost
    code, err = export(capsys, "amc", arm_mcap, "-o", both)
    assert code == 2, err
    assert f"the skeleton is written beside it as {both}, the same file" in err
    read_only = tmp_path / "ro.asf"
    read_only.write_text("an earlier skeleton\n")
    read_only.chmod(0o444)  # refused by root too
    code, err = export(capsys, "amc", arm_mcap, "-o", tmp_path / "ro.amc")
    assert code == 2, err
    assert err == f"bodynet export: cannot write {read_only}: it is read-only\n"
    assert read_only.read_text() == "an earlier skeleton\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.asf", "ro.asf"]
    # a read-only default output (the recording's name, no -o) is refused as -o's is
    default = tmp_path / "rec.csv"
    default.write_text("an earlier export\n")
    default.chmod(0o444)
    code, err = export(capsys, "csv", recording)
    assert code == 2, err
    assert err == f"bodynet export: cannot write {default}: it is read-only\n"
    assert default.read_text() == "an earlier export\n"
