"""SlimeVR trackers over real UDP on loopback, into the bridge and a real gateway.

The emulated tracker speaks the protocol as a tracker does (handshake until
answered, rotations, battery, signal strength, sensor info, ping echoes); the
bridge is bodynet in the place of the SlimeVR server. The tests "against the
standard" build the tracker's datagrams as the SlimeVR firmware builds them and
check the answers against the SlimeVR server's, both written here from their
sources (not from bodynet's codec).
"""

from __future__ import annotations

import json
import math
import socket
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from zenoh_helpers import Collector, Liveliness, Running, client, raw_collector, wait_until

from bodynet.cli.main import main
from bodynet.core.codecs import slimevr as codec
from bodynet.core.errors import Reason, Rejected
from bodynet.core.keys import LEFT_ARM, LEFT_LEG, RIGHT_ARM, Site
from bodynet.core.messages import NodeStatus, Quat, Source, Tick
from bodynet.gateway.service import Gateway
from bodynet.nodes.publisher import NodeHealth
from bodynet.nodes.slimevr_bridge import SlimeVRBridge
from bodynet.nodes.sources.slimevr import EmulatedTracker, emulated_mac, free_udp_port
from bodynet.nodes.timing import LinkTiming, Timers
from bodynet.session import profile_file

UPPER, FORE = Site(LEFT_ARM, "upperarm"), Site(RIGHT_ARM, "forearm")
THIGH = Site(LEFT_LEG, "thigh")  # where the firmware-built tracker below is assigned
HALF = math.sqrt(0.5)


# --- the standard's bytes, written from the SlimeVR sources (not from bodynet's codec) ---
# The firmware: SlimeVR-Tracker-ESP 12f4b22, src/network/connection.cpp (cpp:),
# connection.h, packets.h. The server: SlimeVR-Server 5549763,
# server/core/src/main/java/dev/slimevr/tracking/trackers/udp/ (UDPProtocolParser.kt,
# TrackersUDPServer.kt, UDPDevice.kt, UDPPacket.kt).

FW_MAC = bytes.fromhex("a1b2c3d4e5f6")
FW_TRACKER = "a1b2c3d4e5f6-0"
#: the server's handshake answer: its 64-byte buffer, 3 then "Hey OVR =D 5"
#: (UDPProtocolParser.kt:84-86,161-168; sent whole, TrackersUDPServer.kt:191-194)
SERVER_HANDSHAKE = bytes([3]) + b"Hey OVR =D 5" + bytes(51)
# the types the server writes (UDPProtocolParser.kt:126-160) and the firmware
# reads at byte 3 of a datagram (cpp:682; packets.h:62-72)
T_HEARTBEAT, T_SERVER_HEARTBEAT, T_HANDSHAKE, T_PING, T_SENSOR_INFO = 0, 1, 3, 10, 15


def server_packet(kind: int, body: bytes = b"") -> bytes:
    """A server->tracker packet: type int32, number int64 "always 0 when sending
    data to trackers" (UDPProtocolParser.kt:77-81), then the body."""
    return struct.pack(">i", kind) + bytes(8) + body


def short_string(text: str) -> bytes:
    return bytes([len(text)]) + text.encode("ascii")  # sendShortString (cpp:167-178)


