"""When the gateway's worker solves whole frames (gateway/rounds.py), driven with
explicit clock values: no sleeps, no timing asserted."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import pytest
import zenoh
from zenoh_helpers import client

from bodynet.core.messages import RawSample, Source
from bodynet.gateway.rounds import (
    EARLY_S,
    EARLY_WIDE_S,
    FRAMES,
    LATE_S,
    POLL_S,
    POLL_WIDE_S,
    Cadence,
    Rounds,
    next_poll,
)
from bodynet.gateway.service import Gateway
from bodynet.nodes.emulator import BodyEmulator, imu_tags
from bodynet.nodes.motion import ROUTINES

PERIOD = 0.01
STEP = 0.00025  # the worker's rounds in the driven feed


def test_frames_wait_for_the_round_only_while_the_worker_is_busy() -> None:
    rounds = Rounds(PERIOD, busy_on=0.5, busy_off=0.25, window_s=1.0)
    assert rounds.hold(0.0, 20) == 0.0  # no window measured yet: at once
    assert rounds.due(0.5, 0.5, 20)
    assert rounds.hold(1.0, 20) == rounds.hold_s == PERIOD / 4  # a window without sleep
    assert rounds.hold(1.0, 1) == 0.0  # one body: nothing to batch it with
    assert not rounds.due(1.0 + rounds.hold_s / 2, 1.0, 20)
    assert rounds.due(1.0 + rounds.hold_s, 1.0, 20)
    rounds.slept(0.625)  # busy 0.375 of the next window: between the two, it keeps holding
    assert rounds.hold(2.0, 20) == rounds.hold_s
    rounds.slept(0.875)  # busy 0.125: it stops
    assert rounds.hold(3.0, 20) == 0.0
    rounds.slept(0.625)  # busy 0.375: not enough to start again
    assert rounds.hold(4.0, 20) == 0.0
    assert rounds.busy == 0.375


def _feed(gw: Gateway, bodies: int, seconds: float) -> list[int]:
    """Feed ``bodies`` unsynchronised bodies (every node at its own phase, as the
    realistic feed of ``bodynet bench --only gateway`` does) to the worker's round
    with a clock stepping 0.25 ms at a time; the ticks each body got."""
    tags = imu_tags()
    readings, _ = BodyEmulator(ROUTINES["walk"], tags, seed=3).sample(0.2)
    rng = np.random.default_rng(7)
    made = [gw._body(f"s{b}") for b in range(bodies)]
    assert None not in made
    # each body at its own phase, each of its nodes at its own phase after that
    phases = rng.uniform(0, PERIOD, (bodies, 1)) + rng.uniform(0, PERIOD, (bodies, len(tags)))
    sent = np.zeros((bodies, len(tags)), dtype=int)
    for step in range(1, int(seconds / STEP) + 1):
        now = step * STEP
        touched = set()
        for b, body in enumerate(made):
            assert body is not None
            for i, tag in enumerate(tags):
                while phases[b, i] + sent[b, i] * PERIOD <= now:
                    t_ns = round((phases[b, i] + sent[b, i] * PERIOD) * 1e9)
                    body.take(tag.site, RawSample(readings[i], int(sent[b, i]), t_ns,
                                                  Source.IMU_CENTRAL), now)  # fmt: skip
                    sent[b, i] += 1
                    touched.add(body)
        gw._round(now, touched)
    return [body.ticks for body in made if body is not None]


def test_unsynchronised_bodies_get_every_tick_in_batches_when_the_worker_is_busy(
    router_endpoint: str,
) -> None:
    """A busy worker holds whole frames for the round and solves them together
    (batches of several bodies, not one by one), and still gives every body a
    tick every period: a sample taken while a whole frame waits counts for the
    next frame, not lost to the frame being solved."""
    seconds, bodies = 1.0, 6
    session = client(router_endpoint)
    results = {}
    try:
        for name, busy_on in (("holding", 0.0), ("at once", 2.0)):
            gw = Gateway(session, all_subjects=True)
            # busy_on 0: the worker counts as busy from the first window on; 2: never
            gw.rounds = Rounds(PERIOD, hold_s=PERIOD / 2, busy_on=busy_on, busy_off=0.0)
            try:
                ticks = _feed(gw, bodies, seconds)
                results[name] = (ticks, sum(ticks) / gw.solves)
            finally:
                gw.close()
    finally:
        session.close()
    for name, (ticks, _) in results.items():
        # a period to start (a new body waits one), then a tick every period (a sample
        # taken during the hold lost to the next frame cost 4 ticks in 100 here)
        assert min(ticks) >= 0.97 * seconds / PERIOD, (name, ticks)
    held, at_once = results["holding"][1], results["at once"][1]
    assert at_once < 1.5, results  # bodies at their own phases come whole one by one
    assert held >= 2.0, results  # the bodies whole within half a period, together


def test_a_body_a_whole_frame_behind_starts_afresh(router_endpoint: str) -> None:
    """Every site delivered twice before the solve (the worker a period late):
    the solve takes the newest, and the next frame needs new samples of every
    site, not a tick on the old ones."""
    tags = imu_tags()
    readings, _ = BodyEmulator(ROUTINES["walk"], tags, seed=4).sample(0.1)
    session: zenoh.Session = client(router_endpoint)
    gw = Gateway(session)
    try:
        body = gw._bodies[None]
        body.ticks = 1  # past its first tick
        for k in range(2):
            for tag, reading in zip(tags, readings, strict=True):
                body.take(tag.site, RawSample(reading, k, k, Source.IMU_CENTRAL), 0.001 * k)
        assert body.frame_complete(0.002)
        body.snapshot(0.002)
        assert body.ready_sites == 0
        body.take(tags[0].site, RawSample(readings[0], 2, 2, Source.IMU_CENTRAL), 0.01)
        assert not body.frame_complete(0.01)
        # one site twice (a node early), the others once: its second counts for the next
        for tag, reading in zip(tags[1:], readings[1:], strict=True):
            body.take(tag.site, RawSample(reading, 2, 2, Source.IMU_CENTRAL), 0.011)
        body.take(tags[0].site, RawSample(readings[0], 3, 3, Source.IMU_CENTRAL), 0.012)
        assert body.frame_complete(0.012)
        body.snapshot(0.012)
        assert body.ready_sites == 1
        assert not body.frame_complete(0.013)
        for tag, reading in zip(tags[1:], readings[1:], strict=True):
            body.take(tag.site, RawSample(reading, 3, 3, Source.IMU_CENTRAL), 0.02)
        assert body.frame_complete(0.02)  # tags[0] delivered for this frame already
    finally:
        gw.close()
        session.close()


def cadence_of(instants: Sequence[float]) -> Cadence:
    cadence = Cadence(PERIOD)
    for t in instants:
        cadence.whole(t)
    return cadence


def next_window(now: float, bodies: Sequence[tuple[Cadence, bool]]) -> float:
    """When the first of ``bodies``' windows opens (``now`` while one is open)."""
    return min((cadence.window(now, unsolved) for cadence, unsolved in bodies),
               default=float("inf"))  # fmt: skip


