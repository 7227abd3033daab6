"""What a source is: a transport, a sans-io decoder, a site map and period, and
one adapter from decoder events to stamped readings.

A :class:`Source` subclass describes one kind of device or file (the SmartSuit
CAN bus, the Data Concentrator, the IMU central, SlimeVR trackers, orientation
files). The same :class:`Adapter` turns its decoder's events into readings with
a sequence number and a time for the live bridge (``live.Bridge``) and for the
capture reader (:meth:`Source.read`), so a sample has one meaning whichever
way it came. Nothing here imports Zenoh: offline processing reads captures
without loading it; the live parts import it when a bridge runs.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from bodynet.core.errors import Reason, RejectCounts, Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import (
    RESUMED,
    NodeStatus,
    NoNewData,
    OleAccel,
    Quat,
    Reading,
    SensorAbsent,
    StreamEvent,
    Tick,
)

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)

CHUNK = 1 << 16


class CaptureError(ValueError):
    """A capture or file that cannot be read; the message says where (file, line)."""


class EmulatorError(Exception):
    """An emulated device that cannot start (its link cannot be made, its bus
    opened, its server found); the message names the link, bus or server."""


def time_refused(t_s: float) -> str | None:
    """Why a capture's time of a sample (s) cannot be one, or None: it must be
    finite and within the signed 64-bit ns of a raw sample's time (+-292 years
    from 1970, ``core/codecs/raw_sample.py``)."""
    if not math.isfinite(t_s):
        return f"time {t_s} is not finite"
    if abs(t_s) * 1e9 >= 2**63:
        return f"time {t_s:g} s is beyond what a sample's time holds (64-bit ns, +-292 years)"
    return None


class Transport(StrEnum):
    """What carries a source's bytes."""

    CAN = "can bus"
    SERIAL = "serial port"
    UDP = "udp socket"
    FILE = "file"


class Decoder(Protocol):
    """A sans-io stream decoder: units in (bytes, a CAN frame, a datagram), events out."""

    def feed(self, data: Any) -> list[StreamEvent]: ...
    def close(self) -> list[StreamEvent]: ...


class Sink(Protocol):
    """Where an adapter puts what it makes of the events."""

    def sample(self, reading: Reading, seq: int, t_s: float, flags: int = 0) -> None: ...
    def reject(self, rejected: Rejected) -> None: ...
    def status(self, event: NoNewData | SensorAbsent | NodeStatus) -> None: ...


@dataclass(slots=True)
class _Grid:
    """One node's numbering (see :class:`PeriodicSeq`)."""

    count: int  # frames so far, less one
    phase: float  # when frame number 0 was due, on the grid of the node's frames
    last_t: float
    lost: int = 0  # periods counted as missed
    #: (time, time less ``count`` periods) of the last ``backlog_s`` of frames,
    #: the second rising (a sliding minimum: the front is the least)
    recent: deque[tuple[float, float]] = field(default_factory=deque)


