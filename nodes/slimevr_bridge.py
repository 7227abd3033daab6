"""The live SlimeVR bridge: bodynet in the place of the SlimeVR server, on UDP 6969.

One UDP socket takes every tracker's datagrams; the sans-io server
(``core.codecs.slimevr``) decodes them and says what to answer; the source's
adapter numbers the samples from the trackers' packet counters. Each second
every connected tracker gets a heartbeat and a ping (its echo gives the round
trip, in health with battery, signal strength and the tracker's identity).

A tracker whose id has a site (profile, ``--assign``, or ``bodynet calibrate
assign`` live on ``body/@assign``) publishes there like any sensor. One that
has none holds a liveliness token on ``body/@unassigned/<tracker id>`` while it
streams, so the gateway lists it in ``body/@topology`` for the user to assign.
"""

from __future__ import annotations

import json
import logging
import socket
import struct
import sys
import threading
import time
from collections.abc import Mapping

import zenoh

from bodynet.core import keys
from bodynet.core.codecs import slimevr as codec
from bodynet.core.keys import KeySpaceError, Site, site_named
from bodynet.core.messages import NodeStatus, NoNewData, Reading, SensorAbsent
from bodynet.nodes.sources.live import Bridge
from bodynet.nodes.sources.slimevr import SlimeVR

log = logging.getLogger(__name__)

RECV_TIMEOUT_S = 0.05
DATAGRAM_MAX = 2048
#: Linux's ``SO_TIMESTAMPNS`` (``SCM_TIMESTAMPNS`` in the control message), which
#: Python's socket module does not name: each datagram's arrival, on the wall clock,
#: as the kernel took it
SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")


