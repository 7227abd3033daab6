"""No number without a measurement, in every export: a recording whose poses
flag some angles as not measured (``unobserved``, ``uncalibrated``) for a
window of frames, and one flagged ``clamped`` (measured), exported to each
format and read back by that format's reader. What is expected of each frame
follows its own flags (the window's and any the gateway set)."""

from __future__ import annotations

import csv
from pathlib import Path

import ezc3d
import numpy as np
import pytest
from export_recordings import WINDOW, export, read_c3d

from bodynet.clients.mcap_store import read_poses
from bodynet.core.codecs import pose
from bodynet.core.codecs.pose import is_measured as measured
from bodynet.core.skeleton import build_skeleton


@pytest.fixture(scope="module")
def frames(flagged: Path) -> list[pose.PoseFrame]:
    return [frame for _, frame in read_poses(flagged)]


def joint_measured(frame: pose.PoseFrame, joint: str) -> bool:
    return all(measured(frame, a) for a in frame.angles_deg if a.startswith(joint + "_"))


def test_csv_leaves_the_cell_empty(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "f.csv"
    export(capsys, "csv", flagged, "-o", out)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(frames)
    for name in ("left_elbow_pronation_deg", "left_knee_flexion_deg", "right_elbow_flexion_deg",
                 "left_elbow_flexion_deg", "left_elbow_rel_deg", "left_knee_rel_deg",
                 "right_elbow_rel_deg"):  # fmt: skip
        joint = name.rsplit("_", 2)[0]
        for index, (row, frame) in enumerate(zip(rows, frames, strict=True)):
            if name.endswith("_rel_deg"):
                ok, want = joint_measured(frame, joint), frame.rel_deg.get(joint)
            else:
                ok, want = measured(frame, name), frame.angles_deg[name]
            if ok:
                assert float(row[name]) == pytest.approx(want, rel=1e-5, abs=1e-4), (index, name)
            else:
                assert row[name] == "", (index, name)
        window_flagged = name.startswith(("left_elbow_p", "left_knee", "left_elbow_rel"))
        in_window = {rows[i][name] == "" for i in WINDOW}
        assert in_window == {window_flagged}, name


def test_c3d_marks_the_angle_point_invalid(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "f.c3d"
    export(capsys, "c3d", flagged, "-o", out)
    c3d = ezc3d.c3d(str(out))
    labels = list(c3d["parameters"]["POINT"]["LABELS"]["value"])
    points = c3d["data"]["points"]
    residuals = c3d["data"]["meta_points"]["residuals"]
    for joint, angle in (("left_elbow", "left_elbow_flexion_deg"),
                         ("left_knee", "left_knee_flexion_deg"),
                         ("right_elbow", "right_elbow_flexion_deg")):  # fmt: skip
        p = labels.index(f"{joint}_angles")
        invalid = np.isnan(points[:3, p, :]).any(axis=0)
        want_invalid = np.array([not joint_measured(f, joint) for f in frames])
        assert want_invalid[WINDOW.start : WINDOW.stop].all() == (joint != "right_elbow")
        np.testing.assert_array_equal(invalid, want_invalid, err_msg=joint)
        assert np.isnan(points[:3, p, want_invalid]).all()  # the whole point
        np.testing.assert_array_equal(residuals[0, p, :] < 0, want_invalid, err_msg=joint)
        got = points[0, p, ~want_invalid]
        want = [f.angles_deg[angle] for i, f in enumerate(frames) if not want_invalid[i]]
        np.testing.assert_allclose(got, want, atol=1e-3)


def held(frames: list[pose.PoseFrame], angle: str) -> np.ndarray:
    """Each frame's value of ``angle``, or the last measured one before it (0 before any)."""
    out, last = [], 0.0
    for frame in frames:
        if measured(frame, angle):
            last = frame.angles_deg[angle]
        out.append(last)
    return np.array(out)


def test_bvh_holds_the_last_measured_value_and_says_so(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The forearm's second channel is the elbow's pronation, the shank's first
    the knee's flexion (the channels follow the dofs): where nothing measured
    them they hold the last measured value, and the export counts them."""
    from test_export import bvh_channels

    out = tmp_path / "f.bvh"
    err = export(capsys, "bvh", flagged, "-o", out, "--up", "z")
    unmeasured = sum(not measured(f, a) for f in frames for a in f.angles_deg)
    assert f"{unmeasured} values of " in err
    for angle in ("left_elbow_pronation_deg", "left_knee_flexion_deg"):
        count = sum(not measured(f, angle) for f in frames)
        assert count >= len(WINDOW)
        assert f"{angle} ({count})" in err
    channels, motion, _ = bvh_channels(out)
    start = {}
    column = 0
    for name, names in channels.items():
        start[name] = column
        column += len(names)
    # bodynet's axes (--up z): the left pronation is about -Z, the knee's flexion about +Y
    for column, angle, sign in ((start["left_forearm"] + 1, "left_elbow_pronation_deg", -1.0),
                                (start["left_shank"], "left_knee_flexion_deg", 1.0)):  # fmt: skip
        truth = np.array([f.angles_deg[angle] for f in frames])
        assert np.ptp(truth[WINDOW.start : WINDOW.stop]) > 1.0  # it moved meanwhile
        np.testing.assert_allclose(motion[:, column], sign * held(frames, angle), atol=0.01)
    # the elbow's flexion, measured, is not held
    flexion = np.array([f.angles_deg["left_elbow_flexion_deg"] for f in frames])
    np.testing.assert_allclose(-motion[:, start["left_forearm"]],
                               held(frames, "left_elbow_flexion_deg"), atol=0.01)  # fmt: skip
    window = slice(WINDOW.start, WINDOW.stop)
    np.testing.assert_allclose(-motion[window, start["left_forearm"]], flexion[window], atol=0.01)


#: The angles on the way from the pelvis to each segment of the .sto's columns.
CHAINS = {
    "pelvis_imu": [],
    "torso_imu": ["lumbar"],
    "humerus_l_imu": ["lumbar", "left_shoulder"],
    "radius_l_imu": ["lumbar", "left_shoulder", "left_elbow"],
    "hand_l_imu": ["lumbar", "left_shoulder", "left_elbow", "left_wrist"],
    "femur_l_imu": ["left_hip"],
    "tibia_l_imu": ["left_hip", "left_knee"],
    "calcn_l_imu": ["left_hip", "left_knee", "left_ankle"],
    "radius_r_imu": ["lumbar", "right_shoulder", "right_elbow"],
}


def test_opensim_files_write_nan(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """.mot: the coordinate of an unmeasured angle is NaN; .sto: so is the
    orientation of every segment below an unmeasured angle (OpenSim's readers)."""
    import opensim as osim

    mot, sto = tmp_path / "f.mot", tmp_path / "f.sto"
    export(capsys, "mot", flagged, "-o", mot)
    export(capsys, "sto", flagged, "-o", sto)
    table = osim.TimeSeriesTable(str(mot))
    for coordinate, angle in (("pro_sup_l", "left_elbow_pronation_deg"),
                              ("knee_angle_l", "left_knee_flexion_deg"),
                              ("elbow_flex_l", "left_elbow_flexion_deg"),
                              ("elbow_flex_r", "right_elbow_flexion_deg"),
                              ("knee_angle_r", "right_knee_flexion_deg")):  # fmt: skip
        values = table.getDependentColumn(coordinate).to_numpy()
        want = np.array([not measured(f, angle) for f in frames])
        np.testing.assert_array_equal(np.isnan(values), want, coordinate)
    flat = osim.TimeSeriesTableQuaternion(str(sto)).flatten()
    for label, joints in CHAINS.items():
        want = np.array([not all(joint_measured(f, j) for j in joints) for f in frames])
        below_window = label in {"radius_l_imu", "hand_l_imu", "tibia_l_imu", "calcn_l_imu"}
        assert want[WINDOW.start : WINDOW.stop].all() == below_window, label
        for k in range(1, 5):
            values = flat.getDependentColumn(f"{label}_{k}").to_numpy()
            np.testing.assert_array_equal(np.isnan(values), want, label)


#: Joint centres and the flagged angle their place rests on in WINDOW (the
#: left knee's flexion is on the ankle's chain, the elbow's pronation on the
#: wrist's); the knee and elbow centres sit above them, measured.
CENTRES = {"left_ankle": True, "left_wrist": True, "left_knee": False, "left_elbow": False,
           "right_wrist": False}  # fmt: skip


def centre_measured(frame: pose.PoseFrame, joint: str) -> bool:
    """The angles from the pelvis to the segment the joint centre sits on are measured."""
    chain = SKELETON.segment_chains()[SKELETON.joint(joint).parent]
    return all(measured(frame, a) for a in chain)


SKELETON = build_skeleton()


C3dRead = tuple[list[str], np.ndarray, np.ndarray]  # read_c3d's labels, points, residuals


def centres_given(joint: str, ok: np.ndarray, frames: list[pose.PoseFrame],
                  rows: list[dict[str, str]], c3d: C3dRead) -> None:  # fmt: skip
    """The joint's centre is the pose's in the frames ``ok``, else absent: an
    empty CSV cell, an invalid C3D point (residual -1, NaN)."""
    labels, points, residuals = c3d
    cells = np.array([[row[f"{joint}_{a}_m"] for a in "xyz"] for row in rows])
    assert (cells[~ok] == "").all(), joint
    want = np.array([f.joints_m[joint] for f in frames])
    np.testing.assert_allclose(cells[ok].astype(float), want[ok], atol=1e-5, err_msg=joint)
    p = labels.index(joint)
    np.testing.assert_array_equal(residuals[p] < 0, ~ok, joint)
    assert np.isnan(points[:3, p, ~ok]).all(), joint
    np.testing.assert_allclose(points[:3, p, ok].T, want[ok] * 1000, atol=1e-3, err_msg=joint)


def test_csv_and_c3d_joint_centres_resting_on_an_unmeasured_angle_are_not_given(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """CSV: empty cells; C3D: the point invalid (residual -1, NaN), as for an
    angle point; elsewhere the pose's joint centre."""
    out = tmp_path / "f.csv"
    export(capsys, "csv", flagged, "-o", out)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    c3d_out = tmp_path / "f.c3d"
    export(capsys, "c3d", flagged, "-o", c3d_out)
    read = read_c3d(c3d_out)
    assert len(rows) == read[1].shape[2] == len(frames)  # regular ticks: frame for frame
    for joint, below_window in CENTRES.items():
        ok = np.array([centre_measured(f, joint) for f in frames])
        assert (not ok[WINDOW.start : WINDOW.stop].any()) == below_window, joint
        centres_given(joint, ok, frames, rows, read)


def transformed(
    path: Path, frames: list[pose.PoseFrame], tmp_path: Path
) -> list[tuple[str, dict[int, set[str]]]]:
    """The segments of each ``body/tf`` message (by time), read with the mcap
    reader and Foxglove's message class, of the recording at ``path`` and of
    one the recorder wrote from ``frames`` as received (encoded)."""
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from mcap.reader import make_reader

    from bodynet.clients.mcap_store import McapSink
    from bodynet.core import keys

    as_received = tmp_path / "received.mcap"
    sink = McapSink(as_received, tf_min_gap_ns=1)
    for frame in frames:
        sink.write_pose_message(keys.pose_key(), pose.encode(frame))
    sink.close()
    out = []
    for source in (path, as_received):
        with source.open("rb") as f:
            stamped = {}
            for _, _, message in make_reader(f).iter_messages(topics=[keys.TRANSFORMS]):
                parsed = FrameTransforms()
                parsed.ParseFromString(message.data)
                stamped[message.publish_time] = {t.child_frame_id for t in parsed.transforms}
        out.append((source.name, stamped))
    return out


def test_foxglove_transforms_leave_out_a_segment_resting_on_an_unmeasured_angle(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path
) -> None:
    """``body/tf`` read with the mcap reader and Foxglove's message class: in
    WINDOW no transform of the segments below the flagged angles, whichever
    way the poses were stored (decoded, or as received: the recorder's way)."""
    below = {"left_forearm", "left_hand", "left_shank", "left_foot"}
    for name, stamped in transformed(flagged, frames, tmp_path):
        assert len(stamped) > len(frames) // 2
        for index, frame in enumerate(frames):
            got = stamped.get(frame.t_ns)
            if got is None:
                continue  # no transforms for this pose (a display's rate)
            want = {s for s in SKELETON.segments
                    if all(measured(frame, a) for a in SKELETON.segment_chains()[s])}  # fmt: skip
            assert got == want, (name, index)
            assert below.isdisjoint(got) == (index in WINDOW), (name, index)


def test_an_arm_alone_has_its_joint_centres_and_transforms(
    arm_mcap: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The golden SmartSuit capture (a left arm and a head IMU: no pelvis or
    thorax sensor) processed: its lumbar is the upright model's, not measured
    (flag ``unobserved``, reason ``upright``: its CSV cells empty, its C3D angle
    point invalid), and the arm, measured against that reference as against the
    pelvis, has its CSV and C3D joint centres and its Foxglove transforms (as
    ``bodynet process`` recorded them, and as the recorder writes them from the
    messages as received)."""
    from bodynet.clients.exports.c3d import ANGLE_SUFFIX

    frames = [frame for _, frame in read_poses(arm_mcap)]
    lumbar = SKELETON.joint("lumbar").angle_names()
    assert {(f.flags[a], tuple(f.reasons[a])) for f in frames for a in lumbar} == {
        (pose.UNOBSERVED, (pose.UNOBSERVED, pose.UPRIGHT))}  # fmt: skip
    chains = SKELETON.segment_chains()

    def stands(frame: pose.PoseFrame, segment: str) -> bool:  # on measures and the upright model
        return all(measured(frame, a) or a in lumbar for a in chains[segment])

    out = tmp_path / "arm.csv"
    export(capsys, "csv", arm_mcap, "-o", out)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(frames)
    assert all(row[a] == "" for row in rows for a in lumbar)
    c3d_out = tmp_path / "arm.c3d"
    export(capsys, "c3d", arm_mcap, "-o", c3d_out)
    read = labels, _, residuals = read_c3d(c3d_out)
    assert (residuals[labels.index("lumbar" + ANGLE_SUFFIX)] < 0).all()
    for joint, segment in (("left_shoulder", "thorax"), ("left_elbow", "left_upperarm"),
                           ("left_wrist", "left_forearm")):  # fmt: skip
        ok = np.array([stands(f, segment) for f in frames])
        # the encoders and tilts of the upper arm throughout; the elbow's pronation
        # (the forearm's chain) only where the forearm is off the vertical
        assert ok.all() if segment != "left_forearm" else ok.sum() > 10, joint
        centres_given(joint, ok, frames, rows, read)

    arm = {"left_upperarm", "left_forearm", "left_hand"}
    for name, stamped in transformed(arm_mcap, frames, tmp_path):
        assert len(stamped) > len(frames) // 10, name
        for index, frame in enumerate(frames):
            got = stamped.get(frame.t_ns)
            if got is None:
                continue  # no transforms for this pose (a display's rate)
            assert got == {s for s in SKELETON.segments if stands(frame, s)}, (name, index)
        assert all("left_upperarm" in got for got in stamped.values()), name
        assert any(arm <= got for got in stamped.values()), name


def test_a_recording_from_before_the_stale_reason_exports_no_angle_resting_on_a_stale_sensor(
    tmp_path: Path,
) -> None:
    """Poses as an older gateway wrote them (the elbow module listed stale, no dof
    flagged): the export's track takes the elbow and wrist as unmeasured (as LSL,
    metrics and the report do), and the forearm's orientation with them."""
    from bodynet.clients.exports.track import load_track
    from bodynet.clients.mcap_store import McapSink
    from bodynet.core import keys

    skeleton = build_skeleton()
    stale = [keys.raw_key("arm", "left", "elbow")]
    path = tmp_path / "old.mcap"
    sink = McapSink(path)
    for i in range(3):
        t_ns = 1_700_000_000_000_000_000 + i * 10_000_000
        segments = dict.fromkeys(skeleton.segments, ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0)))
        frame = pose.PoseFrame(i, t_ns, dict.fromkeys(skeleton.angle_names(), 1.0), {},
                               segments, {}, stale=stale if i else [])  # fmt: skip
        sink.write_pose(keys.pose_key(), frame, t_ns)
    sink.close()
    track = load_track(path, progress=False, every_tick=True)
    unmeasured = {a for k, a in enumerate(track.angles) if not track.measured[1:, k].any()}
    assert unmeasured == {*skeleton.joint("left_elbow").angle_names(),
                          *skeleton.joint("left_wrist").angle_names()}  # fmt: skip
    assert track.measured[0].all()
    forearm = track.segments.index("left_forearm")
    assert track.chain_measured()[:, forearm].tolist() == [True, False, False]