class PeriodicSeq:
    """Sequence numbers of a source that sends every ``period_s`` and numbers
    nothing itself, from the times its frames came.

    A node's frames are numbered one after the other, and a period counts as
    missed (its number skipped) once all the node's frames of the last
    :attr:`BACKLOG_S` ran at least half a period behind the grid its earlier
    frames kept. So a frame that comes late, however late within that (a
    busy host, or an adapter holding frames back and handing them on at once),
    is not a missed period: the frames after it catch up with the grid. A missed
    frame keeps the node's frames a period behind: counted, at most
    :attr:`BACKLOG_S` later, where it shows; a node silent for longer than that is
    counted at its next frame. The grid goes back at once to a node that sends
    sooner than it, and follows one whose clock is slower than the host's by up
    to :attr:`DRIFT`.
    """

    #: how long frames may run late (and catch up) before a period counts as missed
    BACKLOG_S = 0.5
    #: how fast (s/s) the grid follows a node whose clock is slower than the host's
    DRIFT = 0.05

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._grids: dict[int, _Grid] = {}

    def next(self, node: int, t_s: float) -> int:
        grid = self._grids.get(node)
        if grid is None:
            self._grids[node] = _Grid(0, t_s, t_s, recent=deque([(t_s, t_s)]))
            return 0
        period = self.period_s
        grid.count += 1
        offset = t_s - grid.count * period
        recent = grid.recent
        while recent and recent[-1][1] >= offset:
            recent.pop()
        recent.append((t_s, offset))
        while recent[0][0] < t_s - self.BACKLOG_S:
            recent.popleft()
        behind = recent[0][1] - grid.lost * period - grid.phase  # the least lag of late
        if behind >= period / 2:
            missed = round(behind / period)
            grid.lost += missed
            behind -= missed * period
        late = offset - grid.lost * period - grid.phase  # this frame's
        if late < 0:
            grid.phase += late  # sooner than the grid: it was late
        elif behind > 0:
            grid.phase += min(behind, self.DRIFT * max(0.0, t_s - grid.last_t))
        grid.last_t = t_s
        return grid.count + grid.lost

    def resync(self) -> None:
        """The device was opened again: how late its frames came before tells
        nothing of the ones to come; a node's next frame is set on its grid at once."""
        for grid in self._grids.values():
            grid.recent.clear()


#: A SmartSuit node silent this long (s), and for this many of its periods or more
#: in a row, on a link its bridge saw alive, may have rebooted: its next sample is
#: ``RESUMED`` (a dsPIC33F's power-up timer alone is 128 ms; a lost frame is no reboot)
REBOOT_SILENCE_S = 0.1
REBOOT_MISSED = 2
#: A stretch this long in which the link was not seen (nothing read: a host too busy
#: to read, whose transport stamps frames when they are read) hides whether a node
#: was silent in it: no silence across it counts.
BLIND_S = REBOOT_SILENCE_S / 2
#: A whole bus quiet this long (s) or longer is a suit switched off and on (a battery
#: swap takes a person a second or more), every node's next sample ``RESUMED``; a
#: shorter one claims nothing (a logger or a bridge held up loses the whole bus at
#: once). A live bridge must have watched it all along: ``QUIET_READS`` or more
#: reads in a row that waited for a frame and came back on time (:meth:`Adapter.quiet`).
SUIT_QUIET_S = 0.5
QUIET_READS = 3


