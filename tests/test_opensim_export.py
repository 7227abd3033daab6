"""`bodynet export mot|sto` read back by OpenSim's own Python package
(``TimeSeriesTable``, ``TimeSeriesTableQuaternion``) and compared with the
recording's poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import opensim as osim
import pytest
from export_recordings import export
from scipy.spatial.transform import Rotation

from bodynet.clients.mcap_store import read_poses
from bodynet.core.codecs import pose

# bodynet (+X forward, +Y left, +Z up) -> OpenSim's ground (+X forward, +Y up, +Z right)
TO_OPENSIM = Rotation.from_matrix([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# Each OpenSim coordinate as OpenSim's models define it, from bodynet's angles
# (core/skeleton.py): (bodynet angle, sign, offset in deg).
#   hip_flexion + flexion, hip_adduction + adduction, hip_rotation + internal;
#   knee_angle + flexion (Rajagopal); ankle_angle + dorsiflexion;
#   lumbar_extension + extension, lumbar_bending + to the right, lumbar_rotation
#   + to the left; arm_flex + flexion, arm_add + adduction, arm_rot + internal;
#   elbow_flex + flexion; pro_sup + pronation, 0 in full supination (bodynet's 0
#   is the neutral forearm, 90 deg of pronation from it); wrist_flex + flexion,
#   wrist_dev + ulnar deviation (bodynet: + radial).
EXPECTED = {
    "lumbar_extension": ("lumbar_flexion_deg", -1, 0),
    "lumbar_bending": ("lumbar_lateral_deg", 1, 0),
    "lumbar_rotation": ("lumbar_rotation_deg", 1, 0),
    **{
        f"{coordinate}_{side[0]}": (f"{side}_{angle}_deg", sign, offset)
        for side in ("right", "left")
        for coordinate, angle, sign, offset in (
            ("hip_flexion", "hip_flexion", 1, 0),
            ("hip_adduction", "hip_abduction", -1, 0),
            ("hip_rotation", "hip_rotation", 1, 0),
            ("knee_angle", "knee_flexion", 1, 0),
            ("ankle_angle", "ankle_flexion", 1, 0),
            ("arm_flex", "shoulder_flexion", 1, 0),
            ("arm_add", "shoulder_abduction", -1, 0),
            ("arm_rot", "shoulder_rotation", 1, 0),
            ("elbow_flex", "elbow_flexion", 1, 0),
            ("pro_sup", "elbow_pronation", 1, 90),
            ("wrist_flex", "wrist_flexion", 1, 0),
            ("wrist_dev", "wrist_deviation", -1, 0),
        )
    },
}
IMUS = {
    "pelvis_imu": "pelvis", "torso_imu": "thorax", "head_imu": "head",
    **{f"{body}_{side[0]}_imu": f"{side}_{segment}"
       for side in ("right", "left")
       for body, segment in (("femur", "thigh"), ("tibia", "shank"), ("calcn", "foot"),
                             ("humerus", "upperarm"), ("radius", "forearm"), ("hand", "hand"))},
}  # fmt: skip


def poses(path: Path) -> list[pose.PoseFrame]:
    return [frame for _, frame in read_poses(path)]


def columns(table: osim.TimeSeriesTable) -> dict[str, np.ndarray]:
    return {label: table.getDependentColumn(label).to_numpy()
            for label in table.getColumnLabels()}  # fmt: skip


def test_mot_read_by_opensim(
    body_mcap: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "session.mot"
    export(capsys, "mot", body_mcap, "-o", out)
    table = osim.TimeSeriesTable(str(out))
    frames = poses(body_mcap)
    assert table.getNumRows() == len(frames)
    assert table.getTableMetaDataAsString("inDegrees") == "yes"
    assert float(table.getTableMetaDataAsString("DataRate")) == pytest.approx(25.0)
    assert int(table.getTableMetaDataAsString("bodynet_start_ns")) == frames[0].t_ns
    time = np.array(table.getIndependentColumn())
    np.testing.assert_allclose(time, np.arange(len(frames)) / 25.0, atol=1e-6)
    got = columns(table)
    assert list(got) == ["pelvis_tilt", "pelvis_list", "pelvis_rotation", *EXPECTED]
    for coordinate, (angle, sign, offset) in EXPECTED.items():
        want = np.array([sign * f.angles_deg[angle] + offset for f in frames])
        np.testing.assert_allclose(got[coordinate], want, atol=1e-5, err_msg=coordinate)
        assert np.ptp(want) > 5.0, coordinate  # every coordinate moves in this recording
    # the pelvis: OpenSim's ground_pelvis turns by tilt about Z, list about X, rotation
    # about Y, body-fixed (OpenSim's own Rotation builds it)
    for index, frame in enumerate(frames[::7]):
        row = index * 7
        angles = [np.radians(got[c][row]) for c in ("pelvis_tilt", "pelvis_list",
                                                     "pelvis_rotation")]  # fmt: skip
        r = osim.Rotation(
            osim.BodyRotationSequence,
            angles[0],
            osim.CoordinateAxis(2),
            angles[1],
            osim.CoordinateAxis(0),
            angles[2],
            osim.CoordinateAxis(1),
        )
        matrix = np.array([[r.get(i, j) for j in range(3)] for i in range(3)])
        pelvis = Rotation.from_quat(frame.segments["pelvis"][1], scalar_first=True)
        want = (TO_OPENSIM * pelvis * TO_OPENSIM.inv()).as_matrix()
        np.testing.assert_allclose(matrix, want, atol=1e-6)


def quaternions(table: osim.TimeSeriesTableQuaternion) -> dict[str, np.ndarray]:
    """Each column's (F, 4) quaternions w, x, y, z, through OpenSim's flatten."""
    flat = columns(table.flatten())
    return {label: np.stack([flat[f"{label}_{k}"] for k in range(1, 5)], axis=1)
            for label in table.getColumnLabels()}  # fmt: skip


def test_sto_read_by_opensim(
    body_mcap: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "session.sto"
    export(capsys, "sto", body_mcap, "-o", out)
    header = out.read_text().split("endheader", 1)[0].splitlines()
    assert {"DataType=Quaternion", "version=3", "OpenSimVersion=4.6"} <= set(header)
    table = osim.TimeSeriesTableQuaternion(str(out))
    frames = poses(body_mcap)
    assert table.getNumRows() == len(frames)
    assert float(table.getTableMetaDataAsString("DataRate")) == pytest.approx(25.0)
    assert table.getTableMetaDataAsString("sensor_to_opensim_rotations") == "0 0 0"
    got = quaternions(table)
    assert set(got) == set(IMUS)
    for label, segment in IMUS.items():
        q = got[label]
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
        world = Rotation.from_quat([f.segments[segment][1] for f in frames], scalar_first=True)
        want = TO_OPENSIM * world * TO_OPENSIM.inv()
        error = Rotation.from_quat(q, scalar_first=True) * want.inv()
        assert np.degrees(error.magnitude()).max() < 1e-4, label

    # OpenSim's frame is Y up: in the T-pose (the first frame) the trunk's long
    # axis is ground +Y, the right arm points to +Z (the right), the left to -Z,
    # the thighs down (each segment's long axis is its -Y in OpenSim's axes)
    def axis(label: str, body_axis: list[float]) -> np.ndarray:
        return Rotation.from_quat(got[label][0], scalar_first=True).apply(body_axis)

    np.testing.assert_allclose(axis("torso_imu", [0, 1, 0]), [0, 1, 0], atol=0.05)
    np.testing.assert_allclose(axis("humerus_r_imu", [0, -1, 0]), [0, 0, 1], atol=0.05)
    np.testing.assert_allclose(axis("humerus_l_imu", [0, -1, 0]), [0, 0, -1], atol=0.05)
    np.testing.assert_allclose(axis("femur_r_imu", [0, -1, 0]), [0, -1, 0], atol=0.05)


# OpenSense's IMU inverse kinematics against bodynet's own angles: the
# coordinates it must find, and within how much (deg; measured: at most 0.4,
# 1.7 for arm_flex and arm_rot: near 90 deg of abduction, the T-pose's and
# much of this recording's, they turn about nearly one axis and the solver's
# share between them is ill-conditioned).
IK_CHECKED = {
    **{f"{c}_{s}": 0.5 for s in "rl" for c in ("hip_flexion", "hip_adduction", "hip_rotation",
                                                "knee_angle", "ankle_angle", "arm_add",
                                                "elbow_flex", "pro_sup", "wrist_flex",
                                                "wrist_dev")},
    **{f"{c}_{s}": 2.5 for s in "rl" for c in ("arm_flex", "arm_rot")},
    "lumbar_extension": 0.5,
    "lumbar_bending": 0.5,
    "lumbar_rotation": 0.5,
}  # fmt: skip


def test_opensense_ik_on_the_sto_finds_the_mot(
    body_mcap: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """OpenSim's IMUPlacer and IMUInverseKinematicsTool, on the exported .sto and a
    model with the full-body models' coordinates (``opensim_model``), in the
    pose of the .mot's first frame where every value was measured; over two
    seconds of motion the knee, elbow, forearm, wrist, hip, ankle and lumbar
    coordinates it finds are the .mot's."""
    from opensim_model import build_model

    sto, mot = tmp_path / "s.sto", tmp_path / "s.mot"
    export(capsys, "sto", body_mcap, "-o", sto, "-q")
    export(capsys, "mot", body_mcap, "-o", mot, "-q")
    osim.Logger.setLevelString("warn")
    ours = osim.TimeSeriesTable(str(mot))
    values = columns(ours)
    time = np.array(ours.getIndependentColumn())
    quats = quaternions(osim.TimeSeriesTableQuaternion(str(sto)))
    finite = np.all([np.isfinite(v) for v in values.values()], axis=0)
    finite &= np.all([np.isfinite(q).all(axis=1) for q in quats.values()], axis=0)
    first = int(np.argmax(finite))
    assert finite[first:].all()
    # the placer calibrates on the file's first frame: the file from that frame on
    table = osim.TimeSeriesTableQuaternion(str(sto))
    table.trimFrom(float(time[first]))
    calibration = tmp_path / "from_first.sto"
    osim.STOFileAdapterQuaternion.write(table, str(calibration))
    model_file, placed = tmp_path / "model.osim", tmp_path / "placed.osim"
    build_model({c: float(v[first]) for c, v in values.items()}).printToXML(str(model_file))
    placer = osim.IMUPlacer()
    placer.set_model_file(str(model_file))
    placer.set_orientation_file_for_calibration(str(calibration))
    placer.set_sensor_to_opensim_rotations(osim.Vec3(0.0, 0.0, 0.0))
    assert placer.run(False)
    placer.getCalibratedModel().printToXML(str(placed))
    ik = osim.IMUInverseKinematicsTool()
    ik.set_model_file(str(placed))
    ik.set_orientations_file(str(calibration))
    ik.set_sensor_to_opensim_rotations(osim.Vec3(0.0, 0.0, 0.0))
    ik.set_results_directory(str(tmp_path / "ik"))
    start = 3.2  # s, into the motion after the T-pose
    ik.set_time_range(0, start)
    ik.set_time_range(1, start + 2.0)
    ik.run(False)
    result = osim.TimeSeriesTable(str(tmp_path / "ik" / "ik_from_first.mot"))
    assert result.getTableMetaDataAsString("inDegrees") == "yes"
    found = columns(result)
    rows = np.searchsorted(time, np.array(result.getIndependentColumn()) - 1e-6)
    assert len(rows) >= 45
    for coordinate, tolerance in IK_CHECKED.items():
        error = np.abs(found[coordinate] - values[coordinate][rows])
        assert error.max() < tolerance, (coordinate, error.max())
    for coordinate in ("knee_angle_r", "knee_angle_l", "elbow_flex_r", "elbow_flex_l"):
        assert np.ptp(values[coordinate][rows]) > 3.0, coordinate  # they moved
