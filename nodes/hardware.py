"""Emulated hardware on real transports, driven by a :class:`BodyEmulator`.

- :class:`CanNodes`: SmartSuit sensing nodes sending their frames every 10 ms
  on any python-can bus (``virtual`` in one process, ``socketcan`` vcan...).
- :class:`ConcentratorEmulator`: a Data Concentrator on a pseudo-terminal
  answering request characters on its ~22 ms cycle (115200 baud).
- :class:`ImuCentralEmulator`: the IMU central on a pseudo-terminal printing the
  data matrix every tick (230400 baud).
- :class:`SlcanAdapterEmulator`: a Lawicel slcan USB-CAN adapter on a
  pseudo-terminal, with SmartSuit nodes behind it, so python-can's ``slcan``
  interface is exercised end to end.

Each pseudo-terminal is reached through a stable symlink (like udev's
``/dev/serial/by-id/...``), so :meth:`PtyPort.unplug` and :meth:`PtyPort.plug`
emulate pulling the USB cable and putting it back.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import select
import termios
import threading
import time
import tty
from collections.abc import Callable, Sequence
from pathlib import Path

import can

from bodynet.core.codecs import concentrator, imu_matrix, smartsuit_can
from bodynet.core.codecs.smartsuit_can import SlcanDecoder, SlcanReply
from bodynet.core.messages import NoNewData, OleAccel, Quat, Reading, SensorAbsent
from bodynet.nodes.emulator import BodyEmulator, Truth
from bodynet.nodes.loop import Loop
from bodynet.nodes.sources.base import EmulatorError
from bodynet.session.argtypes import is_pty_link

log = logging.getLogger(__name__)

TruthSink = Callable[[int, Truth, int], None]  # node, truth, t_ns
# the devices' timing is their protocol's: the emulators keep to it
CAN_PERIOD_S = smartsuit_can.PERIOD_S
CONCENTRATOR_CYCLE_S = concentrator.CYCLE_S
IMU_TICK_S = imu_matrix.TICK_S
_BAUD = {115200: termios.B115200, 230400: termios.B230400}


class Clock:
    """Seconds since ``t0`` on the monotonic clock; shared so emulators agree."""

    def __init__(self, t0: float | None = None) -> None:
        self.t0 = time.monotonic() if t0 is None else t0

    def now(self) -> float:
        return time.monotonic() - self.t0


def _sample(body: BodyEmulator, clock: Clock, truth: TruthSink | None) -> list[Reading]:
    readings, truths = body.sample(clock.now())
    if truth is not None:
        t_ns = time.time_ns()
        for reading, tr in zip(readings, truths, strict=True):
            truth(reading.node, tr, t_ns)
    return readings


class CanNodes(Loop):
    """SmartSuit nodes on a python-can bus, one frame each every 10 ms."""

    def __init__(
        self,
        bus: can.BusABC,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        period_s: float = CAN_PERIOD_S,
    ) -> None:
        super().__init__("can-nodes")
        self.bus, self.body, self.clock, self.truth = bus, body, clock or Clock(), truth
        self.period_s = period_s
        self.sent = 0

    def run(self) -> None:
        deadline = time.monotonic()
        while not self.stop_event.is_set():
            for reading in _sample(self.body, self.clock, self.truth):
                frame = smartsuit_can.encode_reading(reading)
                self.bus.send(
                    can.Message(
                        arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=True
                    )
                )
                self.sent += 1
            deadline += self.period_s
            self.stop_event.wait(max(0.0, deadline - time.monotonic()))


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
                 clock: Clock | None, truth: TruthSink | None) -> None:  # fmt: skip
        super().__init__(name)
        self.port = PtyPort(link, baud)
        self.body, self.clock, self.truth = body, clock or Clock(), truth

    def sample(self) -> list[Reading]:
        return _sample(self.body, self.clock, self.truth)

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


class ConcentratorEmulator(_PtyEmulator):
    """The Data Concentrator: one reply per ~22 ms cycle to each request.

    Requests are short (``'I'`` for node 1...) or extended lines; replies come
    in the same form. Nodes in ``silent`` never answer (a dead sensor).
    """

    def __init__(
        self,
        link: Path,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        cycle_s: float = CONCENTRATOR_CYCLE_S,
        silent: Sequence[int] = (),
    ) -> None:
        super().__init__("concentrator-emulator", link, concentrator.BAUD, body, clock, truth)
        self.cycle_s = cycle_s
        self.silent = set(silent)
        self.replies = 0

    def run(self) -> None:
        pending: list[tuple[int, bool]] = []  # (node, extended)
        line = bytearray()
        next_cycle = time.monotonic()
        while not self.stop_event.is_set():
            wait = max(0.0, next_cycle - time.monotonic()) if pending else 0.05
            for b in self.port.read(wait):
                node = concentrator.node_of_request(b)
                if node is not None and not line:
                    pending.append((node, False))
                elif b in b"\r\n":
                    if line:
                        try:
                            result = concentrator.decode_extended(line)
                        except ValueError:
                            result = None
                        if isinstance(result, int):
                            pending.append((result, True))
                        line.clear()
                elif 0x30 <= b <= 0x39 or b in b" +-":
                    line.append(b)
            if pending and time.monotonic() >= next_cycle:
                node, extended = pending.pop(0)
                self._answer(node, extended)
                next_cycle = time.monotonic() + self.cycle_s

    def _answer(self, node: int, extended: bool) -> None:
        if node in self.silent:
            return
        for reading in self.sample():
            if reading.node == node and isinstance(reading, OleAccel):
                self.port.write(
                    concentrator.encode_extended_reply(reading)
                    if extended
                    else concentrator.encode_reply(reading)
                )
                self.replies += 1


class ImuCentralEmulator(_PtyEmulator):
    """The IMU central: every tick one line per sensor slot 1..15.

    Emulated tags print flag 01 with their quaternion; slots with no tag print
    ff (never seen); a tag in ``dropouts`` prints 00 (no new data) on every
    ``dropout_every``-th tick.
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
    ) -> None:
        super().__init__("imu-central-emulator", link, imu_matrix.BAUD, body, clock, truth)
        self.tick_s = tick_s
        self.dropouts, self.dropout_every = set(dropouts), dropout_every
        self.ticks = 0

    def run(self) -> None:
        deadline = time.monotonic()
        while not self.stop_event.is_set():
            readings = {r.node: r for r in self.sample()}
            lines = []
            for slot in range(1, imu_matrix.MAX_SENSORS + 1):
                reading = readings.get(slot)
                if not isinstance(reading, Quat):
                    lines.append(imu_matrix.encode_line(SensorAbsent(slot)))
                elif slot in self.dropouts and self.ticks % self.dropout_every == 1:
                    lines.append(imu_matrix.encode_line(NoNewData(slot)))
                else:
                    extra = (self.ticks & 0xFFFF).to_bytes(2, "little")  # a line counter
                    lines.append(imu_matrix.encode_line(Quat(slot, reading.wxyz, extra)))
            self.port.write(b"".join(lines))
            self.ticks += 1
            deadline += self.tick_s
            self.port.read(max(0.0, deadline - time.monotonic()))  # drain, and pace


