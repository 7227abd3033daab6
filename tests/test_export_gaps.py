"""No number without a measurement, across a hole in the poses and below a
dead tag: a real capture (ideal IMU tags on the whole body but the left
forearm, whose tag is dead from the start) in which every tag is silent for
a second, processed by ``bodynet process`` (no pose in the hole) and exported
to each format, read back by that format's reader. Nothing in the hole, and
nothing resting on the unobserved left elbow, may come out as valid; what
was measured comes out as the poses say."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from export_recordings import export, read_c3d
from mcap.reader import make_reader

from bodynet.cli.main import main
from bodynet.clients.mcap_store import read_poses
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.messages import Quat
from bodynet.core.profile import mount
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
from bodynet.nodes.motion import ROUTINES

RATE_HZ = 25
HOLE_S = (3.0, 4.0)  # every tag silent: 25 ticks without a pose
DEAD = "left_forearm"


@pytest.fixture(scope="module")
def gap_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """6 s of the full-body routine as an orientation CSV (the tags square on
    their segments: ``--tpose-s 0``), processed."""
    tags = imu_tags()
    body = BodyEmulator(ROUTINES["full-body"], tags, realism=Realism.ideal(), seed=3)
    segment = {t.node: mount(t.site).segment for t in tags}
    live = [t for t in tags if segment[t.node] != DEAD]
    lines = [",".join(["time", *(f"{segment[t.node]}_{c}" for t in live for c in "wxyz")])]
    for k in range(6 * RATE_HZ):
        t = k / RATE_HZ
        q = {r.node: r.wxyz for r in body.sample(t)[0] if isinstance(r, Quat)}
        silent = HOLE_S[0] <= t < HOLE_S[1]
        lines.append(",".join([repr(t), *("nan" if silent else repr(c)
                                          for tag in live for c in q[tag.node])]))  # fmt: skip
    tmp = tmp_path_factory.mktemp("gap")
    (tmp / "gap.csv").write_text("\n".join(lines) + "\n")
    out = tmp / "gap.mcap"
    assert main(["process", str(tmp / "gap.csv"), "--tpose-s", "0", "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def poses(gap_mcap: Path) -> list[pose.PoseFrame]:
    frames = [frame for _, frame in read_poses(gap_mcap)]
    t0 = frames[0].t_ns
    rel = [(f.t_ns - t0) / 1e9 for f in frames]
    # the capture as the tests expect it: no pose in the hole, the left elbow unobserved
    assert not any(HOLE_S[0] + 0.01 < t < HOLE_S[1] - 0.01 for t in rel)
    assert max(np.diff(rel)) > 20 / RATE_HZ
    assert all(not pose.is_measured(f, "left_elbow_flexion_deg") for f in frames)
    assert all(pose.is_measured(f, "right_elbow_flexion_deg") for f in frames)
    return frames


def grid(frames: list[pose.PoseFrame]) -> tuple[np.ndarray, dict[int, pose.PoseFrame]]:
    """The export's frame times (s from the first pose, at the recording's rate)
    and, for each frame on a pose, that pose."""
    t0 = frames[0].t_ns
    n = round((frames[-1].t_ns - t0) / 1e9 * RATE_HZ) + 1
    on = {round((f.t_ns - t0) / 1e9 * RATE_HZ): f for f in frames}
    return np.arange(n) / RATE_HZ, on


def in_hole(times: np.ndarray) -> np.ndarray:
    return (times > HOLE_S[0] - 1e-6) & (times < HOLE_S[1] - 1e-6)


def test_mot_and_sto_are_nan_in_the_hole_and_below_the_dead_tag(
    gap_mcap: Path, poses: list[pose.PoseFrame], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    import opensim as osim

    mot, sto = tmp_path / "g.mot", tmp_path / "g.sto"
    export(capsys, "mot", gap_mcap, "-o", mot)
    export(capsys, "sto", gap_mcap, "-o", sto)
    times, on = grid(poses)
    hole = in_hole(times)
    assert hole.sum() == 25
    table = osim.TimeSeriesTable(str(mot))
    np.testing.assert_allclose(table.getIndependentColumn(), times, atol=1e-6)
    for label in table.getColumnLabels():
        values = table.getDependentColumn(label).to_numpy()
        assert np.isnan(values[hole]).all(), label  # the pelvis's too
        if label in ("elbow_flex_l", "pro_sup_l"):
            assert np.isnan(values).all(), label
    for label, angle in (("knee_angle_r", "right_knee_flexion_deg"),
                         ("hip_flexion_r", "right_hip_flexion_deg"),
                         ("elbow_flex_r", "right_elbow_flexion_deg")):  # fmt: skip
        values = table.getDependentColumn(label).to_numpy()
        assert not np.isnan(values[~hole]).any(), label
        for i, frame in on.items():
            assert values[i] == pytest.approx(frame.angles_deg[angle], abs=1e-4), (label, i)
    flat = osim.TimeSeriesTableQuaternion(str(sto)).flatten()
    for label in ("pelvis_imu", "torso_imu", "humerus_l_imu", "radius_l_imu", "hand_l_imu",
                  "radius_r_imu", "tibia_l_imu"):  # fmt: skip
        values = flat.getDependentColumn(f"{label}_1").to_numpy()
        assert np.isnan(values[hole]).all(), label
        below_dead = label in ("radius_l_imu", "hand_l_imu")
        np.testing.assert_array_equal(np.isnan(values[~hole]), below_dead, label)


def test_c3d_points_are_invalid_in_the_hole_and_below_the_dead_tag(
    gap_mcap: Path, poses: list[pose.PoseFrame], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    out = tmp_path / "g.c3d"
    export(capsys, "c3d", gap_mcap, "-o", out)
    labels, points, residuals = read_c3d(out)
    times, on = grid(poses)
    hole = in_hole(times)
    assert points.shape[2] == len(times)
    assert (residuals[:, hole] == -1).all()  # every point
    assert np.isnan(points[:3][:, :, hole]).all()
    # the wrist centre and the hand's rest on the unobserved elbow; the elbow
    # centre sits on the upper arm, measured
    for label in ("left_wrist", "left_elbow_angles"):
        p = labels.index(label)
        assert (residuals[p] == -1).all(), label
        assert np.isnan(points[:3, p]).all(), label
    for label, joint in (("left_elbow", "left_elbow"), ("right_wrist", "right_wrist"),
                         ("left_ankle", "left_ankle")):  # fmt: skip
        p = labels.index(label)
        assert (residuals[p, ~hole] == 0).all(), label
        for i, frame in on.items():
            np.testing.assert_allclose(points[:3, p, i], np.multiply(frame.joints_m[joint], 1000),
                                       atol=1e-3, err_msg=f"{label} {i}")  # fmt: skip
    pelvis = labels.index("pelvis")
    assert (residuals[pelvis, ~hole] == 0).all()


def test_csv_leaves_the_joint_centres_below_the_dead_tag_empty(
    gap_mcap: Path, poses: list[pose.PoseFrame], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    out = tmp_path / "g.csv"
    export(capsys, "csv", gap_mcap, "-o", out)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(poses)  # a row per pose: none in the hole
    for row, frame in zip(rows, poses, strict=True):
        for axis in "xyz":
            assert row[f"left_wrist_{axis}_m"] == ""
        for joint in ("left_elbow", "right_wrist", "left_ankle"):
            got = [float(row[f"{joint}_{axis}_m"]) for axis in "xyz"]
            np.testing.assert_allclose(got, frame.joints_m[joint], atol=1e-5)


def test_bvh_and_amc_hold_the_last_pose_over_the_hole_and_say_so(
    gap_mcap: Path, poses: list[pose.PoseFrame], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    from test_export import bvh_channels

    out = tmp_path / "g.bvh"
    err = export(capsys, "bvh", gap_mcap, "-o", out, "--up", "z")
    times, _ = grid(poses)
    hole = np.flatnonzero(in_hole(times))
    assert "25 frames fall in gaps in the poses" in err
    assert "right_knee_flexion_deg (25)" in err or "and " in err  # counted with the rest
    _, motion, _ = bvh_channels(out)
    before = hole[0] - 1  # the last frame on a pose
    # every channel, the root's six too, holds the last pose across the hole
    np.testing.assert_array_equal(motion[hole], np.repeat(motion[[before]], len(hole), axis=0))
    assert not np.array_equal(motion[before], motion[hole[-1] + 1])  # it moved meanwhile

    amc = tmp_path / "g.amc"
    err = export(capsys, "amc", gap_mcap, "-o", amc)
    assert "25 frames fall in gaps in the poses" in err
    frames: list[list[str]] = []
    for line in amc.read_text().splitlines():
        if line.isdigit():
            frames.append([])
        elif frames:
            frames[-1].append(line)
    assert len(frames) == len(times)
    for i in hole:
        assert frames[i] == frames[before], i


def test_foxglove_transforms_leave_out_the_segments_below_the_dead_tag(
    gap_mcap: Path, poses: list[pose.PoseFrame]
) -> None:
    """``body/tf`` as the mcap reader and Foxglove's own message class read it."""
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

    children = []
    with gap_mcap.open("rb") as f:
        for _, _, message in make_reader(f).iter_messages(topics=[keys.TRANSFORMS]):
            parsed = FrameTransforms()
            parsed.ParseFromString(message.data)
            children.append({t.child_frame_id for t in parsed.transforms})
    assert len(children) == len(poses)
    for got in children:
        assert "left_forearm" not in got
        assert "left_hand" not in got
        assert {"pelvis", "left_upperarm", "right_forearm", "right_hand"} <= got
        assert len(got) == 13
