"""One body's sites as rows of arrays, and the frame a solve takes from them.

The gateway keeps what it needs of each site's latest sample, its frame
accounting and its recent orientations in a row of :class:`Columns`, which the
compiled intake (``kernels.take_batch``, ``kernels.take_messages``) writes a
whole batch or round of samples into in one call: no Python object per sample.
A solve takes a :class:`Frame`: a copy of the rows, read as the mapping of
site -> :class:`RawSample` every consumer of samples knows, whose samples are
made only when one is read (the solver reads the arrays).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping

import numpy as np

from bodynet.core.codecs import raw_sample
from bodynet.core.keys import Site
from bodynet.core.messages import Quat, RawSample

# the integer columns: the latest quaternion sample's fields (SOURCE: its id);
# PENDING: the latest came through the compiled intake, its sample not made yet;
# QUAT: the site's latest is a quaternion (the compiled intake takes only those);
# the frame's accounting (OWED, FRESH: see gateway/service.py's _Body); LEFT: samples
# until the site's Rhythm ends a run, ENDED: it has (its run's end is Python's); the
# round its latest came in (ROUND); the recent orientations' ring (HEAD, COUNT)
T_NS, NODE, SEQ, SOURCE, PENDING, QUAT, OWED, FRESH, LEFT, ENDED, ROUND, HEAD, COUNT = range(13)
INTS = 13
# the float columns: the latest quaternion (W..Z, 4 columns), its arrival (monotonic
# s), the age past which it is stale (the Rhythm's after_s), the sample time of the
# ring's newest entry (s), the clock lead of this window (s, see gateway/service.py)
W, ARRIVED, AFTER, KEPT_AT, LEAD = 0, 4, 5, 6, 7
FLOATS = 8
# the body's tally: samples taken, sites turned unsolved, sites turned ready, runs ended
SAMPLES, UNSOLVED, READY, RUNS = range(4)
TALLY = 4


class Columns:
    """A body's sites, a row each in the order they came (rows are never
    removed): ``ints`` and ``floats`` (the columns above), ``history`` (each
    row's recent orientations, a ring of ``(sample time s, w, x, y, z)`` kept
    every ``step_s`` of sample time) and ``tally``. ``keys`` and ``ends``: the
    rows' raw keys (without a subject) as bytes end to end, for the compiled
    intake to find a batch entry's row; ``flags``: a byte a row, for a kernel's
    answer (``kernels.settle_rows``)."""

    __slots__ = ("depth", "ends", "flags", "floats", "history", "ints", "keys", "n", "tally")

    def __init__(self, depth: int, capacity: int = 16) -> None:
        self.n = 0
        self.depth = depth  # the ring's length
        self.ints = np.zeros((capacity, INTS), dtype=np.int64)
        self.floats = np.zeros((capacity, FLOATS))
        self.history = np.zeros((capacity, depth, 5))
        self.tally = np.zeros(TALLY, dtype=np.int64)
        self.flags = np.zeros(capacity, dtype=np.uint8)  # a row each, for a kernel's answer
        self.keys = np.zeros(0, dtype=np.uint8)
        self.ends = np.zeros(0, dtype=np.int64)

    def add(self, raw_key: str, after_s: float) -> int:
        """A new site's row (its key as a batch names it)."""
        row = self.n
        if row == len(self.ints):
            grow = 2 * row
            self.ints = np.resize(self.ints, (grow, INTS))  # the new rows filled below
            self.floats = np.resize(self.floats, (grow, FLOATS))
            self.history = np.concatenate([self.history, np.zeros_like(self.history)])
            self.flags = np.zeros(grow, dtype=np.uint8)
        self.ints[row] = 0
        self.floats[row] = 0.0
        self.floats[row, AFTER] = after_s
        self.floats[row, KEPT_AT] = self.floats[row, LEAD] = -math.inf
        key = np.frombuffer(raw_key.encode("ascii"), dtype=np.uint8)
        self.keys = np.concatenate([self.keys, key])
        self.ends = np.append(self.ends, len(self.keys))
        self.n = row + 1
        return row

    def recent(self, row: int, span_s: float) -> list[tuple[float, float, float, float, float]]:
        """Row ``row``'s ring, oldest first, within ``span_s`` of its newest."""
        count, head = int(self.ints[row, COUNT]), int(self.ints[row, HEAD])
        ring = self.history[row]
        order = np.arange(head - count, head) % self.depth
        entries = ring[order]
        if count:
            entries = entries[entries[-1, 0] - entries[:, 0] <= span_s]
        return [tuple(e) for e in entries.tolist()]

    def made(self, row: int) -> RawSample:
        """The sample of row ``row``'s numbers (its latest quaternion's)."""
        return _made(self.ints[row], self.floats[row])


def _made(ints: np.ndarray, floats: np.ndarray) -> RawSample:
    node, seq, t_ns, source = ints[[NODE, SEQ, T_NS, SOURCE]].tolist()
    w, x, y, z = floats[W : W + 4].tolist()
    return raw_sample.of_fields((node, seq, t_ns, source, w, x, y, z))  # what decode gives


class Frame(Mapping[Site, RawSample]):
    """What one solve of one body takes: each site's latest sample, as arrays
    (``ints`` and ``floats``, the rows of :class:`Columns` at the time) and as
    the mapping site -> :class:`RawSample`. ``kinds``: each row's reading's
    type; ``objects``: each row's sample, made from the arrays when first
    read if PENDING says the arrays hold a newer one."""

    __slots__ = ("_index", "floats", "ints", "kinds", "objects", "sites")

    def __init__(self, sites: tuple[Site, ...], index: Mapping[Site, int],
                 kinds: tuple[type, ...], ints: np.ndarray, floats: np.ndarray,
                 objects: list[RawSample]) -> None:  # fmt: skip
        self.sites, self._index, self.kinds = sites, index, kinds
        self.ints, self.floats, self.objects = ints, floats, objects

    @classmethod
    def of(cls, samples: Mapping[Site, RawSample]) -> Frame:
        """The frame of a mapping of samples (offline, tests)."""
        if type(samples) is Frame:
            return samples
        sites = tuple(samples)
        values = list(samples.values())
        ints = np.zeros((len(sites), INTS), dtype=np.int64)
        floats = np.zeros((len(sites), FLOATS))
        for row, s in enumerate(values):
            ints[row, T_NS], ints[row, SOURCE] = s.t_ns, int(s.source)
            if type(s.reading) is Quat:
                floats[row, W : W + 4] = s.reading.wxyz
        return cls(sites, {s: i for i, s in enumerate(sites)},
                   tuple([type(s.reading) for s in values]), ints, floats, values)  # fmt: skip

    @property
    def t_ns(self) -> np.ndarray:
        """Each row's sample time (ns)."""
        return self.ints[:, T_NS]

    def reading(self, row: int) -> RawSample:
        """Row ``row``'s sample."""
        ints = self.ints
        if ints[row, PENDING]:
            self.objects[row] = _made(ints[row], self.floats[row])
            ints[row, PENDING] = 0
        return self.objects[row]

    def __getitem__(self, site: Site) -> RawSample:
        row = self._index[site]
        if row >= len(self.sites):
            raise KeyError(site)
        return self.reading(row)

    def __iter__(self) -> Iterator[Site]:
        return iter(self.sites)

    def __len__(self) -> int:
        return len(self.sites)

    def __contains__(self, site: object) -> bool:
        row = self._index.get(site)  # type: ignore[call-overload]
        return row is not None and row < len(self.sites)
