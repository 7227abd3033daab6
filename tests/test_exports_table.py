"""The export table and the exports' pure conversions, alone (no recording)."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

from bodynet.cli.main import build_parser
from bodynet.clients.exports import WRITERS, Option
from bodynet.clients.exports.mot import COORDINATES
from bodynet.clients.exports.track import PoseTrack, hold_unmeasured, resample
from bodynet.core.opensim import IMU_BODIES, imu_label, segment_of_imu
from bodynet.core.skeleton import build_skeleton


def test_every_format_is_one_module_with_write_and_a_command(tmp_path: Path) -> None:
    recording = tmp_path / "in.mcap"
    recording.write_bytes(b"")  # the parser checks that it can be read
    assert list(WRITERS) == ["csv", "bvh", "c3d", "mot", "sto", "amc"]
    for name, entry in WRITERS.items():
        assert entry.name == name
        assert entry.suffix == f".{name}"
        module = importlib.import_module(f"bodynet.clients.exports.{entry.module}")
        assert entry.module == name  # named after its format
        assert callable(module.write)
        args = build_parser().parse_args(["export", name, str(recording)])
        assert args.kind == name
        assert args.output is None  # the recording's name with the suffix
        for option in entry.options:
            assert hasattr(args, option.dest)
        assert hasattr(args, "rate_hz") == entry.regular


def test_option_dest_is_argparse_s() -> None:
    assert Option(("--rate-hz",)).dest == "rate_hz"
    assert Option(("-u", "--up")).dest == "up"
    assert Option(("--x",), {"dest": "y"}).dest == "y"


def test_hold_keeps_the_last_measured_value_across_chunks() -> None:
    values = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0], [4.0, 40.0]])
    measured = np.array([[False, True], [True, False], [False, False], [True, True]])
    last = np.zeros(2)
    got = hold_unmeasured(values, measured, last)
    np.testing.assert_array_equal(got, [[0.0, 10.0], [2.0, 10.0], [2.0, 10.0], [4.0, 40.0]])
    np.testing.assert_array_equal(last, [4.0, 40.0])
    # the next chunk starts from the held values
    got = hold_unmeasured(np.array([[5.0, 50.0]]), np.array([[False, False]]), last)
    np.testing.assert_array_equal(got, [[4.0, 40.0]])


def track(measured: list[bool], t_ms: list[int]) -> PoseTrack:
    """Still poses at times ``t_ms``, the first angle measured as given."""
    skeleton = build_skeleton()
    f, s, j = len(t_ms), len(skeleton.segments), len(skeleton.joints)
    a = len(skeleton.angle_names())
    quats = np.zeros((f, s, 4))
    quats[..., 0] = 1.0
    mask = np.ones((f, a), dtype=bool)
    mask[:, 0] = measured
    return PoseTrack(np.array(t_ms, dtype=np.int64) * 1_000_000, skeleton.segments,
                     np.zeros((f, s, 3)), quats, tuple(x.name for x in skeleton.joints),
                     np.zeros((f, j, 3)), skeleton.angle_names(),
                     np.arange(f * a, dtype=float).reshape(f, a), np.zeros((f, j)),
                     mask)  # fmt: skip


def test_a_resampled_angle_is_measured_only_between_measured_poses() -> None:
    t = track([True, True, False, True], [0, 20, 40, 60])
    out = resample(t, 100.0)  # 10 ms: every pose, and one between each pair
    assert out.rate_hz == 100.0
    assert list(out.t_ns // 1_000_000) == [0, 10, 20, 30, 40, 50, 60]
    assert out.measured[:, 0].tolist() == [True, True, True, False, False, False, True]
    assert out.measured[:, 1:].all()
    assert resample(t, 50.0).measured[:, 0].tolist() == [True, True, False, True]  # as it was


@pytest.mark.parametrize("tick_ms", [10, 40])
def test_a_frame_in_a_gap_in_the_poses_is_no_measurement(tick_ms: int) -> None:
    """Poses every ``tick_ms`` with one tick missing (bridged: a tick lost is
    no gap) and then five (a gap): the frames resampled inside the gap stand
    on no pose, whatever the tick (the limit is the recording's own)."""
    ticks = [0, 1, 2, 4, 5, 11, 12]  # 3 missing, then 6 to 10
    t = track([True] * len(ticks), [k * tick_ms for k in ticks])
    out = resample(t, 2000.0 / tick_ms)  # half a tick: every pose and one between each pair
    half = (out.t_ns - out.t_ns[0]) / 1e6 / tick_ms * 2
    inside = (half > 10) & (half < 22)  # strictly between the poses at ticks 5 and 11
    assert inside.sum() == 11
    np.testing.assert_array_equal(out.measured.all(axis=1), ~inside)
    assert not out.measured[inside].any()
    np.testing.assert_array_equal(out.frame_posed(), ~inside)
    assert not out.chain_measured()[inside].any()  # the pelvis's orientation too
    assert out.chain_measured()[~inside].all()
    # the frames on poses keep their values
    np.testing.assert_array_equal(out.angle_deg[np.isin(half, [2 * k for k in ticks])],
                                  t.angle_deg)  # fmt: skip


def test_mot_has_every_coordinate_of_the_brief() -> None:
    names = {c.name for c in COORDINATES}
    for side in "rl":
        for stem in ("hip_flexion", "hip_adduction", "hip_rotation", "knee_angle",
                     "ankle_angle", "arm_flex", "arm_add", "arm_rot", "elbow_flex", "pro_sup",
                     "wrist_flex", "wrist_dev"):  # fmt: skip
            assert f"{stem}_{side}" in names
    assert "lumbar_extension" in names
    angles = set(build_skeleton().angle_names())
    assert all(c.angle in angles for c in COORDINATES)
    assert len(names) == len(COORDINATES)


@pytest.mark.parametrize("segment", sorted(IMU_BODIES))
def test_opensense_labels_name_their_segment(segment: str) -> None:
    assert segment in build_skeleton().segments
    assert imu_label(segment).endswith("_imu")
    assert segment_of_imu(imu_label(segment)) == segment
    assert segment_of_imu("not_a_body_imu") is None
