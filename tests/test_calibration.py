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
    assert "imu_scatter_deg" not in path.read_text()  # none known: none written
    # each tag's noise from its calibration window, which its dofs' uncertainty carries
    noisy = replace(held, imu_scatter_deg={"body/arm/left/upperarm/raw": 1.73})
    profile_file.save(noisy, path)
    assert profile_file.load(path) == noisy


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("version = 2\n", "version 2"),
        ("version = 1\n[ole.left_elbow_flexion_deg]\nradius_mm = -1\n", "radius"),
        ("version = 1\n[imu_mounts]\n'body/arm/left/upperarm/raw' = [1, 0]\n", "4 numbers"),
        ("version = [\n", "not valid TOML"),
        ("version = 1\ndrift = 'sometimes'\n", "drift must be one of auto, joints, hinges, off"),
        ("", "no version in the profile"),
        ("version = '1'\n", "profile version must be a number .*, not str '1'"),
        ("version = 1\n[heading_reference]\nkey = 'a/b/raw'\n",
         "heading_reference needs key and axis; axis missing"),
        ("version = 1\n[ole.left_elbow_flexion_deg]\nsf = [1]\n",
         "ole.left_elbow_flexion_deg needs radius_mm"),
    ],
)  # fmt: skip
def test_bad_profiles_say_why(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ProfileError, match=message):
        profile_file.load(path)


def test_a_profile_saved_with_a_byte_order_mark_loads_as_without(tmp_path: Path) -> None:
    """Notepad's "UTF-8 with BOM": the same profile, not "not valid TOML"."""
    path = tmp_path / "s7.toml"
    profile_file.save(Profile(subject="s7"), path)
    marked = tmp_path / "marked.toml"
    marked.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert profile_file.load(marked) == profile_file.load(path)


MOUNT = "'body/arm/left/upperarm/raw'"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("accel_counts_per_g = 0", r"accel_counts_per_g must be at least 0\.001 .*, not 0$"),
        ("accel_counts_per_g = -1024", r"accel_counts_per_g must be .*, not -1024$"),
        ("accel_counts_per_g = inf", r"accel_counts_per_g must be a finite number, not inf"),
        ("accel_counts_per_g = true", r"accel_counts_per_g must be a number, not bool"),
        ("accel_filter = nan", r"accel_filter must be a finite number, not nan"),
        ("[segments]\nforearm = 0", r"segments\.forearm must be above 0 m .*, not 0$"),
        ("[segments]\nthigh = -0.4", r"segments\.thigh must be above 0 m .*, not -0\.4$"),
        ("[segments]\nforearm = 1e300", r"segments\.forearm must be .* at most 3 m .*not 1e\+300"),
        ("[segments]\nshank = 3.5", r"segments\.shank must be .* at most 3 m .*not 3\.5$"),
        ("[segments]\nshank = 'long'", r"segments\.shank must be a number, not 'long'"),
        ("[segments]\nupperam = 0.3", r"unknown key segments\.upperam \(known here: upperarm, "),
        ("[imu_headings]\n'a/b/raw' = nan", r"imu_headings\['a/b/raw'\] must be a finite number"),
        ("[imu_headings]\n'a/b/raw' = -inf", r"imu_headings\['a/b/raw'\] must be a finite"),
        ("[imu_headings]\n'a/b/raw' = 1e300", r"imu_headings\['a/b/raw'\] must be at least -360"),
        (f"[imu_scatter_deg]\n{MOUNT} = -0.5", r"imu_scatter_deg\[.*\] must be at least 0 deg"),
        (f"[imu_scatter_deg]\n{MOUNT} = 400", r"imu_scatter_deg\[.*\] must be .* at most 90 deg"),
        (f"[imu_scatter_deg]\n{MOUNT} = 'low'", r"imu_scatter_deg\[.*\] must be a number"),
        (f"[imu_mounts]\n{MOUNT} = [0, 0, 0, 0]", r"imu_mounts\[.*\] must be a rotation .*norm"),
        (f"[imu_mounts]\n{MOUNT} = [1e300, 0, 0, 0]", r"norm at least 0\.001 and at most 1000"),
        (f"[imu_mounts]\n{MOUNT} = [1, 0, nan, 0]", r"imu_mounts\[.*\] must be a finite number"),
        (f"[imu_mounts]\n{MOUNT} = 'wxyz'", r"imu_mounts\[.*\] needs 4 numbers"),
        ("accel_count_per_g = 512", r"unknown key accel_count_per_g \(known here: version, "),
        ("[ole.left_elbow]\nradius_mm = 20", r"unknown key ole\.left_elbow \(known here: "),
        ("[ole.left_elbow_flexion_deg]\nradius_mm = 20\nsf_d_mm = [0]",
         r"unknown key ole\.left_elbow_flexion_deg\.sf_d_mm \(known here: radius_mm, "),
        ("[heading_reference]\nkey = 'a/b/raw'\naxis = '+x'\nangle = 3",
         r"unknown key heading_reference\.angle"),
    ],
)  # fmt: skip
def test_profile_values_out_of_range_are_refused_by_name(
    tmp_path: Path, text: str, message: str
) -> None:
    """Every number in a profile is finite and in its range, and every key known: a
    zero accelerometer scale divided by zero in the solver, a huge length overflowed
    its poses to null, a misspelt key was dropped without a word."""
    path = tmp_path / "bad.toml"
    path.write_text(f"version = 1\n{text}\n")
    with pytest.raises(ProfileError, match=message) as caught:
        profile_file.load(path)
    assert str(caught.value).startswith(f"{path}: ")


