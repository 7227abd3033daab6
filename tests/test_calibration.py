"""Known answers from the 000 seed: calibration of the optical linear encoder."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest

from bodynet.core.calibration import OleCalibration, default_ole
from bodynet.core.subject import Profile, ProfileError
from bodynet.gateway.calibrate import fit_radius, fit_scale_factors, radius_from_pair
from bodynet.session import profile_file


@pytest.mark.parametrize(
    ("travel_cm", "angle"),
    [(0.0, 0.0), (1.41, 30.0), (2.80, 60.0), (3.91, 90.0), (4.86, 120.0), (5.22, 140.0)],
)
def test_table_4_1_counts_to_calibrated_angle(travel_cm: float, angle: float) -> None:
    counts = travel_cm * 100  # 0.1 mm per count
    assert default_ole("elbow").angle_deg(counts) == pytest.approx(angle, abs=0.2)


def test_chapter_2_example() -> None:
    # R = 3 cm, 2 cm of travel: 38.2 degrees
    assert OleCalibration(30.0).angle_deg(200) == pytest.approx(38.2, abs=0.01)


def test_powercube_radius_eq_25() -> None:
    travel_at_90 = 31.4 * math.pi / 2
    assert radius_from_pair(travel_at_90, 90.0) == pytest.approx(31.4)


def test_radius_least_squares_eq_26() -> None:
    angles = list(range(0, 100, 10))  # the PowerCube sweep: 0 to 90 degrees by 10
    counts = [round(31.4 * math.radians(a) / 0.1) for a in angles]
    fit = fit_radius(angles, counts)
    assert fit.radius_mm == pytest.approx(31.4, abs=0.05)
    assert fit.r > 0.9999


def test_scale_factors_reproduce_their_reference_angles() -> None:
    angles = [0, 30, 60, 90, 120, 140]
    counts = [0, 141, 280, 391, 486, 522]
    cal = fit_scale_factors(angles, counts, 26.93)
    for a, c in zip(angles, counts, strict=True):
        assert cal.angle_deg(c) == pytest.approx(a, abs=1e-6)
    assert cal.sf[2] == pytest.approx(1.007, abs=0.002)  # Table 4.1
    assert cal.sf[-1] == pytest.approx(1.261, abs=0.002)


def test_inverse_of_the_calibration_curve() -> None:
    cal = default_ole("elbow")
    for angle in (0.0, 12.5, 45.0, 89.0, 139.0):
        assert cal.angle_deg(cal.travel_mm(angle) / 0.1) == pytest.approx(angle, abs=1e-6)


def test_profile_toml_round_trip(tmp_path: Path) -> None:
    profile = Profile(subject="s7", lengths={"upperarm": 0.31}).with_mounts(
        {"body/arm/left/upperarm/raw": (0.5, 0.5, 0.5, 0.5)}
    )
    path = tmp_path / "s7.toml"
    profile_file.save(profile, path)
    assert path.stat().st_mode & 0o777 == 0o600  # health data: owner only
    assert profile_file.load(path) == profile
    assert "[ole.left_elbow_flexion_deg]" in path.read_text()
    assert "drift" not in path.read_text()  # the default (auto) is not written
    held = replace(profile, drift="joints")  # which joints hold drifting tags' headings
    profile_file.save(held, path)
    assert profile_file.load(path) == held


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("version = 2\n", "version 2"),
        ("version = 1\n[ole.left_elbow_flexion_deg]\nradius_mm = -1\n", "radius"),
        ("version = 1\n[imu_mounts]\n'body/arm/left/upperarm/raw' = [1, 0]\n", "4 numbers"),
        ("version = [\n", "not valid TOML"),
        ("version = 1\ndrift = 'sometimes'\n", "drift must be one of auto, joints, hinges, off"),
    ],
)
def test_bad_profiles_say_why(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ProfileError, match=message):
        profile_file.load(path)
