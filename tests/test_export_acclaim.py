"""`bodynet export amc` read back by two readers independent of the writer, which
must find the joint centres of the recording's poses: pyacclaim (PyPI, a
third-party ASF/AMC parser with forward kinematics; the `dev` extra) and an
Acclaim reader written here from the format's description (text parsing and
forward kinematics), which also checks the held angles."""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from export_recordings import WINDOW, export
from pyacclaim import loadAMC, loadASF
from scipy.spatial.transform import Rotation

from bodynet.cli.main import main
from bodynet.clients.mcap_store import McapSink, read_poses
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.codecs.pose import is_measured as measured
from bodynet.core.skeleton import build_skeleton

# bodynet (+X forward, +Y left, +Z up) -> the file's axes with --up y
TO_Y_UP = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


@dataclass
class AsfBone:
    direction: np.ndarray
    length: float
    c: Rotation  # the bone's local frame (its ``axis``)
    dofs: list[str] = field(default_factory=list)


@dataclass
class Asf:
    root_order: list[str]
    root_c: Rotation
    bones: dict[str, AsfBone]
    children: dict[str, list[str]]


def rotation(letters: list[str], degrees: list[float]) -> Rotation:
    """The Acclaim convention: rotations applied in the order listed (the first
    letter first), about the fixed axes: R = R_n ... R_2 R_1."""
    r = Rotation.identity()
    for letter, angle in zip(letters, degrees, strict=True):
        r = Rotation.from_euler(letter[-1].lower(), angle, degrees=True) * r
    return r


def read_asf(path: Path) -> Asf:
    sections = re.split(r"^:(\w+)", path.read_text(), flags=re.MULTILINE)
    text = dict(zip(sections[1::2], sections[2::2], strict=True))
    assert "angle deg" in text["units"]
    root = {line.split()[0]: line.split()[1:] for line in text["root"].strip().splitlines()}
    root_axis = root["axis"][0]
    bones: dict[str, AsfBone] = {}
    for block in re.findall(r"begin(.*?)end", text["bonedata"], flags=re.DOTALL):
        entry = {line.split()[0]: line.split()[1:] for line in block.strip().splitlines()}
        axis = entry["axis"]
        bones[entry["name"][0]] = AsfBone(
            np.array([float(v) for v in entry["direction"]]),
            float(entry["length"][0]),
            rotation(list(axis[3]), [float(v) for v in axis[:3]]),
            entry.get("dof", []),
        )
    children = {}
    for line in text["hierarchy"].strip().splitlines()[1:-1]:
        parent, *kids = line.split()
        children[parent] = kids
    return Asf(root["order"], rotation(list(root_axis), [0.0, 0.0, 0.0]), bones, children)


def read_amc(path: Path) -> list[dict[str, list[float]]]:
    frames: list[dict[str, list[float]]] = []
    for line in path.read_text().splitlines():
        if not line or line.startswith(("#", ":")):
            continue
        words = line.split()
        if len(words) == 1 and words[0].isdigit():
            assert int(words[0]) == len(frames) + 1
            frames.append({})
        else:
            frames[-1][words[0]] = [float(v) for v in words[1:]]
    return frames


def joint_positions(asf: Asf, frame: dict[str, list[float]]) -> dict[str, np.ndarray]:
    """Where each bone starts (and the root), by the Acclaim forward kinematics:
    a bone's world rotation is its parent's times C M C^-1 (M its dofs'
    rotation), and it ends ``length`` along its direction so turned."""
    values = frame["root"]
    translation = [values[i] for i, o in enumerate(asf.root_order) if o.startswith("T")]
    turns = [(o, values[i]) for i, o in enumerate(asf.root_order) if o.startswith("R")]
    root_r = asf.root_c * rotation([o for o, _ in turns], [v for _, v in turns]) * asf.root_c.inv()
    starts = {"root": np.array(translation)}

    def walk(name: str, start: np.ndarray, parent_r: Rotation) -> None:
        for child in asf.children.get(name, []):
            bone = asf.bones[child]
            m = rotation(bone.dofs, frame[child]) if bone.dofs else Rotation.identity()
            r = parent_r * bone.c * m * bone.c.inv()
            starts[child] = start
            walk(child, start + bone.length * r.apply(bone.direction), r)

    walk("root", starts["root"], root_r)
    return starts


