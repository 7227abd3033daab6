"""An ankle's stated uncertainty against the emulator's truth: tags on timers of
their own, noisy or jittered, their orientations brought to each tick's time
(``kernels.align_quats``). A foot at heel strike turns at hundreds of deg/s; a
tag whose last two samples showed that turn within its noise was not turned
forward and stated nothing for it, so a sample 15-35 ms old stood for the tick's
time with the tags' noise alone as its uncertainty: ankles 12-19 deg off
stating 6."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bodynet.bench import truth
from bodynet.gateway import kernels
from bodynet.gateway.solver import (
    ALIGN_AHEAD_NS,
    ALIGN_CHANGE_PER_S,
    ALIGN_RATE_MAX_DEG_S,
    ALIGN_RATE_MEMORY_S,
    ALIGN_SPAN_NS,
    tag_unc,
)


@pytest.mark.parametrize(
    ("noise", "jitter_s", "drop", "seed"),
    [(2.0, 0.002, 0.0, 1), (0.3, 0.02, 0.1, 2)],
    ids=["noise2", "jitter20-drop10"],
)
def test_a_walks_ankles_are_within_twice_their_uncertainty(
    tmp_path: Path, noise: float, jitter_s: float, drop: float, seed: int
) -> None:
    """Ten seconds of walking (the pose held three) from fifteen tags on their own
    timers: every measured ankle dof within twice its ``unc_deg`` of the truth
    (before, 1-27 of some 2,900 were off by more, up to 15 deg stating 3-6), and
    the uncertainty not inflated to get there: its median within half again of
    what two tags' noise alone gives."""
    sc = truth.Scenario("ankle", noise=noise, jitter_s=jitter_s, drop=drop, seed=seed,
                        heading_mode="fixed", seconds=10.0)  # fmt: skip
    rows, _, _ = truth.session(sc, tmp_path)
    ankles = [r for r in rows if "_ankle_" in r[1]]
    assert len(ankles) > 2500  # four dofs at up to 100 Hz for 7 s: nothing flagged away
    beyond = [r for r in ankles if abs(r[2]) > 2 * r[4]]
    assert not beyond, sorted(beyond, key=lambda r: -abs(r[2]))[:5]
    floor = tag_unc([noise * math.sqrt(3.0)] * 2)  # the scatter of noise per axis, two tags
    assert np.median([r[4] for r in ankles]) < 1.5 * floor


