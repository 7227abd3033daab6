"""The SlimeVR tracker protocol: what a SlimeVR tracker sends its server on UDP 6969.

SlimeVR trackers (open-source Wi-Fi IMU trackers, ESP8266/ESP32 firmware) look
for a server by broadcasting a handshake to port 6969, then stream to the
address that answered. This module speaks the server's side with no I/O:
:class:`SlimeVRServer` takes datagrams with their sender's address and gives
decoder events (readings, per-tracker ticks, node states, rejections) plus the
datagrams to send back; the tracker side (for the emulated tracker) is the
``encode_*`` functions and :func:`decode_server_packet`.

Strategy: every datagram is one packet, decoded whole or rejected whole with a
countable reason (nothing a datagram holds can disturb another's decoding).
State is kept per sender address, and only once a handshake has come from it:
a flood from an address that never shook hands costs a counter, not memory.

What is supported: the layouts and rules of the SlimeVR server (SlimeVR-Server
5549763, ``UDPProtocolParser.kt``, ``UDPPacket.kt``, ``UDPDevice.kt``,
``TrackersUDPServer.kt`` in server/core/src/main/java/dev/slimevr/tracking/trackers/udp)
and of the firmware (SlimeVR-Tracker-ESP 12f4b22, src/network/connection.cpp,
connection.h, packets.h), read from their sources; file:line references here
are to those versions. Every tracker->server packet is::

    int32 BE packet type, int64 BE packet number, payload

+------+---------------------+-------------------------------------------------+
| type | packet              | payload read here                               |
+======+=====================+=================================================+
| 0    | heartbeat (tracker) | none                                            |
| 1    | heartbeat (server)  | none; sent by us every second, numbered 0 (from |
|      |                     | a tracker, 1 is a deprecated rotation: ignored) |
| 3    | handshake           | board i32, IMU i32, MCU i32, 3 x i32 IMU info,  |
|      |                     | protocol version i32 (``build`` here), firmware |
|      |                     | string (u8 length + bytes), MAC 6 bytes; the    |
|      |                     | full form only; answered with the server's 64   |
|      |                     | bytes: 3, ``Hey OVR =D 5``, zeros               |
| 10   | ping                | i32 id: we send pings (numbered 0), the tracker |
|      |                     | echoes the datagram verbatim                    |
| 12   | battery             | f32 voltage, f32 level                          |
| 15   | sensor info         | sensor id u8, status u8, IMU type u8 (more      |
|      |                     | bytes of newer firmware ignored); acknowledged  |
|      |                     | as the server does: 6 bytes, type i32, sensor   |
|      |                     | id u8, status u8, no packet number              |
| 17   | rotation data       | sensor id u8, data type u8 (1 normal; 2         |
|      |                     | correction, ignored), quaternion x, y, z, w as  |
|      |                     | 4 x f32 BE, accuracy u8                         |
| 19   | signal strength     | sensor id u8, RSSI i8 (dBm)                     |
| 23   | rotation + accel    | sensor id u8, quaternion x, y, z, w 4 x i16 BE  |
|      |                     | Q15, acceleration x, y, z 3 x i16 BE Q7 (m/s^2) |
+------+---------------------+-------------------------------------------------+

The other types the server parses or today's firmware sends (1 and 16
deprecated rotations, 4 acceleration, 11 serial, 13 tap, 14 error, 18
magnetometer accuracy, 20 temperature, 21 user action, 22 feature flags, 24
config change acknowledged, 26 flex data, 27 position, 105 inspection, 200
protocol change) take their packet number and are counted as ``ignored`` in the
tracker's state, not rejected. Feature flags are not answered, so the firmware
never bundles its packets (100, 101: not read). Any other type is rejected
(``bad_kind``; the server would skip it silently).

Readings: each tracker sensor (MAC + sensor id, written ``aabbccddeeff-0``) is
one node, numbered in order of first appearance and kept across reconnects.
A rotation gives a :class:`Quat` (w, x, y, z); packet 23 also gives its
acceleration as ``extra``: the packet's six bytes (3 x int16 BE, Q7 m/s^2).
Sequence numbers come from the packet counter: a sensor's sample is numbered
one after its last plus every packet of its tracker lost since (numbers
skipped), so a lost packet is a gap of the sensors it could have carried (an
upper bound: a lost battery packet is counted too). A packet whose number is
not above the last one is dropped, as the server drops it: one of the last
:data:`REORDER_WINDOW` numbers skipped (a datagram overtaken by a later one)
is a late packet, already counted as its gap, so counted no more than that
(its tracker's sensors get status ``late_packets``, how many came late); any
other (a duplicate, one older still) is rejected (``out_of_order``). The
server counts a swapped pair as one packet lost too (its refused one), and
no gap. Number 0 is the exception, as in the
server (``UDPDevice.isNextPacket``): always taken, no gap counted, the last
number left as it was. Every packet the server sends is numbered 0, and the
firmware answers a ping (10) by sending the server's datagram back verbatim.
A handshake (numbered 0) leaves no last number: the firmware's counter runs on
from boot across reconnects, so the first packet after it counts no gap.

Versions: the packet framing above (int32 type + int64 number) is that of
SlimeVR firmware since its numbered packets; handshakes are read in their full
form only (board, IMU, MCU, IMU info, protocol version, firmware string, MAC;
today's firmware, protocol 22, adds a tracker type and vendor strings after,
not read): an older, shorter handshake is refused as ``truncated``. The tests
build the tracker's datagrams from the firmware's sources and check the
answers byte for byte against the server's; a real tracker is yet to be tried.

Where bodynet does otherwise than the server, knowingly:
- quaternions are taken in the tracker's own (z-up) world frame, as sent; the
  server turns them into its y-up frame (AXES_OFFSET, TrackersUDPServer.kt:407,427);
- the battery level is passed on as sent, 0-1 (the server shows it x 100,
  TrackersUDPServer.kt:488);
- heartbeats and pings go out every second, not every 500 ms
  (TrackersUDPServer.kt:346-385): well within the firmware's 3 s timeout
  (connection.cpp:32,640).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Hashable
from dataclasses import dataclass, field

from ..errors import MAX_KEPT, DecodeError, Reason, Rejected
from ..messages import NodeStatus, Quat, StreamEvent, Tick
from ._common import unit_quat

PORT = 6969
HEARTBEAT_S = 1.0
#: The tracker gives up on a server it has not heard from for about this long.
TRACKER_TIMEOUT_S = 3.0
#: A packet up to this many numbers behind the last one taken, whose number was
#: skipped, is taken for a late one (overtaken on the way), not a duplicate.
REORDER_WINDOW = 64

HEARTBEAT, SERVER_HEARTBEAT, HANDSHAKE = 0, 1, 3
PING, BATTERY, SENSOR_INFO, ROTATION_DATA, SIGNAL_STRENGTH, ROTATION_ACCEL = 10, 12, 15, 17, 19, 23
#: what the SlimeVR server parses (UDPProtocolParser.kt:99-123) or today's firmware sends
#: (packets.h:32-60) and bodynet has no use for: 1 and 16 deprecated rotations, 4
#: acceleration, 11 serial, 13 tap, 14 error, 18 magnetometer accuracy, 20 temperature,
#: 21 user action, 22 feature flags (not answered: no bundles then, connection.cpp:92-101),
#: 24 config change acknowledged, 26 flex data, 27 position, 105 inspection, 200 protocol change
IGNORED_TYPES = frozenset({1, 4, 11, 13, 14, 16, 18, 20, 21, 22, 24, 26, 27, 105, 200})
#: what the firmware looks for in the server's answer to its handshake: byte 0 is 3,
#: then these 12 characters (connection.cpp:562-564)
HANDSHAKE_MAGIC = b"\x03Hey OVR =D 5"
#: the server's answer: its whole 64-byte buffer, the magic then zeros
#: (UDPProtocolParser.kt:84-86,161-168; TrackersUDPServer.kt:191-194)
HANDSHAKE_REPLY = HANDSHAKE_MAGIC.ljust(64, b"\0")
#: the packet number of every server->tracker packet: "Packet number is always 0
#: when sending data to trackers" (UDPProtocolParser.kt:79, TrackersUDPServer.kt:382)
SERVER_NUMBER = 0
DEVICE_SENSOR = 255  # a sensor id meaning the whole tracker
#: the NodeStatus key under which an echoed ping's id comes out (for a round trip)
PING_ECHO = "ping_echo"
DATA_NORMAL, DATA_CORRECTION = 1, 2
Q15, Q7 = 1 << 15, 1 << 7

_HEADER = struct.Struct(">iq")
_I32 = struct.Struct(">i")
_HANDSHAKE_INTS = struct.Struct(">7i")
_ROTATION = struct.Struct(">BB4fB")
_COMPACT = struct.Struct(">B4h3h")
_BATTERY = struct.Struct(">2f")
_SENSOR_INFO = struct.Struct(">BBB")
_RSSI = struct.Struct(">Bb")
#: the server's answer to a sensor info: type, sensor id, status, and no packet
#: number (writeSensorInfoResponse, UDPProtocolParser.kt:89-97)
_SENSOR_ACK = struct.Struct(">iBB")
_PING_SIZE = _HEADER.size + _I32.size
MAC_LEN = 6


@dataclass(frozen=True, slots=True)
class Handshake:
    mac: bytes
    board: int = 0
    imu: int = 0
    mcu: int = 0
    build: int = 0
    firmware: str = ""


@dataclass(frozen=True, slots=True)
class Rotation:
    sensor: int
    xyzw: tuple[float, float, float, float]
    data_type: int = DATA_NORMAL
    accuracy: int = 0
    accel: bytes = b""  # packet 23: 3 x int16 BE, Q7 m/s^2


@dataclass(frozen=True, slots=True)
class Battery:
    voltage: float
    level: float


@dataclass(frozen=True, slots=True)
class SensorInfo:
    sensor: int
    status: int
    imu: int


@dataclass(frozen=True, slots=True)
class SignalStrength:
    sensor: int
    rssi: int


@dataclass(frozen=True, slots=True)
class Ping:
    id: int


@dataclass(frozen=True, slots=True)
class Heartbeat:
    pass


@dataclass(frozen=True, slots=True)
class Ignored:
    kind: int


Payload = Handshake | Rotation | Battery | SensorInfo | SignalStrength | Ping | Heartbeat | Ignored


@dataclass(frozen=True, slots=True)
class Packet:
    kind: int
    number: int
    payload: Payload


def _need(data: bytes, size: int, what: str) -> None:
    if len(data) < size:
        raise DecodeError(Reason.TRUNCATED, f"{what}: {len(data)} bytes, {size} needed")


def decode_packet(data: bytes) -> Packet:
    """One tracker->server datagram; ``DecodeError`` if it is not one."""
    _need(data, _HEADER.size, "header")
    kind, number = _HEADER.unpack_from(data)
    body = data[_HEADER.size :]
    payload: Payload
    if kind == HEARTBEAT:
        payload = Heartbeat()
    elif kind == HANDSHAKE:
        payload = _handshake(body)
    elif kind == ROTATION_DATA:
        _need(body, _ROTATION.size, "rotation")
        sensor, data_type, x, y, z, w, accuracy = _ROTATION.unpack_from(body)
        payload = Rotation(sensor, _unit_xyzw(x, y, z, w), data_type, accuracy)
    elif kind == ROTATION_ACCEL:
        _need(body, _COMPACT.size, "rotation and acceleration")
        sensor, x, y, z, w, *_ = _COMPACT.unpack_from(body)
        xyzw = _unit_xyzw(x / Q15, y / Q15, z / Q15, w / Q15)
        payload = Rotation(sensor, xyzw, accel=bytes(body[9:15]))
    elif kind == BATTERY:
        _need(body, _BATTERY.size, "battery")
        voltage, level = _BATTERY.unpack_from(body)
        if not (math.isfinite(voltage) and math.isfinite(level)):
            raise DecodeError(Reason.NOT_FINITE, f"battery {voltage} V, level {level}")
        payload = Battery(voltage, level)
    elif kind == SENSOR_INFO:
        _need(body, _SENSOR_INFO.size, "sensor info")
        payload = SensorInfo(*_SENSOR_INFO.unpack_from(body))
    elif kind == SIGNAL_STRENGTH:
        _need(body, _RSSI.size, "signal strength")
        payload = SignalStrength(*_RSSI.unpack_from(body))
    elif kind == PING:
        _need(body, _I32.size, "ping")
        payload = Ping(_I32.unpack_from(body)[0])
    elif kind in IGNORED_TYPES:
        payload = Ignored(kind)
    else:
        raise DecodeError(Reason.BAD_KIND, f"packet type {kind}")
    return Packet(kind, number, payload)


def _unit_xyzw(x: float, y: float, z: float, w: float) -> tuple[float, float, float, float]:
    """A rotation's quaternion checked (finite, norm near 1) and normalised: a packet
    that carries a bad one is rejected whole, its number not taken."""
    w, x, y, z = unit_quat(w, x, y, z)
    return (x, y, z, w)


def _handshake(body: bytes) -> Handshake:
    """The handshake's fields, in the full form (the MAC, its last 6 bytes, is the
    tracker's identity)."""
    if len(body) < _HANDSHAKE_INTS.size + 1 + MAC_LEN:
        raise DecodeError(Reason.TRUNCATED, f"handshake of {len(body)} bytes has no MAC")
    board, imu, mcu, _, _, _, build = _HANDSHAKE_INTS.unpack_from(body)
    n = body[_HANDSHAKE_INTS.size]
    start = _HANDSHAKE_INTS.size + 1
    if len(body) < start + n + MAC_LEN:
        raise DecodeError(Reason.TRUNCATED, f"firmware string of {n} bytes, then no MAC")
    firmware = body[start : start + n].decode("ascii", "replace")
    mac = bytes(body[start + n : start + n + MAC_LEN])
    return Handshake(mac, board, imu, mcu, build, firmware)