class Adapter:
    """A source's decoder events -> readings with a sequence number and a time.

    ``t_s`` given to :meth:`events` is the time of the unit the events came in
    (its arrival, or the time a log gives it); ``None`` where the medium has
    none, and then the source's own counter times the sample: ``tick /
    rate_hz``. The default numbers samples by the last :class:`Tick` (the
    stream's own, or the node's own when the tick names it); a source whose
    stream has no ticks numbers them otherwise (:meth:`stamp`).

    A SmartSuit sample is flagged ``RESUMED`` when its node may have rebooted
    since its last one (:meth:`resumed`): by default when the node was asked and
    did not answer (a ``no_reply``: a polled source) while its bridge watched
    (:meth:`unwatched`); :class:`PeriodicAdapter`
    judges its nodes' silences too. A device opened again (:meth:`restart`)
    claims nothing: its nodes' first samples are not flagged.
    """

    def __init__(self, period_s: float, rate_hz: float | None = None) -> None:
        self.period_s = period_s
        self.rate_hz = rate_hz or 1.0 / period_s
        self.tick = 0
        self.node_ticks: dict[int, int] = {}
        self.base = 0  # ticks of earlier connections, so sequence numbers keep rising
        self.unanswered: set[int] = set()  # nodes asked and silent since their last sample
        self._unwatched: set[int] = set()  # nodes whose last request claims nothing
        #: whether the units' times may be when they were read, not when they came (a
        #: live bridge's): then a stretch in which nothing was read is no silence
        self.watched = False

    def events(self, events: Iterable[StreamEvent], t_s: float | None, sink: Sink) -> None:
        """Hand each event to ``sink``: samples stamped (and flagged), markers taken,
        the rest as is."""
        for event in events:
            if isinstance(event, OleAccel):
                seq, t = self.stamp(event, t_s)
                sink.sample(event, seq, t, RESUMED if self.resumed(event.node, t) else 0)
            elif isinstance(event, Quat):
                seq, t = self.stamp(event, t_s)
                sink.sample(event, seq, t)
            elif isinstance(event, Tick):
                self.take_tick(event)
            elif isinstance(event, Rejected):
                if event.node is not None and event.reason in (Reason.NO_REPLY,
                                                               Reason.LATE_REPLY):  # fmt: skip
                    unwatched = event.node in self._unwatched
                    self._unwatched.discard(event.node)
                    if event.reason is Reason.NO_REPLY and not unwatched:
                        self.unanswered.add(event.node)
                sink.reject(event)
            else:
                sink.status(event)

    def resumed(self, node: int, t_s: float) -> bool:
        """Whether ``node``'s sample at ``t_s`` is its first after a silence that may
        have held a reboot (its encoder's zero lost): here, after a request it left
        unanswered (at least the reply's timeout and late window: 0.2 s)."""
        if node in self.unanswered:
            self.unanswered.discard(node)
            return True
        return False

    def unwatched(self, node: int) -> None:
        """A live bridge left its last request to ``node`` unanswered while it was
        held up itself (it did not look at the link all along): that request's
        ``no_reply`` claims no silence of the node."""
        self._unwatched.add(node)

    def seen(self, t_s: float) -> None:
        """The link was seen alive at ``t_s``: a unit of no node (another device's
        frame). Only :class:`PeriodicAdapter` needs it."""

    def quiet(self, t_from: float, t_to: float) -> None:
        """A live bridge watched the link from ``t_from`` to ``t_to`` and no unit
        came: a read that waited for one and came back on time (its thread ran all
        along). Only :class:`PeriodicAdapter` needs it."""

    def take_tick(self, tick: Tick) -> None:
        if tick.node is None:
            self.tick = tick.index
        else:
            self.node_ticks[tick.node] = tick.index

    def stamp(self, reading: Reading, t_s: float | None) -> tuple[int, float]:
        tick = self.node_ticks.get(reading.node, self.tick)
        return self.base + tick, (tick / self.rate_hz if t_s is None else t_s)

    def restart(self) -> None:
        """The device was opened again: its ticks start over, ours go on; what its
        nodes did while it was away is not known."""
        self.base += self.tick + 1
        self.tick = 0
        self.unanswered.clear()
        self._unwatched.clear()