def arrival_stamps(sock: socket.socket) -> bool:
    """Ask the kernel to stamp each datagram ``sock`` receives with its arrival
    (Linux); False where it cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def receive(sock: socket.socket, stamped: bool) -> tuple[bytes, object, float]:
    """A datagram, its sender and its arrival (s, wall clock): the kernel's stamp
    when ``stamped``, else now. A bridge that gets to its socket late (a loaded
    host) stamps with when the datagram came, not when it was read: a tracker's
    samples read in a burst after 50 ms keep their own times."""
    if not stamped:
        data, addr = sock.recvfrom(DATAGRAM_MAX)
        return data, addr, time.time()
    data, ancillary, _, addr = sock.recvmsg(DATAGRAM_MAX, socket.CMSG_SPACE(_TIMESPEC.size))
    for level, kind, value in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(value) >= _TIMESPEC.size:
            sec, ns = _TIMESPEC.unpack_from(value)
            return data, addr, sec + ns * 1e-9
    return data, addr, time.time()


class SlimeVRBridge(Bridge):
    """SlimeVR trackers onto Zenoh; see the module docstring."""

    def __init__(self, session: zenoh.Session, name: str,
                 assignments: Mapping[str, Site] | None = None) -> None:  # fmt: skip
        source = SlimeVR({}, None, assignments)
        super().__init__(session, source, name)
        self.session = session
        self.assignments = source.assignments
        self.server = source.decoder()
        self.trackers: dict[int, str] = {}  # node -> tracker id
        self.unassigned_samples = 0
        self._unassigned: dict[str, zenoh.LivelinessToken] = {}
        self._heard: dict[object, float] = {}  # tracker address -> its last datagram (monotonic)
        self._pings: dict[int, float] = {}  # ping id -> monotonic time sent
        self._ping_id = 0
        self._lock = threading.Lock()
        self._assign_sub = session.declare_subscriber(keys.ASSIGN, self._on_assign)
        self.sock: socket.socket | None = None

    # --- assignment ---------------------------------------------------------------------
    def assign(self, tracker: str, site: Site) -> None:
        """``tracker`` sits at ``site`` from now on (and any other tracker there moves off)."""
        with self._lock:
            for other in [t for t, s in self.assignments.items() if s == site and t != tracker]:
                del self.assignments[other]
            self.assignments[tracker] = site
            nodes = [n for n, t in self.trackers.items() if t == tracker]
            token = self._unassigned.pop(tracker, None)
        if token is not None:
            token.undeclare()
        for node in nodes:
            self.publisher.move(node, site)
        log.info("%s: tracker %s assigned to %s", self.publisher.name, tracker, site)

    def _on_assign(self, sample: zenoh.Sample) -> None:  # Zenoh's thread
        try:
            message = json.loads(sample.payload.to_bytes())
            tracker = codec.normalise_tracker_id(str(message["tracker"]))
            site = site_named(str(message["site"]))
        except (ValueError, KeyError, TypeError, KeySpaceError) as exc:
            log.warning("%s: a bad assignment on %s: %s", self.publisher.name, keys.ASSIGN, exc)
            return
        self.assign(tracker, site)

    def _unassigned_token(self, tracker: str) -> None:
        with self._lock:
            if tracker in self._unassigned or tracker in self.assignments:
                return
            key = keys.unassigned_key(tracker)
            self._unassigned[tracker] = self.session.liveliness().declare_token(key)
        log.info("%s: tracker %s has no site yet (bodynet calibrate assign %s SITE)",
                 self.publisher.name, tracker, tracker)  # fmt: skip

    # --- the adapter's sink -------------------------------------------------------------
    def sample(self, reading: Reading, seq: int, t_s: float, flags: int = 0) -> None:
        if reading.node not in self.publisher.sites:
            tracker = self.trackers.get(reading.node)
            site = self.assignments.get(tracker) if tracker else None
            if site is None:
                self.unassigned_samples += 1
                if tracker is not None:
                    self._unassigned_token(tracker)
                return
            self.publisher.move(reading.node, site)
        super().sample(reading, seq, t_s, flags)

    def status(self, event: NoNewData | SensorAbsent | NodeStatus) -> None:
        if isinstance(event, NodeStatus):
            if event.key == "tracker":
                self.trackers[event.node] = str(event.value)
            elif event.key == codec.PING_ECHO:
                sent = self._pings.get(int(event.value))
                if sent is not None:
                    rtt_ms = round((time.monotonic() - sent) * 1e3, 2)
                    self.publisher.set_status(event.node, "rtt_ms", rtt_ms)
                return
        super().status(event)

    # --- the socket ---------------------------------------------------------------------
    def run(self, listen: tuple[str, int], stop: threading.Event) -> None:
        """Serve the trackers on ``listen`` until ``stop``."""
        sock = self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        try:
            sock.bind(listen)
        except OSError as exc:
            sock.close()
            raise OSError(exc.errno, f"cannot take udp/{listen[0]}:{listen[1]}: {exc.strerror}"
                          " (is a SlimeVR server running?)") from None  # fmt: skip
        sock.settimeout(RECV_TIMEOUT_S)
        stamped = arrival_stamps(sock)
        self.publisher.set_device("listening")
        log.info("%s: SlimeVR trackers on udp/%s:%d", self.publisher.name, *sock.getsockname())
        next_beat = time.monotonic()
        try:
            while not stop.is_set():
                data: bytes | None
                try:
                    data, addr, t_s = receive(sock, stamped)
                except TimeoutError:
                    data = None
                except OSError as exc:  # e.g. ICMP port unreachable reported on Linux
                    log.debug("%s: %s", self.publisher.name, exc)
                    data = None
                now = time.monotonic()
                if data is not None:  # an empty datagram too: counted (truncated)
                    self.feed(self.server.receive(data, addr), t_s)
                    if addr in self.server.connections:  # a tracker that shook hands
                        self._heard[addr] = now
                    for to, reply in self.server.take_replies():
                        self._send(to, reply)
                if now >= next_beat:
                    next_beat = now + codec.HEARTBEAT_S
                    self._beat(now)
        finally:
            sock.close()

    def _send(self, to: object, data: bytes) -> None:
        assert self.sock is not None
        try:
            self.sock.sendto(data, to)  # type: ignore[arg-type]
        except OSError as exc:
            log.debug("%s: cannot answer %s: %s", self.publisher.name, to, exc)

    def _beat(self, now: float) -> None:
        """Heartbeats and a ping to every tracker; forget the silent ones (a tracker
        that comes back shakes hands again; one that never streams, e.g. a
        forged handshake, holds no place for long)."""
        for addr, conn in list(self.server.connections.items()):
            if now - self._heard.get(addr, now) > codec.TRACKER_TIMEOUT_S:
                self.server.forget(addr)
                self._heard.pop(addr, None)
                for node in conn.nodes.values():
                    tracker = self.trackers.get(node)
                    token = self._unassigned.pop(tracker, None) if tracker else None
                    if token is not None:
                        token.undeclare()
        self._ping_id += 1
        self._pings = {i: t for i, t in self._pings.items() if now - t < 10.0}
        self._pings[self._ping_id] = now
        for to, data in self.server.heartbeats() + self.server.ping(self._ping_id):
            self._send(to, data)

    def close(self) -> None:
        self._assign_sub.undeclare()
        with self._lock:
            tokens, self._unassigned = list(self._unassigned.values()), {}
        for token in tokens:
            token.undeclare()
        super().close()


def run_bridge(session: zenoh.Session, stop: threading.Event, name: str,
               listen: tuple[str, int] = ("0.0.0.0", codec.PORT),
               assignments: Mapping[str, Site] | None = None,
               batch_s: float = 0.0) -> None:  # fmt: skip
    """A SlimeVR bridge on ``listen`` until ``stop``; its samples in batches of
    ``batch_s`` at most if not 0."""
    bridge = SlimeVRBridge(session, name, assignments)
    bridge.publisher.batch(batch_s)
    try:
        bridge.run(listen, stop)
    finally:
        bridge.close()
