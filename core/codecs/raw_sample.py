"""The raw-sample message bodynet carries on Zenoh (version 1).

Compact binary, little-endian, one message per sample; a Zenoh payload may
hold several messages back to back (a batch), which :class:`RawSampleDecoder`
splits. Layout::

    offset size  field
    0      2     magic  b"BN"
    2      1     version = 1
    3      1     kind: 1 = OLE + accelerometer, 2 = quaternion
    4      1     source id: 0 unknown, 1 CAN, 2 concentrator, 3 IMU central,
                 4 SlimeVR, 5 orientation file; any other id is accepted too
                 (a source this version has not heard of), see ``Source``
    5      1     flags: kind 1, bit 0 ``messages.RESUMED`` (the node's first sample after
                 it was silent, on a link its bridge saw alive, long enough
                 to have rebooted: its encoder's zero is lost); the other
                 bits, and a kind 2's byte, reserved: sent as 0, ignored on
                 receipt (a kind 2 decodes with flags 0)
    6      2     node number (uint16, >= 1)
    8      4     sequence number (uint32, per node, wraps)
    12     8     source timestamp t_ns (int64, ns since the Unix epoch)
    20     ...   body
    kind 1: encoder, accel x, y, z     4 x int16              ->  28 bytes in all
    kind 2: w, x, y, z                 4 x float64, then
            extra length n, extra      uint8, n bytes        ->  53 + n bytes

Quaternions travel as float64 so a sample decodes to exactly what was sent;
they must be finite with a norm in 0.9..1.1, as every decoder checks.
"""

from __future__ import annotations

import struct

from ..errors import DecodeError, Reason, Rejected
from ..messages import OleAccel, Quat, RawSample, Source
from ._common import _SQ_HI, _SQ_LO, GarbageRun, ole_values, unit_quat

MAGIC = b"BN"
VERSION = 1
KIND_OLE_ACCEL = 1
KIND_QUAT = 2

_HEADER = struct.Struct("<2sBBBBHIq")
_OLE = struct.Struct("<4h")
_QUAT = struct.Struct("<4dB")
HEADER_LEN = _HEADER.size
#: every byte's source: the named one where this version knows it, else the id itself
_SOURCES: tuple[int, ...] = tuple(
    Source(v) if v in Source._value2member_map_ else v for v in range(256)
)

RawEvent = RawSample | Rejected


def encode(sample: RawSample) -> bytes:
    """One message for ``sample``; ``ValueError`` for flags on a quaternion (its
    byte is reserved) or beyond a byte."""
    r = sample.reading
    flags = sample.flags
    if isinstance(r, Quat):
        if len(r.extra) > 255:
            raise ValueError("extra bytes longer than 255")
        if flags:
            raise ValueError(f"flags {flags:#x} on a quaternion sample (reserved there)")
        kind, body = KIND_QUAT, _QUAT.pack(*r.wxyz, len(r.extra)) + r.extra
    else:
        if not 0 <= flags <= 0xFF:
            raise ValueError(f"flags {flags:#x} beyond a byte")
        kind, body = KIND_OLE_ACCEL, _OLE.pack(*ole_values(r))
    header = _HEADER.pack(
        MAGIC, VERSION, kind, sample.source, flags, r.node, sample.seq & 0xFFFFFFFF, sample.t_ns
    )
    return header + body


def encode_batch(samples: list[RawSample]) -> bytes:
    return b"".join(map(encode, samples))


def _length(buf: bytes | bytearray, pos: int) -> int | None:
    """Total length of the message at ``pos``, or None if more bytes are needed.

    Each header field is checked as soon as its bytes are there, so a bad
    stretch is judged the same way however the input is chunked; raises
    ``DecodeError`` on a bad field.
    """
    avail = len(buf) - pos
    if avail <= 0:
        return None
    if buf[pos] != MAGIC[0] or (avail > 1 and buf[pos + 1] != MAGIC[1]):
        raise DecodeError(Reason.BAD_MAGIC, f"magic {bytes(buf[pos : pos + 2])!r}")
    if avail > 2 and buf[pos + 2] != VERSION:
        raise DecodeError(Reason.BAD_VERSION, f"version {buf[pos + 2]}")
    kind = buf[pos + 3] if avail > 3 else None
    if kind is not None and kind not in (KIND_OLE_ACCEL, KIND_QUAT):
        raise DecodeError(Reason.BAD_KIND, f"kind {kind}")
    if avail < HEADER_LEN:
        return None
    if kind == KIND_OLE_ACCEL:
        return HEADER_LEN + _OLE.size
    if avail < HEADER_LEN + _QUAT.size:
        return None
    return HEADER_LEN + _QUAT.size + buf[pos + HEADER_LEN + _QUAT.size - 1]


