"""SlimeVR trackers over Wi-Fi (UDP 6969): bodynet as the trackers' server.

The protocol is ``core.codecs.slimevr`` (sans-io, its module docstring says
which packets and fields are read). This module is the source: its sites come
from the subject profile's ``[trackers]`` table (tracker id -> site), from
``--assign`` on the command line, or live from ``bodynet calibrate assign``;
the live bridge is ``nodes.slimevr_bridge``. :class:`EmulatedTracker` is a
tracker on a real UDP socket, speaking the same protocol: handshake until the
server answers, then rotations (packet 17, or 23 with acceleration), battery,
signal strength and sensor info, heartbeats and ping echoes; it goes back to
its handshake when the server has been silent for three seconds, as the
firmware does.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

from bodynet.core.codecs import slimevr as codec
from bodynet.core.errors import DecodeError
from bodynet.core.keys import KeySpaceError, Site, site_named
from bodynet.core.messages import Source as SourceId
from bodynet.nodes.loop import Loop
from bodynet.nodes.sources.base import EmulatorError, NodeParts, Source, Transport
from bodynet.nodes.timing import Clock, LinkTiming, NodeTimers
from bodynet.session import argtypes

Quaternion = tuple[float, float, float, float]  # w, x, y, z

log = logging.getLogger(__name__)

MAX_PROFILE_BYTES = 1 << 20
#: How often an emulated tracker sends its battery and signal strength.
STATUS_S = 1.0
#: the state an emulated tracker's sensors report in their sensor info (1: OK)
SENSOR_OK = 1


def parse_assignment(text: str) -> tuple[str, Site]:
    """``TRACKER=SITE`` (``aabbccddeeff-0=left-arm/upperarm``) -> (tracker id, site);
    an argparse type, refusing a bad one with its reason."""
    tracker, sep, site = text.partition("=")
    try:
        if not sep:
            raise ValueError(f"not TRACKER=SITE: {text!r}")
        return codec.normalise_tracker_id(tracker), site_named(site)
    except (ValueError, KeySpaceError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def address(text: str) -> tuple[str, int]:
    """``host:port`` (an argparse type)."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"not host:port: {text!r}")
    return host or "127.0.0.1", int(port)


