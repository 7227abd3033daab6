"""The live gateway: raw samples in, poses and joint angles out, on Zenoh.

One process, by default with an embedded Zenoh router. A subscription to
every raw key (or a chosen subset of branches), and to the bridges' batches
(``body/@batch/*``, split into their samples: ``codecs.raw_batch``), keeps
each site's latest sample; one worker thread takes the samples from Zenoh's queues and, when
a body has a whole frame or has waited a period, solves it at most once per
tick (``rate_hz``), the bodies that are due together, publishing the whole
body on ``body/pose`` and each branch's view on ``body/<limb>/<side>/pose``.
Nodes are tracked through their liveliness tokens; the topology is published
on ``body/@topology`` when it changes and answered as a query there. A site that stops delivering
keeps its last sample and, once that is older than a few of its usual
intervals (``solver.Rhythm``), is listed stale and the dofs resting on it are
flagged ``unobserved`` (reason ``stale``); other branches carry on. Garbage on the
raw keys is counted (``body/@health/gateway``), never fatal. Each site's clock
offset (its node host's clock against the gateway's, from the most a sample's
time led its arrival) is shown in topology and health, and logged as a warning
past ``CLOCK_WARN_MS``: detected, not corrected.
``body/@calibrate/tpose`` answers a query by calibrating the IMU mounts from
the last ``seconds`` of samples (the subject standing still in the T-pose, or
with ``pose=npose`` the N-pose), or refuses with the reason and a report;
until the tags' heading is known (found from a hinge's motion, see
gateway/heading.py) the dofs they drive are flagged ``uncalibrated``.
``body/@calibrate/yaw`` is the yaw reset: the subject faces forward now.

Several subjects: a gateway in a subject's namespace (``--subject``) serves
that subject as above. With ``all_subjects`` it serves every subject present
(``<subject>/body/...``, and the namespace-less ``body/...``) from one
process: each subject is a body of its own (solver, topology, publishers and
profile file, created when its first sample comes), all solved by one worker.
Nothing one subject sends reaches another's output.
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import json
import logging
import math
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose, raw_batch, raw_sample
from bodynet.core.codecs._common import _SQ_HI, _SQ_LO
from bodynet.core.codecs.raw_batch import subject_of_batch
from bodynet.core.codecs.raw_sample import QUAT_MESSAGE_LEN
from bodynet.core.errors import DecodeError, Reason, RejectCounts, Rejected
from bodynet.core.keys import BRANCHES, Branch, Site
from bodynet.core.messages import OleAccel, Quat, RawSample, source_name
from bodynet.core.profile import OLE_DOF, mount
from bodynet.core.subject import Profile, ProfileError, QuatWxyz
from bodynet.gateway import columns, kernels
from bodynet.gateway.aside import AsideFits
from bodynet.gateway.columns import Columns, Frame
from bodynet.gateway.encoders import (
    EncoderZero,
    states,
    zero_from_window,
)
from bodynet.gateway.frames import branch_views, pose_frame, whole_body_message
from bodynet.gateway.heading import (
    INLINE,
    BodyHeading,
    CalibrationRefused,
    Fits,
    calibrate_window,
    dropped_note,
    pose_angles,
    yaw_reset,
)
from bodynet.gateway.rounds import Cadence, Rounds, next_poll
from bodynet.gateway.shards import Share
from bodynet.gateway.solver import (
    STALE_S,
    BodyOutput,
    BodySolver,
    Rhythm,
    fresh_samples,
    solve_bodies,
)
from bodynet.session import profile_file

log = logging.getLogger(__name__)

HISTORY_S = 5.0
#: The T-pose history keeps a site's orientation at most this often: fifty a second
#: average a still pose as well as a thousand, and a short history is a short walk
#: for Python's cyclic collector.
HISTORY_STEP_S = 0.02
#: The entries of a site's ring of recent orientations (gateway/columns.py): a step
#: apart at least, they span the history and a little more.
HISTORY_DEPTH = math.ceil(HISTORY_S / HISTORY_STEP_S) + 2
#: A calibration asked before its window has filled waits while a sensor was heard
#: within this (longer than STALE_S: a loaded machine's sensors and worker lag).
FILL_HEARD_S = 2.0
#: Bodies one gateway takes on; samples of further subjects are counted, not served
#: (a publisher inventing subject names must not exhaust the gateway).
MAX_SUBJECTS = 64
#: Raw samples Zenoh queues for the gateway's worker (some 2 s of 20 bodies); when
#: full, Zenoh waits (the publishers' congestion control decides what follows).
INTAKE_DEPTH = 1 << 16
#: Raw keys of subjects another sharing gateway serves, remembered so that their
#: samples are skipped before decoding (past this many they are still skipped).
MAX_FOREIGN_KEYS = 1 << 14
#: How long the idle worker sleeps at most before it looks again (while a frame may
#: come whole, less: ``rounds.next_poll``).
IDLE_QUIET_S = 0.005
#: A sample's time (ns since 1970) is refused (``out_of_range``, counted) before
#: 1970 or more than this far ahead of the gateway's clock: no host's clock is, and
#: one such time would date every pose of its body (the newest sample's time). A
#: host's clock far behind (a board that booted without a clock) is shown, as any
#: offset is, not refused.
AHEAD_MAX_NS = 366 * 86_400 * 10**9
#: A source's clock offset (its host's clock minus the gateway's) is the most its
#: samples' times led their arrival over the last one to two windows of this many
#: seconds: network delay only delays, so the least delayed sample tells. Only
#: rounds that emptied the gateway's queues count (``Gateway._take_pending``): a
#: round cut short took samples that waited in them, which says the gateway is
#: behind, not a clock. Each site's last sample of a round is counted against the
#: round's end (each arrived before it: against its start, a sample that arrived
#: during a long round, a loaded gateway's, led by up to the round's length).
CLOCK_WINDOW_S = 2.0
#: An offset past this (ms, beyond a LAN's delay) is logged as a warning, once, and
#: again when it has moved by ``CLOCK_REWARN_MS``.
CLOCK_WARN_MS, CLOCK_REWARN_MS = 20.0, 100.0
#: The offset shown (topology, health) moves only by this much (ms) at least: the
#: topology, which goes out when it changes, does not follow the network's jitter.
CLOCK_STEP_MS = 5.0


#: Round numbers (``Gateway._take_pending``; ``_Body.take`` outside one): the
#: round each site's latest sample came in, for its clock offset (``fold_leads``).
_ROUNDS = itertools.count(1)


class _Site:
    """What the gateway keeps of one site besides its row of the body's
    columns (gateway/columns.py: its latest sample, the frame's accounting, its
    recent orientations for T-pose calibration, its clock's lead): its
    Rhythm, the clock offset shown, and a SmartSuit module's encoder."""

    __slots__ = ("body", "counts", "lead_before", "offset_ms", "rhythm", "row", "tag",
                 "warned_ms", "zero")  # fmt: skip

    def __init__(self, body: _Body, row: int) -> None:
        self.body, self.row = body, row
        self.tag = row.to_bytes(kernels.ROW_TAG, "little")  # before its deferred messages
        self.rhythm = Rhythm()  # its usual interval between arrivals: when it is stale
        # the most a sample's time led its arrival in the window before this one (this
        # window's is the row's LEAD; see _Body.clock_check)
        self.lead_before = -math.inf
        self.offset_ms: float | None = None  # the offset shown (see _Body.clock_check)
        self.warned_ms: float | None = None  # the offset last warned of
        # a SmartSuit module's: its encoder's zero (shared with the solver) and its
        # recent (sample time, count) at HISTORY_STEP_S, for a calibration pose's zero
        self.zero: EncoderZero | None = None
        self.counts: deque[tuple[float, int]] | None = None

    @property
    def sample(self) -> RawSample:
        """The site's latest sample."""
        return self.body.sample(self.row)

    @property
    def arrived(self) -> float:
        """When its latest sample came (monotonic)."""
        return float(self.body.columns.floats[self.row, columns.ARRIVED])

    @property
    def owed(self) -> int:
        """How many of the body's frames it has delivered for since the last solve."""
        return int(self.body.columns.ints[self.row, columns.OWED])

    @property
    def lead(self) -> float:
        """The most its samples' times led their arrival in this clock window (s)."""
        return float(self.body.columns.floats[self.row, columns.LEAD])

    @lead.setter
    def lead(self, lead: float) -> None:
        self.body.columns.floats[self.row, columns.LEAD] = lead

    @property
    def history(self) -> list[tuple[float, float, float, float, float]] | None:
        """Its recent orientations, (sample time s, w, x, y, z) every
        ``HISTORY_STEP_S`` over ``HISTORY_S``, oldest first; None if it never
        delivered one."""
        cols = self.body.columns
        if not cols.ints[self.row, columns.COUNT]:
            return None
        return cols.recent(self.row, HISTORY_S)


class _Body:
    """One subject's body in the gateway: its latest samples, solver and publishers.

    ``prefix`` is what the gateway's session puts before ``body/...`` for this
    subject (empty in a subject's own namespace). Callers hold the gateway's lock
    around anything that touches the samples."""

    def __init__(self, session: zenoh.Session, prefix: str, profile: Profile,
                 profile_path: Path | None, branches: Sequence[Branch],
                 period_s: float, fits: Fits = INLINE) -> None:  # fmt: skip
        self.prefix = prefix
        self.fits = fits  # where its heading search's fits run (gateway/aside.py)
        self.profile_path = profile_path
        #: each SmartSuit encoder's zero, by raw key (gateway/encoders.py)
        self.encoders: dict[str, EncoderZero] = {}
        self.solver = BodySolver(profile)
        self.solver.encoder_zeros = self.encoders
        # the tags' heading: known, or being found; then held against drift
        self.heading = BodyHeading(profile, fits)
        self.last_output: BodyOutput | None = None
        # each site's row of columns (gateway/columns.py), and beside them, by row: its
        # site, its latest reading's type, and its latest sample where one was made
        # (not a plain quaternion, or one read: see sample()); ``latest`` and ``rows``
        # find a site's record and row (sites come in row order)
        self.columns = Columns(HISTORY_DEPTH)
        self.latest: dict[Site, _Site] = {}
        self.rows: dict[Site, int] = {}
        self.sites: tuple[Site, ...] = ()
        self.kinds: list[type] = []
        self.objects: list[RawSample] = []
        # a round's plain messages, each after its row's tag, taken at its end
        # (take_deferred), and the tags of the rows they are for
        self.inbox: list[bytes] = []
        self.deferred: set[bytes] = set()
        self.alive: set[str] = set()
        # keys whose token went away -> when (monotonic): stale until a sample comes
        # after that with the token back (a node declares it just before its first
        # sample, and the sample from before it went is no measurement of now)
        self.gone: dict[str, float] = {}
        self.unassigned: set[str] = set()  # trackers streaming with no site yet
        self.published_stale: set[str] = set()
        self.topology_text = ""
        self.ticks = 0
        self.first_new: float | None = None  # when the oldest unsolved sample came
        self.cadence = Cadence(period_s)  # when its frames come whole (monotonic)
        self.next_housekeeping = 0.0  # monotonic: when its topology and health go out next
        self.clock_window_end = 0.0  # monotonic: when the clock offsets' window rolls on
        cc = zenoh.CongestionControl.BLOCK
        self.body_pub = session.declare_publisher(prefix + keys.pose_key(), congestion_control=cc)
        self.branch_pubs = {
            b: session.declare_publisher(prefix + keys.pose_key(b), congestion_control=cc)
            for b in branches
        }
        self.topology_pub = session.declare_publisher(prefix + keys.TOPOLOGY)
        self.health_pub = session.declare_publisher(prefix + keys.health_key("gateway"))
        # who listens, kept current by Zenoh's matching listeners (None: the whole body);
        # asking each publisher's matching status every tick costs more than a solve's tenth
        self.matching: dict[Branch | None, bool] = {}
        self._listeners: list[zenoh.MatchingListener] = []
        for view, pub in ((None, self.body_pub), *self.branch_pubs.items()):
            self._listeners.append(
                pub.declare_matching_listener(
                    lambda status, view=view: self.matching.__setitem__(view, status.matching)
                )
            )
            # the status read now can be older than a notification the listener has had
            # meanwhile (a subscriber arriving): that one stands
            self.matching.setdefault(view, pub.matching_status.matching)

    @property
    def samples(self) -> int:
        """Samples taken."""
        return int(self.columns.tally[columns.SAMPLES])

    @property
    def unsolved_sites(self) -> int:
        """Sites whose latest sample is not in a solved tick yet."""
        return int(self.columns.tally[columns.UNSOLVED])

    @property
    def ready_sites(self) -> int:
        """Sites that have delivered for the next frame (see :meth:`snapshot`)."""
        return int(self.columns.tally[columns.READY])

    def take(self, site: Site, sample: RawSample, now: float, wall: float | None = None,
             rnd: int | None = None) -> _Site:  # fmt: skip
        """Keep a sample as its site's latest (and, for T-pose, in its recent
        history of ``HISTORY_S``). Returns the site's record, for
        :meth:`take_into`. ``now`` is the monotonic clock; ``rnd`` the round
        that took it (``_ROUNDS``), else ``wall`` the wall clock (s; now if
        None) when it was taken, a round of its own."""
        kept = self.latest.get(site)
        if kept is None:
            row = self.columns.add(site.raw_key, STALE_S)
            kept = self.latest[site] = _Site(self, row)
            self.rows[site] = row
            self.sites = (*self.sites, site)
            self.kinds.append(type(sample.reading))
            self.objects.append(sample)
            if type(sample.reading) is OleAccel and site.name in OLE_DOF:
                kept.zero = self.encoders[site.raw_key] = EncoderZero()
                kept.counts = deque()
        alone = rnd is None
        rnd = next(_ROUNDS) if rnd is None else rnd
        self.take_into(kept, sample, now, rnd)
        if alone:
            self.fold_leads(rnd, time.time() if wall is None else wall)
        return kept

    def take_into(self, kept: _Site, sample: RawSample, now: float, rnd: int) -> None:
        """:meth:`take` for a site whose record the caller holds (a key's first
        sample, and samples that are not plain quaternion messages, which the
        compiled intake takes: :meth:`take_batch`, :meth:`take_deferred`)."""
        cols, row, reading = self.columns, kept.row, sample.reading
        kind = type(reading)
        if kind is Quat:
            w, x, y, z = reading.wxyz
            kernels.take_fields(cols.ints, cols.floats, cols.history, cols.tally, row,
                                reading.node, sample.seq, sample.t_ns, int(sample.source),
                                w, x, y, z, now, rnd, HISTORY_STEP_S)  # fmt: skip
        else:
            kernels.take_other(cols.ints, cols.floats, cols.tally, row, sample.t_ns, now, rnd)
            if kept.zero is not None and kind is OleAccel:
                self._encoder(kept, kept.zero, sample)
        cols.ints[row, columns.PENDING] = 0
        self.objects[row] = sample  # as it came (with a quaternion's extra bytes)
        self.kinds[row] = kind
        self._taken(now)

    def take_batch(self, batch: np.ndarray, pos: int, now: float, rnd: int, ahead_ns: int) -> int:
        """A bridge's batch for this body (its bytes), from the entry at ``pos``,
        in one compiled call (``kernels.take_batch``): where it stopped (the
        batch's length: at its end), -1 if it is not well formed."""
        cols = self.columns
        end = kernels.take_batch(batch, pos, cols.keys, cols.ends, cols.n, cols.ints, cols.floats,
                                 cols.history, cols.tally, now, rnd, ahead_ns, _SQ_LO, _SQ_HI,
                                 HISTORY_STEP_S)  # fmt: skip
        if end > pos:
            self._taken(now)
        return end

    def defer(self, kept: _Site, message: bytes) -> None:
        """A message of ``raw_sample.QUAT_MESSAGE_LEN`` bytes that came on
        ``kept``'s key, for :meth:`take_deferred`."""
        self.inbox += (kept.tag, message)
        self.deferred.add(kept.tag)

    def take_deferred(self, now: float, rnd: int, ahead_ns: int) -> Iterator[tuple[_Site, bytes]]:
        """The messages deferred this round (:meth:`defer`), in the order they
        came: the plain quaternion messages taken in one compiled call
        (``kernels.take_messages``), each other one yielded for the caller to
        take (decode or reject) before the call goes on after it."""
        inbox, self.inbox = self.inbox, []
        self.deferred.clear()
        buf = np.frombuffer(b"".join(inbox), np.uint8)
        cols, pos, taken = self.columns, 0, False
        while True:
            stop = kernels.take_messages(buf, pos, cols.ints, cols.floats, cols.history,
                                         cols.tally, now, rnd, ahead_ns, _SQ_LO, _SQ_HI,
                                         HISTORY_STEP_S)  # fmt: skip
            taken = taken or stop > pos
            if stop == len(buf):
                break
            index = 2 * (stop // (kernels.ROW_TAG + QUAT_MESSAGE_LEN))
            site = self.sites[int.from_bytes(inbox[index], "little")]
            yield self.latest[site], inbox[index + 1]
            pos = stop + kernels.ROW_TAG + QUAT_MESSAGE_LEN
        if taken:
            self._taken(now)

    def _taken(self, now: float) -> None:
        """Samples came: the frame's clock, and the runs of Rhythm they ended."""
        if self.first_new is None:
            self.first_new = now
        cols = self.columns
        if cols.tally[columns.RUNS]:
            cols.tally[columns.RUNS] = 0
            ints, floats = cols.ints, cols.floats
            for row in np.flatnonzero(ints[: cols.n, columns.ENDED]).tolist():
                rhythm = self.latest[self.sites[row]].rhythm
                past = -1 - int(ints[row, columns.LEFT])  # samples taken after it ended
                rhythm.end_run(now)
                ints[row, columns.LEFT] = max(rhythm.left - past, 0)
                ints[row, columns.ENDED] = 0
                floats[row, columns.AFTER] = rhythm.after_s

    def fold_leads(self, rnd: int, wall: float) -> None:
        """Round ``rnd`` emptied the queues at ``wall``: its samples' clock leads."""
        cols = self.columns
        kernels.fold_leads(cols.ints, cols.floats, cols.n, rnd, wall)

    def sample(self, row: int) -> RawSample:
        """Row ``row``'s latest sample (made once read)."""
        cols = self.columns
        if cols.ints[row, columns.PENDING]:
            self.objects[row] = cols.made(row)
            cols.ints[row, columns.PENDING] = 0
        return self.objects[row]

    def _encoder(self, kept: _Site, zero: EncoderZero, sample: RawSample) -> None:
        """A module's sample: one its bridge flagged ``RESUMED`` loses its encoder's
        zero (gateway/encoders.py) and the counts kept before it; its count kept."""
        t, counts = sample.t_ns / 1e9, kept.counts
        assert counts is not None
        generation = zero.generation
        if lost := zero.take(sample):
            log.warning("gateway: %s node %d: %s", source_name(sample.source),
                        sample.reading.node, lost)  # fmt: skip
        if zero.generation != generation:
            counts.clear()  # counted from before a reboot: no zero comes of them
        if not counts or t - counts[-1][0] >= HISTORY_STEP_S or t < counts[-1][0]:
            if counts and t < counts[-1][0]:
                counts.clear()  # its clock went back (a bridge restarted): a new history
            counts.append((t, sample.reading.encoder))  # type: ignore[union-attr]
            while t - counts[0][0] > HISTORY_S:
                counts.popleft()

    def frame_complete(self, now: float) -> bool:
        """Has every site that is not stale delivered for the next frame (and every
        node whose token is up delivered at all), with something new since the last
        solve?"""
        cols = self.columns
        tally = cols.tally
        if len(self.alive) > cols.n or not self.ticks or not tally[columns.UNSOLVED]:
            return False  # a node's first sample is on its way; a new body waits a period
        if tally[columns.READY] < cols.n - len(self.published_stale):
            return False  # some live site has not delivered yet: the common, cheap answer
        return bool(kernels.all_delivered(cols.ints, cols.floats, cols.n, now))

    def newly_stale(self, now: float) -> bool:
        cols = self.columns
        floats = cols.floats[: cols.n]
        stale = np.flatnonzero(now - floats[:, columns.ARRIVED] > floats[:, columns.AFTER])
        return any(self.sites[row].raw_key not in self.published_stale for row in stale.tolist())

    def snapshot(self, now: float) -> tuple[Frame, list[str], BodySolver]:
        """What the next solve needs; marks every sample as used.

        The solve takes each site's newest sample. Where a site delivered twice
        since the last solve (nodes at their own phases, the solve a few ms after
        the frame was whole), its second sample counts for the next frame too: the
        next frame is whole when the others deliver again, not a period after
        that site's next sample (which cost one tick in three at twenty
        unsynchronised bodies). A body a whole frame behind starts afresh."""
        cols = self.columns
        n = cols.n
        frame = Frame(self.sites, self.rows, tuple(self.kinds), cols.ints[:n].copy(),
                      cols.floats[:n].copy(), self.objects.copy())  # fmt: skip
        # stale: past a few of its usual intervals (in cols.flags)
        ready, n_stale = kernels.settle_rows(cols.ints, cols.floats, n, now, cols.flags)
        stale = [self.sites[row].raw_key for row in np.flatnonzero(cols.flags[:n]).tolist()] \
            if n_stale else []  # fmt: skip
        if gone := self.gone:
            for row, site in enumerate(self.sites):
                key = site.raw_key
                if cols.flags[row] or (went := gone.get(key)) is None:
                    continue
                if cols.floats[row, columns.ARRIVED] > went and key in self.alive:
                    del gone[key]  # back, and heard from since
                else:
                    stale.append(key)
        cols.tally[columns.UNSOLVED] = 0
        cols.tally[columns.READY] = ready
        stale.sort()
        self.published_stale = set(stale)
        self.first_new = None
        self.solver.expect(self.alive)
        self.solver.set_stale(stale)
        return frame, stale, self.solver

    def listened(self) -> tuple[bool, list[Branch]]:
        """Whether anyone subscribes to the whole body, and to which branch views:
        a message nobody matches is not built (Zenoh's matching status)."""
        matching = self.matching
        return matching[None], [b for b in self.branch_pubs if matching[b]]

    def messages(self, output: BodyOutput, stale: list[str], body: bool,
                 branches: list[Branch]) -> list[tuple[zenoh.Publisher, bytes]]:  # fmt: skip
        """The encoded pose of tick ``self.ticks`` of the whole body (if ``body``)
        and of ``branches``: the whole body's encoded straight from the arrays,
        the branch views cut from its frame."""
        out = [(self.body_pub, whole_body_message(output, self.ticks, stale))] if body else []
        if branches:
            frame = pose_frame(output, self.ticks, stale)
            for branch, view in branch_views(frame, branches).items():
                out.append((self.branch_pubs[branch], pose.encode(view)))
        return out

    def topology(self, now: float) -> dict[str, object]:
        branches: dict[str, dict[str, object]] = {}
        for key in sorted(self.alive | {s.raw_key for s in self.latest}):
            try:
                site, _ = keys.parse(key)
            except keys.KeySpaceError:
                continue
            seen = self.latest.get(site)
            state = "alive" if key in self.alive else "gone"
            # a node's state for people: stale past STALE_S (a tag late by a few of
            # its intervals is flagged in the poses, not flapped here)
            if seen is None or now - seen.arrived > STALE_S:
                state = "stale" if key in self.alive else state
            branch = branches.setdefault(str(site.branch), {"nodes": {}})
            nodes = branch["nodes"]
            assert isinstance(nodes, dict)
            nodes[key] = {"state": state, "node": seen.sample.reading.node if seen else None,
                          "last_t_ns": seen.sample.t_ns if seen else None,
                          "clock_offset_ms": seen.offset_ms if seen else None}  # fmt: skip
        out: dict[str, object] = {"t_ns": time.time_ns(), "branches": branches}
        if self.unassigned:
            out["unassigned"] = sorted(self.unassigned)
        return out

    def clock_check(self, now: float) -> list[tuple[bool, str, str, float]]:
        """Each site's clock offset (its host's clock minus the gateway's, ms): the
        most its samples' times led their arrival in this window and the one
        before (``CLOCK_WINDOW_S`` each; the offset less the least network delay),
        shown once it has moved by ``CLOCK_STEP_MS``; a new window when this one
        is over. Returns the sites to warn of (True: beyond ``CLOCK_WARN_MS``, new
        or moved by ``CLOCK_REWARN_MS``; False: back within it), as (warn, branch,
        raw key, offset)."""
        roll = now >= self.clock_window_end
        if roll:
            self.clock_window_end = now + CLOCK_WINDOW_S
        out = []
        for site, kept in self.latest.items():
            lead = max(kept.lead, kept.lead_before)
            if roll:
                kept.lead_before, kept.lead = kept.lead, -math.inf
            if lead == -math.inf:
                continue  # nothing came for two windows: the last offset shown stays
            if kept.offset_ms is None or abs(lead * 1e3 - kept.offset_ms) >= CLOCK_STEP_MS:
                kept.offset_ms = round(lead * 1e3, 1)
            ms, warned = kept.offset_ms, kept.warned_ms
            if abs(ms) > CLOCK_WARN_MS:
                if warned is None or abs(ms - warned) >= CLOCK_REWARN_MS:
                    kept.warned_ms = ms
                    out.append((True, str(site.branch), site.raw_key, ms))
            elif warned is not None:
                kept.warned_ms = None
                out.append((False, str(site.branch), site.raw_key, ms))
        return out

    def tpose_window(self, now: float, seconds: float
                     ) -> dict[Site, list[tuple[float, QuatWxyz]]]:  # fmt: skip
        """Every orientation site's samples (sample time s, (w, x, y, z)) of its last
        ``seconds`` (an empty list for a site that is stale)."""
        return {
            site: [(t, (w, x, y, z)) for t, w, x, y, z in kept.history
                   if kept.history[-1][0] - t <= seconds] if now - kept.arrived <= STALE_S else []
            for site, kept in self.latest.items()
            if kept.history is not None
        }  # fmt: skip

    def encoder_window(self, now: float, seconds: float) -> dict[str, list[int]]:
        """Each live encoder's counts of its last ``seconds``, by raw key."""
        return {site.raw_key: [c for t, c in kept.counts if kept.counts[-1][0] - t <= seconds]
                for site, kept in self.latest.items()
                if kept.counts and now - kept.arrived <= STALE_S}  # fmt: skip

    def encoder_generations(self) -> dict[str, int]:
        """Each encoder's :attr:`EncoderZero.generation`, taken with its window
        (:meth:`encoder_window`) for :meth:`set_zeros`."""
        return {key: zero.generation for key, zero in self.encoders.items()}

    def set_zeros(self, zeros: Mapping[str, int], generations: Mapping[str, int]
                  ) -> dict[str, str]:  # fmt: skip
        """Set the encoders' zeros found in a calibration window taken at
        ``generations``; those whose zero was lost since (a node resumed: the
        window counted from before its reboot) are left lost: returned, with why."""
        skipped = {}
        for key, counts in zeros.items():  # the pose is each encoder's joint's zero
            zero = self.encoders[key]
            if zero.generation != generations.get(key):
                skipped[key] = ("its node resumed during the calibration window (it may have "
                                "rebooted): hold the pose and calibrate again")  # fmt: skip
                continue
            zero.counts, zero.lost, zero.rezeroed = counts, None, True
        return skipped

    def zero_encoders(self, window: dict[str, list[int]], profile: Profile,
                      pose: str) -> dict[str, int]:  # fmt: skip
        """The encoders' zeros from a still window of the calibration ``pose``
        (each joint's angle there): ``ZeroRefused`` if a joint moved in it,
        ValueError if ``pose`` is no calibration pose."""
        angles = pose_angles(pose)
        out = {}
        for key, counts in sorted(window.items()):
            site, _ = keys.parse(key)
            angle = mount(site).ole_angle or ""
            out[key] = zero_from_window(counts, profile.ole.get(angle), angles.get(angle, 0.0),
                                        key)  # fmt: skip
        return out

    def history_s(self) -> float | None:
        """How far back every orientation site's history reaches (None: no such site)."""
        spans = [k.history[-1][0] - k.history[0][0] for k in self.latest.values() if k.history]
        return min(spans, default=None)

    def set_profile(self, profile: Profile, heading: BodyHeading | None = None) -> None:
        """A new calibration: a new solver, heading state and, if it has a file, saved."""
        self.solver = BodySolver(profile)
        self.solver.encoder_zeros = self.encoders
        self.heading = heading or BodyHeading(profile, self.fits)
        if self.profile_path is not None:
            profile_file.save(profile, self.profile_path)

    def close(self) -> None:
        for listener in self._listeners:
            listener.undeclare()
        for pub in (self.body_pub, self.topology_pub, self.health_pub,
                    *self.branch_pubs.values()):  # fmt: skip
            pub.undeclare()


@dataclass(frozen=True, slots=True)
class _Token:
    """A node's liveliness token came (``alive``) or went."""

    key: str
    alive: bool


class Gateway:
    """See the module docstring. ``run(stop)`` serves until ``stop`` is set.

    ``profile``/``profile_path`` are the subject's (single-subject gateway).
    With ``all_subjects``, each subject's profile is ``profile_dir/<subject>.toml``
    (``default.toml`` for the namespace-less subject), the defaults until a
    calibration writes it."""

    def __init__(self, session: zenoh.Session, profile: Profile | None = None,
                 profile_path: Path | None = None, branches: Sequence[Branch] | None = None,
                 rate_hz: float = 100.0, *, all_subjects: bool = False,
                 profile_dir: Path | None = None, share: str | None = None) -> None:  # fmt: skip
        self.session = session
        self.branches = tuple(branches) if branches else BRANCHES
        self.period_s = 1.0 / rate_hz
        self.all_subjects = all_subjects
        self.profile_dir = profile_dir
        self.rejected = RejectCounts()
        self.solver_errors = 0
        self.refused_subjects = 0
        self.solves = 0  # batched solves: ticks / solves is the mean batch
        # rounds whose period ran out with samples still waiting (the gateway behind
        # its feed), and since when every round has (monotonic; None: it is not)
        self.rounds_cut_short = 0
        self._behind_since: float | None = None
        self._said_behind = False
        self.session_lost = False  # run() ended because the session was closed
        # the heading searches' fits, off the worker (hundreds of ms each, at times)
        self.fits = AsideFits()
        self.rounds = Rounds(self.period_s)  # when whole frames are solved (batching)
        # bodies whose frame is whole, waiting for the round (-> since when), oldest first
        self._held: dict[_Body, float] = {}
        self._next_due = float("inf")  # no body is due before this (its oldest new sample)
        # --share: the gateways that share the subjects, and what is not this one's
        self.share = Share(share) if share is not None and all_subjects else None
        self.foreign_samples = 0  # samples of subjects another gateway serves
        self._foreign: set[str] = set()  # their raw keys, skipped undecoded
        self._foreign_alive: dict[str | None, set[str]] = {}  # their live nodes' keys
        self._members: queue.SimpleQueue[tuple[str, bool]] = queue.SimpleQueue()
        # liveliness tokens that came or went (on Zenoh's threads), for the worker
        self._events: queue.SimpleQueue[tuple[str | None, _Token]] = queue.SimpleQueue()
        self._lock = threading.RLock()
        self._bodies: dict[str | None, _Body] = {}
        self._routes: dict[str, tuple[_Body, _Site]] = {}  # raw key -> where its samples go
        self._batch_bodies: dict[str, _Body] = {}  # a batch's key -> its subject's body
        # each routed raw key declared to Zenoh, which then routes its samples by the
        # declaration instead of matching the key's text against every declaration of
        # this session, sample by sample (8% of the gateway's CPU at twenty bodies)
        self._declared: dict[str, zenoh.KeyExpr] = {}
        if not all_subjects:
            self._bodies[None] = _Body(session, "", profile or Profile(), profile_path,
                                       self.branches, self.period_s, self.fits)  # fmt: skip
        prefixes = ("", keys.ANY_SUBJECT + "/") if all_subjects else ("",)
        inner = [keys.all_raw()] if branches is None else [f"{b.key}/*/raw" for b in branches]
        inner.append(keys.all_batches())  # bridges run with --batch-ms
        self._unserved: set[str] = set()  # raw keys in batches of branches not served here
        self._subs = [session.declare_subscriber(p + sel, zenoh.handlers.FifoChannel(INTAKE_DEPTH))
                      for p in prefixes for sel in inner]  # fmt: skip
        self._live = [
            session.liveliness().declare_subscriber(p + sel, self._on_token, history=True)
            for p in prefixes
            for sel in (keys.all_raw(), keys.UNASSIGNED + "/*")  # sensors, unassigned trackers
        ]  # fmt: skip
        self._share_decls: list[object] = []
        if self.share is not None:
            self._join_share(self.share)
        self._queryables = [
            q
            for p in prefixes
            for q in (
                session.declare_queryable(p + keys.TOPOLOGY, self._on_topology_query),
                session.declare_queryable(p + keys.CALIBRATE_TPOSE, self._on_tpose_query),
                session.declare_queryable(p + keys.CALIBRATE_YAW, self._on_yaw_query),
            )
        ]

    # --- counters over every body ---------------------------------------------------
    @property
    def samples(self) -> int:
        return sum(b.samples for b in list(self._bodies.values()))

    @property
    def ticks(self) -> int:
        return sum(b.ticks for b in list(self._bodies.values()))

    @property
    def solver(self) -> BodySolver:
        """The solver of the subject of a single-subject gateway."""
        return self._bodies[None].solver

    def subjects(self) -> list[str | None]:
        """The subjects served so far (``None``: the namespace-less one)."""
        with self._lock:
            return list(self._bodies)

    # --- input ------------------------------------------------------------------------
    def _take_pending(self, now: float) -> tuple[int, set[_Body], bool]:
        """Take the raw samples waiting in the subscribers' queues (the worker's
        thread), for at most a period: each is decoded and kept as its site's
        latest, or counted as a rejection. Taking comes before solving, so no
        sample waits behind solves: under load bodies are solved less often.
        Returns how many were taken, the bodies they went to, and whether the
        period ran out first (samples may still be waiting)."""
        taken, touched = 0, set()
        until = now + self.period_s  # a flood (of garbage, say) still leaves time to solve
        routes, foreign, batches = self._routes, self._foreign, self._batch_bodies
        rnd = next(_ROUNDS)  # the round its samples came in, for the clock offset
        ahead = time.time_ns() + AHEAD_MAX_NS  # the latest sample time taken
        with self._lock:
            for sub in self._subs:
                while (taken % 256 or time.monotonic() < until) and (
                    (sample := sub.try_recv()) is not None
                ):
                    taken += 1
                    key = str(sample.key_expr)
                    route = routes.get(key)
                    if route is None and key in foreign:  # another gateway's: not read
                        self.foreign_samples += 1
                        continue
                    payload = sample.payload.to_bytes()
                    if route is not None:
                        body = route[0]
                        touched.add(body)
                        if len(payload) == QUAT_MESSAGE_LEN:  # the common case: at the end
                            body.defer(route[1], payload)
                            continue
                        self._take_one(key, payload, route, now, rnd, ahead, touched)
                        continue
                    if (body := batches.get(key)) is not None:
                        self._take_batch(key, payload, body, now, rnd, ahead, touched)
                        continue
                    if subject_of_batch(key) is not None:
                        self._take_entries(key, raw_batch.split(key, payload), now, rnd, ahead,
                                           touched)  # fmt: skip
                        continue
                    self._take_one(key, payload, None, now, rnd, ahead, touched)
            for body in touched:
                if body.inbox:
                    self._take_deferred(body, now, rnd, ahead)
        # the loops stop at an empty queue, or on a 256th sample past the period
        more = not taken % 256 and time.monotonic() >= until
        if not more:
            wall = time.time()
            for body in touched:
                body.fold_leads(rnd, wall)
        return taken, touched, more

    def _take_batch(self, key: str, payload: bytes, body: _Body, now: float, rnd: int,
                    ahead: int, touched: set[_Body]) -> None:  # fmt: skip
        """A bridge's batch for ``body``: its plain quaternion messages in one
        compiled call each run of them (``_Body.take_batch``), any other entry
        as a sample on its own key; a batch that is not well formed as
        ``raw_batch.split`` says."""
        if body.inbox:  # its samples that came before, first
            self._take_deferred(body, now, rnd, ahead)
        batch = np.frombuffer(payload, np.uint8)
        pos = raw_batch.HEADER_LEN
        while (end := body.take_batch(batch, pos, now, rnd, ahead)) < len(payload):
            if end < 0:
                self._take_entries(key, raw_batch.split(key, payload), now, rnd, ahead, touched)
                return
            entry, pos = raw_batch.entry_at(payload, end, body.prefix)
            self._take_entries(key, [entry], now, rnd, ahead, touched)
        touched.add(body)

    def _take_deferred(self, body: _Body, now: float, rnd: int, ahead: int) -> None:
        """``body``'s samples of this round (``_Body.take_deferred``): those the
        compiled intake does not take, one by one here."""
        for kept, message in body.take_deferred(now, rnd, ahead):
            self._take_one(body.sites[kept.row].raw_key, message, (body, kept), now, rnd, ahead,
                           set())  # fmt: skip

    def _take_entries(self, key: str, entries: list[raw_batch.Entry | Rejected], now: float,
                      rnd: int, ahead: int, touched: set[_Body]) -> None:  # fmt: skip
        """A batch's entries (``raw_batch.split``) taken one by one; the body they
        went to remembered for the batch's next ones (``_take_batch``)."""
        for entry in entries:
            if isinstance(entry, Rejected):
                self.rejected[entry.reason] += 1
                continue
            k, message = entry
            self._take_one(k, message, self._routes.get(k), now, rnd, ahead, touched)
            if key not in self._batch_bodies and (route := self._routes.get(k)) is not None:
                self._batch_bodies[key] = route[0]

    def _take_one(self, key: str, payload: bytes, route: tuple[_Body, _Site] | None,
                  now: float, rnd: int, ahead: int, touched: set[_Body]) -> None:  # fmt: skip
        """Take one raw sample that came on ``key`` (``route``: where its key's
        samples go, if known): decoded and kept, or counted as a rejection, or
        passed over (a subject another gateway serves; a branch this one does not,
        from a bridge's batch)."""
        try:
            if route is None:
                if key in self._foreign:
                    self.foreign_samples += 1
                    return
                if key in self._unserved:
                    return
                subject, body_key = keys.split_subject(key)
                site, _ = keys.parse(body_key)
                if site.branch not in self.branches:
                    if len(self._unserved) < MAX_FOREIGN_KEYS:
                        self._unserved.add(key)
                    return
                if self.share is not None and not self.share.owns(subject):
                    if len(self._foreign) < MAX_FOREIGN_KEYS:
                        self._foreign.add(key)
                    self.foreign_samples += 1
                    return
            raw = raw_sample.decode(payload)
            if not 0 <= raw.t_ns <= time.time_ns() + AHEAD_MAX_NS:
                raise DecodeError(Reason.OUT_OF_RANGE, f"time {raw.t_ns} ns")
        except DecodeError as exc:
            self.rejected[exc.reason] += 1
            return
        except keys.KeySpaceError:
            self.rejected[Reason.UNKNOWN_NODE] += 1
            return
        if route is None:  # a key's first good sample: its body is made now
            if (body := self._body(subject)) is None:
                return
            self._route(key, body, body.take(site, raw, now, rnd=rnd))
        else:
            body = route[0]
            # its site's samples that came before it, first (a lone message or a
            # batch's entry); another site's, as a SmartSuit module's among tags,
            # wait for the round's end
            if route[1].tag in body.deferred:
                self._take_deferred(body, now, rnd, ahead)
            body.take_into(route[1], raw, now, rnd)
        touched.add(body)

    def _route(self, key: str, body: _Body, kept: _Site) -> None:
        """Where a raw key's samples go from now on (at most MAX_SUBJECTS times the
        key space's sites), the key declared to Zenoh."""
        self._routes[key] = (body, kept)
        with contextlib.suppress(zenoh.ZError):  # a closing session: routed by the text then
            self._declared[key] = self.session.declare_keyexpr(key)

    def _join_share(self, share: Share) -> None:
        """Declare this gateway's token and learn the members already there
        before serving (a newcomer that took itself for alone would serve every
        subject twice until the others' tokens came)."""
        group = keys.GATEWAYS + "/*"

        def on_member(sample: zenoh.Sample) -> None:  # Zenoh's thread
            member = str(sample.key_expr).rsplit("/", 1)[-1]
            self._members.put((member, sample.kind == zenoh.SampleKind.PUT))

        liveliness = self.session.liveliness()
        self._share_decls = [
            liveliness.declare_token(keys.gateway_token(share.id)),
            liveliness.declare_subscriber(group, on_member, history=True),
        ]
        for reply in liveliness.get(group, timeout=1.0):
            if reply.ok is not None:
                share.update(str(reply.ok.key_expr).rsplit("/", 1)[-1], True)
        log.info("gateway %s: sharing the subjects with %d other gateways", share.id,
                 len(share.members) - 1)  # fmt: skip

    def _reshare(self) -> int:
        """Apply the members that came or went: drop the bodies of subjects now
        another gateway's (their profiles stay in the profile folder), and let
        samples of the others be looked at again. How many events there were."""
        assert self.share is not None
        events, changed = 0, False
        while True:
            try:
                member, alive = self._members.get_nowait()
            except queue.Empty:
                break
            events += 1
            changed |= self.share.update(member, alive)
        if not changed:
            return events
        with self._lock:
            for subject, body in list(self._bodies.items()):
                if not self.share.owns(subject):
                    del self._bodies[subject]
                    self._foreign_alive[subject] = set(body.alive)
                    for key in [k for k, (b, _) in self._routes.items() if b is body]:
                        del self._routes[key]
                        if (declared := self._declared.pop(key, None)) is not None:
                            self.session.undeclare(declared)
                    for key in [k for k, b in self._batch_bodies.items() if b is body]:
                        del self._batch_bodies[key]
                    body.close()
                    log.info("gateway: subject %s is now another gateway's", subject)
            self._foreign.clear()
        log.info("gateway %s: %d gateways share the subjects", self.share.id,
                 len(self.share.members))  # fmt: skip
        return events

    def _on_token(self, sample: zenoh.Sample) -> None:  # Zenoh's thread
        try:
            subject, key = keys.split_subject(str(sample.key_expr))
        except keys.KeySpaceError:
            return
        self._events.put((subject, _Token(key, sample.kind == zenoh.SampleKind.PUT)))

    def _body(self, subject: str | None) -> _Body | None:
        """The subject's body, made on first sight (a refusal is counted); None
        for a subject another sharing gateway serves."""
        body = self._bodies.get(subject)
        if body is not None:
            return body
        with self._lock:
            if subject in self._bodies:
                return self._bodies[subject]
            if self.share is not None and not self.share.owns(subject):
                return None
            if len(self._bodies) >= MAX_SUBJECTS:
                self.refused_subjects += 1
                return None
            path = None
            if self.profile_dir is not None:
                path = self.profile_dir / f"{subject or 'default'}.toml"
            try:
                profile = profile_file.load(path) if path and path.exists() else Profile()
            except ProfileError as exc:
                log.error("gateway: %s; subject %s runs on default calibration", exc, subject)
                profile = Profile()
            prefix = keys.subject_prefix(subject)
            body = _Body(self.session, prefix, profile, path, self.branches, self.period_s,
                         self.fits)  # fmt: skip
            body.alive |= self._foreign_alive.pop(subject, set())  # nodes seen while not ours
            self._bodies[subject] = body
            log.info("gateway: serving subject %s", subject or "(no namespace)")
            return body

    # --- topology ------------------------------------------------------------------
    def topology(self, subject: str | None = None) -> dict[str, object]:
        """The topology of one subject's body (empty if it has not been seen)."""
        body = self._bodies.get(subject)
        if body is None:
            return {"t_ns": time.time_ns(), "branches": {}}
        with self._lock:
            return body.topology(time.monotonic())

    def _publish_topology(self, body: _Body) -> None:
        with self._lock:
            topo = body.topology(time.monotonic())
            text = json.dumps({k: v for k, v in topo.items() if k != "t_ns"}, sort_keys=True)
            if text == body.topology_text:
                return
            body.topology_text = text
        body.topology_pub.put(json.dumps(topo).encode())

    def _answering(self, query: zenoh.Query, key: str) -> list[tuple[str | None, _Body, str]]:
        """The bodies whose ``key`` (under their prefix) the query asks for."""
        asked = query.key_expr
        return [
            (subject, body, body.prefix + key)
            for subject, body in list(self._bodies.items())
            if asked.intersects(zenoh.KeyExpr(body.prefix + key))
        ]

    def _on_topology_query(self, query: zenoh.Query) -> None:
        for subject, _, key in self._answering(query, keys.TOPOLOGY):
            query.reply(key, json.dumps(self.topology(subject)).encode())

    # --- calibration of the orientation sensors ---------------------------------------
    def calibrate_tpose(
        self, seconds: float = 1.0, subject: str | None = None, pose: str | None = None
    ) -> dict[str, object]:
        """Mounts of every orientation sensor of a subject from its last ``seconds``
        (still in ``pose``: the profile's by default); the calibration report, or a
        refusal (``ok`` false, ``error`` why) that leaves the profile as it was.
        Asked before every sensor has ``seconds`` of history (right after the
        sensors start), it waits for the window to fill while sensors deliver, up
        to ``2 seconds + 2 s`` (the worker may be behind the samples Zenoh holds
        for it). ``seconds`` must be within the history kept (``HISTORY_S``)."""
        if not 0 < seconds <= HISTORY_S:  # NaN too: a window the history cannot hold
            return {"ok": False, "error": f"seconds must be above 0 and at most {HISTORY_S:g} "
                    f"(the history the gateway keeps), not {seconds!r}"}  # fmt: skip
        body = self._bodies.get(subject)
        if body is None:
            return {"ok": False, "error": "no samples of this subject"}
        try:  # a raw query's ?pose= is anything
            pose_angles(pose or body.solver.profile.pose)
        except ValueError as exc:
            log.warning("calibration refused: %s", exc)
            return {"ok": False, "error": str(exc)}
        deadline = time.monotonic() + 2 * seconds + 2.0
        while True:
            now = time.monotonic()
            with self._lock:
                reach = body.history_s()
                # only live sensors fill a window: with every one silent, waiting is no use
                filling = any(now - k.arrived < FILL_HEARD_S
                              for k in body.latest.values() if k.history)  # fmt: skip
            filled = reach is None or reach >= seconds or not filling
            if filled or now >= deadline:
                break
            time.sleep(0.02)
        with self._lock:
            window = body.tpose_window(now, seconds)
            encoders = body.encoder_window(now, seconds)
            generations = body.encoder_generations()
            profile = body.solver.profile
        try:
            zeros = body.zero_encoders(encoders, profile, pose or profile.pose)
            result = (calibrate_window(window, profile, pose, expected=window, seconds=seconds)
                      if window or not zeros else None)  # fmt: skip
        except (CalibrationRefused, ValueError, ProfileError) as exc:
            log.warning("calibration refused: %s", str(exc))
            report = exc.report if isinstance(exc, CalibrationRefused) else {}
            return {
                "ok": False,
                "error": str(exc),
                **{k: v for k, v in report.items() if k not in ("ok", "error")},
            }
        if result is not None:
            profile = result.apply(profile, pose)
        with self._lock:
            if result is not None:
                body.set_profile(profile)
            skipped = body.set_zeros(zeros, generations)
        encoders = {k: {"skipped": skipped[k]} if k in skipped else {"zero_counts": v}
                    for k, v in zeros.items()}  # fmt: skip
        for key, why in skipped.items():
            log.warning("calibration: %s's zero not set: %s", key, why)
        if result is None:  # SmartSuit modules alone (the seed's arm): their zeros only
            log.info("calibration (%s) of %d encoders' zeros", pose or profile.pose, len(zeros))
            return {"ok": True, "pose": pose or profile.pose, "calibrated": [],
                    "encoders": encoders, "profile": str(body.profile_path or "")}  # fmt: skip
        log.info("calibration (%s) of %d sensors; heading %s", profile.pose, len(result.mounts),
                 result.report["heading"]["state"])  # fmt: skip
        note = dropped_note(result.report)
        if note:
            log.warning("calibration: %s", note)
        return {**result.report, "encoders": encoders, "profile": str(body.profile_path or "")}

    def _on_tpose_query(self, query: zenoh.Query) -> None:
        text = query.parameters.get("seconds")
        try:
            seconds: float | None = float(text or 1.0)
        except ValueError:  # refused, not read as the default window
            seconds = None
        pose = query.parameters.get("pose") or None
        try:
            for subject, _, key in self._answering(query, keys.CALIBRATE_TPOSE):
                try:
                    answer = (self.calibrate_tpose(seconds, subject, pose) if seconds is not None
                              else {"ok": False, "error": f"seconds={text!r:.40} is not a "
                                                          "number of seconds"})  # fmt: skip
                except Exception as exc:  # a calibration that fails must not end the service
                    log.exception("gateway: calibration failed")
                    answer = {"ok": False, "error": f"calibration failed: {exc}"}
                query.reply(key, json.dumps(answer).encode())
        finally:
            # answered: a refusal's traceback can keep this frame, and so the query,
            # alive until a collection, and the asker would wait for its end till then
            query.drop()

    def reset_yaw(self, subject: str | None = None) -> dict[str, object]:
        """The yaw reset: the subject faces forward now (see :func:`yaw_reset`)."""
        body = self._bodies.get(subject)
        if body is None or body.last_output is None:
            return {"ok": False, "error": "no pose of this subject yet"}
        with self._lock:
            output, profile = body.last_output, body.solver.profile
        try:
            profile, turned = yaw_reset(profile, output)
        except ValueError as exc:
            return {"ok": False, "error": str(exc)}
        with self._lock:
            body.set_profile(profile)
        return {"ok": True, "turned_deg": round(turned, 2), "heading": body.heading.state()}

    def _on_yaw_query(self, query: zenoh.Query) -> None:
        try:
            for subject, _, key in self._answering(query, keys.CALIBRATE_YAW):
                query.reply(key, json.dumps(self.reset_yaw(subject)).encode())
        finally:
            query.drop()

    def _find_headings(self, work: Sequence[tuple[_Body, dict[Site, RawSample], object, object]],
                       now: float) -> None:  # fmt: skip
        """Each body's solved tick to its heading (``BodyHeading.step``, as
        ``bodynet process`` does): while unknown, a heading once found (a new
        solver, the profile saved); once known, the joints' constraints keep the
        tags' headings from drifting (JointDrift: the hinge and two-dof joints,
        and the three-dof joints' twist where the profile's ``drift`` says); never
        from a stale site's frozen sample."""
        for body, latest, stale, _ in work:
            step = body.heading.step(now, fresh_samples(latest, stale), body.solver.profile,
                                     body.encoders)  # fmt: skip
            if step is None:
                continue
            what, profile = step
            with self._lock:
                if what in ("found", "switched"):  # switched: auto met 6-axis tags
                    body.set_profile(profile, body.heading)
                # the joints' constraints turned drifting tags' headings, or a new
                # solver: how well the headings are known (unc_deg)
                body.heading.hold(body.solver, profile)
            if what == "found":
                log.info("heading found: %s", body.heading.state())
            elif what == "switched":
                log.warning("heading: %s", body.heading.switched)

    # --- the work loop -----------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Take the samples waiting in Zenoh's queues, then solve every body that
        has a whole frame of its sources (every live site has delivered since its
        last solve: the lowest latency), or that has waited ``period_s`` since its
        first new sample (sources of different rates), all together.

        One thread does all the Python work, so it never waits for the GIL
        behind Zenoh's callbacks: samples queue up in Zenoh (``INTAKE_DEPTH``)
        while it solves, and the next round takes them all. Under load bodies
        are solved less often, in larger batches (cheaper per body), each with
        its newest samples; no sample is lost and none waits behind a backlog
        of solves.

        If the Zenoh session is closed under it, it returns, logged and with
        ``session_lost`` set: nothing more can come in or go out."""
        # What exists before serving (modules, models) is left out of the cyclic
        # collector's full passes, which otherwise paused this loop for tens of ms.
        gc.freeze()
        last_sample = time.monotonic()
        try:
            while not stop.is_set():
                now = time.monotonic()
                taken, touched, more = self._take_pending(now)
                self._behind(now, more)
                acted, wake = self._round(now, touched)
                if taken:
                    last_sample = now
                # after a solve or a cut-short take, look again at once (samples came
                # meanwhile); else poll again soon, or when a frame may be whole
                if not (acted or more):
                    until = self._idle_until(now, wake, now - last_sample < 1.0)
                    if (idle := until - (start := time.monotonic())) > 0:
                        time.sleep(idle)
                        self.rounds.slept(time.monotonic() - start)
        except zenoh.ZError as exc:
            if not self.session.is_closed():
                raise
            self.session_lost = True
            log.error("gateway: its Zenoh session was closed (%s); the gateway stops", exc)

    def _behind(self, now: float, more: bool) -> None:
        """Count a round cut short (``more``: samples left waiting), and say once
        when every round has been for ``CLOCK_WINDOW_S``: the samples' lag is then
        the gateway's own backlog, which no source's offset is judged from."""
        if not more:
            self._behind_since = None
            return
        self.rounds_cut_short += 1
        if self._behind_since is None:
            self._behind_since = now
        elif not self._said_behind and now - self._behind_since >= CLOCK_WINDOW_S:
            self._said_behind = True
            log.warning("gateway: behind its feed for %.0f s: every round ran out of its "
                        "period with samples still waiting in its queues, so poses lag "
                        "them; the sources' time offsets are judged only from rounds that "
                        "catch up; give it more CPU, or share the subjects (--share)",
                        now - self._behind_since)  # fmt: skip

    def _idle_until(self, now: float, wake: float, flowing: bool) -> float:
        """Until when the idle worker sleeps: ``wake`` (a body due) at the latest;
        while samples flow (``flowing``), a poll while a frame may come whole, else
        until one may (``rounds.next_poll``); ``IDLE_QUIET_S`` at most."""
        until = now + IDLE_QUIET_S
        if flowing:
            bodies = ((b.cadence, b.first_new is not None) for b in self._bodies.values())
            until = min(next_poll(now, bodies), until)
        return min(until, wake)

    def _round(self, now: float, touched: set[_Body]) -> tuple[bool, float]:
        """One round of the worker after taking samples (``touched``: the bodies
        they went to): solve what is due, in one batched call (see
        gateway/rounds.py for when a whole frame waits for the round), and one
        body's housekeeping. Whether it solved or had events, and when it has to
        look again at the latest (if no sample comes before)."""
        held = self._held
        due: dict[_Body, bool] = {}  # body -> solve even with nothing new
        with self._lock:
            for body in touched:
                if body in held:
                    continue
                if body.frame_complete(now):
                    body.cadence.whole(now)
                    held[body] = now
                elif body.first_new is not None:
                    self._next_due = min(self._next_due, body.first_new + self.period_s)
        events = self._reshare() if self.share is not None else 0
        while True:
            try:
                subject, token = self._events.get_nowait()
            except queue.Empty:
                break
            events += 1
            if (body := self._token(subject, token)) is not None and body.latest:
                due[body] = True  # the topology changed: a tick that says so
        if now >= self._next_due:  # bodies whose slowest source has kept them waiting a period
            for body in list(self._bodies.values()):
                if body.first_new is not None and now - body.first_new >= self.period_s:
                    due.setdefault(body, False)
            firsts = [b.first_new for b in self._bodies.values()
                      if b.first_new is not None and b not in due]  # fmt: skip
            self._next_due = min(firsts, default=float("inf")) + self.period_s
        wake = self._next_due
        if held:
            since = next(iter(held.values()))
            if due or self.rounds.due(now, since, len(self._bodies)):
                for body in held:  # the round: every whole frame in one solve
                    due.setdefault(body, False)
                held.clear()
            else:
                wake = min(wake, since + self.rounds.hold_s)
        self._solve_and_publish(due, now)
        self._housekeeping(now)
        return bool(due or events), wake

    def _token(self, subject: str | None, token: _Token) -> _Body | None:
        """Apply a token's coming or going to its subject's body; that body (to
        be solved at once, its topology having changed), if there is one."""
        if token.key.startswith(keys.UNASSIGNED + "/"):
            self._unassigned(subject, token)
            return None
        try:
            site, _ = keys.parse(token.key)
        except keys.KeySpaceError:
            return None
        if site.branch not in self.branches:
            return None  # a node this gateway does not serve (it subscribes to a subset)
        body = self._body(subject)
        if body is None:
            foreign = self._foreign_alive
            if (
                self.share is not None
                and not self.share.owns(subject)
                and (subject in foreign or len(foreign) < MAX_SUBJECTS * len(self.share.members))
            ):
                alive = foreign.setdefault(subject, set())
                (alive.add if token.alive else alive.discard)(token.key)
            return None
        with self._lock:
            (body.alive.add if token.alive else body.alive.discard)(token.key)
            if not token.alive:
                body.gone[token.key] = time.monotonic()
        self._publish_topology(body)
        return body

    def _unassigned(self, subject: str | None, token: _Token) -> None:
        """A tracker with no site (a bridge's ``body/@unassigned/<id>`` token) came
        or went: the topology lists it, for the user to assign."""
        body = self._body(subject)
        if body is None:
            return
        tracker = token.key[len(keys.UNASSIGNED) + 1 :]
        with self._lock:
            (body.unassigned.add if token.alive else body.unassigned.discard)(tracker)
        self._publish_topology(body)

    def _housekeeping(self, now: float) -> None:
        """Once a second for each body, one body a round (twenty bodies' topology
        and health at once stalled a tick by a millisecond and more): stale
        sites get a tick of their own, topology and health go out."""
        for body in self._bodies.values():  # only this thread adds bodies
            if now >= body.next_housekeeping:
                break
        else:
            return
        body.next_housekeeping = now + 1.0
        with self._lock:
            stale = body.newly_stale(now)
            clocks = body.clock_check(now)
        self._log_clocks(body, clocks)
        if stale:
            self._solve_and_publish({body: True}, now)
        self._publish_topology(body)
        body.health_pub.put(json.dumps(self.health(body)).encode())

    @staticmethod
    def _log_clocks(body: _Body, clocks: list[tuple[bool, str, str, float]]) -> None:
        """Warn of the sources whose host's clock is off (``_Body.clock_check``), a
        line per branch; and say when they are back within ``CLOCK_WARN_MS``."""
        by_branch: dict[tuple[bool, str], list[tuple[str, float]]] = {}
        for warn, branch, key, ms in clocks:
            by_branch.setdefault((warn, branch), []).append((key, ms))
        for (warn, branch), found in sorted(by_branch.items()):
            lo, hi = min(ms for _, ms in found), max(ms for _, ms in found)
            off = f"{lo:+.0f} ms" if hi - lo < 1 else f"{lo:+.0f} to {hi:+.0f} ms"
            where = f"{body.prefix}{branch} ({', '.join(sorted(k for k, _ in found))})"
            if warn:
                # a late sample may be a slow clock or a delay on the way, which one
                # timestamp cannot tell apart; one from the future is only a clock
                late = ("" if lo > 0 else "; or its samples are held up on the way (a loaded "
                        "host, network or router: the bare relay's latency says)")  # fmt: skip
                log.warning("gateway: the clock of the host sending %s is off by %s against "
                            "the gateway's (+: ahead): its samples' times, and the poses, "
                            "recordings and LSL times taken from them, are off by as much; "
                            "synchronise that node's host clock (NTP, chrony or PTP)%s",
                            where, off, late)  # fmt: skip
            else:
                log.info("gateway: the clock of the host sending %s is back within %g ms "
                         "(%s)", where, CLOCK_WARN_MS, off)  # fmt: skip

    def _solve_and_publish(self, due: dict[_Body, bool], now: float) -> None:
        """Solve the bodies ``due`` (body -> even with nothing new) together, one
        tick each, and publish what someone listens to."""
        work = []
        with self._lock:
            for body, force in due.items():
                if force or body.unsolved_sites:
                    work.append((body, *body.snapshot(now)))
        if not work:
            return
        self.solves += 1
        try:
            outputs = solve_bodies([(solver, latest) for _, latest, _, solver in work])
        except Exception:  # one body's bad tick must not cost the others theirs
            alone = [(body, self._solve_alone(solver, latest), stale)
                     for body, latest, stale, solver in work]  # fmt: skip
            self._publish(
                [(body, output, stale) for body, output, stale in alone if output is not None]
            )
            return
        self._publish([(body, output, stale) for (body, _, stale, _), output
                       in zip(work, outputs, strict=True)])  # fmt: skip
        self._find_headings(work, now)

    def _publish(self, ticks: list[tuple[_Body, BodyOutput, list[str]]]) -> None:
        """Count the bodies' ticks and publish what someone listens to. Every message
        is built before the first goes out: Zenoh sends puts that come back to back
        together, at a third of the cost of a put alone."""
        messages = []
        for body, output, stale in ticks:
            body.ticks += 1
            body.last_output = output
            whole, branches = body.listened()
            if whole or branches:
                messages += body.messages(output, stale, whole, branches)
        for pub, payload in messages:
            pub.put(payload)

    def _solve_alone(self, solver: BodySolver, latest: dict[Site, RawSample]) -> BodyOutput | None:
        try:
            return solver.solve(latest)
        except Exception:  # one bad tick must not end the service
            self.solver_errors += 1
            if self.solver_errors <= 3:
                log.exception("gateway: a tick failed (%d so far)", self.solver_errors)
            return None

    def health(self, body: _Body | None = None) -> dict[str, object]:
        """Counters of the gateway (and of one body's share of it)."""
        out: dict[str, object] = {"source": "gateway", "t_ns": time.time_ns(),
                                  "samples": self.samples, "ticks": self.ticks,
                                  "solves": self.solves,
                                  "solver_errors": self.solver_errors,
                                  "rounds_cut_short": self.rounds_cut_short,
                                  "rejected": dict(self.rejected),
                                  "subjects": len(self._bodies),
                                  "refused_subjects": self.refused_subjects}  # fmt: skip
        if self.share is not None:
            out["share"] = {"gateway": self.share.id, "members": sorted(self.share.members),
                            "foreign_samples": self.foreign_samples}  # fmt: skip
        if body is not None:
            heading = body.heading.state()
            drift = body.heading.drift
            if drift is not None and drift.pairs:
                # how far the joints' constraints have turned each child tag's heading
                # since calibration (6-axis drift); the other tags' drift is not corrected
                heading["drift_corrected_deg"] = {k: round(v, 2) for k, v
                                                  in drift.corrected_deg.items()}  # fmt: skip
                # how well each tag's heading is held: by a joint's constraint, or not
                # (a 6-axis tag's then drifts freely since calibration)
                heading["held_by"] = {k: pair[0] for k, pair in drift.pairs.items()}
                heading["not_held"] = sorted(set(body.solver.profile.imu_mounts)
                                             - set(drift.pairs))  # fmt: skip
                # per segment: what holds its tag's heading and how well it is known
                heading["segments"] = drift.segments(body.solver.profile)
            out["body"] = {"samples": body.samples, "ticks": body.ticks, "heading": heading}
            # sites by the source they come through, ids this version has no name for too
            with self._lock:
                kinds = Counter(source_name(s.sample.source) for s in body.latest.values())
                # each site's host clock against the gateway's (ms, + ahead; clock_check)
                clocks = {s.raw_key: k.offset_ms for s, k in body.latest.items()
                          if k.offset_ms is not None}  # fmt: skip
                # encoders whose zero is lost (their dofs flagged) or set by a pose
                encoders = states(body.encoders)
            out["sources"] = dict(sorted(kinds.items()))
            if encoders:
                out["encoders"] = encoders
            out["clock_offset_ms"] = dict(sorted(clocks.items()))
        return out

    def close(self) -> None:
        for decl in self._share_decls:
            decl.undeclare()  # type: ignore[attr-defined]
        for q in self._queryables:
            q.undeclare()
        for sub in self._subs:
            sub.undeclare()
        for live in self._live:
            live.undeclare()
        for body in list(self._bodies.values()):
            body.close()
        self.fits.close()
        for key_expr in self._declared.values():
            self.session.undeclare(key_expr)
        self._declared.clear()
