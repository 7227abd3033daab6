"""`bodynet export mot|sto` read back by OpenSim's own Python package
(``TimeSeriesTable``, ``TimeSeriesTableQuaternion``) and compared with the
recording's poses."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import opensim as osim
import pytest
from scipy.spatial.transform import Rotation

from bodynet.clients.mcap_store import read_poses
from bodynet.core.codecs import pose

BODYNET = Path(sys.executable).with_name("bodynet")
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


def export(kind: str, recording: Path, out: Path, *args: object) -> None:
    result = subprocess.run([str(BODYNET), "export", kind, str(recording), "-o", str(out),
                             *map(str, args)], capture_output=True, text=True, timeout=120,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr


def poses(path: Path) -> list[pose.PoseFrame]:
    return [frame for _, frame in read_poses(path)]


def columns(table: osim.TimeSeriesTable) -> dict[str, np.ndarray]:
    return {label: table.getDependentColumn(label).to_numpy()
            for label in table.getColumnLabels()}  # fmt: skip


def test_mot_read_by_opensim(body_mcap: Path, tmp_path: Path) -> None:
    out = tmp_path / "session.mot"
    export("mot", body_mcap, out)
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
        r = osim.Rotation(osim.BodyRotationSequence, angles[0], osim.CoordinateAxis(2),
                          angles[1], osim.CoordinateAxis(0), angles[2], osim.CoordinateAxis(1))
        matrix = np.array([[r.get(i, j) for j in range(3)] for i in range(3)])
        pelvis = Rotation.from_quat(frame.segments["pelvis"][1], scalar_first=True)
        want = (TO_OPENSIM * pelvis * TO_OPENSIM.inv()).as_matrix()
        np.testing.assert_allclose(matrix, want, atol=1e-6)


def quaternions(table: osim.TimeSeriesTableQuaternion) -> dict[str, np.ndarray]:
    """Each column's (F, 4) quaternions w, x, y, z, through OpenSim's flatten."""
    flat = columns(table.flatten())
    return {label: np.stack([flat[f"{label}_{k}"] for k in range(1, 5)], axis=1)
            for label in table.getColumnLabels()}  # fmt: skip


def test_sto_read_by_opensim(body_mcap: Path, tmp_path: Path) -> None:
    out = tmp_path / "session.sto"
    export("sto", body_mcap, out)
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
