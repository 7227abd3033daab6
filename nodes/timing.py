"""When emulated nodes send: their timers, clock errors, jitter and losses.

Real sensing nodes are not phase-locked. SmartSuit nodes on a CAN bus each run
on a timer of their own: each sends at its own phase in the period, and its
clock is off by up to ~100 ppm; every send is late by up to about a
millisecond (the node's firmware, the bus, the host); now and then a frame is
lost. A serial receiver (the IMU central) prints its lines one after another
on one clock. This module says when such senders send, with no I/O: the
hardware emulators (``nodes.hardware``) put their frames on real transports at
these times, and the gateway benchmark's feeder (``bench.gateway``) publishes
on Zenoh at them.

- :class:`LinkTiming`: how a link's timing falls short of an ideal one.
- :func:`feed_schedule`: the benchmark's feeds, many bodies at once.
- :class:`Sends`: a heap of each sender's next send, late by its jitter.
- :class:`NodeTimers`: the sends of one device's nodes, and which are lost.
- :class:`Clock`: the emulators' shared time, and its times on the wall clock.
"""

from __future__ import annotations

import heapq
import math
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

LINE_S = 55 * 10 / 230_400  # one IMU-central line at 230,400 baud (55 bytes, 8N1)
JITTER_S = 1e-3  # a send is late by up to this much (OS and radio)
DRIFT_PPM = 100.0  # each node's own timer runs this much fast or slow at most

#: (offset, period) in seconds: when a sender first sends after the start, and how often
Timer = tuple[float, float]


class Timers(StrEnum):
    """Whose clock a device's nodes send on."""

    LOCKED = "locked"  # one for all: every node in the same instant, every period
    INDEPENDENT = "independent"  # each its own: own phase in the period, own clock error


@dataclass(frozen=True, slots=True)
class LinkTiming:
    """How the timing of emulated nodes' link falls short of an ideal one.

    ``timers``: ``LOCKED`` nodes all send in the same instant every period;
    ``INDEPENDENT`` ones each at a phase of its own, drawn in the period, on a
    clock off by a rate drawn within +/- ``clock_ppm``. ``jitter_s``: each send is
    late by a time drawn in [0, ``jitter_s``]. ``drop``: the probability a frame
    (a CAN frame, an IMU tag's notification, a SlimeVR tracker's rotation, a
    concentrator's reply) is lost. ``late``: the probability a polled device
    (the Data Concentrator) answers a request only after the bridge's reply
    timeout. ``reorder``: the
    probability a datagram (UDP: a SlimeVR tracker's rotation) is overtaken by
    the one after it. ``seed`` makes the draws repeatable. The default is the
    ideal link: lock-step, no jitter, no loss; :meth:`realistic` is healthy
    real hardware."""

    timers: Timers = Timers.LOCKED
    clock_ppm: float = DRIFT_PPM
    jitter_s: float = 0.0
    drop: float = 0.0
    late: float = 0.0
    seed: int = 0
    reorder: float = 0.0

    def __post_init__(self) -> None:
        for name in ("clock_ppm", "jitter_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, not {value}")
        for name in ("drop", "late", "reorder"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} is a probability (0 to 1), not {value}")

    @classmethod
    def ideal(cls) -> LinkTiming:
        """Lock-step, no jitter, nothing lost or late (the default)."""
        return cls()

    @classmethod
    def realistic(cls, seed: int = 0) -> LinkTiming:
        """Healthy real hardware: independent timers (up to ``DRIFT_PPM``) and sends
        late by up to ``JITTER_S``; nothing lost or late."""
        return cls(Timers.INDEPENDENT, DRIFT_PPM, JITTER_S, seed=seed)

    def draws(self) -> np.random.Generator:
        """The generator of the per-send draws (jitter, losses, late replies)."""
        return np.random.default_rng([self.seed, 1])

    def of(self, part: int) -> LinkTiming:
        """This timing for one of several devices on the link (a SlimeVR tracker, an
        IMU central beside its tags), with draws of its own: the same seed would
        give each the same phase and the same losses."""
        seed = int(np.random.SeedSequence([self.seed, part]).generate_state(1)[0])
        return replace(self, seed=seed)