def worst_error(asf: Asf, amc: list[dict[str, list[float]]], frames: list[pose.PoseFrame],
                m: np.ndarray, scale: float, rows: range | list[int],
                joints: list[str] | None = None) -> float:  # fmt: skip
    """The largest distance (m) between a joint centre of the poses and where
    the reader puts the bone that hangs from it."""
    skeleton = build_skeleton()
    names = joints or [j.name for j in skeleton.joints]
    child = {j.name: j.child for j in skeleton.joints}
    worst = 0.0
    for f in rows:
        starts = joint_positions(asf, amc[f])
        want = m @ np.array(frames[f].segments["pelvis"][0]) * scale
        worst = max(worst, float(np.abs(starts["root"] - want).max()) / scale)
        for joint in names:
            want = m @ np.array(frames[f].joints_m[joint]) * scale
            worst = max(worst, float(np.abs(starts[child[joint]] - want).max()) / scale)
    return worst


@pytest.mark.parametrize(("up", "units"), [("y", "m"), ("z", "cm")])
def test_acclaim_reader_finds_the_joint_centres(
    body_mcap: Path, tmp_path: Path, up: str, units: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "session.amc"
    err = export(capsys, "amc", body_mcap, "-o", out, "--up", up, "--units", units)
    assert f"skeleton -> {out.with_suffix('.asf')}" in err
    asf, amc = read_asf(out.with_suffix(".asf")), read_amc(out)
    frames = [frame for _, frame in read_poses(body_mcap)]
    assert len(amc) == len(frames)
    segments = set(build_skeleton().segments) - {"pelvis"}
    assert {b for b, bone in asf.bones.items() if bone.dofs} == segments
    assert all(bone.dofs == ["rx", "ry", "rz"] for b, bone in asf.bones.items() if bone.dofs)
    m = TO_Y_UP if up == "y" else np.eye(3)
    worst = worst_error(asf, amc, frames, m, 100.0 if units == "cm" else 1.0, range(len(frames)))
    assert worst < 2e-5, worst  # metres: the pose messages carry 1 µm


@pytest.mark.parametrize(("up", "units"), [("y", "m"), ("z", "cm")])
def test_pyacclaim_reads_the_poses_joint_centres_and_orientations(
    body_mcap: Path, tmp_path: Path, up: str, units: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """pyacclaim's forward kinematics of the exported pair: where each bone
    starts is the joint centre of the pose (the root: the pelvis), within 20 µm,
    and each moving bone's world rotation is its segment's orientation (the rest
    pose is anatomical neutral, where every segment frame is the world's), seen
    in the file's axes, within 1e-3 deg; every frame."""
    out = tmp_path / "session.amc"
    export(capsys, "amc", body_mcap, "-o", out, "--up", up, "--units", units)
    frames = [frame for _, frame in read_poses(body_mcap)]
    asf = loadASF(str(out.with_suffix(".asf")), verbose=False)  # prints a line anyway
    # pyacclaim 0.0.1's loadAMC keeps a frame's values when it meets the NEXT frame's
    # number, so it drops the last frame of every file: it returns the first n - 1,
    # in order. The file as written must give exactly those; a copy with one more
    # frame number appended (nothing else changed) gives all n, the last included.
    assert len(loadAMC(asf, str(out))) == len(frames) - 1
    closed = tmp_path / "closed.amc"
    closed.write_text(out.read_text() + f"{len(frames) + 1}\n")
    amc = loadAMC(asf, str(closed))
    assert len(amc) == len(frames)

    m = TO_Y_UP if up == "y" else np.eye(3)
    scale = 100.0 if units == "cm" else 1.0
    bones = asf["bones"]
    skeleton = build_skeleton()
    worst_m = worst_deg = 0.0
    for values, frame in zip(amc, frames, strict=True):
        bones["root"].set_pose(values)  # poses the whole tree from the root
        got = bones["root"].global_coordinate / scale
        worst_m = max(worst_m, float(np.abs(got - m @ frame.segments["pelvis"][0]).max()))
        for joint in skeleton.joints:  # a bone starts where its parent bone ends
            got = bones[joint.child].parent.global_coordinate / scale
            worst_m = max(worst_m, float(np.abs(got - m @ frame.joints_m[joint.name]).max()))
        for segment in skeleton.segments:
            w, x, y, z = frame.segments[segment][1]
            want = m @ Rotation.from_quat([x, y, z, w]).as_matrix() @ m.T
            got = bones["root" if segment == "pelvis" else segment].transformation[:3, :3]
            off = Rotation.from_matrix(got @ want.T).magnitude()
            worst_deg = max(worst_deg, float(np.degrees(off)))
    assert worst_m < 2e-5, worst_m  # metres: the pose messages carry 1 µm
    assert worst_deg < 1e-3, worst_deg  # the .amc's angles have 6 decimals


def test_acclaim_holds_what_nothing_measured(
    flagged: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The left knee's flexion flagged for a window of frames: the export says it
    held it; outside the window every joint centre is the poses', inside it those
    that do not hang below the knee too, and the left shank keeps its angle to
    the thigh from the frame before."""
    out = tmp_path / "f.amc"
    err = export(capsys, "amc", flagged, "-o", out)
    assert "left_knee_flexion_deg (21)" in err
    asf, amc = read_asf(out.with_suffix(".asf")), read_amc(out)
    frames = [frame for _, frame in read_poses(flagged)]
    outside = [
        f
        for f, frame in enumerate(frames)
        if f not in WINDOW and all(measured(frame, a) for a in frame.angles_deg)
    ]
    assert len(outside) > len(frames) / 2
    assert worst_error(asf, amc, frames, TO_Y_UP, 1.0, outside) < 2e-5
    above = ["lumbar", "neck", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee",
             "right_shoulder", "right_elbow", "left_shoulder"]  # fmt: skip
    assert worst_error(asf, amc, frames, TO_Y_UP, 1.0, WINDOW, above) < 2e-5

    def knee_angle(f: int) -> float:
        starts = joint_positions(asf, amc[f])
        thigh = starts["left_shank"] - starts["left_thigh"]
        shank = starts["left_foot"] - starts["left_shank"]
        cos = thigh @ shank / np.linalg.norm(thigh) / np.linalg.norm(shank)
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    before = knee_angle(WINDOW.start - 1)
    assert before == pytest.approx(frames[WINDOW.start - 1].angles_deg["left_knee_flexion_deg"],
                                   abs=0.01)  # fmt: skip
    truth = [frames[f].angles_deg["left_knee_flexion_deg"] for f in WINDOW]
    assert np.ptp(truth) > 1.0
    for f in WINDOW:
        assert knee_angle(f) == pytest.approx(before, abs=0.01)


@pytest.mark.parametrize("value", [1e308, -1e308, 3600.0])
def test_an_angle_no_rotation_is_rebuilt_from_is_one_line_and_nothing_written(
    flagged: Path, tmp_path: Path, value: float, capsys: pytest.CaptureFixture[str]
) -> None:
    """A held angle (the pose decoder takes any number) past a turn: one line
    naming the recording, the pose (its time and AMC frame) and the angle, exit 2,
    neither file written (1e308 gave scipy's "zero norm quaternions" traceback)."""
    bad = tmp_path / "big.mcap"
    sink = McapSink(bad)
    for log_time, frame in read_poses(flagged):
        angles = dict.fromkeys(frame.angles_deg, value)
        sink.write_pose(keys.pose_key(), dataclasses.replace(frame, angles_deg=angles), log_time)
    sink.close()
    out = tmp_path / "y.amc"
    assert main(["export", "amc", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"bodynet export: {bad}: the pose "), err
    assert re.search(r"the pose \d+\.\d{3} s into the recording \(AMC frame \d+\) holds", err)
    assert f"= {value:g} deg, no joint angle" in err
    assert err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.mcap"]