class Firmware:
    """What a SlimeVR tracker puts on the wire, byte for byte as the firmware
    builds it; with :meth:`link`, on a real UDP socket on loopback."""

    def __init__(self, mac: bytes = FW_MAC, number: int = 0) -> None:
        self.mac = mac
        # uint64_t m_PacketNumber = 0 (connection.h:221): never reset, not by a
        # timeout (cpp:640-660) nor by reset() (cpp:603-627)
        self.packet_number = number
        self.sock: socket.socket | None = None
        self.server: tuple[str, int] = ("127.0.0.1", 0)

    def header(self, kind: int, number: int | None = None) -> bytes:
        """sendPacketType: three 0 bytes then the type (cpp:180-186); then
        sendPacketNumber: ``m_PacketNumber++``, uint64 big-endian (cpp:157-165,
        convert_to_chars reverses the bytes, cpp:34-40), or an override (connection.h:161-179)."""
        if number is None:
            number, self.packet_number = self.packet_number, self.packet_number + 1
        return bytes([0, 0, 0, kind]) + struct.pack(">Q", number)

    def handshake(self) -> bytes:
        """sendTrackerDiscovery (cpp:356-396), number overridden to 0 (cpp:394):
        board, IMU, MCU, three 0s, PROTOCOL_VERSION 22 (debug.h:99), firmware
        version, MAC, tracker type, vendor name and URL, product name, update
        address and name (globals.h:61-77 defaults)."""
        ints = struct.pack(">7I", 6, 10, 1, 0, 0, 0, 22)  # BOARD_WEMOSD1MINI (consts.h:81)...
        strings = b"".join(short_string(t) for t in
                           ("Unknown", "", "DIY SlimeVR Tracker", "", ""))  # fmt: skip
        return (self.header(T_HANDSHAKE, 0) + ints + short_string("0.6.1") + self.mac
                + bytes([1]) + strings)  # fmt: skip

    def rotation(self, sensor: int = 0, xyzw: tuple[float, ...] = (0.0, 0.0, HALF, HALF)) -> bytes:
        """PACKET_ROTATION_DATA 17 (cpp:275-294): RotationDataPacket (packets.h:151-159):
        sensor id, data type 1 (normal), x, y, z, w big-endian floats, accuracy."""
        return self.header(17) + bytes([sensor, 1]) + struct.pack(">4f", *xyzw) + bytes([0])

    def sensor_info(self, sensor: int = 0, state: int = 1) -> bytes:
        """PACKET_SENSOR_INFO 15 (cpp:255-272): SensorInfoPacket (packets.h:135-149):
        sensor id, state, type, config bits (u16 BE), rest calibration done, position,
        data type, then two debug floats."""
        body = bytes([sensor, state, 10]) + struct.pack(">H", 0) + bytes([0, 0, 0])
        return self.header(T_SENSOR_INFO) + body + struct.pack(">2f", 100.0, 100.0)

    # --- on a socket -------------------------------------------------------------------
    def link(self, server: tuple[str, int]) -> Firmware:
        self.server = server
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(5.0)
        return self

    @property
    def address(self) -> tuple[str, int]:
        assert self.sock is not None
        return self.sock.getsockname()  # type: ignore[no-any-return]

    def send(self, data: bytes) -> None:
        assert self.sock is not None
        self.sock.sendto(data, self.server)

    def receive(self, kind: int) -> bytes:
        """The next datagram of type ``kind`` (read at byte 3, as update() does,
        cpp:682), skipping others (heartbeats, pings meanwhile)."""
        assert self.sock is not None
        while True:
            data = self.sock.recv(128)  # m_Packet[128] (connection.h:220)
            if len(data) > 3 and data[3] == kind:
                return data

    def connect(self) -> bytes:
        """A handshake a second until answered: byte 0 is 3 and "Hey OVR =D 5"
        follows (searchForServer, cpp:560-601); the answer as it came."""
        assert self.sock is not None
        for _ in range(10):
            self.send(self.handshake())
            self.sock.settimeout(1.0)
            try:
                while True:
                    data = self.sock.recv(128)
                    if data[:1] == b"\x03" and data[1:13] == b"Hey OVR =D 5":
                        return data
            except TimeoutError:
                continue
            finally:
                self.sock.settimeout(5.0)
        raise AssertionError("no answer to ten handshakes")

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()


@pytest.fixture
def firmware() -> Iterator[Callable[..., Firmware]]:
    made: list[Firmware] = []

    def make(server: tuple[str, int], number: int = 0, mac: bytes = FW_MAC) -> Firmware:
        fw = Firmware(mac, number).link(server)
        made.append(fw)
        return fw

    yield make
    for fw in made:
        fw.close()


def stream(fw: Firmware, bridge: SlimeVRBridge, count: int, batch: int = 100) -> None:
    """``count`` rotations from ``fw``, a batch at a time, each batch waited for
    until the bridge has taken or refused all of it (no loss to a full socket buffer)."""

    def done() -> int:
        node = bridge.server.nodes.get(FW_TRACKER)
        health = bridge.publisher.nodes.get(node) if node is not None else None
        return (health.samples if health else 0) + sum(bridge.publisher.rejected.values())

    target = done()
    for start in range(0, count, batch):
        n = min(batch, count - start)
        for _ in range(n):
            fw.send(fw.rotation())
        target += n
        wait_until(lambda t=target: done() >= t, what=f"{target} packets through the bridge")


def fw_health(bridge: SlimeVRBridge) -> tuple[codec.Connection, NodeHealth]:
    node = bridge.server.nodes[FW_TRACKER]
    conn = next(c for c in bridge.server.connections.values() if c.handshake.mac == FW_MAC)
    return conn, bridge.publisher.nodes[node]


def still(_sensor: int, _t: float) -> tuple[float, float, float, float]:
    return (HALF, 0.0, 0.0, HALF)  # w, x, y, z: a quarter turn about z


@pytest.fixture
def served(zsession: zenoh.Session) -> Iterator[tuple[SlimeVRBridge, tuple[str, int]]]:
    listen = ("127.0.0.1", free_udp_port())
    assignments = {codec.tracker_id(emulated_mac(1), 0): UPPER, FW_TRACKER: THIGH}
    bridge = SlimeVRBridge(zsession, "slimevr-test", assignments)
    running = Running(lambda stop: bridge.run(listen, stop))
    yield bridge, listen
    running.stop()
    bridge.close()