def independent_timers(rng: np.random.Generator, nodes: int, period_s: float,
                       clock_ppm: float = DRIFT_PPM) -> list[Timer]:  # fmt: skip
    """``nodes`` timers of their own: each an offset drawn in the period and a
    period off by a rate drawn within +/- ``clock_ppm``."""
    offsets = rng.uniform(0, period_s, nodes)
    periods = period_s * (1 + rng.uniform(-clock_ppm, clock_ppm, nodes) * 1e-6)
    return [(float(o), float(p)) for o, p in zip(offsets, periods, strict=True)]


def link_schedule(nodes: int, period_s: float, timing: LinkTiming) -> list[Timer]:
    """The timers of one device's ``nodes`` as ``timing`` says: all at once, or
    each its own (:func:`independent_timers`, drawn from ``timing.seed``)."""
    if timing.timers is Timers.LOCKED:
        return [(0.0, period_s)] * nodes
    return independent_timers(np.random.default_rng(timing.seed), nodes, period_s,
                              timing.clock_ppm)  # fmt: skip


def feed_schedule(bodies: range, nodes: int, rate_hz: float, feed: str,
                  seed: int = 0) -> list[Timer]:  # fmt: skip
    """When each node of each body first sends, and its own period, in seconds:
    ``(offset, period)`` per (body, node), bodies in order, nodes in order.

    ``locked``: every node of every body at once, every period (the gateway's
    best case). ``realistic``: as real suits are: each body at its own phase;
    even bodies are CAN suits, each node on its own timer (own phase in the
    period, own clock error up to ``DRIFT_PPM``); odd bodies are serial
    receivers, whose lines go out one after another (``LINE_S`` apart, spread
    over the period when they do not fit). Jitter is added per send (:class:`Sends`)."""
    period = 1.0 / rate_hz
    if feed == "locked":
        return [(0.0, period) for _ in bodies for _ in range(nodes)]
    rng = np.random.default_rng(seed + bodies.start)
    out = []
    for b in bodies:
        phase = float(rng.uniform(0, period))
        if b % 2 == 0:  # CAN: independent node timers
            timers = independent_timers(rng, nodes, period)
        else:  # serial receiver: line after line, one clock
            step = min(LINE_S, period / nodes)
            timers = [(k * step, period) for k in range(nodes)]
        out += [(phase + o, p) for o, p in timers]
    return out


class Sends:
    """When each of a set of periodic senders sends next: a heap of ``(due,
    sender, tick)``. Sender ``i`` sends its tick ``k`` at ``start + offset + k *
    period`` (``schedule[i]``), every tick but the first late by a time drawn in
    [0, ``jitter_s``] from ``rng``; no tick after the first is due at or after
    ``end``. Senders due at the same time come in their order."""

    def __init__(
        self,
        schedule: Sequence[Timer],
        start: float,
        jitter_s: float = 0.0,
        rng: np.random.Generator | None = None,
        end: float = math.inf,
    ) -> None:
        if jitter_s and rng is None:
            raise ValueError("jitter needs a generator to draw it from")
        self._schedule = list(schedule)
        self.start, self.end = start, end
        self._jitter_s = jitter_s
        self._rng = rng if rng is not None else np.random.default_rng(0)  # unused: no jitter
        self._due = [(start + offset, i, 0) for i, (offset, _) in enumerate(self._schedule)]
        heapq.heapify(self._due)

    def __bool__(self) -> bool:
        return bool(self._due)

    @property
    def next_due(self) -> float:
        """When the next send is due (``inf`` when none is left)."""
        return self._due[0][0] if self._due else math.inf

    def pop(self) -> tuple[float, int, int]:
        """The next send, ``(due, sender, tick)``; that sender's following one is queued."""
        due, i, tick = heapq.heappop(self._due)
        offset, period = self._schedule[i]
        nxt = self.start + offset + (tick + 1) * period
        if nxt < self.end:
            late = float(self._rng.uniform(0, self._jitter_s)) if self._jitter_s else 0.0
            heapq.heappush(self._due, (nxt + late, i, tick + 1))
        return due, i, tick