def profile_trackers(text: str) -> dict[str, Site]:
    """The tracker -> site table of the profile at ``text`` (an argparse type: a
    profile that does not read is refused; one not written yet assigns none)."""
    from bodynet.core.subject import ProfileError
    from bodynet.session import profile_file

    path = argtypes.input_or_new_file(text)
    if not path.exists():
        return {}
    if not path.is_file() or path.stat().st_size > MAX_PROFILE_BYTES:  # /dev/zero, /dev/full...
        raise argparse.ArgumentTypeError(f"{text}: not a profile (a TOML file up to 1 MB)")
    try:
        profile = profile_file.load(path)
    except (ProfileError, OSError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return {t: site_named(s) for t, s in profile.trackers.items()}


class SlimeVR(Source):
    name = "slimevr"
    wire_id = SourceId.SLIMEVR
    transport = Transport.UDP
    help = "SlimeVR trackers over Wi-Fi (their server's protocol, UDP 6969)"
    PERIOD_S = 0.01
    emulators: ClassVar = {"slimevr": "SlimeVR trackers on UDP, for a bridge to take"}
    TIMING: ClassVar = frozenset({"timers", "clock_ppm", "jitter_s", "drop", "reorder"})

    def __init__(self, sites: Mapping[int, Site] | None = None, period_s: float | None = None,
                 assignments: Mapping[str, Site] | None = None) -> None:  # fmt: skip
        super().__init__(sites, period_s)
        #: tracker id -> site; nodes get their sites as their trackers appear
        self.assignments: dict[str, Site] = dict(assignments or {})

    def decoder(self) -> codec.SlimeVRServer:
        return codec.SlimeVRServer()

    @classmethod
    def add_bridge_args(cls, p: argparse.ArgumentParser) -> None:
        p.add_argument("--udp", type=address, default=("0.0.0.0", codec.PORT), metavar="HOST:PORT",
                       help=f"where to take the trackers' datagrams (default "
                            f"0.0.0.0:{codec.PORT}, where trackers look)")  # fmt: skip
        p.add_argument("--profile", type=profile_trackers, default={},
                       help="subject profile whose [trackers] table assigns sites")  # fmt: skip
        p.add_argument("--assign", type=parse_assignment, action="append", default=[],
                       metavar="TRACKER=SITE",
                       help="assign a tracker (aabbccddeeff-0) to a site (left-arm/upperarm); "
                            "repeatable, over the profile's")  # fmt: skip

    @classmethod
    def bridge_name(cls, args: argparse.Namespace) -> str:
        return f"slimevr-{args.udp[1]}"

    def bridge(self, session: Any, stop: threading.Event, name: str,
               args: argparse.Namespace) -> None:  # fmt: skip
        from bodynet.nodes.slimevr_bridge import run_bridge

        assignments = {**args.profile, **dict(args.assign)}
        run_bridge(session, stop, name, args.udp, assignments, args.batch_ms / 1e3)

    # --- emulation ----------------------------------------------------------------------
    @classmethod
    def add_emulate_args(cls, device: str, p: argparse.ArgumentParser) -> None:
        p.add_argument("--server", type=address, default=("127.0.0.1", codec.PORT),
                       metavar="HOST:PORT",
                       help=f"the server's host:port (default 127.0.0.1:{codec.PORT})")  # fmt: skip
        p.add_argument("--rate-hz", type=argtypes.bounded_float(0.1, 1000.0, "per second"),
                       default=100.0, help="rotations per second (default 100)")  # fmt: skip

    def emulated_sensors(self, sensors: Any = None, branches: Any = None) -> list[Any]:
        from bodynet.nodes.emulator import imu_tags

        return imu_tags(sensors, branches)

    def emulator(self, device: str, body: Any, truth: Any, opts: dict[str, Any]) -> Any:
        return EmulatedTrackers(body, opts.get("server") or ("127.0.0.1", codec.PORT),
                                opts.get("rate_hz") or 100.0, truth=truth,
                                timing=opts.get("timing"))  # fmt: skip

    def node(self, device: str, body: Any, where: Path, clock: Any, truth: Any,
             sensors: list[Any], label: str, timing: Any = None) -> NodeParts:  # fmt: skip
        """Emulated trackers, each on its own timer as ``timing`` says (a rotation
        every ``period_s``), and their bridge."""
        from bodynet.nodes.slimevr_bridge import run_bridge

        listen = ("127.0.0.1", free_udp_port())
        trackers = EmulatedTrackers(body, listen, 1.0 / self.period_s, clock, truth, timing=timing)
        assignments = {trackers.tracker_of(s.node): s.site for s in sensors}
        return trackers, run_bridge, {"listen": listen, "assignments": assignments}


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def resolve(server: tuple[str, int]) -> tuple[str, int]:
    """``(host, port)`` with the host's IPv4 address; :class:`EmulatorError` if
    the name is not known."""
    host, port = server
    try:
        found = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    except OSError as exc:  # socket.gaierror
        raise EmulatorError(f"cannot find the server {host}: {exc.strerror or exc}") from None
    return str(found[0][4][0]), port


def emulated_mac(number: int) -> bytes:
    """The MAC of emulated tracker ``number`` (locally administered, unicast)."""
    return bytes([0x02, 0xB0, 0xD1, 0x00, (number >> 8) & 0xFF, number & 0xFF])


class EmulatedTracker(Loop):
    """One SlimeVR tracker on its own UDP socket; see the module docstring.

    ``orientation(sensor, t_s)`` gives each sensor's quaternion (w, x, y, z).
    Its rotations go out every ``1 / rate_hz`` on a timer of its own as
    ``timing`` says (own phase and clock error when independent, late by up to
    the jitter); a share ``timing.drop`` of them is lost on the air, after the
    packet counter counted it (:attr:`dropped`; :meth:`silence` loses all for a
    span), and a share ``timing.reorder`` is overtaken by the datagram after it
    (:attr:`reordered`). :meth:`pause` and :meth:`resume` unplug and plug it
    (silence, then a new handshake once the server forgets it... or the same
    connection if not), :meth:`reboot` restarts its firmware (counter from 0, a
    new handshake), :meth:`skip` jumps its packet counter, :meth:`send` sends
    any bytes."""

    def __init__(self, server: tuple[str, int], mac: bytes, sensors: Sequence[int],
                 orientation: Callable[[int, float], Quaternion],
                 rate_hz: float = 100.0, compact: bool = False, clock: Any = None,
                 name: str = "tracker", timing: LinkTiming | None = None,
                 sent: Callable[[int], None] | None = None) -> None:  # fmt: skip
        super().__init__(name)
        self.server = resolve(server)  # once: a name looked up for each datagram could block
        self.mac = mac
        self.sensors = list(sensors)
        self.orientation = orientation
        self.period_s = 1.0 / rate_hz
        self.compact = compact
        self.clock = clock
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("", 0))
        self.sock.settimeout(0.0)
        self.number = 0
        self.connected = threading.Event()
        self.paused = threading.Event()
        self.sent = 0
        self.pings_echoed = 0
        self.heartbeats = 0
        self.acked: set[int] = set()
        self.timing = timing or LinkTiming()
        self.timers = NodeTimers([0], self.period_s, self.timing)  # 0: the tracker
        #: rotation datagrams sent after the one numbered after them
        self.reordered = 0
        #: told each sensor whose rotation goes out, just before it goes (a truth
        #: sink's hook: what it notes then is before the datagram's arrival stamp)
        self.sent_hook = sent
        self._held: tuple[bytes, int] | None = None  # a datagram to go out after the next one
        self._reboot = threading.Event()
        self._heard = 0.0
        self._t0 = time.monotonic()

    @property
    def dropped(self) -> int:
        """Rotation datagrams lost on the air (their numbers taken all the same)."""
        return self.timers.dropped[0]

    def silence(self, seconds: float) -> None:
        """Lose every rotation from now for ``seconds`` (the tracker out of reach)."""
        self.timers.silence(0, time.monotonic(), seconds)

    def reboot(self) -> None:
        """Restart the firmware: its packet counter from 0 and a new handshake."""
        self._reboot.set()

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()  # type: ignore[no-any-return]

    def tracker_ids(self) -> list[str]:
        return [codec.tracker_id(self.mac, s) for s in self.sensors]

    def _next(self) -> int:
        """``m_PacketNumber++`` (connection.cpp:162): the first packet is numbered 0."""
        number, self.number = self.number, self.number + 1
        return number

    def send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):  # nobody listening yet: like a lost datagram
            self.sock.sendto(data, self.server)

    def skip(self, n: int) -> None:
        """Jump the packet counter by ``n``: ``n`` packets the server never sees."""
        self.number += n

    def pause(self) -> None:
        self.paused.set()

    def resume(self) -> None:
        self.paused.clear()

    def stop(self) -> None:
        super().stop()
        self.sock.close()

    def _now(self) -> float:
        return self.clock.now() if self.clock is not None else time.monotonic() - self._t0

    def _handshake(self) -> None:
        """Numbered 0 (connection.cpp:394); the packet counter runs on across
        reconnects, as the firmware's does (connection.h:221, never reset)."""
        hs = codec.Handshake(self.mac, board=2, imu=10, mcu=2, build=17, firmware="bodynet-emu")
        self.send(codec.encode_handshake(0, hs))

    def _read(self) -> None:
        while True:
            try:
                data, _ = self.sock.recvfrom(2048)
            except (BlockingIOError, OSError):
                return
            try:
                packet = codec.decode_server_packet(data)
            except DecodeError:
                continue
            self._heard = time.monotonic()
            if packet.kind == codec.HANDSHAKE:
                if not self.connected.is_set():
                    self.connected.set()
                    self.acked.clear()
            elif packet.kind == codec.PING:
                # the datagram as it came, the server's packet number in it; the
                # firmware's counter does not move (returnLastPacket, connection.cpp:494-502)
                self.send(data)
                self.pings_echoed += 1
            elif packet.kind == codec.SERVER_HEARTBEAT:
                self.heartbeats += 1
            # acknowledged in the state it was sent in, or sent again (connection.cpp:532-538)
            elif (packet.kind == codec.SENSOR_INFO and packet.sensor is not None
                  and packet.status == SENSOR_OK):  # fmt: skip
                self.acked.add(packet.sensor)

    def run(self) -> None:
        timers = self.timers
        timers.start(time.monotonic())
        rng = self.timing.draws()
        next_status = next_handshake = time.monotonic()
        while not self.stop_event.is_set():
            now = time.monotonic()
            if self._reboot.is_set():
                self._reboot.clear()
                self.number, self._held = 0, None
                self.connected.clear()
                next_handshake = now
            if self.paused.is_set():
                self.stop_event.wait(0.01)
                with contextlib.suppress(OSError, BlockingIOError):
                    while self.sock.recvfrom(2048):  # what comes meanwhile is lost
                        pass
                timers.due(time.monotonic(), lossy=False)  # and nothing is sent
                continue
            self._read()
            if self.connected.is_set() and now - self._heard > codec.TRACKER_TIMEOUT_S:
                self.connected.clear()  # the server is gone: look for it again
            if not self.connected.is_set():
                if now >= next_handshake:
                    self._handshake()
                    next_handshake = now + 0.2
                self.stop_event.wait(0.01)
                timers.due(time.monotonic(), lossy=False)  # no rotations before the server
                continue
            if now >= next_status:
                self._status()
                next_status = now + STATUS_S
            lost = timers.dropped[0]
            sends = len(timers.due(now))
            for _ in range(timers.dropped[0] - lost):  # numbered, then lost on the air
                for _sensor in self.sensors:
                    self._next()
            for _ in range(sends):
                self._rotations(rng)
            self.stop_event.wait(max(0.0, min(timers.next_due, next_status) - time.monotonic()))

    def _rotations(self, rng: Any) -> None:
        """One rotation datagram per sensor, each maybe overtaken by the next."""
        t = self._now()
        for sensor in self.sensors:
            w, x, y, z = self.orientation(sensor, t)
            if self.compact:
                data = codec.encode_rotation_accel(self._next(), sensor, (x, y, z, w),
                                                   (0.0, 0.0, 9.81))  # fmt: skip
            else:
                data = codec.encode_rotation(self._next(), sensor, (x, y, z, w), 3)
            held, self._held = self._held, None
            if held is None and self.timing.reorder and rng.random() < self.timing.reorder:
                self._held = (data, sensor)  # goes out after the next one
                self.reordered += 1
            else:
                self._send_rotation(data, sensor)
            if held is not None:
                self._send_rotation(*held)
            self.sent += 1

    def _send_rotation(self, data: bytes, sensor: int) -> None:
        if self.sent_hook is not None:
            self.sent_hook(sensor)
        self.send(data)

    def _status(self) -> None:
        for sensor in self.sensors:
            if sensor not in self.acked:
                self.send(codec.encode_sensor_info(self._next(), sensor, SENSOR_OK, 10))
        self.send(codec.encode_battery(self._next(), 3.9, 0.8))
        self.send(codec.encode_signal_strength(self._next(), codec.DEVICE_SENSOR, -52))
        self.send(codec.encode_heartbeat(self._next()))