class PeriodicAdapter(Adapter):
    """For a stream with no ticks of its own: numbered by arrival
    (:class:`PeriodicSeq`: a gap is a missed period), or, without times, by order
    at ``rate_hz``.

    A node's sample is ``RESUMED`` when the node said nothing for
    ``REBOOT_SILENCE_S`` and ``REBOOT_MISSED`` or more of its periods (and half
    one more, for jitter) while the link was seen alive: other units came (of
    any node, or of none: :meth:`seen`), no ``BLIND_S`` apart. A stretch of
    ``BLIND_S`` in which none came (the whole bus quiet) claims nothing across
    it, unless it lasted ``SUIT_QUIET_S`` (a suit switched off and on) and, for a
    live bridge (``watched`` True: its transport may stamp frames when they are
    read), it watched it all along (:meth:`quiet`). A capture's times are its
    link's record (``watched`` False): its quiet stretches need no watching. A
    bridge's single read that waited is no proof: nodes emulated beside it stall
    with it under load, and send what they owe at once."""

    def __init__(self, period_s: float, rate_hz: float | None = None) -> None:
        super().__init__(period_s, rate_hz)
        self._periodic = PeriodicSeq(period_s)
        self.count = 0
        self._last: dict[int, float] = {}  # each node's last sample since the link opened
        self._seen = -math.inf  # the last time the link was seen alive
        self._blind_end = -math.inf  # when it was seen again after a blind stretch
        self._silence_s = max(REBOOT_SILENCE_S, (REBOOT_MISSED + 0.5) * period_s)
        #: the reads in a row that watched the link quiet since then: (from, to, count)
        self._quiet: tuple[float, float, int] | None = None

    def quiet(self, t_from: float, t_to: float) -> None:
        q = self._quiet
        if q is not None and t_from - q[1] <= BLIND_S:
            self._quiet = (q[0], max(q[1], t_to), q[2] + 1)
        else:
            self._quiet = (t_from, t_to, 1)

    def seen(self, t_s: float) -> None:
        gap = t_s - self._seen
        if gap > BLIND_S and not (gap >= SUIT_QUIET_S and self._watched_quiet(t_s)):
            self._blind_end = t_s
        self._quiet = None
        self._seen = max(self._seen, t_s)

    def _watched_quiet(self, t_s: float) -> bool:
        """Whether the link was watched all along from its last unit to ``t_s``."""
        if not self.watched:
            return True
        q = self._quiet
        return (q is not None and q[2] >= QUIET_READS
                and q[0] - self._seen <= BLIND_S and t_s - q[1] <= BLIND_S)  # fmt: skip

    def resumed(self, node: int, t_s: float) -> bool:
        self.seen(t_s)
        last = self._last.get(node)
        self._last[node] = t_s
        asked = super().resumed(node, t_s)
        if last is None:
            return asked
        return asked or (t_s - last >= self._silence_s and last >= self._blind_end)

    def stamp(self, reading: Reading, t_s: float | None) -> tuple[int, float]:
        if t_s is None:
            t_s = self.count / self.rate_hz
        self.count += 1
        return self._periodic.next(reading.node, t_s), t_s

    def restart(self) -> None:
        super().restart()
        self._periodic.resync()
        self._last.clear()
        self._seen = self._blind_end = -math.inf
        self._quiet = None


@dataclass(frozen=True, slots=True)
class CapturedSample:
    """A decoded reading, where it sits, and the capture's time of it."""

    t_s: float
    reading: Reading
    site: Site
    flags: int = 0  # as a raw sample's (``RESUMED``)


@dataclass(slots=True)
class CaptureStats:
    """What a capture held besides its samples."""

    decoded: int = 0
    rejected: RejectCounts = field(default_factory=RejectCounts)
    no_new_data: int = 0
    sensor_absent: int = 0
    #: well-formed messages of other devices (a CAN bus shared with them), by kind
    foreign: Counter[str] = field(default_factory=Counter)
    #: where each line (byte, in a binary log) skipped as garbled was: "line 12"
    bad_places: list[str] = field(default_factory=list)
    #: a file's cells with no sample (a NaN or empty orientation cell: a dropped sample)
    no_sample: int = 0
    #: what else the reader says of the capture ("left out 3 columns ...")
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """``decoded N, rejected M (reason: count, ...)`` plus idle lines if any."""
        total = sum(self.rejected.values())
        text = f"decoded {self.decoded}, rejected {total}"
        if total:
            text += f" ({self.rejected.summary()})"
        idle = [(n, what) for n, what in ((self.no_new_data, "no new data"),
                (self.sensor_absent, "sensor absent"),
                (sum(self.foreign.values()), "other devices' frames"),
                (self.no_sample, "empty or NaN cells")) if n]  # fmt: skip
        if idle:
            text += "; not samples: " + ", ".join(f"{what} {n}" for n, what in idle)
        if self.bad_places:
            shown = ", ".join(self.bad_places[:10])
            more = f" and {len(self.bad_places) - 10} more" if len(self.bad_places) > 10 else ""
            text += f"; skipped garbled {shown}{more}"
        return "; ".join([text, *self.notes])

    def count(self, rejected: Rejected) -> None:
        self.rejected[rejected.reason] += 1
        log.debug("rejected %s: %s %r", rejected.reason, rejected.detail, rejected.data)