class NodeTimers:
    """The sends of one device's ``nodes`` every ``period_s`` as ``timing`` says
    (:func:`link_schedule`, :class:`Sends`), and which of them are lost.

    :meth:`due` gives the nodes whose frame is due; a frame lost on the way
    (probability :attr:`drop`, or any while the node is silenced: :meth:`silence`)
    is not among them but counted in :attr:`dropped`. :attr:`drop` starts as
    ``timing.drop`` and may be changed while the device runs (a test turns
    losses off to let a receiver's counts settle)."""

    def __init__(self, nodes: Sequence[int], period_s: float, timing: LinkTiming) -> None:
        self.nodes = list(nodes)
        self.period_s = period_s
        self.timing = timing
        self.schedule = link_schedule(len(self.nodes), period_s, timing)
        self.drop = timing.drop
        #: frames lost, by node
        self.dropped: Counter[int] = Counter()
        self._rng = timing.draws()
        self._sends = Sends(self.schedule, 0.0, timing.jitter_s, self._rng)
        self._silent: dict[int, tuple[float, float]] = {}  # node -> [from, until)

    def silence(self, node: int, start: float, seconds: float) -> None:
        """Lose every frame of ``node`` due from ``start`` for ``seconds`` (a tag
        out of range, a tracker behind a wall, a node's connector working loose):
        an outage, where :attr:`drop` loses frames one at a time."""
        if node not in self.nodes:
            raise ValueError(f"node {node} is not one of {self.nodes}")
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"seconds must be a finite number >= 0, not {seconds}")
        self._silent[node] = (start, start + seconds)

    def _lost(self, node: int, due: float) -> bool:
        start, until = self._silent.get(node, (0.0, 0.0))
        if start <= due < until:
            return True
        return bool(self.drop) and self._rng.random() < self.drop

    def start(self, now: float) -> None:
        """The nodes are switched on at ``now`` (monotonic seconds): each first
        sends at its offset after it."""
        self._sends = Sends(self.schedule, now, self.timing.jitter_s, self._rng)

    @property
    def next_due(self) -> float:
        return self._sends.next_due

    def due(self, now: float, lossy: bool = True) -> list[int]:
        """The nodes whose send is due by ``now``, in the order they came due (a
        node more than once if its sends fell behind); with ``lossy``, the frames
        lost are left out and counted, without it (nothing listens) none is."""
        return [node for node, _ in self.due_at(now, lossy)]

    def due_at(self, now: float, lossy: bool = True) -> list[tuple[int, float]]:
        """:meth:`due`, each node with when its send was due (monotonic)."""
        out = []
        while self._sends.next_due <= now:
            due, i, _ = self._sends.pop()
            node = self.nodes[i]
            if lossy and self._lost(node, due):
                self.dropped[node] += 1
            else:
                out.append((node, due))
        return out


class Clock:
    """Seconds since ``t0`` on the monotonic clock; shared so emulators agree.

    :meth:`wall_ns` gives one of its times on the wall clock, by an offset read
    once: a thread stalled between reading the two clocks (a loaded host) would
    otherwise put a reading's truth later than the body it sampled."""

    def __init__(self, t0: float | None = None) -> None:
        self.t0 = time.monotonic() if t0 is None else t0
        self._wall_s = time.time() - time.monotonic() + self.t0  # ``t0`` on the wall clock

    def now(self) -> float:
        return time.monotonic() - self.t0

    def wall_ns(self, t: float) -> int:
        """This clock's time ``t`` (s) on the wall clock (ns since the epoch)."""
        return round((self._wall_s + t) * 1e9)