def test_next_window_opens_around_each_expected_whole_frame() -> None:
    inf = float("inf")
    assert next_window(5.0, []) == inf  # no body: nothing to poll for
    assert next_window(5.0, [(Cadence(PERIOD), True)]) == 5.0  # never whole, samples waiting
    assert next_window(5.0, [(Cadence(PERIOD), False)]) == inf
    steady = cadence_of([PERIOD * k for k in range(101)])  # whole every period up to 1.0
    assert next_window(2.5, [(steady, True)]) == 2.5  # not whole for a second: poll
    assert steady.every == pytest.approx(PERIOD)
    assert np.isclose(next_window(1.001, [(steady, True)]), 1.01 - EARLY_S)
    assert next_window(1.01 - EARLY_S / 2, [(steady, True)]) == 1.01 - EARLY_S / 2
    assert next_window(1.01 + LATE_S / 2, [(steady, True)]) == 1.01 + LATE_S / 2
    # past the window: the frame after next (a body solved when its oldest sample waited)
    assert np.isclose(next_window(1.01 + 2 * LATE_S, [(steady, True)]), 1.02 - EARLY_S)
    # the soonest of two bodies
    later = cadence_of([PERIOD * k + 0.003 for k in range(101)])
    assert np.isclose(next_window(1.001, [(steady, True), (later, False)]), 1.01 - EARLY_S)
    # while few frames are known, the wider margin
    young = cadence_of([0.97, 0.98, 0.99, 1.0])
    assert np.isclose(next_window(1.001, [(young, True)]), 1.01 - EARLY_WIDE_S)
    # frames that come whole more often than the early margin: always about to
    fast = cadence_of([1.0 + k * EARLY_S / 2 for k in range(20)])
    assert next_window(fast.at + 1e-5, [(fast, False)]) == fast.at + 1e-5