# --- the tracker's side: what the emulated tracker sends -----------------------------


def _packet(kind: int, number: int, body: bytes = b"") -> bytes:
    return _HEADER.pack(kind, number) + body


def encode_handshake(number: int, hs: Handshake) -> bytes:
    fw = hs.firmware.encode("ascii")[:255]
    ints = _HANDSHAKE_INTS.pack(hs.board, hs.imu, hs.mcu, 0, 0, 0, hs.build)
    return _packet(HANDSHAKE, number, ints + bytes([len(fw)]) + fw + hs.mac)


def encode_rotation(number: int, sensor: int, xyzw: tuple[float, float, float, float],
                    accuracy: int = 0, data_type: int = DATA_NORMAL) -> bytes:  # fmt: skip
    return _packet(ROTATION_DATA, number, _ROTATION.pack(sensor, data_type, *xyzw, accuracy))


def _q(value: float, scale: int) -> int:
    return max(-0x8000, min(0x7FFF, round(value * scale)))


def encode_rotation_accel(
    number: int,
    sensor: int,
    xyzw: tuple[float, float, float, float],
    accel: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> bytes:
    q = [_q(c, Q15) for c in xyzw]
    a = [_q(c, Q7) for c in accel]
    return _packet(ROTATION_ACCEL, number, _COMPACT.pack(sensor, *q, *a))


def encode_battery(number: int, voltage: float, level: float) -> bytes:
    return _packet(BATTERY, number, _BATTERY.pack(voltage, level))


def encode_sensor_info(number: int, sensor: int, status: int = 1, imu: int = 0) -> bytes:
    return _packet(SENSOR_INFO, number, _SENSOR_INFO.pack(sensor, status, imu))


def encode_signal_strength(number: int, sensor: int, rssi: int) -> bytes:
    return _packet(SIGNAL_STRENGTH, number, _RSSI.pack(sensor, rssi))


def encode_ping(number: int, ping_id: int) -> bytes:
    return _packet(PING, number, _I32.pack(ping_id))


def encode_heartbeat(number: int, kind: int = HEARTBEAT) -> bytes:
    return _packet(kind, number)


@dataclass(frozen=True, slots=True)
class ServerPacket:
    """A server->tracker datagram as the tracker reads it."""

    kind: int  # HANDSHAKE (the reply), SERVER_HEARTBEAT, PING, SENSOR_INFO (ack)
    ping_id: int | None = None
    sensor: int | None = None
    status: int | None = None  # of the sensor-info acknowledgement


def decode_server_packet(data: bytes) -> ServerPacket:
    """A datagram from the server as the firmware reads it (connection.cpp
    ``update``); ``DecodeError`` if it is none the firmware acts on.

    The type is byte 3 (connection.cpp:682). A ping is echoed whole, so its id
    is only read if there (after the 12-byte header). The sensor-info
    acknowledgement is the server's 6 bytes, type then sensor id and status with
    no packet number (UDPProtocolParser.kt:89-97), read at byte 4 (connection.cpp:705-716).
    """
    if data.startswith(HANDSHAKE_MAGIC):
        return ServerPacket(HANDSHAKE)
    _need(data, _I32.size, "type")
    kind = data[3]
    if kind == SERVER_HEARTBEAT:
        return ServerPacket(kind)
    if kind == PING:
        ping_id = _I32.unpack_from(data, _HEADER.size)[0] if len(data) >= _PING_SIZE else None
        return ServerPacket(kind, ping_id=ping_id)
    if kind == SENSOR_INFO:
        _need(data, _SENSOR_ACK.size, "sensor info acknowledgement")
        _, sensor, status = _SENSOR_ACK.unpack_from(data)
        return ServerPacket(kind, sensor=sensor, status=status)
    raise DecodeError(Reason.BAD_KIND, f"server packet type {kind}")


# --- the server's side ---------------------------------------------------------------


def tracker_id(mac: bytes, sensor: int) -> str:
    """``aabbccddeeff-0``: a tracker sensor's name (a valid key chunk)."""
    return f"{mac.hex()}-{sensor}"


def normalise_tracker_id(text: str) -> str:
    """A tracker id as a user may write it (``AA:BB:CC:DD:EE:FF/0``) in its canonical
    form; ``ValueError`` if it is none."""
    mac_text, sep, sensor_text = text.strip().lower().replace("/", "-").rpartition("-")
    mac_hex = mac_text.replace(":", "").replace("-", "")
    if not sep or len(mac_hex) != 2 * MAC_LEN or not sensor_text.isdigit():
        raise ValueError(f"not a tracker id like aabbccddeeff-0: {text!r}")
    try:
        mac = bytes.fromhex(mac_hex)
    except ValueError:
        raise ValueError(f"not a tracker id like aabbccddeeff-0: {text!r}") from None
    if int(sensor_text) > 255:
        raise ValueError(f"sensor id above 255: {text!r}")
    return tracker_id(mac, int(sensor_text))


@dataclass
class Connection:
    """One tracker as the server knows it, from its handshake on."""

    address: Hashable
    handshake: Handshake
    #: the number of the tracker's last packet taken; none since its handshake
    last_number: int | None = None
    lost: int = 0  # packets whose numbers were skipped
    late: int = 0  # of those, packets that came after all (dropped: too late)
    missing: set[int] = field(default_factory=set)  # the last numbers skipped
    ignored: int = 0
    nodes: dict[int, int] = field(default_factory=dict)  # sensor id -> node
    pending_lost: dict[int, int] = field(default_factory=dict)  # node -> lost since


class SlimeVRServer:
    """The server side of the protocol, sans I/O.

    :meth:`receive` takes a datagram and its sender's address and returns the
    decoder events; :meth:`take_replies` the ``(address, datagram)`` pairs to
    send (handshake replies, sensor-info acknowledgements); :meth:`heartbeats`
    and :meth:`ping` what to send every :data:`HEARTBEAT_S` (a ping's echo
    comes out as a ``NodeStatus`` :data:`PING_ECHO` with its id).
    """

    def __init__(self, max_trackers: int = 256) -> None:
        self.max_trackers = max_trackers
        self.connections: dict[Hashable, Connection] = {}
        self.nodes: dict[str, int] = {}  # tracker id -> node, kept across reconnects
        self.trackers: dict[int, str] = {}  # node -> tracker id
        self.seqs: dict[int, int] = {}  # node -> last sequence number, across reconnects
        self._replies: list[tuple[Hashable, bytes]] = []

    def take_replies(self) -> list[tuple[Hashable, bytes]]:
        out, self._replies = self._replies, []
        return out

    def heartbeats(self) -> list[tuple[Hashable, bytes]]:
        """A heartbeat for every tracker that shook hands (the firmware reconnects
        when it has heard nothing for :data:`TRACKER_TIMEOUT_S`)."""
        return [(addr, encode_heartbeat(SERVER_NUMBER, SERVER_HEARTBEAT))
                for addr in self.connections]  # fmt: skip

    def ping(self, ping_id: int) -> list[tuple[Hashable, bytes]]:
        """A ping for every tracker; the firmware echoes the datagram as it came
        (``returnLastPacket``, connection.cpp:494-502,701-702), number 0 included."""
        return [(addr, encode_ping(SERVER_NUMBER, ping_id)) for addr in self.connections]

    def forget(self, address: Hashable) -> None:
        """Drop a sender's connection (it went silent); its nodes keep their numbers."""
        self.connections.pop(address, None)

    def receive(self, data: bytes, address: Hashable) -> list[StreamEvent]:
        """The events of one datagram from ``address``."""
        try:
            packet = decode_packet(data)
        except DecodeError as exc:
            known = self.connections.get(address)
            node = next(iter(known.nodes.values()), None) if known else None
            return [Rejected.of(exc, data, node)]
        payload = packet.payload
        if isinstance(payload, Handshake):
            return self._handshake(payload, address, data)
        conn = self.connections.get(address)
        if conn is None:
            return [Rejected(Reason.UNKNOWN_NODE, "no handshake from this address",
                             bytes(data[:MAX_KEPT]))]  # fmt: skip
        if packet.number != SERVER_NUMBER:  # 0 is always taken and moves nothing (see _take)
            last = conn.last_number
            if packet.number < 0 or (last is not None and packet.number <= last):
                if packet.number in conn.missing:  # overtaken: its gap is counted
                    conn.missing.discard(packet.number)
                    conn.late += 1
                    return [NodeStatus(n, "late_packets", conn.late) for n in conn.nodes.values()]
                node = next(iter(conn.nodes.values()), None)
                after = "its handshake" if last is None else last
                detail = f"packet {packet.number} after {after}"
                return [Rejected(Reason.OUT_OF_ORDER, detail, bytes(data[:MAX_KEPT]), node)]
            self._take(conn, packet.number)
        return self._payload(conn, payload)

    @staticmethod
    def _take(conn: Connection, number: int) -> None:
        """The tracker's packet ``number`` (above its last) is taken; the numbers
        skipped are packets lost.

        Number 0 never comes here: the SlimeVR server accepts it whatever came
        before (``packetId == 0L || packetId > lastPacketNumber``, UDPDevice.kt:92)
        since it is the number the server writes in everything it sends
        (UDPProtocolParser.kt:79), which comes back in the firmware's verbatim ping
        echo. The server then sets its last number to 0, which would let a stale
        packet through; here the last number stays, and no gap is counted (nor
        one just after it, where the firmware's first packet from boot is 0).

        The first packet after a handshake counts no gap either: the firmware
        numbers its packets from a counter it never resets (connection.h:221,
        connection.cpp:157-165), not from its handshake (numbered 0,
        connection.cpp:394), and the server starts over at each handshake
        (lastPacketNumber -1 for a new tracker, UDPDevice.kt:46; 0 for one back,
        TrackersUDPServer.kt:84,107), taking any number above. (The server counts
        as lost only the packets it refuses, UDPDevice.kt:97, never a gap.)"""
        last, conn.last_number = conn.last_number, number
        if last is None:
            return
        skipped = number - last - 1
        if skipped:
            conn.lost += skipped
            conn.missing = {m for m in conn.missing if m > number - REORDER_WINDOW}
            conn.missing.update(range(max(last + 1, number - REORDER_WINDOW), number))
            for node in conn.nodes.values():
                conn.pending_lost[node] = conn.pending_lost.get(node, 0) + skipped

    def _handshake(self, hs: Handshake, address: Hashable, data: bytes) -> list[StreamEvent]:
        self._replies.append((address, HANDSHAKE_REPLY))
        conn = self.connections.get(address)
        if conn is not None and conn.handshake.mac == hs.mac:
            conn.last_number = None  # a reconnect: its counter runs on, from no last number
            conn.missing.clear()
            return []
        if conn is None and len(self.connections) >= self.max_trackers:
            self._replies.pop()
            return [Rejected(Reason.OUT_OF_RANGE, f"more than {self.max_trackers} trackers",
                             bytes(data[:MAX_KEPT]))]  # fmt: skip
        # a new tracker, or another one at this address: forget whoever was there
        for other in [a for a, c in self.connections.items() if c.handshake.mac == hs.mac]:
            del self.connections[other]  # the same tracker from a new address
        conn = self.connections[address] = Connection(address, hs)
        return self._sensor(conn, 0, [])

    def _sensor(self, conn: Connection, sensor: int, out: list[StreamEvent]) -> list[StreamEvent]:
        """Make sure the tracker's ``sensor`` is a node (announcing it if new)."""
        if sensor in conn.nodes:
            return out
        ident = tracker_id(conn.handshake.mac, sensor)
        node = self.nodes.get(ident)
        if node is None:
            node = self.nodes[ident] = len(self.nodes) + 1
            self.trackers[node] = ident
        conn.nodes[sensor] = node
        self.seqs.setdefault(node, -1)
        hs = conn.handshake
        out.append(NodeStatus(node, "tracker", ident))
        out.append(NodeStatus(node, "firmware", f"{hs.firmware} (build {hs.build})"))
        out.append(NodeStatus(node, "board", hs.board))
        return out

    def _nodes_of(self, conn: Connection, sensor: int) -> list[int]:
        if sensor == DEVICE_SENSOR:
            return list(conn.nodes.values())
        return [conn.nodes[sensor]] if sensor in conn.nodes else []

    def _payload(self, conn: Connection, payload: Payload) -> list[StreamEvent]:
        out: list[StreamEvent] = []
        if isinstance(payload, Rotation):
            if payload.data_type != DATA_NORMAL:
                conn.ignored += 1
                return out
            x, y, z, w = payload.xyzw
            self._sensor(conn, payload.sensor, out)
            node = conn.nodes[payload.sensor]
            seq = self.seqs[node] + 1 + conn.pending_lost.pop(node, 0)
            self.seqs[node] = seq
            out.append(Tick(seq, node))
            out.append(Quat(node, (w, x, y, z), payload.accel))
        elif isinstance(payload, Ping):  # the echo of one of our pings (trackers start none)
            for node in conn.nodes.values():
                out.append(NodeStatus(node, PING_ECHO, payload.id))
        elif isinstance(payload, SensorInfo):
            self._sensor(conn, payload.sensor, out)
            node = conn.nodes[payload.sensor]
            out.append(NodeStatus(node, "sensor_status", payload.status))
            ack = _SENSOR_ACK.pack(SENSOR_INFO, payload.sensor, payload.status)
            self._replies.append((conn.address, ack))
        elif isinstance(payload, Battery):
            for node in self._nodes_of(conn, DEVICE_SENSOR):
                out.append(NodeStatus(node, "battery_v", round(payload.voltage, 3)))
                out.append(NodeStatus(node, "battery_level", round(payload.level, 3)))
        elif isinstance(payload, SignalStrength):
            for node in self._nodes_of(conn, payload.sensor):
                out.append(NodeStatus(node, "rssi_dbm", payload.rssi))
        elif isinstance(payload, Ignored):
            conn.ignored += 1
        # a tracker's heartbeat only says it is there: its packet number is taken above
        return out