def test_profile_values_at_their_bounds_load_as_written(tmp_path: Path) -> None:
    """The bounds are generous: a 3 m segment, a heading of -360 deg, a mount of any
    norm away from 0 (normalised where it is used) load unchanged."""
    path = tmp_path / "edge.toml"
    path.write_text(
        "version = 1\naccel_counts_per_g = 9.81\naccel_filter = 1\n"
        f"[segments]\nthigh = 3.0\nshoulder_drop = 0.001\n[imu_mounts]\n{MOUNT} = [2, 0, 0, 0]\n"
        "[imu_headings]\n'body/arm/left/upperarm/raw' = -360\n"
    )
    profile = profile_file.load(path)
    assert profile.lengths == {"thigh": 3.0, "shoulder_drop": 0.001}
    assert profile.imu_mounts == {"body/arm/left/upperarm/raw": (2.0, 0.0, 0.0, 0.0)}
    assert profile.imu_headings == {"body/arm/left/upperarm/raw": -360.0}
    assert (profile.accel_counts_per_g, profile.accel_filter) == (9.81, 1.0)


def test_the_documented_profile_loads(tmp_path: Path) -> None:
    """The layout ``core/subject.py`` shows loads as it reads (its keys where it
    puts them: ``pose`` after ``[ole...]`` would belong to that table)."""
    from bodynet.core import subject

    doc = subject.__doc__ or ""
    path = tmp_path / "doc.toml"
    path.write_text(doc[doc.index("```toml") + 7 : doc.rindex("```")])
    profile = profile_file.load(path)
    assert profile.lengths == {"upperarm": 0.293, "forearm": 0.265}
    assert profile.heading_reference == ("body/trunk/mid/sacrum/raw", "+z")
    assert profile.trackers == {"aabbccddeeff-0": "left-arm/upperarm"}


def test_a_calibrated_profile_round_trips(tmp_path: Path) -> None:
    """What the gateway writes after calibrating (mounts turned by their headings,
    the headings wrapped, a declared reference, a tracker) loads back the same."""
    from bodynet.gateway.heading import with_headings

    key = "body/arm/left/upperarm/raw"
    profile = with_headings(
        Profile(lengths={"upperarm": 0.31}, heading_reference=(key, "-y")).with_mounts(
            {key: (0.5, 0.5, 0.5, 0.5), "body/arm/left/forearm/raw": (1.0, 0.0, 0.0, 0.0)}
        ),
        {key: 541.0, "body/arm/left/forearm/raw": -179.5},
    ).with_tracker("aabbccddeeff-0", "left-arm/upperarm")
    path = tmp_path / "s.toml"
    profile_file.save(profile, path)
    assert profile_file.load(path) == profile
