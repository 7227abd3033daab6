"""When the gateway's worker solves the bodies whose frames are whole.

Bodies solved in one call share the solver's fixed costs (``bodynet bench
--only solver``: about 240 us per body-tick alone, 85 in a batch of twenty).
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
period, or less for faster sources), at the phase of its slowest source, so
:func:`next_window` tells the worker when the next frame may come whole: it
polls in a window around that instant and sleeps through the rest.

Pure: the worker tells it when it slept and what the clock says.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

#: Share of a period a whole frame may wait for the round when the worker is busy:
#: bodies at random phases come whole every ``period / bodies`` on average, so at
#: twenty bodies a quarter of a period gathers about six of them.
HOLD_OF_PERIOD = 0.25
#: The worker's busy share (time not sleeping, over ``WINDOW_S``) above which it
#: holds frames for the round, and below which it stops.
BUSY_ON, BUSY_OFF = 0.5, 0.25
WINDOW_S = 0.1
#: How long before a body's frame is expected whole the worker starts polling
#: (nodes' sends are late by up to a millisecond each, so a frame comes whole up
#: to that much earlier than the last one did, a period on), and how long after
#: it keeps polling for a frame that has not come (then it is solved when its
#: oldest sample has waited a period, as frames that never come whole are).
EARLY_S, LATE_S = 0.0015, 0.004


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

    def slept(self, seconds: float) -> None:
        """The worker slept (waited for samples) this long."""
        self._idle += seconds

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


def next_window(now: float, bodies: Iterable[tuple[float | None, float, bool]],
                early_s: float = EARLY_S, late_s: float = LATE_S) -> float:  # fmt: skip
    """When the idle worker next has to poll for whole frames: ``now`` while a
    window is open, else when the next opens. ``bodies``: per body, when its
    last frame came whole (``None``: never), how long its frames come apart,
    and whether it holds samples not solved yet. A body's frames are expected
    whole that often after the last (windows from ``early_s`` before to
    ``late_s`` after each); one that has not come whole for a second, or
    never, and holds unsolved samples keeps the worker polling; one without
    unsolved samples needs no window."""
    opens = math.inf
    for whole_at, every, unsolved in bodies:
        if whole_at is None or now - whole_at > 1.0:
            if unsolved:
                return now
            continue
        if every <= early_s:  # frames as often as that: always about to come whole
            return now
        k = max(1, math.ceil((now - whole_at - late_s) / every))  # first window not closed
        start = whole_at + k * every - early_s
        if start <= now:
            return now
        opens = min(opens, start)
    return opens
