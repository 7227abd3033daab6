"""Emulated hardware on real transports, driven by a :class:`BodyEmulator`.

- :class:`CanNodes`: SmartSuit sensing nodes sending their frames every 10 ms
  on any python-can bus (``virtual`` in one process, ``socketcan`` vcan...).
- :class:`ConcentratorEmulator`: a Data Concentrator on a pseudo-terminal
  answering request characters on its ~22 ms cycle (115200 baud).
- :class:`ImuCentralEmulator`: the IMU central on a pseudo-terminal printing the
  data matrix every tick (230400 baud), its BLE tags each on a timer of its own.
- :class:`SlcanAdapterEmulator`: a Lawicel slcan USB-CAN adapter on a
  pseudo-terminal, with SmartSuit nodes behind it, so python-can's ``slcan``
  interface is exercised end to end.

How their link's timing falls short of an ideal one is a
:class:`~bodynet.nodes.timing.LinkTiming` (the default: lock-step, nothing
lost): CAN nodes on timers of their own (own phase, own clock error), each
send late by up to the jitter, frames lost (not sent, counted in ``dropped``
per node); a concentrator answering late now and then, past the bridge's
reply timeout, or not at all; IMU tags on timers of their own whose
notifications are lost (the central prints "no new data" when none came since
its last line). A CAN node or an IMU tag can be silenced for a span (an
outage: ``silence``). The truth of each reading that goes out is handed to the
``truth`` sink, with the time the reading was taken. A SmartSuit node behind
the CAN emulators or the concentrator can be rebooted (``reboot(node)``: a
brown-out, a loose connector): it says nothing for its start-up time, then its
encoder counts from 0 where its joint is then, as the real firmware's QEI reset
makes it (000 seed, ch. 3.4.1); or the whole suit switched off and on
(``power_cycle``: a battery swap), every node at once.

Each pseudo-terminal is reached through a stable symlink (like udev's
``/dev/serial/by-id/...``), so :meth:`PtyPort.unplug` and :meth:`PtyPort.plug`
emulate pulling the USB cable and putting it back.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import secrets
import select
import termios
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import can

from bodynet.core.codecs import concentrator, imu_matrix, smartsuit_can
from bodynet.core.codecs.smartsuit_can import SlcanDecoder, SlcanReply
from bodynet.core.messages import (
    STAMP_SPREAD_S,
    NoNewData,
    OleAccel,
    Quat,
    Reading,
    SensorAbsent,
    Source,
)
from bodynet.nodes.emulator import BodyEmulator, Truth
from bodynet.nodes.loop import Loop
from bodynet.nodes.sources.base import EmulatorError
from bodynet.nodes.sources.concentrator import LATE_WINDOW_S, REPLY_TIMEOUT_S
from bodynet.nodes.timing import Clock, LinkTiming, NodeTimers, Sends, link_schedule
from bodynet.session.argtypes import is_pty_link

log = logging.getLogger(__name__)

TruthSink = Callable[[int, Truth, int], None]  # node, truth, t_ns
# the devices' timing is their protocol's: the emulators keep to it
CAN_PERIOD_S = smartsuit_can.PERIOD_S
CONCENTRATOR_CYCLE_S = concentrator.CYCLE_S
IMU_TICK_S = imu_matrix.TICK_S
#: how often an IMU tag sends its reading: its BLE connection interval, the longest
#: the tags allow (003 seed, Table 7.6: 10 to 30 ms), which the gateway states a
#: central's sample may be older than its stamp; shorter than the central's tick,
#: so a tag whose notifications get through has a new reading at every tick
TAG_INTERVAL_S = STAMP_SPREAD_S[Source.IMU_CENTRAL]
_BAUD = {115200: termios.B115200, 230400: termios.B230400}
#: A node's reading is the body at most this long before its send: sends due this
#: close together share one sample of the body (which costs as much for one sensor
#: as for all)
SAMPLE_REUSE_S = 0.002
#: When a late concentrator answers, after the request: past the bridge's reply
#: timeout, early in the window in which it still takes the reply as late
LATE_REPLY_S = REPLY_TIMEOUT_S + LATE_WINDOW_S / 4
#: How long a rebooted node says nothing: the dsPIC33F's power-up timer (128 ms
#: in its default configuration), then the oscillator's and the CAN controller's
#: start-up in the firmware's initialisation
BOOT_S = 0.2
#: How long a suit switched off and on is off: a battery swapped by hand
SWAP_S = 1.5


class Held(NamedTuple):
    """A reading kept to be sent later, with its truth and when it was taken."""

    reading: Reading
    truth: Truth
    t_ns: int


class _Sampler:
    """The body's readings for a device's sends, and the truth of each one sent.

    :meth:`readings` samples the body now, or gives the last sample when it is
    less than ``reuse_s`` old; :meth:`sent` hands the truth of a reading of it
    that went out to the sink, with the time it was taken."""

    def __init__(self, body: BodyEmulator, clock: Clock, truth: TruthSink | None,
                 reuse_s: float = 0.0) -> None:  # fmt: skip
        self.body, self.clock, self.truth, self.reuse_s = body, clock, truth, reuse_s
        self._at = -math.inf
        self._readings: dict[int, Reading] = {}
        self._truths: dict[int, Truth] = {}
        self._t_ns = 0

    def readings(self, at: float | None = None) -> dict[int, Reading]:
        """Every emulated sensor's reading, by node: the body as of ``at``
        (monotonic, a send's due time; default now)."""
        at = time.monotonic() if at is None else at
        if abs(at - self._at) >= self.reuse_s:
            t = at - self.clock.t0
            readings, truths = self.body.sample(t)
            self._at, self._t_ns = at, self.clock.wall_ns(t)
            self._readings = {r.node: r for r in readings}
            self._truths = {r.node: truth for r, truth in zip(readings, truths, strict=True)}
        return self._readings

    def invalidate(self) -> None:
        """The next :meth:`readings` samples the body afresh (a sensor changed)."""
        self._at = -math.inf

    def sent(self, reading: Reading, t_ns: int | None = None) -> None:
        """``reading`` (of the last :meth:`readings`) went out; its truth is given as
        of ``t_ns`` (the time its frame carries), else as of when it was taken."""
        self.give(Held(reading, self._truths[reading.node], self._t_ns if t_ns is None else t_ns))

    def held(self, node: int, at: float | None = None) -> Held:
        """``node``'s reading as of ``at`` (as :meth:`readings`), with its truth, to
        send later."""
        reading = self.readings(at)[node]
        return Held(reading, self._truths[node], self._t_ns)

    def give(self, held: Held) -> None:
        """``held`` went out: its truth, as of when it was taken, to the sink."""
        if self.truth is not None:
            self.truth(held.reading.node, held.truth, held.t_ns)


class _OnTimers:
    """Nodes that send on their own timers (:class:`NodeTimers`): the frames they
    lost, and the loss in force."""

    timers: NodeTimers

    @property
    def dropped(self) -> Counter[int]:
        """Frames lost, by node (an slcan adapter's: while it was open)."""
        return self.timers.dropped

    @property
    def drop(self) -> float:
        """The probability a frame is lost, in force now (settable)."""
        return self.timers.drop

    @drop.setter
    def drop(self, value: float) -> None:
        self.timers.drop = value

    def silence(self, node: int, seconds: float) -> None:
        """Lose every frame of ``node`` from now for ``seconds`` (an outage)."""
        self.timers.silence(node, time.monotonic(), seconds)


class _Reboots:
    """SmartSuit nodes that can be rebooted (:meth:`reboot`)."""

    body: BodyEmulator
    clock: Clock
    _sampler: _Sampler
    #: node -> when (monotonic) it is up again, while it is starting
    _off: dict[int, float]
    #: reboots, by node
    reboots: Counter[int]

    def reboot(self, node: int, boot_s: float = BOOT_S) -> None:
        """Node ``node`` loses power now: it sends nothing for ``boot_s``, then
        starts again, its encoder counting from 0 where its joint is then.
        ``KeyError`` if ``node`` is no SmartSuit module."""
        if node not in self.body.module_nodes:
            raise KeyError(f"node {node} is no SmartSuit module of this body")
        self._off[node] = time.monotonic() + boot_s
        self.reboots[node] += 1

    def power_cycle(self, off_s: float = SWAP_S) -> None:
        """The whole suit switched off now and on ``off_s`` later (a battery swap):
        every node (the trunk's IMUs too) says nothing until then; each module then
        starts as after :meth:`reboot`, its encoder counting from 0 where its joint
        is then."""
        until = time.monotonic() + off_s
        for sensor in self.body.sensors:
            self._off[sensor.node] = until
            self.reboots[sensor.node] += 1

    def _powered(self, nodes: Sequence[int]) -> list[int]:
        """Of ``nodes``, those up now (:meth:`_up`)."""
        if not self._off:
            return list(nodes)
        now = time.monotonic()
        return [node for node in nodes if self._up(node, now)]

    def _up(self, node: int, at: float) -> bool:
        """Whether ``node`` is up at ``at`` (monotonic); a node whose start-up has
        ended by then is powered on (its encoder's zero where its joint is now)."""
        until = self._off.get(node)
        if until is None:
            return True
        if at < until:
            return False
        del self._off[node]
        if node in self.body.module_nodes:  # an IMU's orientation is absolute
            self.body.power_on(node, self.clock.now())
        self._sampler.invalidate()
        return True


class CanNodes(_Reboots, _OnTimers, Loop):
    """SmartSuit nodes on a python-can bus, each sending a frame every 10 ms.

    When each node sends, and which frames are lost, ``timing`` says (default:
    all at once, none lost); a lost frame is not sent and is counted in
    :attr:`dropped`. :attr:`drop` is the probability of a loss in force (it may
    be changed while the nodes run).

    Each frame carries when it was due (``msg.timestamp``, the wall clock), and
    its truth is given as of then: real nodes send on their own timers whatever
    the host does, and an adapter stamps their frames as they come (socketcan's
    kernel time), where these nodes share a host that a loaded machine starves,
    and then send what they owe at once. A virtual bus opened with
    ``preserve_timestamps`` keeps those times; a node rebooting is silent for
    the frames due while it is off, even those sent after it."""

    def __init__(
        self,
        bus: can.BusABC,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        period_s: float = CAN_PERIOD_S,
        timing: LinkTiming | None = None,
    ) -> None:
        super().__init__("can-nodes")
        self.bus, self.body, self.clock, self.truth = bus, body, clock or Clock(), truth
        self.period_s = period_s
        self.timers = NodeTimers([s.node for s in body.sensors], period_s, timing or LinkTiming())
        #: frames sent, by node
        self.sent: Counter[int] = Counter()
        self._sampler = _Sampler(body, self.clock, truth, SAMPLE_REUSE_S)
        self._off, self.reboots = {}, Counter()

    def run(self) -> None:
        timers = self.timers
        timers.start(time.monotonic())
        while not self.stop_event.is_set():
            wait = timers.next_due - time.monotonic()
            if wait > 0:
                self.stop_event.wait(wait)
                continue
            sends = [(n, due) for n, due in timers.due_at(time.monotonic()) if self._up(n, due)]
            readings = self._sampler.readings() if sends else {}
            for node, due in sends:
                reading = readings[node]
                frame = smartsuit_can.encode_reading(reading)
                due_ns = self.clock.wall_ns(due - self.clock.t0)
                self.bus.send(
                    can.Message(
                        timestamp=due_ns / 1e9,
                        arbitration_id=frame.arbitration_id,
                        data=frame.data,
                        is_extended_id=True,
                    )
                )
                self.sent[node] += 1
                self._sampler.sent(reading, due_ns)


class PtyPort:
    """A pseudo-terminal whose far end is reached through a stable symlink.

    ``read``, ``write`` and ``unplug`` take one lock: a descriptor is never
    closed while another thread is using it, since the number could otherwise be
    handed to a new socket or file and that thread read or write someone else's data.
    """

    #: Longest a write waits for the far end to make room before the rest is dropped
    #: (a UART's buffer overflowing); bounds how long ``unplug`` can wait.
    WRITE_TIMEOUT_S = 0.5

    def __init__(self, link: Path, baud: int) -> None:
        self.link = Path(link)
        self.baud = baud
        self.master: int | None = None
        self._slave: int | None = None
        self.plugged = threading.Event()
        self.dropped = 0  # bytes the far end did not make room for
        self._lock = threading.Lock()
        self._target: str | None = None  # the terminal the link was pointed at

    def plug(self) -> None:
        """Create the device (again) and point the symlink at it.

        :class:`EmulatorError` if the link cannot be made, or if something other
        than a link to a pseudo-terminal (a stale one, which is replaced) is there:
        nothing is deleted that the port did not make."""
        master, slave = os.openpty()
        try:
            os.set_blocking(master, False)
            tty.setraw(slave)
            attrs = termios.tcgetattr(slave)
            attrs[4] = attrs[5] = _BAUD.get(self.baud, termios.B115200)
            termios.tcsetattr(slave, termios.TCSANOW, attrs)
            self._point_link(os.ttyname(slave))
        except BaseException:
            os.close(master)
            os.close(slave)
            raise
        with self._lock:
            self.master, self._slave = master, slave
        self.plugged.set()

    def _point_link(self, target: str) -> None:
        if os.path.lexists(self.link) and not is_pty_link(self.link):
            raise EmulatorError(f"refusing to replace {self.link}: it is not a link to a "
                                "pseudo-terminal; give a new name")  # fmt: skip
        # a new name of this process's (never one that may be someone's file), then
        # renamed over the link: a bridge opening it meanwhile finds the old or the new
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
        try:
            tmp.symlink_to(target)
            try:
                tmp.replace(self.link)
            except OSError:
                tmp.unlink(missing_ok=True)
                raise
        except OSError as exc:
            why = exc.strerror or exc
            raise EmulatorError(f"cannot make the link {self.link}: {why}") from None
        self._target = target

    def unplug(self) -> None:
        """Remove the device: its users' reads and writes fail, as on a USB unplug."""
        self.plugged.clear()
        # the link only if it is still the one made here (not a file put there since)
        with contextlib.suppress(OSError):
            if self._target is not None and os.readlink(self.link) == self._target:
                self.link.unlink()
        with self._lock:
            for fd in (self.master, self._slave):
                if fd is not None:
                    os.close(fd)
            self.master = self._slave = None

    def read(self, timeout: float) -> bytes:
        """What the far end wrote, waiting up to ``timeout``; b"" if nothing."""
        with self._lock:
            master = self.master
            if master is not None:
                try:
                    ready, _, _ = select.select([master], [], [], timeout)
                    return os.read(master, 4096) if ready else b""
                except OSError:  # the far end hung up
                    return b""
        self.plugged.wait(timeout)
        return b""

    def write(self, data: bytes) -> None:
        """Send ``data`` to the far end; dropped if unplugged or not read in time."""
        view = memoryview(data)
        deadline = time.monotonic() + self.WRITE_TIMEOUT_S
        with self._lock:
            master = self.master
            while master is not None and view:
                try:
                    _, ready, _ = select.select(
                        [], [master], [], max(0.0, deadline - time.monotonic())
                    )
                    if not ready:
                        break
                    view = view[os.write(master, view) :]
                except BlockingIOError:
                    continue
                except OSError:  # the far end hung up
                    break
            self.dropped += len(view)


class _PtyEmulator(Loop):
    """A device on a pseudo-terminal, driven by an emulated body."""

    def __init__(self, name: str, link: Path, baud: int, body: BodyEmulator,
                 clock: Clock | None, truth: TruthSink | None,
                 reuse_s: float = 0.0) -> None:  # fmt: skip
        super().__init__(name)
        self.port = PtyPort(link, baud)
        self.body, self.clock, self.truth = body, clock or Clock(), truth
        self._sampler = _Sampler(body, self.clock, truth, reuse_s)

    @property
    def link(self) -> Path:
        return self.port.link

    def start(self) -> None:
        self.port.plug()
        super().start()

    def stop(self) -> None:
        super().stop()
        if self.port.master is not None:
            self.port.unplug()


class ConcentratorEmulator(_Reboots, _PtyEmulator):
    """The Data Concentrator: one reply per ~22 ms cycle to each request.

    Requests are short (``'I'`` for node 1...) or extended lines; replies come
    in the same form. Nodes in ``silent`` never answer (a dead sensor). Of the
    other requests, a share ``timing.late`` is answered ``late_s`` after it
    came, past the bridge's reply timeout (counted in :attr:`answered_late`),
    and a share ``timing.drop`` not at all (counted in :attr:`dropped`); the
    probabilities in force are :attr:`late` and :attr:`drop` (they may be
    changed while it runs).
    """

    def __init__(
        self,
        link: Path,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        cycle_s: float = CONCENTRATOR_CYCLE_S,
        silent: Sequence[int] = (),
        timing: LinkTiming | None = None,
        late_s: float = LATE_REPLY_S,
    ) -> None:
        super().__init__("concentrator-emulator", link, concentrator.BAUD, body, clock, truth)
        self.cycle_s = cycle_s
        self.silent = set(silent)
        timing = timing or LinkTiming()
        self.drop, self.late, self.late_s = timing.drop, timing.late, late_s
        self._rng = timing.draws()
        self.replies = 0
        #: replies given late, and requests never answered (not ``silent``), by node
        self.answered_late: Counter[int] = Counter()
        self.dropped: Counter[int] = Counter()
        #: requests received, by node
        self.asked: Counter[int] = Counter()
        self._off, self.reboots = {}, Counter()

    def run(self) -> None:
        pending: list[tuple[int, bool, float, str]] = []  # (node, extended, when, fate)
        line = bytearray()
        next_cycle = time.monotonic()
        while not self.stop_event.is_set():
            due = max(next_cycle, pending[0][2]) if pending else math.inf
            wait = max(0.0, due - time.monotonic()) if pending else 0.05
            for b in self.port.read(wait):
                node = concentrator.node_of_request(b)
                if node is not None and not line:
                    pending.append(self._request(node, False))
                elif b in b"\r\n":
                    if line:
                        try:
                            result = concentrator.decode_extended(line)
                        except ValueError:
                            result = None
                        if isinstance(result, int):
                            pending.append(self._request(result, True))
                        line.clear()
                elif 0x30 <= b <= 0x39 or b in b" +-":
                    line.append(b)
            if pending and time.monotonic() >= max(next_cycle, pending[0][2]):  # its turn
                node, extended, _, fate = pending.pop(0)
                self._answer(node, extended, fate)
                next_cycle = time.monotonic() + self.cycle_s

    def _request(self, node: int, extended: bool) -> tuple[int, bool, float, str]:
        """A request just came: when it is to be answered, and how."""
        now = time.monotonic()
        self.asked[node] += 1
        if self.drop and self._rng.random() < self.drop:
            return node, extended, now, "lost"
        if self.late and self._rng.random() < self.late:
            return node, extended, now + self.late_s, "late"
        return node, extended, now, "on time"

    def _answer(self, node: int, extended: bool, fate: str) -> None:
        if node in self.silent or not self._powered([node]):
            return
        if fate == "lost":
            self.dropped[node] += 1
            return
        reading = self._sampler.readings().get(node)
        if isinstance(reading, OleAccel):
            self.port.write(
                concentrator.encode_extended_reply(reading)
                if extended
                else concentrator.encode_reply(reading)
            )
            self.replies += 1
            self.answered_late[node] += fate == "late"
            self._sampler.sent(reading)


class ImuCentralEmulator(_OnTimers, _PtyEmulator):
    """The IMU central and its BLE tags: every tick one line per sensor slot 1..15.

    Each tag sends its reading every ``interval_s`` (its connection interval) on
    a timer of its own as ``timing`` says (own phase and clock error when
    independent, late by up to the jitter), and a share ``timing.drop`` of its
    notifications is lost on the air (:attr:`dropped`, :attr:`drop` in force;
    :meth:`silence` loses all of a tag's for a span). The central keeps each
    tag's latest reading, with the truth at the time it was taken (when it was
    due on the tag's timer, also when a loaded host held the emulator up), and prints
    its lines on a clock of its own every ``tick_s`` (its own clock error and
    jitter): flag 01 with the quaternion when a reading came since its last
    line, 00 (no new data) when none did, ff for a slot no tag has sent on yet.
    A tag in ``dropouts`` prints 00 on every ``dropout_every``-th tick too.
    :attr:`no_new` counts the 00 lines of each tag.
    """

    def __init__(
        self,
        link: Path,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        tick_s: float = IMU_TICK_S,
        dropouts: Sequence[int] = (),
        dropout_every: int = 4,
        timing: LinkTiming | None = None,
        interval_s: float = TAG_INTERVAL_S,
    ) -> None:
        super().__init__("imu-central-emulator", link, imu_matrix.BAUD, body, clock, truth,
                         SAMPLE_REUSE_S)  # fmt: skip
        self.tick_s = tick_s
        self.dropouts, self.dropout_every = set(dropouts), dropout_every
        timing = timing or LinkTiming()
        self.timers = NodeTimers([s.node for s in body.sensors], interval_s, timing)
        self._central = timing.of(0)  # the central's own clock and jitter, not a tag's
        self.ticks = 0
        #: lines of no new data (00) of each tag
        self.no_new: Counter[int] = Counter()

    def run(self) -> None:
        tags, central = self.timers, self._central
        start = time.monotonic()
        tags.start(start)
        ticks = Sends(link_schedule(1, self.tick_s, central), start, central.jitter_s,
                      central.draws())  # fmt: skip
        latest: dict[int, Held] = {}  # each tag's reading not yet printed
        heard: set[int] = set()
        while not self.stop_event.is_set():
            due = min(tags.next_due, ticks.next_due)
            self.port.read(max(0.0, due - time.monotonic()))  # drain, and pace
            now = time.monotonic()
            # in time order, also when behind: the notifications before the next line,
            # each the body as of when it was due (a tag reads on its own timer)
            for node, due_at in tags.due_at(min(now, ticks.next_due)):
                latest[node] = self._sampler.held(node, due_at)
                heard.add(node)
            if ticks.next_due <= now:
                ticks.pop()
                self.port.write(self._lines(latest, heard))
                self.ticks += 1

    def _lines(self, latest: dict[int, Held], heard: set[int]) -> bytes:
        """One tick's lines; the readings printed are taken out of ``latest``."""
        lines = []
        dropout = self.ticks % self.dropout_every == 1
        for slot in range(1, imu_matrix.MAX_SENSORS + 1):
            held = latest.pop(slot, None)
            if slot not in heard:
                lines.append(imu_matrix.encode_line(SensorAbsent(slot)))
            elif (
                held is None
                or not isinstance(held.reading, Quat)
                or (dropout and slot in self.dropouts)
            ):
                lines.append(imu_matrix.encode_line(NoNewData(slot)))
                self.no_new[slot] += 1
            else:
                extra = (self.ticks & 0xFFFF).to_bytes(2, "little")  # a line counter
                lines.append(imu_matrix.encode_line(Quat(slot, held.reading.wxyz, extra)))
                self._sampler.give(held)
        return b"".join(lines)


class SlcanAdapterEmulator(_Reboots, _OnTimers, _PtyEmulator):
    """A Lawicel slcan adapter with SmartSuit nodes on its CAN side.

    Answers the host's commands (``S``/``s`` bitrate, ``O``/``L`` open,
    ``C`` close, ``V`` version, ``N`` serial number, ``T``/``t`` transmit) and,
    while open, forwards each node's frame every 10 ms as a ``T`` line: when,
    and which are lost, ``timing`` says, as for :class:`CanNodes`.
    """

    def __init__(
        self,
        link: Path,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        period_s: float = CAN_PERIOD_S,
        timing: LinkTiming | None = None,
    ) -> None:
        super().__init__("slcan-emulator", link, 115200, body, clock, truth, SAMPLE_REUSE_S)
        self.period_s = period_s
        self.timers = NodeTimers([s.node for s in body.sensors], period_s, timing or LinkTiming())
        self.is_open = False
        #: frames forwarded, by node
        self.sent: Counter[int] = Counter()
        self.received: list[smartsuit_can.CanFrame] = []
        self._off, self.reboots = {}, Counter()

    def run(self) -> None:
        decoder = SlcanDecoder()
        timers = self.timers
        timers.start(time.monotonic())
        while not self.stop_event.is_set():
            for event in decoder.feed(self.port.read(max(0.0, timers.next_due - time.monotonic()))):
                self._command(event)
            now = time.monotonic()
            if now < timers.next_due:
                continue
            nodes = self._powered(timers.due(now, lossy=self.is_open))
            if self.is_open and nodes:
                readings = self._sampler.readings()
                sent = [readings[n] for n in nodes]
                frames = [smartsuit_can.encode_slcan(smartsuit_can.encode_reading(r)) for r in sent]
                self.port.write(b"".join(frames))
                for reading in sent:
                    self.sent[reading.node] += 1
                    self._sampler.sent(reading)

    def _command(self, event: object) -> None:
        if isinstance(event, smartsuit_can.CanFrame):
            self.received.append(event)
            self.port.write(b"Z\r" if event.is_extended_id else b"z\r")
            return
        text = event.text if isinstance(event, SlcanReply) else ""
        reply = {"V": b"V1013\r", "N": b"NBN01\r"}.get(text[:1], b"\r")
        if text[:1] in ("O", "L"):
            self.is_open = True
        elif text[:1] == "C":
            self.is_open = False
        elif text[:1] not in ("S", "s", "V", "N", "F", "Z", "M", "m"):
            reply = b"\a"
        self.port.write(reply)
