"""IMU central "data matrix" lines (003 seed, ch. 7.5.3, Appendix A and B).

Every tick the central prints one line per sensor::

    printf("%02x%02x", n + 1, NewData);           // sensor 1..15, flag
    for (m = 1; m < 26; m++) printf("%02x", CursorLine[m]);   // 25 payload bytes
    printf("\\n");

so a line is 54 hex characters and LF (CRLF tolerated). Flag ``01`` is a new
sample, ``00`` nothing new since the last tick, ``ff`` a sensor never seen;
the last two are events, not errors. Payload bytes 0-15 are the quaternion
w, x, y, z as float32 little-endian (Appendix B reverses the byte pairs before
``hexsingle2num``); bytes 16-24 are kept as opaque ``extra`` bytes.

Strategy: split on LF, decode each line on its own, and resynchronise at the
next LF after anything bad. An overlong line whose last 54 characters form a
valid line is taken as garbage followed by that line, so binary noise before a
line without its own LF costs the noise only. A new tick starts whenever the
sensor number does not increase; the decoder then emits a ``Tick`` event.
"""

from __future__ import annotations

import binascii
import struct

from ..errors import MAX_KEPT, DecodeError, Reason, Rejected
from ..messages import NoNewData, Quat, SensorAbsent, StreamEvent, Tick
from ._common import unit_quat

FLAG_NEW, FLAG_NONE, FLAG_ABSENT = 0x01, 0x00, 0xFF
PAYLOAD_LEN = 25
EXTRA_LEN = PAYLOAD_LEN - 16
LINE_LEN = 2 * (2 + PAYLOAD_LEN)  # 54 hex characters before the LF
MAX_SENSORS = 15
#: The central's serial speed, and its tick: 25 Hz, about what 230400 baud carries
#: for 15 sensors' 55-byte lines (419 lines a second).
BAUD = 230400
TICK_S = 0.04
#: Bytes kept of a line that has not ended yet: enough for any valid tail and
#: for the head an error reports, so chunking never changes what is reported.
_KEEP = max(LINE_LEN + 2, MAX_KEPT)

_QUAT = struct.Struct("<4f")

ImuEvent = Quat | NoNewData | SensorAbsent


def decode_line(line: bytes | bytearray, max_sensors: int = MAX_SENSORS) -> ImuEvent:
    """Decode one line without its terminator; raise ``DecodeError`` if bad."""
    if len(line) != LINE_LEN:
        raise DecodeError(Reason.BAD_LENGTH, f"{len(line)} characters, expected {LINE_LEN}")
    try:
        raw = binascii.a2b_hex(line)
    except (binascii.Error, ValueError):
        raise DecodeError(Reason.NOT_HEX, "non-hex characters in line") from None
    sensor, flag = raw[0], raw[1]
    if not 1 <= sensor <= max_sensors:
        raise DecodeError(Reason.UNKNOWN_NODE, f"sensor {sensor}")
    if flag == FLAG_NEW:
        w, x, y, z = _QUAT.unpack_from(raw, 2)
        return Quat(sensor, unit_quat(w, x, y, z), raw[18:])
    if flag == FLAG_NONE:
        return NoNewData(sensor)
    if flag == FLAG_ABSENT:
        return SensorAbsent(sensor)
    raise DecodeError(Reason.BAD_FLAG, f"flag {flag:#04x} of sensor {sensor}")


def encode_line(event: ImuEvent) -> bytes:
    """One line, LF included. A quaternion is sent as float32; ``extra`` is
    padded with zero bytes (or cut) to its 9 bytes."""
    if isinstance(event, Quat):
        payload = _QUAT.pack(*event.wxyz) + event.extra[:EXTRA_LEN].ljust(EXTRA_LEN, b"\0")
        flag = FLAG_NEW
    else:
        payload = bytes(PAYLOAD_LEN)
        flag = FLAG_NONE if isinstance(event, NoNewData) else FLAG_ABSENT
    return b"%02x%02x%s\n" % (event.node, flag, binascii.b2a_hex(payload))


class ImuMatrixDecoder:
    """Streaming decoder of the data matrix; see the module docstring."""

    def __init__(self, max_sensors: int = MAX_SENSORS) -> None:
        self.max_sensors = max_sensors
        self._buf = bytearray()
        self._dropped = 0  # bytes cut from the front of an unfinished overlong line
        self._dropped_head = b""
        self._last_sensor = max_sensors + 1  # so the first line opens tick 0
        self._tick = -1

    def feed(self, data: bytes) -> list[StreamEvent]:
        buf = self._buf
        buf += data
        out: list[StreamEvent] = []
        pos = 0
        while (nl := buf.find(b"\n", pos)) >= 0:
            self._line(buf[pos:nl], out)
            pos = nl + 1
        del buf[:pos]
        if len(buf) > _KEEP:  # an unfinished overlong line: keep its head and tail only
            cut = len(buf) - _KEEP
            if not self._dropped:
                self._dropped_head = bytes(buf[:MAX_KEPT])
            self._dropped += cut
            del buf[:cut]
        return out

    def close(self) -> list[StreamEvent]:
        """End of input: an unterminated last line is reported as truncated."""
        out: list[StreamEvent] = []
        if self._buf or self._dropped:
            size = self._dropped + len(self._buf)
            head = self._dropped_head if self._dropped else bytes(self._buf[:MAX_KEPT])
            out.append(Rejected(Reason.TRUNCATED, f"{size} bytes without LF", head))
        self._buf.clear()
        self._dropped = 0
        return out

    def _line(self, line: bytearray, out: list[StreamEvent]) -> None:
        dropped, self._dropped = self._dropped, 0
        if line[-1:] == b"\r":
            del line[-1:]
        if not line and not dropped:
            return
        if dropped or len(line) > LINE_LEN:
            head = self._dropped_head if dropped else bytes(line[:MAX_KEPT])
            size = dropped + len(line)
            try:
                event = decode_line(line[-LINE_LEN:], self.max_sensors)
            except DecodeError:
                out.append(Rejected(Reason.BAD_LENGTH, f"{size} characters", head))
                return
            out.append(Rejected(Reason.GARBAGE, f"{size - LINE_LEN} bytes", head))
        else:
            try:
                event = decode_line(line, self.max_sensors)
            except DecodeError as exc:
                out.append(Rejected.of(exc, line))
                return
        if event.node <= self._last_sensor:
            self._tick += 1
            out.append(Tick(self._tick))
        self._last_sensor = event.node
        out.append(event)
