"""When the gateway's worker solves the bodies whose frames are whole.

Bodies solved in one call share the solver's fixed costs (``bodynet bench
--only solver``: about 350 us per body-tick alone, 106 in a batch of twenty).
Suits that are not phase-locked come whole one by one, so a worker that
solves each body the moment its frame is whole pays the single body's cost
for every tick, and at twenty bodies falls behind. So: while the worker has
time to spare it solves at once (the lowest latency); when it has been busy
for more than ``busy_on`` of its time, a whole frame waits for the round, at
most ``hold_s``, and every body whole by then is solved in the same call. It
stops holding when it is busy less than ``busy_off`` of its time.

Pure: the worker tells it when it slept and what the clock says.
"""

from __future__ import annotations

#: Share of a period a whole frame may wait for the round when the worker is busy:
#: bodies at random phases come whole every ``period / bodies`` on average, so at
#: twenty bodies a quarter of a period gathers about six of them.
HOLD_OF_PERIOD = 0.25
#: The worker's busy share (time not sleeping, over ``WINDOW_S``) above which it
#: holds frames for the round, and below which it stops.
BUSY_ON, BUSY_OFF = 0.5, 0.25
WINDOW_S = 0.1


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