class CaptureSink:
    """A capture reader's sink: samples placed on their sites, the rest counted."""

    def __init__(self, sites: Mapping[int, Site], stats: CaptureStats) -> None:
        self.sites = sites
        self.stats = stats
        self.out: list[CapturedSample] = []

    def sample(self, reading: Reading, seq: int, t_s: float, flags: int = 0) -> None:
        site = self.sites.get(reading.node)
        if site is None:
            self.reject(Rejected(Reason.UNKNOWN_NODE, f"node {reading.node} has no site"))
            return
        self.stats.decoded += 1
        self.out.append(CapturedSample(round(t_s, 9), reading, site, flags))

    def reject(self, rejected: Rejected) -> None:
        self.stats.count(rejected)

    def status(self, event: NoNewData | SensorAbsent | NodeStatus) -> None:
        if isinstance(event, NoNewData):
            self.stats.no_new_data += 1
        elif isinstance(event, SensorAbsent):
            self.stats.sensor_absent += 1

    def take(self) -> list[CapturedSample]:
        out, self.out = self.out, []
        return out


def numbers(text: str) -> tuple[int, ...]:
    """``"1-3,7"`` -> (1, 2, 3, 7): node or sensor numbers as a user writes them,
    each within 1..65535 (an argparse type: a bad list is refused with its reason;
    bounds are checked before a range is expanded)."""
    from bodynet.session import argtypes

    return argtypes.number_list(1, 0xFFFF)(text)


def file_chunks(path: Path) -> Iterator[bytes]:
    """A file's bytes in chunks, then ``b""`` for the end (decoders' close())."""
    with path.open("rb") as f:
        while chunk := f.read(CHUNK):
            yield chunk
    yield b""


class Feed(Protocol):
    """What a source's :meth:`Source.serve` hands its events to (the live bridge)."""

    adapter: Adapter

    def feed(self, events: Iterable[StreamEvent], t_s: float | None = None) -> None: ...


#: Starts one emulated device with a bridge for it; returns what to stop, the
#: bridge's target and its keyword arguments (see :meth:`Source.node`).
NodeParts = tuple[Any, Callable[..., None], dict[str, Any]]


