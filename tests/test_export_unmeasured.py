"""No number without a measurement, in every export: a recording whose poses
flag some angles as not measured (``unobserved``, ``uncalibrated``) for a
window of frames, and one flagged ``clamped`` (measured), exported to each
format and read back by that format's reader."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import ezc3d
import numpy as np
import pytest
from flagged_recording import FLAGS, UNMEASURED, WINDOW

from bodynet.clients.mcap_store import read_poses
from bodynet.core.codecs import pose

BODYNET = Path(sys.executable).with_name("bodynet")
def run(*args: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BODYNET), *map(str, args)], capture_output=True, text=True,
                          timeout=120, check=False)  # fmt: skip


@pytest.fixture(scope="module")
def frames(flagged: Path) -> list[pose.PoseFrame]:
    return [frame for _, frame in read_poses(flagged)]


def test_csv_leaves_the_cell_empty(flagged: Path, frames: list[pose.PoseFrame],
                                   tmp_path: Path) -> None:  # fmt: skip
    out = tmp_path / "f.csv"
    assert run("export", "csv", flagged, "-o", out).returncode == 0
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(frames)
    for index, (row, frame) in enumerate(zip(rows, frames, strict=True)):
        for name in (*FLAGS, "left_elbow_rel_deg", "left_knee_rel_deg", "right_elbow_rel_deg"):
            joint = name.rsplit("_", 2)[0]
            unmeasured = index in WINDOW and any(a.startswith(joint + "_") for a in UNMEASURED)
            if unmeasured:
                assert row[name] == "", (index, name)
            else:
                want = frame.angles_deg.get(name, frame.rel_deg.get(joint))
                assert float(row[name]) == pytest.approx(want, rel=1e-5, abs=1e-4), (index, name)
        assert row["left_elbow_flexion_deg"] != ""  # the other dof of the joint is measured


def test_c3d_marks_the_angle_point_invalid(flagged: Path, frames: list[pose.PoseFrame],
                                           tmp_path: Path) -> None:  # fmt: skip
    out = tmp_path / "f.c3d"
    assert run("export", "c3d", flagged, "-o", out).returncode == 0
    c3d = ezc3d.c3d(str(out))
    labels = list(c3d["parameters"]["POINT"]["LABELS"]["value"])
    points = c3d["data"]["points"]
    residuals = c3d["data"]["meta_points"]["residuals"]
    for label, angle in (("left_elbow_angles", "left_elbow_flexion_deg"),
                         ("left_knee_angles", "left_knee_flexion_deg"),
                         ("right_elbow_angles", "right_elbow_flexion_deg")):  # fmt: skip
        p = labels.index(label)
        invalid = np.isnan(points[:3, p, :]).any(axis=0)
        want_invalid = np.array([i in WINDOW and angle != "right_elbow_flexion_deg"
                                 for i in range(len(frames))])  # fmt: skip
        np.testing.assert_array_equal(invalid, want_invalid, err_msg=label)
        np.testing.assert_array_equal(residuals[0, p, :] < 0, want_invalid, err_msg=label)
        got = points[0, p, ~want_invalid]
        want = [f.angles_deg[angle] for i, f in enumerate(frames) if not want_invalid[i]]
        np.testing.assert_allclose(got, want, atol=1e-3)


def test_bvh_holds_the_last_measured_value_and_says_so(
    flagged: Path, frames: list[pose.PoseFrame], tmp_path: Path
) -> None:
    """The forearm's second channel is the elbow's pronation, the shank's first
    the knee's flexion (the channels follow the dofs): both hold the value of
    the frame before the window through it, and the export counts them."""
    from test_export import bvh_channels

    out = tmp_path / "f.bvh"
    result = run("export", "bvh", flagged, "-o", out, "--up", "z")
    assert result.returncode == 0, result.stderr
    n = len(WINDOW)
    assert f"{2 * n} values of 2 joint angles had no measurement" in result.stderr
    assert f"left_elbow_pronation_deg ({n})" in result.stderr
    assert f"left_knee_flexion_deg ({n})" in result.stderr
    channels, motion, _ = bvh_channels(out)
    start = {}
    column = 0
    for name, names in channels.items():
        start[name] = column
        column += len(names)
    pronation = motion[:, start["left_forearm"] + 1]
    knee = motion[:, start["left_shank"]]
    before = WINDOW.start - 1
    # bodynet's axes (--up z): the left pronation is about -Z, the knee's flexion about +Y
    for channel, angle, sign in ((pronation, "left_elbow_pronation_deg", -1.0),
                                 (knee, "left_knee_flexion_deg", 1.0)):  # fmt: skip
        truth = np.array([f.angles_deg[angle] for f in frames])
        assert np.ptp(truth[WINDOW.start : WINDOW.stop]) > 1.0  # it moved meanwhile
        np.testing.assert_allclose(channel[WINDOW.start : WINDOW.stop], channel[before])
        outside = np.r_[0 : WINDOW.start, WINDOW.stop : len(frames)]
        np.testing.assert_allclose(channel[outside], sign * truth[outside], atol=0.01)
        np.testing.assert_allclose(channel[before], sign * truth[before], atol=0.01)
    # the elbow's flexion, measured, is not held
    flexion = np.array([f.angles_deg["left_elbow_flexion_deg"] for f in frames])
    np.testing.assert_allclose(-motion[:, start["left_forearm"]], flexion, atol=0.01)


def test_opensim_files_write_nan(flagged: Path, frames: list[pose.PoseFrame],
                                 tmp_path: Path) -> None:  # fmt: skip
    """.mot: the coordinate of an unmeasured angle is NaN; .sto: so is the
    orientation of every segment below an unmeasured angle (OpenSim's readers)."""
    import opensim as osim

    mot, sto = tmp_path / "f.mot", tmp_path / "f.sto"
    assert run("export", "mot", flagged, "-o", mot).returncode == 0
    assert run("export", "sto", flagged, "-o", sto).returncode == 0
    window = np.array([i in WINDOW for i in range(len(frames))])
    table = osim.TimeSeriesTable(str(mot))
    for coordinate, nan_in_window in (("pro_sup_l", True), ("knee_angle_l", True),
                                      ("elbow_flex_l", False), ("elbow_flex_r", False),
                                      ("knee_angle_r", False)):  # fmt: skip
        values = table.getDependentColumn(coordinate).to_numpy()
        np.testing.assert_array_equal(np.isnan(values), window & nan_in_window, coordinate)
    flat = osim.TimeSeriesTableQuaternion(str(sto)).flatten()
    below = {"radius_l_imu", "hand_l_imu", "tibia_l_imu", "calcn_l_imu"}
    for label in ("pelvis_imu", "torso_imu", "humerus_l_imu", "femur_l_imu", "radius_r_imu",
                  *below):  # fmt: skip
        for k in range(1, 5):
            values = flat.getDependentColumn(f"{label}_{k}").to_numpy()
            np.testing.assert_array_equal(np.isnan(values), window & (label in below), label)
