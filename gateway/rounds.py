"""When the gateway's worker solves the bodies whose frames are whole.

Bodies solved in one call share the solver's fixed costs (``bodynet bench
--only solver``, 2026-12-07: about 75 us per body-tick alone, 55 in a batch
of twenty, back to back; once a period, as live, some 400 and 80).
Suits that are not phase-locked come whole one by one, so a worker that
solves each body the moment its frame is whole pays the single body's cost
for every tick, and at twenty bodies falls behind. So: while the worker has
time to spare it solves at once (the lowest latency); when it has been busy
for more than ``busy_on`` of its time, a whole frame waits for the round, at
most ``hold_s``, and every body whole by then is solved in the same call. It
stops holding when it is busy less than ``busy_off`` of its time.

Between rounds the idle worker sleeps; each wake costs a context switch (about
16 us of CPU here, more under load), and polling every 0.3 ms was 40% of one
body's worker. A body's frames come whole as often as its sources deliver (a
period, or less for faster sources), at the phase of its slowest source plus
that source's jitter, so its :class:`Cadence` tells the worker when the next
frame may come whole (the earliest such instant seen, a frame on), a window
of polls opens there (:func:`next_poll`: every 0.3 ms in the window of a body
whose frames come whole at a steady instant, or every 2 ms or more often;
every 1 ms in others'), and the worker sleeps through the rest.

Pure: the worker tells it when it slept and what the clock says.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable

#: Share of a period a whole frame may wait for the round when the worker is busy:
#: bodies at random phases come whole every ``period / bodies`` on average, so at
#: twenty bodies a quarter of a period gathers about six of them.
HOLD_OF_PERIOD = 0.25
#: The worker's busy share (time not sleeping, over ``WINDOW_S``) above which it
#: holds frames for the round, and below which it stops.
BUSY_ON, BUSY_OFF = 0.5, 0.25
WINDOW_S = 0.1
#: How long before a body's frame is expected whole the worker starts polling:
#: for frames that come whole at the gateway's period, :class:`Cadence` expects
#: them at the earliest instant seen, so this covers the sources' clocks against
#: ours (500 ppm over the periods it looks at: 0.16 ms); for others, and while
#: few frames are known, the wider margin (nodes' sends are late by up to a
#: millisecond each). How long after it keeps polling for a frame that has not
#: come (then it is solved when its oldest sample has waited a period, as frames
#: that never come whole are).
EARLY_S, EARLY_WIDE_S, LATE_S = 0.0003, 0.0015, 0.004
#: How often the idle worker looks while a window is open: a ``regular`` body's
#: frame is expected within a fraction of a millisecond, others' (a bridge's
#: batches, which a 5 ms window starts at no steady instant; sources at another
#: rate) anywhere in several, where looking every 0.3 ms would find the frame at
#: most 0.7 ms sooner for some 15% more of one body's CPU (docs/benchmarks.md,
#: 2026-12-07).
POLL_S, POLL_WIDE_S = 0.0003, 0.001
#: How many of its last intervals a body's cadence looks at (and periods: the
#: earliest instant of their frames, carried on), and how many intervals it
#: needs before it is trusted.
FRAMES, FRAMES_KNOWN = 32, 8


class Rounds:
    """Whether a whole frame is solved now or waits for the round (see the module
    docstring). ``slept(s)`` after each sleep; ``hold(now, bodies)`` says how long a
    whole frame may wait now; ``due(now, since, bodies)`` whether a frame whole
    since ``since`` is to be solved now."""

    def __init__(self, period_s: float, hold_s: float | None = None,
                 busy_on: float = BUSY_ON, busy_off: float = BUSY_OFF,
                 window_s: float = WINDOW_S) -> None:  # fmt: skip
        self.hold_s = HOLD_OF_PERIOD * period_s if hold_s is None else hold_s
        self.busy_on, self.busy_off, self.window_s = busy_on, busy_off, window_s
        self.holding = False
        self.busy = 0.0  # the busy share of the last whole window
        self._start: float | None = None
        self._idle = 0.0
        self.sleeps = 0  # how often the worker slept (each ends in a wake)

    def slept(self, seconds: float) -> None:
        """The worker slept (waited for samples) this long."""
        self._idle += seconds
        self.sleeps += 1

    def hold(self, now: float, bodies: int) -> float:
        """How long a whole frame may wait for the round now: 0 while the worker
        is not busy, or serves one body (nothing to batch it with)."""
        if self._start is None:
            self._start = now
        elif now - self._start >= self.window_s:
            self.busy = max(0.0, 1.0 - self._idle / (now - self._start))
            if self.busy >= self.busy_on:
                self.holding = True
            elif self.busy < self.busy_off:
                self.holding = False
            self._start, self._idle = now, 0.0
        return self.hold_s if self.holding and bodies > 1 else 0.0

    def due(self, now: float, since: float, bodies: int) -> bool:
        """Is a frame whole since ``since`` to be solved now?"""
        return now >= since + self.hold(now, bodies)


class Cadence:
    """When a body's frames come whole: ``whole(now)`` each time one does.

    A frame comes whole at the phase of the body's slowest source plus that
    source's jitter (sends late by up to a millisecond, and the worker's poll).
    While its last ``FRAMES`` intervals were each a whole number of the
    gateway's periods, give or take ``EARLY_WIDE_S`` (``regular``), the instant
    to poll from is the lower envelope of those instants, not the last of them:
    ``earliest`` is the earliest of the frames of its last ``FRAMES`` periods,
    each carried on to the last frame by whole periods. Otherwise (sources at
    another rate, or frames that come whole out of step, as when a frame solved
    on its wait leaves the next whole early) the last instant, with ``every``
    the last interval (at most a period) and the wider margin. Each frame costs
    a few operations, not a pass over the frames kept (twenty bodies whole a
    hundred times a second each)."""

    __slots__ = ("_index", "_irregular", "_lows", "_steps", "at", "earliest", "every",
                 "period_s", "regular")  # fmt: skip

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.at: float | None = None  # when the last frame came whole
        self.earliest = 0.0  # the instant the next frames are expected whole from
        self.every = 0.0  # how often they come whole (0: not known)
        self.regular = False
        self._index = 0  # periods since the first frame, as the intervals count them
        # whether each of the last intervals was a whole number of periods, and how
        # many were not
        self._steps: deque[bool] = deque(maxlen=FRAMES)
        self._irregular = 0
        # (period index, instant less that many periods) of the frames that may still
        # be the earliest, their offsets increasing: the window's minimum is first
        self._lows: deque[tuple[int, float]] = deque()

    def whole(self, now: float) -> None:
        """A frame came whole at ``now``."""
        period, steps, lows = self.period_s, self._steps, self._lows
        if self.at is not None:
            interval = now - self.at
            periods = round(interval / period)
            step = periods >= 1 and abs(interval - periods * period) <= EARLY_WIDE_S
            if len(steps) == FRAMES and not steps[0]:
                self._irregular -= 1
            steps.append(step)
            if not step:
                self._irregular += 1
                lows.clear()  # out of step: the envelope starts again
            self._index += max(1, periods)
            self.every = min(interval, period)
        self.at = self.earliest = now
        index = self._index
        offset = now - index * period
        while lows and lows[-1][1] >= offset:
            lows.pop()
        lows.append((index, offset))
        while lows[0][0] <= index - FRAMES:
            lows.popleft()
        self.regular = len(steps) >= FRAMES_KNOWN and not self._irregular
        if self.regular:
            self.every = period
            self.earliest = lows[0][1] + index * period

    def window(self, now: float, unsolved: bool) -> float:
        """When the idle worker has to poll for this body's next whole frame:
        ``now`` while a window is open, else when the next opens. Windows run
        from ``EARLY_S`` before each expected instant (``EARLY_WIDE_S`` unless
        ``regular``) to ``LATE_S`` after. A body that has not come whole for a
        second, or never, and holds unsolved samples (``unsolved``) keeps the
        worker polling; one without unsolved samples needs no window."""
        if self.at is None or now - self.at > 1.0:
            return now if unsolved else math.inf
        early_s = EARLY_S if self.regular else EARLY_WIDE_S
        every = self.every
        if every <= early_s:  # frames as often as that: always about to come whole
            return now
        k = max(1, math.ceil((now - self.earliest - LATE_S) / every))  # first window not closed
        start = self.earliest + k * every - early_s
        return now if start <= now else start


def next_poll(now: float, bodies: Iterable[tuple[Cadence, bool]]) -> float:
    """When the idle worker next looks for whole frames of ``bodies`` (each
    one's cadence, and whether it holds unsolved samples: :meth:`Cadence.window`):
    ``POLL_S`` on while the window of a ``regular`` body, or of one whose frames
    come whole every few milliseconds or not yet at all, is open; ``POLL_WIDE_S``
    on while only other bodies' are (or sooner, where one of the first opens);
    else when the next window opens."""
    opens, wide = math.inf, False
    for cadence, unsolved in bodies:
        start = cadence.window(now, unsolved)
        if start > now:
            opens = min(opens, start)
        elif cadence.regular or cadence.every < 2 * POLL_WIDE_S:
            return now + POLL_S  # (frames as often as that would merge in wide polls)
        else:
            wide = True
    return min(opens, now + POLL_WIDE_S) if wide else opens
