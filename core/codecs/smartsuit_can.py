"""SmartSuit CAN frames (000 seed, ch. 3.4), and the slcan text form of CAN.

Sensing node n (1..15) sends on extended identifier ``((4n + 2) << 16) | 0xFFFF``
(0x0006FFFF, 0x000AFFFF, 0x000EFFFF for nodes 1-3, the seed's CAN buffers),
every 10 ms, eight data bytes: four int16 little-endian, the encoder count
(0.1 mm per count, signed) and the accelerometer x, y, z in counts. Nodes
13-15, the trunk-head IMUs, carry a quaternion w, x, y, z in Q14 (16384 = 1.0)
instead.

:class:`CanFrame` is a plain frame (what python-can's ``Message`` holds), so
the frame codec is independent of the adapter. For adapters that speak over a
serial line, :class:`SlcanDecoder` parses the Lawicel slcan text protocol
(``T0006FFFF8<16 hex>\\r`` and friends) from bytes in any chunking, and
:class:`SmartSuitSlcanDecoder` chains it with the frame codec.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import StrEnum

from ..errors import DecodeError, Reason, Rejected
from ..messages import OleAccel, Quat, Reading, StreamEvent
from ..profile import SMARTSUIT_QUAT_NODES
from ._common import HEX_DIGITS, INT16_MAX, INT16_MIN, GarbageRun, ole_values, unit_quat

MAX_NODES = 15
#: Every node sends one frame each 10 ms (000 seed, ch. 3.4).
PERIOD_S = 0.01
Q14 = 1 << 14
DLC = 8
_ID_LOW = 0xFFFF
_PAYLOAD = struct.Struct("<4h")


@dataclass(frozen=True, slots=True)
class CanFrame:
    """One classic CAN frame as seen on the bus."""

    arbitration_id: int
    data: bytes = b""
    is_extended_id: bool = True
    is_remote_frame: bool = False
    is_error_frame: bool = False
    dlc: int = DLC


def can_id(node: int) -> int:
    """Extended CAN identifier of SmartSuit node ``node``."""
    if not 1 <= node <= MAX_NODES:
        raise ValueError(f"node {node} outside 1..{MAX_NODES}")
    return ((4 * node + 2) << 16) | _ID_LOW


def node_of(arbitration_id: int) -> int:
    """Node number of a SmartSuit identifier; ``DecodeError`` if none."""
    high = arbitration_id >> 16
    if arbitration_id & _ID_LOW != _ID_LOW or high % 4 != 2 or not 1 <= high // 4 <= MAX_NODES:
        raise DecodeError(Reason.UNKNOWN_NODE, f"identifier {arbitration_id:#010x}")
    return high // 4


class Foreign(StrEnum):
    """What makes a well-formed frame on the bus another device's (a bus shared
    with other devices, or the Data Concentrator's polls): not bad input, counted
    apart from rejections."""

    STANDARD_ID = "standard_id"  # an 11-bit identifier: the nodes send 29-bit ones
    EXTENDED_ID = "extended_id"  # a 29-bit identifier none of nodes 1-15 sends on
    REMOTE_FRAME = "remote_frame"  # a request for data: the nodes send data frames


def foreign(frame: CanFrame) -> Foreign | None:
    """Why ``frame`` is another device's, or None: a SmartSuit node's frame (a
    reading, or rejected when malformed: a wrong length, a quaternion that is not
    one) or an error frame (the bus's own trouble, rejected). A frame on a CAN bus
    has passed its CRC: one that no node sends is some other device's."""
    if frame.is_error_frame:
        return None
    if frame.is_remote_frame:
        return Foreign.REMOTE_FRAME
    if not frame.is_extended_id:
        return Foreign.STANDARD_ID
    try:
        node_of(frame.arbitration_id)
    except DecodeError:
        return Foreign.EXTENDED_ID
    return None


def frame_events(frame: CanFrame) -> list[StreamEvent]:
    """A frame as decoder events: its reading, or its rejection (with the node
    where the identifier names one)."""
    try:
        return [decode_frame(frame)]
    except DecodeError as exc:
        node = frame.arbitration_id >> 18 if frame.is_extended_id else None
        return [Rejected.of(exc, frame.data, node)]


def decode_frame(frame: CanFrame) -> Reading:
    """The reading a SmartSuit frame carries; ``DecodeError`` if it carries none."""
    if frame.is_error_frame:
        raise DecodeError(Reason.ERROR_FRAME, f"error frame {frame.arbitration_id:#x}")
    if frame.is_remote_frame:
        raise DecodeError(Reason.REMOTE_FRAME, f"remote frame {frame.arbitration_id:#x}")
    if not frame.is_extended_id:
        raise DecodeError(Reason.STANDARD_ID, f"standard identifier {frame.arbitration_id:#05x}")
    node = node_of(frame.arbitration_id)
    if frame.dlc != DLC or len(frame.data) != DLC:
        raise DecodeError(Reason.BAD_DLC, f"node {node}: {len(frame.data)} data bytes")
    a, b, c, d = _PAYLOAD.unpack(frame.data)
    if node in SMARTSUIT_QUAT_NODES:
        return Quat(node, unit_quat(a / Q14, b / Q14, c / Q14, d / Q14))
    return OleAccel(node, a, (b, c, d))


def _q14(value: float) -> int:
    return max(INT16_MIN, min(INT16_MAX, round(value * Q14)))


def encode_reading(reading: Reading) -> CanFrame:
    """The frame a node sends for ``reading`` (quaternions quantised to Q14)."""
    if isinstance(reading, Quat):
        if reading.node not in SMARTSUIT_QUAT_NODES:
            raise ValueError(f"node {reading.node} carries no quaternion")
        data = _PAYLOAD.pack(*map(_q14, reading.wxyz))
    else:
        if reading.node in SMARTSUIT_QUAT_NODES:
            raise ValueError(f"node {reading.node} carries a quaternion")
        data = _PAYLOAD.pack(*ole_values(reading))
    return CanFrame(can_id(reading.node), data)


# --- slcan (Lawicel) text protocol -------------------------------------------------


@dataclass(frozen=True, slots=True)
class SlcanReply:
    """A non-frame slcan line: a command or its answer. ``ok`` is False for BEL."""

    text: str
    ok: bool = True


_MAX_SLCAN = 64
_SLCAN_END = b"\r\a"
_ID_DIGITS = {ord("T"): 8, ord("R"): 8, ord("t"): 3, ord("r"): 3}
_DLC_DIGITS = {b"%d" % n for n in range(DLC + 1)}


def encode_slcan(frame: CanFrame) -> bytes:
    """A frame as one slcan line (``\\r`` terminated), as adapters send it."""
    if frame.is_error_frame:
        raise ValueError("slcan has no error frames")
    kind = "R" if frame.is_remote_frame else "T"
    if not frame.is_extended_id:
        kind = kind.lower()
    width = 8 if frame.is_extended_id else 3
    data = "" if frame.is_remote_frame else frame.data.hex().upper()
    return f"{kind}{frame.arbitration_id:0{width}X}{frame.dlc:d}{data}\r".encode()


def decode_slcan(line: bytes | bytearray) -> CanFrame | SlcanReply:
    """One slcan line without its terminator."""
    digits = _ID_DIGITS.get(line[0]) if line else None
    if digits is None:
        try:
            return SlcanReply(line.decode("ascii"))
        except UnicodeDecodeError:
            raise DecodeError(Reason.GARBAGE, "non-ASCII slcan line") from None
    remote, extended = line[0] in b"Rr", line[0] in b"TR"
    ident_text, dlc_text = line[1 : 1 + digits], line[1 + digits : 2 + digits]
    if len(ident_text) != digits or len(dlc_text) != 1:
        raise DecodeError(Reason.BAD_LENGTH, "line too short for identifier and DLC")
    if not HEX_DIGITS.issuperset(ident_text) or bytes(dlc_text) not in _DLC_DIGITS:
        raise DecodeError(Reason.NOT_HEX, "bad identifier or DLC digit")
    ident, dlc = int(ident_text, 16), int(dlc_text)
    if ident > (0x1FFFFFFF if extended else 0x7FF):
        raise DecodeError(Reason.OUT_OF_RANGE, f"identifier {ident:#x}")
    payload = line[2 + digits :]
    if len(payload) != (0 if remote else 2 * dlc):
        raise DecodeError(Reason.BAD_LENGTH, f"{len(payload)} data characters for DLC {dlc}")
    if not HEX_DIGITS.issuperset(payload):
        raise DecodeError(Reason.NOT_HEX, "non-hex data")
    return CanFrame(ident, bytes.fromhex(payload.decode()), extended, remote, False, dlc)


class SlcanDecoder:
    """Streaming slcan parser: frames and replies, split on CR (OK) or BEL (error)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._garbage = GarbageRun()

    def feed(self, data: bytes) -> list[CanFrame | SlcanReply | Rejected]:
        buf = self._buf
        buf += data
        out: list[CanFrame | SlcanReply | Rejected] = []
        pos, n = 0, len(buf)
        while pos < n:
            window = pos + _MAX_SLCAN
            ends = [
                i for i in (buf.find(b"\r", pos, window), buf.find(b"\a", pos, window)) if i >= 0
            ]
            if not ends:
                if n < window:
                    break  # the line may end in the next chunk
                self._garbage.add(buf[pos:window])  # no terminator in sight: skip ahead
                pos = window
                continue
            end = min(ends)
            line = buf[pos:end]
            if buf[end] == 7:  # BEL: the adapter refused a command
                self._garbage.flush(out)
                out.append(SlcanReply(line.decode("ascii", "replace"), ok=False))
            elif line:
                try:
                    event = decode_slcan(line)
                except DecodeError as exc:
                    self._garbage.flush(out)
                    out.append(Rejected.of(exc, line))
                else:
                    self._garbage.flush(out)
                    out.append(event)
            else:  # a bare CR acknowledges a command
                self._garbage.flush(out)
                out.append(SlcanReply(""))
            pos = end + 1
        del buf[:pos]
        return out

    def close(self) -> list[CanFrame | SlcanReply | Rejected]:
        out: list[CanFrame | SlcanReply | Rejected] = []
        self._garbage.add(self._buf)
        self._garbage.flush(out, Reason.TRUNCATED)
        self._buf.clear()
        return out


class SmartSuitSlcanDecoder:
    """slcan bytes in, SmartSuit readings (and rejections) out; replies dropped."""

    def __init__(self) -> None:
        self._slcan = SlcanDecoder()

    def _readings(self, events: list[CanFrame | SlcanReply | Rejected]) -> list[StreamEvent]:
        out: list[StreamEvent] = []
        for event in events:
            if isinstance(event, CanFrame):
                out += frame_events(event)
            elif isinstance(event, Rejected):
                out.append(event)
        return out

    def feed(self, data: bytes) -> list[StreamEvent]:
        return self._readings(self._slcan.feed(data))

    def close(self) -> list[StreamEvent]:
        return self._readings(self._slcan.close())