def test_the_worker_polls_a_steady_frame_closely_and_others_every_millisecond() -> None:
    """While a ``regular`` body's window is open the worker looks every POLL_S;
    while only other bodies' are (a bridge's batches come whole at no steady
    instant), every POLL_WIDE_S, or at a regular body's window if that opens
    sooner; outside every window, when the next opens."""
    inf = float("inf")
    assert next_poll(5.0, []) == inf
    assert next_poll(5.0, [(Cadence(PERIOD), False)]) == inf
    assert next_poll(5.0, [(Cadence(PERIOD), True)]) == 5.0 + POLL_S  # never whole yet
    steady = cadence_of([PERIOD * k for k in range(101)])
    assert steady.regular
    assert np.isclose(next_poll(1.001, [(steady, True)]), 1.01 - EARLY_S)  # closed: its start
    assert next_poll(1.01, [(steady, True)]) == 1.01 + POLL_S
    rng = np.random.default_rng(5)
    batched = cadence_of(np.cumsum(rng.uniform(0.006, 0.013, 100)))  # 6-13 ms apart
    assert not batched.regular
    at = batched.earliest + batched.every  # when it may come whole next
    assert batched.window(at, True) == at  # its window is open
    assert next_poll(at, [(batched, True)]) == at + POLL_WIDE_S
    # a regular body's window opening sooner than the wide poll
    opens = at + POLL_WIDE_S / 2
    soon = cadence_of([opens + EARLY_S - PERIOD * k for k in range(100, 0, -1)])
    assert soon.regular
    assert np.isclose(next_poll(at, [(batched, True), (soon, True)]), opens)
    assert next_poll(opens, [(batched, True), (soon, True)]) == opens + POLL_S
    # frames every millisecond or two: as closely as a regular body's (wide polls
    # would merge them)
    fast = cadence_of([1.0 + k * 0.0015 for k in range(40)])
    assert not fast.regular
    assert next_poll(fast.at + 0.0015, [(fast, True)]) == fast.at + 0.0015 + POLL_S