class Source:
    """One kind of source. Subclasses set the class attributes and the methods
    their transport needs; see docs/sources.md for adding one.

    - ``name``: its registry name (``bodynet bridge NAME``);
    - ``wire_id``: the source byte of its raw-sample messages (any 0-255; a
      gateway accepts ids it does not know);
    - ``transport``: what carries its bytes;
    - ``sites``/``period_s``: node number -> site, and how often a node sends;
    - ``formats``: capture formats it reads (``decode``/``process --format``);
    - ``emulators``: emulated devices it offers (``emulate DEVICE``, ``node --via``);
    - ``TIMING``: the fields of ``nodes.timing.LinkTiming`` its emulators honour
      (the CLI refuses a timing flag no emulated device given would use).
    """

    name: ClassVar[str]
    wire_id: ClassVar[int]
    transport: ClassVar[Transport]
    help: ClassVar[str] = ""
    SITES: ClassVar[Mapping[int, Site]] = {}
    PERIOD_S: ClassVar[float] = 0.01
    formats: ClassVar[Mapping[str, str]] = {}
    emulators: ClassVar[Mapping[str, str]] = {}
    TIMING: ClassVar[frozenset[str]] = frozenset()
    #: suffixes of capture files whose format goes without saying
    suffixes: ClassVar[Mapping[str, str]] = {}
    #: serial sources: the link's speed, and how long one read waits
    BAUD: ClassVar[int] = 115200
    SERIAL_TIMEOUT_S: ClassVar[float] = 0.05

    def __init__(self, sites: Mapping[int, Site] | None = None,
                 period_s: float | None = None) -> None:  # fmt: skip
        self.sites: Mapping[int, Site] = dict(self.SITES if sites is None else sites)
        self.period_s = self.PERIOD_S if period_s is None else period_s

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> Source:
        """The source for reading files, given the capture options (``--map``...)."""
        return cls()

    @classmethod
    def add_capture_args(cls, parser: argparse.ArgumentParser) -> None:
        """Options of ``decode``/``process`` this source's files take."""

    # --- the sans-io part, the same live and from files ---------------------------------
    def decoder(self) -> Decoder:
        raise NotImplementedError(f"{self.name} has no stream decoder")

    def adapter(self, rate_hz: float | None = None) -> Adapter:
        return Adapter(self.period_s, rate_hz)

    # --- captures -----------------------------------------------------------------------
    def read(self, path: Path, fmt: str, stats: CaptureStats,
             rate_hz: float | None = None) -> Iterator[CapturedSample]:  # fmt: skip
        """Decode a capture file into samples (capture time), counting the rest in
        ``stats``; :class:`CaptureError` if the file cannot be read as ``fmt``.
        The default feeds the file's bytes to :meth:`decoder`."""
        decoder, adapter = self.decoder(), self.adapter(rate_hz)
        sink = CaptureSink(self.sites, stats)
        for chunk in file_chunks(path):
            adapter.events(decoder.feed(chunk) if chunk else decoder.close(), None, sink)
            yield from sink.take()

    # --- live ---------------------------------------------------------------------------
    @classmethod
    def add_bridge_args(cls, parser: argparse.ArgumentParser) -> None:
        """Options of ``bodynet bridge NAME``; a source without a bridge adds none
        and :meth:`bridge` refuses."""

    @classmethod
    def has_bridge(cls) -> bool:
        return cls.transport is not Transport.FILE

    def bridge(self, session: zenoh.Session, stop: threading.Event, name: str,
               args: argparse.Namespace) -> None:  # fmt: skip
        """Serve the device ``args`` name until ``stop``, publishing on ``session``."""
        raise NotImplementedError(f"{self.name} has no live bridge")

    def serve(self, link: Any, stop: threading.Event, bridge: Feed) -> None:
        """A serial source's work on its open port (pyserial's ``Serial``) until
        ``stop``: by default read what comes and feed it to the decoder."""
        decoder = self.decoder()
        while not stop.is_set():
            bridge.feed(decoder.feed(link.read(max(1, link.in_waiting))))

    @classmethod
    def bridge_name(cls, args: argparse.Namespace) -> str:
        """The name on the health key when ``--name`` is not given."""
        return cls.name

    # --- emulation ----------------------------------------------------------------------
    @classmethod
    def add_emulate_args(cls, device: str, parser: argparse.ArgumentParser) -> None:
        """Options of ``bodynet emulate DEVICE`` besides the emulation ones."""

    def emulate(self, device: str, stop: threading.Event, body: Any, truth: Any,
                args: argparse.Namespace) -> None:  # fmt: skip
        """Run the emulated ``device`` driven by ``body`` until ``stop``."""
        raise NotImplementedError(f"{self.name} has no emulator")

    def emulated_sensors(self, sensors: Any = None, branches: Any = None) -> list[Any]:
        """The emulated sensors of this source (see ``nodes.emulator``)."""
        raise NotImplementedError(f"{self.name} has no emulator")

    def node(self, device: str, body: Any, where: Path, clock: Any, truth: Any,
             sensors: list[Any], label: str) -> NodeParts:  # fmt: skip
        """An emulated ``device`` (started by the caller) beside which a bridge runs."""
        raise NotImplementedError(f"{self.name} has no emulator")