def test_a_tag_not_turned_forward_states_the_turn_it_showed() -> None:
    """A tag whose last two samples, 20 ms apart, turned 3 deg, less than its
    noise (2 deg about each axis) tells from motion, is not turned forward to a
    tick 15 ms later, but states that it may be off by what that turn would
    have made of those 15 ms (before: nothing); two samples stamped 0.1 ms apart
    (a burst) state no more than the fastest limb's rate would make of them; one
    that turned well beyond its noise is turned forward and states at least the
    noise it carried forward."""
    ms = 1_000_000
    scatter = np.radians([2.0 * math.sqrt(3.0)])

    def brought(turn_deg: float, span_ns: int = 20 * ms) -> tuple[float, float]:
        times = np.full((1, 2), kernels.NO_TIME, dtype=np.int64)
        held = np.zeros((1, 2, 4))
        recent = np.full(1, math.inf)
        for t, angle in ((20 * ms - span_ns, 0.0), (20 * ms, turn_deg)):
            half = math.radians(angle) / 2
            q = np.array([[math.cos(half), math.sin(half), 0.0, 0.0]])
            stamped = np.array([t], dtype=np.int64)
            out, residual = kernels.align_quats(
                q, stamped, 35 * ms, times, held, recent, scatter, ALIGN_SPAN_NS, ALIGN_AHEAD_NS,
                ALIGN_CHANGE_PER_S, ALIGN_RATE_MAX_DEG_S, ALIGN_RATE_MEMORY_S, np.zeros(1),
            )  # fmt: skip
        if np.array_equal(out, q):
            return 0.0, float(residual[0])
        return math.degrees(2 * math.acos(min(1.0, abs(float(out[0] @ q[0]))))), float(residual[0])

    moved, residual = brought(3.0)
    assert moved == 0.0
    assert residual == pytest.approx(3.0 * 15 / 20)
    moved, residual = brought(3.0, span_ns=ms // 10)
    assert moved == 0.0
    assert residual == pytest.approx(ALIGN_RATE_MAX_DEG_S * 0.015)
    moved, residual = brought(20.0)
    assert 0.0 < moved < 20.0 * 15 / 20
    noise_axis = 2.0  # deg, one axis of the scatter
    reach = moved / 20.0  # the share of the span's turn it was turned forward
    assert residual >= 2 * noise_axis * math.sqrt(2 * reach * (1 + reach))


def test_a_tag_stamped_on_arrival_states_its_turn_over_how_old_it_may_be() -> None:
    """Two samples 20 ms apart that turned 6 deg (300 deg/s), the tick at the
    newest one's stamp: nothing to bring forward, but a source whose stamp is
    the arrival of a reading up to 30 ms old (the IMU central's) states the 9
    deg it may have turned since (before: nothing); a turn faster than the
    fastest limb states that limb's; a source stamping when read states nothing."""
    ms = 1_000_000
    scatter = np.radians([0.3])

    def stated(turn_deg: float, spread_ms: float) -> float:
        times = np.full((1, 2), kernels.NO_TIME, dtype=np.int64)
        held = np.zeros((1, 2, 4))
        for t, angle in ((0, 0.0), (20 * ms, turn_deg)):
            half = math.radians(angle) / 2
            q = np.array([[math.cos(half), math.sin(half), 0.0, 0.0]])
            out, residual = kernels.align_quats(
                q, np.array([t], dtype=np.int64), 20 * ms, times, held, np.full(1, math.inf),
                scatter, ALIGN_SPAN_NS, ALIGN_AHEAD_NS, ALIGN_CHANGE_PER_S, ALIGN_RATE_MAX_DEG_S,
                ALIGN_RATE_MEMORY_S, np.array([spread_ms * ms], dtype=float),
            )  # fmt: skip
            assert np.array_equal(out, q)  # at the tick's time: as it is
        return float(residual[0])

    assert stated(6.0, 30.0) == pytest.approx(9.0)
    assert stated(6.0, 0.0) == 0.0
    assert stated(40.0, 30.0) == pytest.approx(ALIGN_RATE_MAX_DEG_S * 0.03)


def test_two_samples_stamped_a_hair_apart_turn_no_faster_than_a_limb() -> None:
    """Two samples of a burst, stamped as they arrived 0.1 ms apart (a loaded
    host, an adapter delivering what it held) and 20 deg apart, are no rate of
    20 deg per 0.1 ms: brought forward at most at the fastest a limb turns
    (``ALIGN_RATE_MAX_DEG_S``), they are turned forward no more than 0.2 deg
    (the turn was taken for that: 40 deg, and an encoder after a step of a
    held elbow 16 deg off stating 3)."""
    turned = math.radians(20.0)
    more, _ = kernels.ahead(100_000, 0, 5_000_000, turned, math.radians(0.3), ALIGN_SPAN_NS,
                            ALIGN_AHEAD_NS, ALIGN_CHANGE_PER_S, ALIGN_RATE_MAX_DEG_S,
                            math.inf)  # fmt: skip
    assert 0.0 < math.degrees(more) <= ALIGN_RATE_MAX_DEG_S * 0.2e-3 + 1e-9
    # 20 deg over 20 ms (1000 deg/s) is a rate: forward 5 ms, 5 deg
    more, _ = kernels.ahead(20_000_000, 0, 25_000_000, turned, math.radians(0.3), ALIGN_SPAN_NS,
                            ALIGN_AHEAD_NS, ALIGN_CHANGE_PER_S, ALIGN_RATE_MAX_DEG_S,
                            math.inf)  # fmt: skip
    assert math.degrees(more) == pytest.approx(5.0, abs=0.05)