def test_a_cadence_polls_from_the_earliest_instant_its_frames_come_whole() -> None:
    """Frames come whole at the phase of the slowest source plus up to a
    millisecond of jitter: the window opens before the earliest of those, not
    the last; a frame that never came whole does not halve the cadence; a
    source slower than the gateway's clock, or restarted at a later phase, is
    followed; and a window never opens after a frame came whole."""
    rng = np.random.default_rng(3)
    jitter = rng.uniform(0.0, 0.001, 300)
    instants = [0.5 + PERIOD * k + jitter[k] for k in range(300) if k % 37 != 5]  # some lost
    cadence = cadence_of(instants[:-1])
    assert cadence.every == pytest.approx(PERIOD, abs=1e-5)
    last = instants[-2]
    start = next_window(last + 0.001, [(cadence, True)])
    # from the envelope (about the least jitter seen), not from the last frame's instant
    assert start == pytest.approx(0.5 + PERIOD * 299 + jitter.min() - EARLY_S, abs=2.5e-4)
    assert start <= instants[-1]
    # sources 500 ppm slower or faster than the gateway's clock, then restarted 3 ms
    # later in the period: never a frame before its window
    for rate in (1.0005, 0.9995):
        drifting = [0.5 + PERIOD * rate * k + jitter[k] for k in range(300)]
        jumped = drifting + [drifting[-1] + 0.003 + PERIOD * rate * (k + 1) + jitter[k]
                             for k in range(200)]  # fmt: skip
        cadence = Cadence(PERIOD)
        for t, after in itertools.pairwise(jumped):
            cadence.whole(t)
            assert next_window(t + 1e-6, [(cadence, True)]) <= after
        assert cadence.every == PERIOD
    # the envelope forgets a frame FRAMES periods on: one early frame, then late ones
    early = [1.0] + [1.0 + PERIOD * k + 0.0005 for k in range(1, FRAMES + 10)]
    cadence = cadence_of(early[: FRAMES // 2])
    assert cadence.regular
    assert cadence.earliest == pytest.approx(early[FRAMES // 2 - 1] - 0.0005)
    cadence = cadence_of(early)
    assert cadence.earliest == pytest.approx(early[-1])
    # frames at another rate than the gateway's: measured, polled from the wider margin
    other = cadence_of([0.5 + 0.004 * k + jitter[k] / 10 for k in range(40)])
    assert other.every == pytest.approx(0.004, abs=1e-4)
    assert next_window(other.at + 1e-6, [(other, True)]) <= other.at + 0.004 - EARLY_WIDE_S + 1e-4


@pytest.mark.parametrize(
    ("every", "wakes_per_tick"),
    [(PERIOD, 7), (PERIOD * 1.0005, 7), (PERIOD / 10, None)],
)
def test_the_idle_worker_sleeps_between_whole_frames_and_misses_none(
    router_endpoint: str, every: float, wakes_per_tick: float | None
) -> None:
    """The worker driven as it runs, on a simulated clock: each round takes what
    has come, and an idle worker sleeps as long as ``_idle_until`` says. One
    body with its nodes at their own phases, sending every ``every`` and late
    by up to a millisecond (a tenth of that at 1000 Hz) each time: every frame
    is solved (at 1000 Hz too, where frames come whole ten times a tick),
    each whole one within a poll of its last sample, and at 100 Hz the worker
    wakes a few times a period, not every 0.3 ms (8 a tick when it polled from
    a millisecond and a half before the last frame's instant a period on; about
    5.5 polling from the earliest seen). A round that takes part of a frame
    sleeps as an empty one does (``Gateway.run``). Also with the nodes' clocks
    slower than the gateway's (500 ppm)."""
    tags = imu_tags()
    readings, _ = BodyEmulator(ROUTINES["walk"], tags, seed=5).sample(0.2)
    rng = np.random.default_rng(11)
    seconds = 1.0
    frames = round(seconds / every)
    phases = rng.uniform(0, every, len(tags))
    late = min(1e-3, every / 10)
    sends = sorted(
        (phases[i] + k * every + rng.uniform(0, late), i, k)
        for i in range(len(tags))
        for k in range(frames)
    )  # fmt: skip
    session = client(router_endpoint)
    gw = Gateway(session)
    try:
        body = gw._bodies[None]
        now, nxt, wakes, delays, last = 0.0, 0, 0, [], 0.0
        while nxt < len(sends):
            touched = set()
            while nxt < len(sends) and sends[nxt][0] <= now:
                t, i, k = sends[nxt]
                body.take(tags[i].site, RawSample(readings[i], k, round(t * 1e9),
                                                  Source.IMU_CENTRAL), now)  # fmt: skip
                last, nxt = t, nxt + 1
                touched.add(body)
            ticks = body.ticks
            acted, wake = gw._round(now, touched)
            if body.ticks > ticks and body.cadence.at == now:
                delays.append(now - last)  # a whole frame solved: after its last sample
            if not acted:  # as Gateway.run: a cut-short take aside (none here)
                wakes += 1
                now = max(gw._idle_until(now, wake, True), now + 1e-6)
    finally:
        gw.close()
        session.close()
    assert body.ticks >= 0.97 * frames, (body.ticks, frames)  # the first waits a period
    assert len(delays) >= 0.9 * frames  # nearly every tick a whole frame
    # within a poll of its last sample: the close one once the cadence is regular
    assert max(delays) <= POLL_WIDE_S + 1e-9, max(delays)
    if every == PERIOD:
        assert max(delays[FRAMES:]) <= POLL_S + 1e-9, max(delays[FRAMES:])
    if wakes_per_tick is not None:
        assert wakes / body.ticks < wakes_per_tick, wakes / body.ticks  # polling: about 33
