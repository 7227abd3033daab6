"""bodynet report: each statistic against inputs whose answer is known
independently, then the whole report from a real processed recording."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bodynet.clients import stats

# -- the pure statistics -------------------------------------------------------


def test_rom_and_repetitions_of_a_sine_of_known_amplitude_and_cycles() -> None:
    t = np.arange(0, 5.0, 0.01)  # 5 cycles at 1 Hz, 100 samples each
    x = 20.0 + 30.0 * np.sin(2 * math.pi * t)
    rom = stats.range_of_motion(x)
    assert rom.minimum == pytest.approx(-10.0, abs=1e-3)
    assert rom.maximum == pytest.approx(50.0, abs=1e-3)
    assert rom.span == pytest.approx(60.0, abs=1e-3)
    peaks = stats.repetitions(x)
    assert len(peaks) == 5
    assert t[peaks] == pytest.approx([0.25, 1.25, 2.25, 3.25, 4.25])


def test_repetitions_ignore_noise_and_small_wobbles() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0, 6.0, 0.01)
    # three 0-90-0 cycles, a 3-degree wobble on top and sensor noise
    x = 45 * (1 - np.cos(2 * math.pi * t / 2)) + 3 * np.sin(2 * math.pi * 7 * t)
    x += rng.normal(0, 0.5, t.size)
    assert len(stats.repetitions(x)) == 3
    still = rng.normal(10.0, 0.5, t.size)  # a still channel: noise only
    assert len(stats.repetitions(still)) == 0


def test_trials_meet_at_the_valleys_between_peaks() -> None:
    t = np.arange(0, 3.0, 0.01)
    x = 45 * (1 - np.cos(2 * math.pi * t))  # 0 at t = 0, 1, 2, (3)
    bounds = stats.trial_bounds(x, stats.repetitions(x))
    assert [(round(t[a], 2), round(t[b], 2)) for a, b in bounds] == [
        (0.0, 1.0),
        (1.0, 2.0),
        (2.0, 2.99),
    ]


def test_rms_error_and_correlation_of_synthetic_signals() -> None:
    t = np.linspace(0, 4, 4000, endpoint=False)  # whole cycles at 1 Hz
    ref = 45 * np.sin(2 * math.pi * t)
    assert stats.rms_error(ref + 2.5, ref) == pytest.approx(2.5)
    # an error that is a sine of amplitude a has RMS a / sqrt(2)
    assert stats.rms_error(ref + 3 * np.sin(2 * math.pi * 5 * t), ref) == pytest.approx(
        3 / math.sqrt(2)
    )
    # a gain and an offset do not change the correlation; a phase shift phi makes it cos(phi)
    assert stats.correlation(2 * ref + 7, ref) == pytest.approx(1.0)
    shifted = 45 * np.sin(2 * math.pi * t + math.pi / 3)
    assert stats.correlation(shifted, ref) == pytest.approx(0.5, abs=1e-9)
    with pytest.raises(stats.StatsError, match="differ in length"):
        stats.rms_error(ref[:-1], ref)


def test_repeatability_range_and_sd_of_trial_means() -> None:
    shape = np.sin(np.linspace(0, math.pi, 101))
    offsets = np.array([1.0, 3.0, 2.0, 6.0])
    trials = shape + offsets[:, None]
    rep = stats.repeatability(trials)
    assert rep.trial_means == pytest.approx(shape.mean() + offsets)
    assert rep.range == pytest.approx(5.0)
    # SD of 1, 3, 2, 6 with n - 1: sqrt(14 / 3)
    assert rep.sd == pytest.approx(math.sqrt(14 / 3))
    with pytest.raises(stats.StatsError, match="two or more trials"):
        stats.repeatability(trials[:1])


# Shrout & Fleiss (1979), Table 2: six targets rated by four judges, and their
# published ICCs (Table 4): ICC(1,1) .17, ICC(2,1) .29, ICC(3,1) .71,
# ICC(1,4) .44, ICC(2,4) .62, ICC(3,4) .91.
SHROUT_FLEISS = np.array(
    [[9, 2, 5, 8], [6, 1, 3, 2], [8, 4, 6, 8], [7, 1, 2, 6], [10, 5, 6, 9], [6, 2, 4, 7]]
)


def test_icc_matches_shrout_and_fleiss() -> None:
    result = stats.icc(SHROUT_FLEISS.T)  # rows are trials (judges), columns targets
    assert result.form == "ICC(3,1)"
    assert result.value == pytest.approx(0.71, abs=0.005)
    assert result.ci95[0] < result.value < result.ci95[1]
    published = {"ICC(1,1)": 0.17, "ICC(2,1)": 0.29, "ICC(3,1)": 0.71,
                 "ICC(1,k)": 0.44, "ICC(2,k)": 0.62, "ICC(3,k)": 0.91}  # fmt: skip
    for name, value in published.items():
        assert result.forms[name] == pytest.approx(value, abs=0.005), name
    assert stats.icc(SHROUT_FLEISS.T, "ICC2").value == pytest.approx(0.29, abs=0.005)


def test_icc_refuses_too_few_trials_and_a_flat_channel() -> None:
    with pytest.raises(stats.StatsError, match="two or more trials"):
        stats.icc(SHROUT_FLEISS.T[:1])
    with pytest.raises(stats.StatsError, match="does not move"):
        stats.icc(np.full((3, 10), 4.0))


def test_type_a_of_a_known_sample() -> None:
    result = stats.type_a([1.0, 2.0, 3.0, 4.0, 5.0])
    assert result.n == 5
    assert result.mean == pytest.approx(3.0)
    assert result.variance == pytest.approx(2.5)
    assert result.sd == pytest.approx(math.sqrt(2.5))
    assert result.variance_of_mean == pytest.approx(0.5)
    assert result.sd_of_mean == pytest.approx(math.sqrt(0.5))


def test_still_window_finds_the_stretch_that_does_not_move() -> None:
    rng = np.random.default_rng(2)
    t = np.arange(0, 10.0, 0.01)
    x = np.column_stack([40 * np.sin(2 * math.pi * 0.5 * t), 20 * np.cos(2 * math.pi * t)])
    still = (t >= 6.0) & (t < 8.5)
    x[still] = [12.0, -3.0]
    x += rng.normal(0, 0.05, x.shape)
    start, stop = stats.still_window(t, x, 2.0)
    assert t[start] >= 6.0
    assert t[stop - 1] < 8.5
    assert t[stop - 1] - t[start] == pytest.approx(2.0)
    with pytest.raises(stats.StatsError, match="shorter than"):
        stats.still_window(t, x, 20.0)