def _decode_at(buf: bytes | bytearray, pos: int, length: int) -> RawSample:
    _, _, kind, source, flags, node, seq, t_ns = _HEADER.unpack_from(buf, pos)
    if node == 0:
        raise DecodeError(Reason.UNKNOWN_NODE, "node 0")
    body = pos + HEADER_LEN
    if kind == KIND_OLE_ACCEL:
        e, x, y, z = _OLE.unpack_from(buf, body)
        return RawSample(OleAccel(node, e, (x, y, z)), seq, t_ns, _SOURCES[source], flags)
    w, qx, qy, qz, _ = _QUAT.unpack_from(buf, body)
    extra = bytes(buf[body + _QUAT.size : pos + length])
    reading = Quat(node, unit_quat(w, qx, qy, qz, normalise=False), extra)
    return RawSample(reading, seq, t_ns, _SOURCES[source])


#: A whole quaternion message with no extra bytes: what IMU nodes send, decoded in
#: one unpack on the gateway's path for every sample (magic, version and kind as one
#: field of four bytes).
_QUAT_MESSAGE = struct.Struct("<4sBBHIq4dB")
_QUAT_HEAD = MAGIC + bytes((VERSION, KIND_QUAT))
QUAT_MESSAGE_LEN = _QUAT_MESSAGE.size

#: node, seq, t_ns, source id, w, x, y, z: a quaternion message's fields
QuatFields = tuple[int, int, int, int, float, float, float, float]


def quat_fields(payload: bytes | bytearray) -> QuatFields | None:
    """The fields of a good quaternion message with no extra bytes (the common
    case, on the gateway's path for every sample), as plain numbers; None for
    anything else, good or bad, which :func:`decode` then reads or judges."""
    if len(payload) != QUAT_MESSAGE_LEN:
        return None
    head, source, _, node, seq, t_ns, w, x, y, z, n = _QUAT_MESSAGE.unpack(payload)
    if head != _QUAT_HEAD or n or not node:
        return None
    if not _SQ_LO <= w * w + x * x + y * y + z * z <= _SQ_HI:  # unit_quat's test; NaN fails it
        return None
    return node, seq, t_ns, source, w, x, y, z


def of_fields(fields: QuatFields) -> RawSample:
    """The sample of :func:`quat_fields`' numbers: what :func:`decode` gives."""
    node, seq, t_ns, source, w, x, y, z = fields
    return RawSample(Quat(node, (w, x, y, z)), seq, t_ns, _SOURCES[source])


def decode(payload: bytes | bytearray) -> RawSample:
    """Exactly one message; ``DecodeError`` if ``payload`` is anything else."""
    fields = quat_fields(payload)
    if fields is not None:
        return of_fields(fields)
    # anything else takes the checks below, which say what is wrong
    length = _length(payload, 0)
    if length is None or length > len(payload):
        raise DecodeError(Reason.TRUNCATED, f"{len(payload)} bytes")
    if length != len(payload):
        raise DecodeError(Reason.BAD_LENGTH, f"{len(payload)} bytes, message is {length}")
    return _decode_at(payload, 0, length)


_T_NS = struct.Struct("<q")


def source_time(payload: bytes | bytearray) -> int:
    """The source timestamp ``t_ns`` of one message, nothing else checked: for a
    latency probe that must cost less than what it measures."""
    return int(_T_NS.unpack_from(payload, 12)[0])


def decode_batch(payload: bytes | bytearray) -> list[RawEvent]:
    """Every message of one payload, with rejections in place of bad ones."""
    decoder = RawSampleDecoder()
    return decoder.feed(payload) + decoder.close()


class RawSampleDecoder:
    """Streaming decoder of concatenated messages; resynchronises on the magic."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._garbage = GarbageRun()

    def feed(self, data: bytes | bytearray) -> list[RawEvent]:
        buf = self._buf
        buf += data
        out: list[RawEvent] = []
        pos = 0
        while pos < len(buf):
            try:
                length = _length(buf, pos)
            except DecodeError as exc:
                if exc.reason is Reason.BAD_MAGIC:
                    nxt = buf.find(MAGIC, pos + 1)
                    if nxt < 0:  # keep a last b"B" that may start the next magic
                        nxt = len(buf) - 1 if buf.endswith(MAGIC[:1]) else len(buf)
                    self._garbage.add(buf[pos:nxt])
                    pos = nxt
                else:
                    self._garbage.flush(out)
                    checked = 3 if exc.reason is Reason.BAD_VERSION else 4  # bytes judged
                    out.append(Rejected.of(exc, buf[pos : pos + checked]))
                    pos += len(MAGIC)
                continue
            if length is None or pos + length > len(buf):
                break
            self._garbage.flush(out)
            try:
                out.append(_decode_at(buf, pos, length))
            except DecodeError as exc:
                out.append(Rejected.of(exc, buf[pos : pos + length]))
            pos += length
        del buf[:pos]
        return out

    def close(self) -> list[RawEvent]:
        out: list[RawEvent] = []
        self._garbage.flush(out)
        if self._buf:
            out.append(Rejected(Reason.TRUNCATED, f"{len(self._buf)} bytes", bytes(self._buf[:64])))
        self._buf.clear()
        return out