class SlcanAdapterEmulator(_PtyEmulator):
    """A Lawicel slcan adapter with SmartSuit nodes on its CAN side.

    Answers the host's commands (``S``/``s`` bitrate, ``O``/``L`` open,
    ``C`` close, ``V`` version, ``N`` serial number, ``T``/``t`` transmit) and,
    while open, forwards a frame of each node every 10 ms as a ``T`` line.
    """

    def __init__(
        self,
        link: Path,
        body: BodyEmulator,
        clock: Clock | None = None,
        truth: TruthSink | None = None,
        period_s: float = CAN_PERIOD_S,
    ) -> None:
        super().__init__("slcan-emulator", link, 115200, body, clock, truth)
        self.period_s = period_s
        self.is_open = False
        self.sent = 0
        self.received: list[smartsuit_can.CanFrame] = []

    def run(self) -> None:
        decoder = SlcanDecoder()
        deadline = time.monotonic()
        while not self.stop_event.is_set():
            for event in decoder.feed(self.port.read(max(0.0, deadline - time.monotonic()))):
                self._command(event)
            if time.monotonic() < deadline:
                continue
            deadline += self.period_s
            if self.is_open:
                frames = [smartsuit_can.encode_reading(r) for r in self.sample()]
                self.port.write(b"".join(map(smartsuit_can.encode_slcan, frames)))
                self.sent += len(frames)

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