@pytest.fixture
def trackers() -> Iterator[Callable[..., EmulatedTracker]]:
    made: list[EmulatedTracker] = []

    def make(server: tuple[str, int], number: int, **kw: object) -> EmulatedTracker:
        tracker = EmulatedTracker(server, emulated_mac(number), [0], still, **kw)  # type: ignore[arg-type]
        tracker.start()
        made.append(tracker)
        return tracker

    yield make
    for tracker in made:
        tracker.stop()


def test_a_tracker_connects_streams_and_reports_its_state(
    zsession: zenoh.Session, served: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    raw = raw_collector(zsession, UPPER.raw_key)
    health = Collector(zsession, "body/@health/slimevr-test", json.loads)
    tracker = trackers(listen, 1, compact=True)
    assert tracker.connected.wait(5)  # the handshake reply it waits for came
    seen = raw.wait_for(lambda s: len(s) >= 20)
    for _, sample in seen:
        assert sample.source is Source.SLIMEVR
        assert isinstance(sample.reading, Quat)
        w, x, y, z = sample.reading.wxyz
        assert (w, x, y, z) == pytest.approx((HALF, 0, 0, HALF), abs=1e-4)  # Q15
        accel = struct.unpack(">3h", sample.reading.extra)
        assert accel[2] / codec.Q7 == pytest.approx(9.81, abs=0.01)
    seqs = [s.seq for _, s in seen]
    assert seqs == sorted(seqs)
    wanted = {"battery_v", "rssi_dbm", "rtt_ms", "tracker"}
    report = health.wait_for(lambda h: any(
        wanted <= set(m["nodes"].get("1", {}).get("status", {})) for _, m in h))  # fmt: skip
    status = next(m for _, m in report if wanted <= set(m["nodes"].get("1", {}).get("status", {})))[
        "nodes"]["1"]["status"]  # fmt: skip
    assert status["tracker"] == "02b0d1000001-0"
    assert status["battery_v"] == pytest.approx(3.9)
    assert status["rssi_dbm"] == -52
    assert status["sensor_status"] == 1
    assert report[-1][1]["kind"] == "slimevr"
    assert tracker.heartbeats >= 1  # the server's heartbeats reach it
    assert tracker.pings_echoed >= 1
    assert 0 in tracker.acked  # its sensor info was acknowledged
    assert not bridge.publisher.rejected


def test_silence_and_back_and_a_packet_counter_jump(
    zsession: zenoh.Session, served: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    live = Liveliness(zsession)
    tracker = trackers(listen, 1)
    live.wait_for(lambda alive: UPPER.raw_key in alive)
    tracker.pause()  # unplugged: its token goes after a few periods
    live.wait_for(lambda alive: UPPER.raw_key not in alive)
    tracker.resume()
    live.wait_for(lambda alive: UPPER.raw_key in alive)
    node = bridge.publisher.nodes[1]
    gaps_before = node.gaps
    samples = node.samples
    tracker.skip(5)  # five packets the server never sees
    wait_until(lambda: node.samples > samples + 5, what="samples after the jump")
    assert node.gaps - gaps_before == 5
    conn = next(c for c in bridge.server.connections.values() if c.handshake.mac == tracker.mac)
    assert conn.lost >= 5


def test_a_second_tracker_appears_unassigned_and_is_assigned_live(
    router_endpoint: str, zsession: zenoh.Session, tmp_path: Path,
    served: tuple[SlimeVRBridge, tuple[str, int]], trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    gateway_session = client(router_endpoint)
    gateway = Gateway(gateway_session)
    topology = Collector(zsession, "body/@topology", json.loads)
    running = Running(gateway.run)
    try:
        trackers(listen, 1)
        second = trackers(listen, 2)
        ident = codec.tracker_id(emulated_mac(2), 0)
        topology.wait_for(lambda t: any(ident in m.get("unassigned", []) for _, m in t))
        assert bridge.unassigned_samples > 0
        raw = raw_collector(zsession, FORE.raw_key)
        profile = tmp_path / "subject.toml"
        typed = ident.upper().replace("-", "/")  # as a user may write it
        code = main(["calibrate", "assign", typed, "right-arm/forearm", "--profile", str(profile),
                     "-e", router_endpoint, "--timeout", "10"])  # fmt: skip
        assert code == 0
        assert profile_file.load(profile).trackers == {ident: "right-arm/forearm"}
        raw.wait_for(lambda s: len(s) >= 5)
        topology.wait_for(lambda t: not t[-1][1].get("unassigned")
                          and FORE.raw_key in json.dumps(t[-1][1]))  # fmt: skip
        assert second.connected.is_set()
    finally:
        running.stop()
        gateway.close()
        gateway_session.close()


def test_garbage_is_counted_by_reason_and_an_unknown_flood_costs_nothing(
    zsession: zenoh.Session, served: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    tracker = trackers(listen, 1)
    wait_until(lambda: 1 in bridge.publisher.nodes, what="the tracker's first sample")
    node = bridge.publisher.nodes[1]
    # from the tracker's own address, between its good packets
    bad = {
        Reason.TRUNCATED: b"\x00\x00",
        Reason.BAD_KIND: struct.pack(">iq", 99, 1 << 40),
        Reason.NOT_FINITE: codec.encode_rotation(1 << 41, 0, (math.nan, 0.0, 0.0, 1.0)),
        Reason.BAD_QUAT_NORM: codec.encode_rotation(1 << 42, 0, (0.0, 0.0, 0.0, 2.0)),
        Reason.OUT_OF_ORDER: codec.encode_rotation(3, 0, (0.0, 0.0, 0.0, 1.0)),
    }
    for data in [*bad.values(), b""]:  # an empty datagram is truncated too, and counted
        tracker.send(data)
    wanted = {**dict.fromkeys(bad, 1), Reason.TRUNCATED: 2}
    wait_until(lambda: all(bridge.publisher.rejected.get(r, 0) >= n for r, n in wanted.items()),
               what=f"rejections {dict(bridge.publisher.rejected)}")  # fmt: skip
    # a flood of well-formed rotations from an address that never shook hands
    flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent = 0
    try:
        for i in range(5000):
            flood.sendto(codec.encode_rotation(i + 1, 0, (0.0, 0.0, 0.0, 1.0)), listen)
            sent += 1
        wait_until(lambda: bridge.publisher.rejected.get(Reason.UNKNOWN_NODE, 0) > 0,
                   what="the flood counted")  # fmt: skip
    finally:
        flood.close()
    assert bridge.publisher.rejected[Reason.UNKNOWN_NODE] <= sent
    assert len(bridge.server.connections) == 1  # no state for the flood's address
    assert set(bridge.publisher.nodes) == {1}
    samples = node.samples
    wait_until(lambda: node.samples > samples + 10, what="the tracker still streaming")
    assert {r: bridge.publisher.rejected[r] for r in wanted} == wanted


def test_a_handshake_flood_fills_no_more_than_its_bound() -> None:
    """Handshakes from ever new addresses and MACs: at most ``max_trackers`` are
    kept, the rest refused and counted; a known tracker still reconnects, and a
    tracker's nodes keep their numbers when it comes back from a new address."""
    server = codec.SlimeVRServer(max_trackers=16)
    refused = 0
    for i in range(40):
        hs = codec.Handshake(bytes([2, 0, 0, 0, 0, i]), firmware="flood")
        events = server.receive(codec.encode_handshake(0, hs), ("10.0.0.1", 1000 + i))
        refused += sum(isinstance(e, Rejected) and e.reason is Reason.OUT_OF_RANGE for e in events)
        replies = server.take_replies()
        assert len(replies) == (1 if i < 16 else 0)  # no answer to a refused handshake
    assert (len(server.connections), refused) == (16, 24)
    first = codec.Handshake(bytes([2, 0, 0, 0, 0, 0]))
    server.forget(("10.0.0.1", 1000))
    server.receive(codec.encode_handshake(0, first), ("10.0.0.2", 5))  # back, elsewhere
    events = server.receive(codec.encode_rotation(1, 0, (0.0, 0.0, 0.0, 1.0)), ("10.0.0.2", 5))
    assert [e.node for e in events if isinstance(e, Quat)] == [1]  # its node as before


# --- against the standard: packet numbers ---------------------------------------------


def test_the_handshake_is_answered_with_the_servers_64_bytes(
    served: tuple[SlimeVRBridge, tuple[str, int]], firmware: Callable[..., Firmware],
) -> None:  # fmt: skip
    _, listen = served
    assert firmware(listen).connect() == SERVER_HANDSHAKE


def test_a_ping_echoed_verbatim_after_thousands_of_packets_moves_no_numbering(
    served: tuple[SlimeVRBridge, tuple[str, int]], firmware: Callable[..., Firmware],
) -> None:  # fmt: skip
    """The firmware answers a ping by sending the server's datagram back as it
    came (returnLastPacket, cpp:494-502,701-702). The SlimeVR server numbers
    what it sends 0 (UDPProtocolParser.kt:79; its ping, TrackersUDPServer.kt:379-384)
    and takes a 0 whatever came before (UDPDevice.kt:92): so must bodynet, or the
    echo is refused or throws the tracker's numbering off."""
    bridge, listen = served
    fw = firmware(listen)
    fw.connect()
    stream(fw, bridge, 3000)  # the first numbered 0 (cpp:162): taken as the server takes it
    assert not bridge.publisher.rejected
    heartbeat = fw.receive(T_SERVER_HEARTBEAT)
    assert heartbeat == server_packet(T_SERVER_HEARTBEAT)  # UDPPacket1Heartbeat: no body
    ping = fw.receive(T_PING)
    assert (ping[:12], len(ping)) == (server_packet(T_PING), 16)  # + ping id int32
    fw.send(ping)
    conn, health = fw_health(bridge)
    wait_until(lambda: "rtt_ms" in health.status or bridge.publisher.rejected,
               what="the echo taken")  # fmt: skip
    assert not bridge.publisher.rejected
    stream(fw, bridge, 500)
    assert not bridge.publisher.rejected
    assert (health.samples, health.gaps, conn.lost) == (3500, 0, 0)


def test_an_echo_of_a_ping_sent_after_more_packets_than_the_tracker_sent_moves_nothing() -> None:
    """A server that has sent a tracker more packets than the tracker sent it
    (a heartbeat and a ping a second to each tracker): the echo of its ping is
    still number 0 (UDPProtocolParser.kt:79), taken without a gap, and the
    tracker's next packets are taken after it."""
    server = codec.SlimeVRServer()
    fw, addr = Firmware(), ("10.0.0.5", 4000)
    server.receive(fw.handshake(), addr)
    for _ in range(50):
        server.receive(fw.rotation(), addr)
    for ping_id in range(1, 201):  # 200 s of heartbeats and pings
        assert server.heartbeats() == [(addr, server_packet(T_SERVER_HEARTBEAT))]
        ((to, ping),) = server.ping(ping_id)
    assert (to, ping) == (addr, server_packet(T_PING, struct.pack(">i", 200)))
    events = server.receive(ping, addr)  # the firmware's verbatim echo
    assert events == [NodeStatus(1, codec.PING_ECHO, 200)]
    events = server.receive(fw.rotation(), addr)
    assert [e for e in events if isinstance(e, Tick | Rejected)] == [Tick(50, 1)]
    assert server.connections[addr].lost == 0


def test_the_emulated_tracker_echoes_a_ping_verbatim(
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    """As the firmware does (cpp:494-502,701-702): the server's datagram back as
    it came, its number 0 in it, the tracker's own counter not used."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as server:
        server.bind(("127.0.0.1", 0))
        server.settimeout(5.0)
        trackers(server.getsockname(), 1)
        data, tracker = server.recvfrom(2048)
        while data[3] != T_HANDSHAKE:
            data, tracker = server.recvfrom(2048)
        server.sendto(SERVER_HANDSHAKE, tracker)
        ping = server_packet(T_PING, struct.pack(">i", -123456789))
        server.sendto(ping, tracker)
        while data[3] != T_PING:
            data = server.recv(2048)
        assert data == ping


# --- against the standard: the sensor-info acknowledgement -----------------------------


def test_sensor_info_is_acknowledged_in_the_servers_six_bytes(
    served: tuple[SlimeVRBridge, tuple[str, int]], firmware: Callable[..., Firmware],
) -> None:  # fmt: skip
    """The server answers a sensor info with type, sensor id and status, no
    packet number (writeSensorInfoResponse, UDPProtocolParser.kt:89-97); the
    firmware wants 6 bytes at least and reads the id and state at byte 4
    (cpp:705-716, SensorInfoPacket packets.h:135-137), resending until acknowledged."""
    bridge, listen = served
    fw = firmware(listen)
    fw.connect()
    for state in (1, 2):  # SensorStatus: OK, then an error
        fw.send(fw.sensor_info(0, state))
        ack = fw.receive(T_SENSOR_INFO)
        assert ack == struct.pack(">i", T_SENSOR_INFO) + bytes([0, state])
        assert len(ack) >= 6  # as the firmware checks
        assert (ack[4], ack[5]) == (0, state)  # sensorId, sensorState, as it reads them
    assert not bridge.publisher.rejected


def test_the_emulated_tracker_takes_the_servers_six_byte_acknowledgement(
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as server:
        server.bind(("127.0.0.1", 0))
        server.settimeout(5.0)
        tracker = trackers(server.getsockname(), 1)
        data, address = server.recvfrom(2048)
        while data[3] != T_HANDSHAKE:
            data, address = server.recvfrom(2048)
        server.sendto(SERVER_HANDSHAKE, address)
        while data[3] != T_SENSOR_INFO:
            data = server.recv(2048)
        sensor, state = data[12], data[13]  # as the server reads it (UDPPacket.kt:233-235)
        server.sendto(struct.pack(">i", T_SENSOR_INFO) + bytes([sensor, state]), address)
        wait_until(lambda: sensor in tracker.acked, what="the acknowledgement taken")


# --- against the standard: numbering around the handshake -----------------------------


def test_a_tracker_connecting_and_reconnecting_with_its_counter_running_on(
    served: tuple[SlimeVRBridge, tuple[str, int]], firmware: Callable[..., Firmware],
) -> None:  # fmt: skip
    """The firmware numbers its handshake 0 (cpp:394) and everything else from a
    counter it never resets (connection.h:221): here one that ran before (another
    server, a bridge restarted), then a second handshake, as after a timeout
    (cpp:640-660). The server starts over at each handshake (UDPDevice.kt:46;
    TrackersUDPServer.kt:84,107) and counts no gap: nothing is lost here."""
    bridge, listen = served
    fw = firmware(listen, number=50_000)
    fw.connect()
    stream(fw, bridge, 100)
    conn, health = fw_health(bridge)
    assert (health.samples, conn.lost) == (100, 0)
    fw.connect()  # numbered 0; the packets after it 50_100 on
    stream(fw, bridge, 100)
    assert not bridge.publisher.rejected
    assert (health.samples, health.gaps, conn.lost) == (200, 0, 0)


def test_the_first_packet_after_a_handshake_is_taken_and_starts_the_count() -> None:
    """After the handshake, whatever its number, the tracker's first packet is
    taken and no gap counted; numbers skipped after it are. (A tracker fresh from
    boot numbers its first packet 0, cpp:162: taken as any 0 is.)"""
    server, fw, addr = codec.SlimeVRServer(), Firmware(), ("10.0.0.5", 4000)
    server.receive(fw.handshake(), addr)
    for index in range(3):  # 0, 1, 2
        events = server.receive(fw.rotation(), addr)
        assert [e for e in events if isinstance(e, Tick | Rejected)] == [Tick(index, 1)]
    for first in (1, 7, 2**40):
        server, fw, addr = codec.SlimeVRServer(), Firmware(number=first), ("10.0.0.5", 4000)
        server.receive(fw.handshake(), addr)
        ticks = [e for e in server.receive(fw.rotation(), addr) if isinstance(e, Tick | Rejected)]
        fw.packet_number += 3  # three packets lost
        ticks += [e for e in server.receive(fw.rotation(), addr) if isinstance(e, Tick | Rejected)]
        assert ticks == [Tick(0, 1), Tick(4, 1)]
        assert server.connections[addr].lost == 3


def test_the_emulated_tracker_keeps_its_counter_across_reconnects(
    trackers: Callable[..., EmulatedTracker], monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """Like the firmware: its first packet numbered 0 (``m_PacketNumber++``,
    cpp:162), its handshakes 0 (cpp:394), its counter running on after it gave up
    on a silent server and shook hands again (connection.h:221, cpp:640-660)."""
    monkeypatch.setattr(codec, "TRACKER_TIMEOUT_S", 0.3)  # give up sooner than 3 s
    numbers: list[list[int]] = []  # those numbered after each handshake answered
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as server:
        server.bind(("127.0.0.1", 0))
        server.settimeout(5.0)
        trackers(server.getsockname(), 1)
        while len(numbers) < 2 or len(numbers[-1]) < 5:
            data, address = server.recvfrom(2048)
            number = struct.unpack_from(">q", data, 4)[0]
            if data[3] == T_HANDSHAKE:
                assert number == 0
                if not numbers or numbers[-1]:  # answered once, then silence
                    server.sendto(SERVER_HANDSHAKE, address)
                    numbers.append([])
            elif numbers:
                numbers[-1].append(number)
    before, after = numbers[0], numbers[1]
    assert before[0] == 0
    assert before == sorted(before)
    assert after[0] > before[-1]


# --- against the standard: the packets bodynet has no use for --------------------------

# what the firmware sends (packets.h:32-60; layouts packets.h:113-205, connection.cpp)
# or the server parses (UDPProtocolParser.kt:99-123; layouts UDPPacket.kt), that bodynet
# takes quietly: type -> body
UNUSED_PACKETS = {
    1: struct.pack(">4f", 0.0, 0.0, 0.0, 1.0),  # deprecated rotation (UDPPacket.kt:86-93)
    4: struct.pack(">3f", 0.0, 0.0, 9.81) + bytes([0]),  # AccelPacket (packets.h:113-118)
    11: struct.pack(">I", 5) + b"hello",  # serial: sendLongString (cpp:188-194)
    13: bytes([0, 1]),  # TapPacket (packets.h:125-128)
    14: bytes([0, 5]),  # ErrorPacket (packets.h:130-133)
    16: struct.pack(">4f", 0.0, 0.0, 0.0, 1.0),  # deprecated rotation 2 (UDPPacket.kt:257-264)
    18: bytes([0]) + struct.pack(">f", 1.0),  # MagnetometerAccuracyPacket (packets.h:161-164)
    20: bytes([0]) + struct.pack(">f", 31.5),  # TemperaturePacket (packets.h:171-174)
    21: bytes([3]),  # user action: yaw reset (UDPPacket.kt:316-326)
    22: bytes([0b110]),  # feature flags (cpp:333-338; featureflags.h: bits 1, 2)
    24: bytes([0]) + struct.pack(">H", 1),  # AcknowledgeConfigChangePacket (packets.h:176-179)
    26: bytes([0]) + struct.pack(">f", 0.5),  # FlexDataPacket (packets.h:181-184)
    27: bytes([0]) + struct.pack(">3f", 0.0, 1.0, 0.0),  # position (UDPPacket.kt:398-410)
    # IntRawImuDataInspectionPacket (packets.h:186-205), ENABLE_INSPECTION (cpp:410-450)
    105: bytes([1, 0, 1]) + (struct.pack(">3I", 1, 2, 3) + bytes([0])) * 3,
    200: bytes([1, 1]),  # protocol change (UDPPacket.kt:412-419)
}


def test_packets_of_no_use_are_taken_quietly_and_get_no_answer() -> None:
    """Each takes its number and is counted ``ignored``, not ``bad_kind``, and
    has no answer: feature flags (22) unanswered, the firmware never bundles
    (beginBundle, cpp:92-101)."""
    server, fw, addr = codec.SlimeVRServer(), Firmware(), ("10.0.0.5", 4000)
    server.receive(fw.handshake(), addr)
    server.take_replies()
    for kind, body in UNUSED_PACKETS.items():
        assert server.receive(fw.header(kind) + body, addr) == [], kind
        assert server.take_replies() == [], kind
    events = server.receive(fw.rotation(), addr)
    assert [e for e in events if isinstance(e, Tick)] == [Tick(0, 1)]  # no gap: all were taken
    conn = server.connections[addr]
    assert (conn.ignored, conn.lost) == (len(UNUSED_PACKETS), 0)


def test_packets_of_no_use_between_rotations_count_as_nothing_bad(
    served: tuple[SlimeVRBridge, tuple[str, int]], firmware: Callable[..., Firmware],
) -> None:  # fmt: skip
    bridge, listen = served
    fw = firmware(listen)
    fw.connect()
    stream(fw, bridge, 10)
    for kind, body in UNUSED_PACKETS.items():
        fw.send(fw.header(kind) + body)
        stream(fw, bridge, 1)  # taken after it
    assert not bridge.publisher.rejected
    conn, health = fw_health(bridge)
    assert (conn.ignored, conn.lost) == (len(UNUSED_PACKETS), 0)
    assert (health.samples, health.gaps) == (10 + len(UNUSED_PACKETS), 0)


# --- the link's timing: own timers, losses, datagrams overtaken, a reboot --------------


def test_a_swapped_pair_is_one_gap_and_the_late_packet_no_rejection() -> None:
    """Packets 0 1 3 2 4 (2 overtaken by 3): 3 skips 2, a gap of one; 2, late,
    is dropped as the SlimeVR server drops it (not above the last number,
    UDPDevice.kt:92-97, which counts it as its one packet lost) but not counted
    again: no rejection, its tracker's ``late_packets`` status says it came. A
    duplicate of 3, or 2 again, is a packet out of order (rejected)."""
    server, fw, addr = codec.SlimeVRServer(), Firmware(), ("10.0.0.5", 4000)
    server.receive(fw.handshake(), addr)
    packets = [fw.rotation() for _ in range(5)]
    events = [e for i in (0, 1, 3, 2, 4) for e in server.receive(packets[i], addr)]
    kept = [e for e in events if isinstance(e, Tick | Rejected)
            or (isinstance(e, NodeStatus) and e.key == "late_packets")]  # fmt: skip
    assert kept == [Tick(0, 1), Tick(1, 1), Tick(3, 1), NodeStatus(1, "late_packets", 1),
                    Tick(4, 1)]  # fmt: skip
    conn = server.connections[addr]
    assert (conn.lost, conn.late) == (1, 1)
    for again in (packets[3], packets[2]):
        (rejected,) = server.receive(again, addr)
        assert isinstance(rejected, Rejected)
        assert rejected.reason is Reason.OUT_OF_ORDER


def slimevr_sites() -> dict[str, Site]:
    """Three emulated trackers (1, 2, 3) assigned to sites."""
    sites = (UPPER, FORE, THIGH)
    return {codec.tracker_id(emulated_mac(n), 0): s for n, s in zip((1, 2, 3), sites, strict=True)}


@pytest.fixture
def bridged(zsession: zenoh.Session) -> Iterator[tuple[SlimeVRBridge, tuple[str, int]]]:
    """A bridge with three emulated trackers' sites assigned."""
    listen = ("127.0.0.1", free_udp_port())
    bridge = SlimeVRBridge(zsession, "slimevr-timing", slimevr_sites())
    running = Running(lambda stop: bridge.run(listen, stop))
    yield bridge, listen
    running.stop()
    bridge.close()


def node_health(bridge: SlimeVRBridge, number: int) -> NodeHealth | None:
    node = bridge.server.nodes.get(codec.tracker_id(emulated_mac(number), 0))
    return bridge.publisher.nodes.get(node) if node is not None else None


def test_trackers_on_their_own_timers_every_rotation_lost_is_a_gap(
    zsession: zenoh.Session, bridged: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    """Three trackers each on a timer of its own (own phase and clock error,
    rotations late by up to 3 ms), 10% of rotations lost on the air after the
    counter counted them: per tracker, the bridge's gaps are the rotations it
    lost, and so are the holes in the sequence numbers it published."""
    bridge, listen = bridged
    raw = raw_collector(zsession)
    timing = LinkTiming(Timers.INDEPENDENT, jitter_s=3e-3, drop=0.1, seed=4)
    made = {n: trackers(listen, n, timing=timing.of(n)) for n in (1, 2, 3)}
    assert len({t.timers.schedule[0] for t in made.values()}) == 3  # own phase, own period
    for t in made.values():  # none lost until the bridge has each (it starts counting then)
        t.timers.drop = 0.0
    wait_until(lambda: all(node_health(bridge, n) for n in made), what="every tracker bridged")
    for t in made.values():
        t.timers.drop = timing.drop
    wait_until(lambda: min(t.dropped for t in made.values()) >= 10, 30.0, "rotations lost")
    for t in made.values():
        t.timers.drop = 0.0  # a loss shows at the tracker's next packet
    health = {n: node_health(bridge, n) for n in made}
    wait_until(lambda: all(health[n].gaps >= t.dropped for n, t in made.items()),  # type: ignore[union-attr]
               10.0, "the bridge to count every loss")  # fmt: skip
    for t in made.values():
        t.stop()
    lost = {n: t.dropped for n, t in made.items()}
    print(f"\nlost {lost}, gaps { ({n: h.gaps for n, h in health.items() if h}) }")
    assert not bridge.publisher.rejected
    keys_of = {1: UPPER.raw_key, 2: FORE.raw_key, 3: THIGH.raw_key}
    seen = raw.wait_for(lambda s: all(sum(k == keys_of[n] for k, _ in s) >= health[n].samples  # type: ignore[union-attr]
                                      for n in made), timeout=10)  # fmt: skip
    for n in made:
        assert health[n].gaps == lost[n]  # type: ignore[union-attr]
        seqs = [x.seq for k, x in seen if k == keys_of[n]]
        assert seqs == sorted(set(seqs))
        assert seqs[-1] - seqs[0] + 1 - len(seqs) == lost[n]  # the numbers not received


def test_rotations_overtaken_on_the_way_are_each_one_gap_and_no_rejection(
    bridged: tuple[SlimeVRBridge, tuple[str, int]], trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    """A tracker whose rotations are overtaken by the next one now and then (UDP
    reordering): each is one gap (its sample dropped, too late), counted once:
    no rejection, and the bridge's ``late_packets`` status is how many came."""
    bridge, listen = bridged
    tracker = trackers(listen, 1, timing=LinkTiming(reorder=0.1, seed=2))
    wait_until(lambda: tracker.reordered >= 10, 30.0, "rotations overtaken")
    tracker.timing = LinkTiming()  # the one held back goes out after the next
    health = node_health(bridge, 1)
    assert health is not None
    wait_until(lambda: health.gaps >= tracker.reordered
               and health.status.get("late_packets") == tracker.reordered,
               10.0, "the bridge to count them")  # fmt: skip
    assert health.gaps == tracker.reordered
    assert not bridge.publisher.rejected


def test_a_tracker_rebooting_starts_its_counter_over_with_no_gap(
    bridged: tuple[SlimeVRBridge, tuple[str, int]], trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    """A tracker rebooting (counter back to 0, a new handshake) carries on on the
    same node, its samples numbered on, with no gap and nothing out of order."""
    bridge, listen = bridged
    tracker = trackers(listen, 1)
    wait_until(lambda: (h := node_health(bridge, 1)) is not None and h.samples >= 50,
               what="samples before the reboot")  # fmt: skip
    health = node_health(bridge, 1)
    assert health is not None
    number, samples = tracker.number, health.samples
    tracker.reboot()
    wait_until(lambda: health.samples >= samples + 20, 10.0, "samples after the reboot")
    conn = next(c for c in bridge.server.connections.values() if c.handshake.mac == tracker.mac)
    assert conn.last_number is not None
    assert conn.last_number < number
    wait_until(lambda: health.samples >= samples + 100, 10.0, "more samples")
    assert (health.gaps, dict(bridge.publisher.rejected)) == (0, {})
    assert set(bridge.server.nodes) == {tracker.tracker_ids()[0]}


def test_a_datagram_read_late_keeps_the_time_it_came() -> None:
    """The bridge stamps a tracker's datagram with when it came (the kernel's
    stamp), not when it read it: a bridge held up on a loaded host (live, reads
    50-110 ms late at the 99th percentile) would take a burst of rotations for
    simultaneous ones. Here the socket is read only after another datagram was
    sent: the first keeps a time before that; read without the stamp, it would
    get the time it was read."""
    from bodynet.nodes.slimevr_bridge import arrival_stamps, receive

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as server, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tracker:  # fmt: skip
        server.bind(("127.0.0.1", 0))
        server.settimeout(5.0)
        assert arrival_stamps(server)
        before = time.time()
        tracker.sendto(b"first", server.getsockname())
        sent = time.time()
        tracker.sendto(b"second", server.getsockname())
        read_from = time.time()
        data, addr, t_s = receive(server, True)
        assert data == b"first"
        assert addr[1] == tracker.getsockname()[1]
        assert before <= t_s <= sent < read_from
        _, _, unstamped = receive(server, False)  # without the kernel's stamp: when read
        assert unstamped >= read_from