#: body samples an emulated body's trackers keep (a tracker late by a few steps finds its own)
GRID_KEPT = 8


def _nlerp(a: Quaternion, b: Quaternion, f: float) -> Quaternion:
    """From unit quaternion ``a`` (``f`` = 0) to ``b`` (1), normalised: as slerp
    for the few degrees a body turns between two of its samples."""
    if a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] < 0:
        b = (-b[0], -b[1], -b[2], -b[3])
    w, x, y, z = (p + f * (q - p) for p, q in zip(a, b, strict=True))
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / n, x / n, y / n, z / n)


class EmulatedTrackers:
    """An emulated body's IMU tags as SlimeVR trackers, one per tag (sensor 0),
    the ground truth handed to ``truth`` as the other emulators do: each
    rotation's as it goes out, with the time its reading was taken."""

    def __init__(self, body: Any, server: tuple[str, int], rate_hz: float = 100.0,
                 clock: Any = None, truth: Any = None, compact: bool = False,
                 timing: LinkTiming | None = None) -> None:  # fmt: skip
        self.body = body
        self.truth = truth
        self.clock = clock or Clock()  # one for every tracker, its times on the wall clock
        self.link = f"{server[0]}:{server[1]}"
        self.step_s = 0.5 / rate_hz  # the body sampled every half period, for every tracker
        self._lock = threading.Lock()
        self._grid: dict[int, tuple[dict[int, Quaternion], dict[int, Any]]] = {}  # step -> sample
        nodes = [s.node for s in body.sensors]
        # node -> truths not yet sent; each touched by its tracker's thread alone
        self._taken: dict[int, deque[tuple[Any, int]]] = {n: deque(maxlen=4) for n in nodes}
        timing = timing or LinkTiming()
        self.trackers = [
            EmulatedTracker(server, emulated_mac(node), [0],
                            lambda _sensor, t, node=node: self._quat(node, t),
                            rate_hz, compact, self.clock, f"slimevr-tracker-{node}",
                            timing.of(node),
                            lambda _sensor, node=node: self._sent(node))
            for node in nodes
        ]  # fmt: skip
        self._by_node = dict(zip(nodes, self.trackers, strict=True))

    def tracker_of(self, node: int) -> str:
        return self._by_node[node].tracker_ids()[0]

    def of(self, node: int) -> EmulatedTracker:
        """The tracker of ``node``."""
        return self._by_node[node]

    def silence(self, node: int, seconds: float) -> None:
        """Lose every rotation of ``node``'s tracker from now for ``seconds``."""
        self._by_node[node].silence(seconds)

    def _quat(self, node: int, t: float) -> Quaternion:
        """``node``'s reading at ``t``, and its truth to go with it, each between the
        body's samples of the steps around ``t``: as of ``t`` itself, as a tracker
        reads its IMU as it sends, at one body sample a step for all trackers (a
        reading's noise is the two samples' blended: midway, 1/sqrt(2) of theirs)."""
        steps = t / self.step_s
        k = math.floor(steps)
        f = steps - k
        with self._lock:
            (quats, truths), (quats_after, truths_after) = self._sampled(k), self._sampled(k + 1)
        if self.truth is not None:
            was, then = truths[node], truths_after[node]
            truth = dataclasses.replace(
                was,
                angles_deg={n: a + f * (then.angles_deg[n] - a) for n, a in was.angles_deg.items()},
                segment_quat_wxyz=_nlerp(was.segment_quat_wxyz, then.segment_quat_wxyz, f),
            )
            t_ns = self.clock.wall_ns(t)  # when it was taken: ``t``, not when this ran
            self._taken[node].append((truth, t_ns))
        return _nlerp(quats[node], quats_after[node], f)

    def _sampled(self, step: int) -> tuple[dict[int, Quaternion], dict[int, Any]]:
        """The body's readings and truths at ``step`` (under the lock), the latest
        ``GRID_KEPT`` steps kept."""
        got = self._grid.get(step)
        if got is None:
            readings, truth_list = self.body.sample(step * self.step_s)
            quats = {r.node: r.wxyz for r in readings}
            truths = {r.node: tr for r, tr in zip(readings, truth_list, strict=True)}
            got = self._grid[step] = (quats, truths)
            if len(self._grid) > GRID_KEPT:
                del self._grid[min(self._grid)]
        return got

    def _sent(self, node: int) -> None:
        """``node``'s tracker sends its oldest rotation not yet sent: its truth to the sink."""
        taken = self._taken[node]
        truth = taken.popleft() if taken else None
        if truth is not None and self.truth is not None:
            self.truth(node, *truth)

    def start(self) -> None:
        for tracker in self.trackers:
            tracker.start()

    def stop(self) -> None:
        for tracker in self.trackers:  # all told first: each then ends as soon as it can
            tracker.stop_event.set()
        for tracker in self.trackers:
            tracker.stop()
