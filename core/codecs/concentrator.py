"""The Data Concentrator's serial exchange with the PC (000 seed, ch. 3.4.2, 4.1).

Short form: the PC sends one request character per node, ``'I'`` for node 1,
``'J'`` for node 2 and so on (``chr(ord('I') + n - 1)``, up to ``'W'`` for node
15), and the concentrator answers ``E****X****Y****Z****``: encoder count and
accelerometer x, y, z, each four hex digits of a 16-bit two's complement value
(either case), optionally followed by CR and/or LF. The reply names no node,
so a decoder pairs it with the request before it.

Extended form (ch. 3.2), decimal, space separated, one per line::

    <type> <location> <nodeID>                            request
    <type> <location> <nodeID> <encoder> <X> <Y> <Z>      reply

The seed defines no codes for ``type`` and ``location``; bodynet sends type 1
(motion data) and the 1-based bus branch as location, and reads any integers.

Strategy of the decoder: scan byte by byte for the start of a token (a request
character, ``E``, or a digit or sign that opens an extended line); check a
reply against its template as far as the bytes go, and wait for more only
while everything seen still fits. Anything else is garbage, reported as one
event per run; a reply with no request before it, and a request that got no
reply before the next one, are counted too.

A capture holds both directions, so a request character in it is a request. A
bridge that polls the device decodes only what the device sends
(``replies_only``) and says itself what it asked (:meth:`ConcentratorDecoder.poll`)
and when the answer is overdue (:meth:`ConcentratorDecoder.overdue`): a letter
from the device (a reset banner's ``RESET``) is garbage, never a request, and a
reply is the polled node's only while it is on time; after that it is a
``late_reply``, never the answer to the next request.
"""

from __future__ import annotations

import binascii
import re
import struct

from ..errors import DecodeError, Reason, Rejected
from ..messages import OleAccel, StreamEvent
from ..profile import smartsuit_branch_index
from ._common import HEX_DIGITS, GarbageRun, check_int16, ole_values

MAX_NODES = 15
#: The link's speed, and how long the concentrator takes to answer one request
#: (000 seed, ch. 3.4.2: one reply every 22 ms).
BAUD = 115200
CYCLE_S = 0.022
FIRST_REQUEST = ord("I")
REPLY_LEN = 20
EXTENDED_TYPE = 1  # the type code bodynet sends: motion data
_MAX_EXTENDED = 80  # longest plausible extended line
_TEMPLATE = {0: ord("E"), 5: ord("X"), 10: ord("Y"), 15: ord("Z")}
_REPLY = re.compile(rb"E([0-9A-Fa-f]{4})X([0-9A-Fa-f]{4})Y([0-9A-Fa-f]{4})Z([0-9A-Fa-f]{4})")
_INT16x4 = struct.Struct(">4h")
_EXT_CHARS = frozenset(b"0123456789+- \t")
_EXT_START = frozenset(b"0123456789+-")
_SPACE = frozenset(b"\r\n \t")


def request(node: int) -> bytes:
    """The request character that polls ``node``."""
    if not 1 <= node <= MAX_NODES:
        raise ValueError(f"node {node} outside 1..{MAX_NODES}")
    return bytes([FIRST_REQUEST + node - 1])


def node_of_request(char: int) -> int | None:
    """The node a request byte polls, or None if it is no request."""
    node = char - FIRST_REQUEST + 1
    return node if 1 <= node <= MAX_NODES else None


def encode_reply(reading: OleAccel, *, newline: bytes = b"\r\n", upper: bool = True) -> bytes:
    """``E****X****Y****Z****`` for one reading, then ``newline``."""
    fields = ole_values(reading)
    text = "E{:04x}X{:04x}Y{:04x}Z{:04x}".format(*(v & 0xFFFF for v in fields))
    return (text.upper() if upper else text).encode() + newline


def decode_reply(data: bytes | bytearray, node: int) -> OleAccel:
    """Decode a 20-byte short-form reply to a request for ``node``."""
    if len(data) != REPLY_LEN:
        raise DecodeError(Reason.BAD_LENGTH, f"{len(data)} bytes, expected {REPLY_LEN}")
    m = _REPLY.fullmatch(data)
    if m is None:
        raise DecodeError(Reason.NOT_HEX, "not of the form E****X****Y****Z****")
    return _reading(m, node)


def _reading(m: re.Match[bytes], node: int) -> OleAccel:
    e, x, y, z = _INT16x4.unpack(binascii.a2b_hex(b"".join(m.groups())))
    return OleAccel(node, e, (x, y, z))


def encode_extended_request(node: int, location: int | None = None) -> bytes:
    loc = smartsuit_branch_index(node) if location is None else location
    return b"%d %d %d\r\n" % (EXTENDED_TYPE, loc, node)


def encode_extended_reply(reading: OleAccel, location: int | None = None) -> bytes:
    loc = smartsuit_branch_index(reading.node) if location is None else location
    fields = (EXTENDED_TYPE, loc, reading.node, *ole_values(reading))
    return b"%d %d %d %d %d %d %d\r\n" % fields


def decode_extended(line: bytes | bytearray) -> int | OleAccel:
    """One extended line: a request gives its node number, a reply its reading."""
    fields = line.split()
    if len(fields) not in (3, 7):
        raise DecodeError(Reason.BAD_LENGTH, f"{len(fields)} fields, expected 3 or 7")
    try:
        values = [int(f) for f in fields]
    except ValueError:
        raise DecodeError(Reason.NOT_DECIMAL, "non-decimal field") from None
    node = values[2]
    if not 1 <= node <= MAX_NODES:
        raise DecodeError(Reason.UNKNOWN_NODE, f"node {node}")
    if len(values) == 3:
        return node
    e, x, y, z = (check_int16(v, w) for v, w in zip(values[3:], "EXYZ", strict=True))
    return OleAccel(node, e, (x, y, z))


def _match(data: bytes | bytearray, start: int = 0) -> int:
    """How many bytes from ``start`` fit the reply template (at most 20)."""
    end = min(len(data), start + REPLY_LEN)
    for i in range(start, end):
        k = i - start
        expected = _TEMPLATE.get(k)
        if (data[i] != expected) if expected is not None else (data[i] not in HEX_DIGITS):
            return k
    return end - start


class ConcentratorDecoder:
    """Streaming decoder of a capture of the exchange (both directions), or with
    ``replies_only`` of what the device sends to a bridge polling it (see the
    module's docstring)."""

    def __init__(self, max_nodes: int = MAX_NODES, *, replies_only: bool = False) -> None:
        self.max_nodes = max_nodes
        self.replies_only = replies_only
        self._buf = bytearray()
        self._pending: int | None = None
        self._late: int | None = None  # polled, overdue, still unanswered
        self._garbage = GarbageRun()

    @property
    def waiting(self) -> bool:
        """Whether the last request is unanswered (on time or overdue)."""
        return self._pending is not None or self._late is not None

    def poll(self, node: int) -> list[StreamEvent]:
        """The bridge asks ``node`` now: the last exchange ends (a reply cut short
        is garbage, a request never answered a ``no_reply``), and the next reply
        is ``node``'s."""
        out: list[StreamEvent] = []
        self._garbage.add(self._buf)  # a reply begun in the last exchange: stale now
        self._buf.clear()
        self._garbage.flush(out)
        unanswered = self._pending if self._pending is not None else self._late
        if unanswered is not None:
            out.append(self._no_reply(unanswered))
        self._pending, self._late = node, None
        return out

    def overdue(self) -> None:
        """The reply to the last request is past its time: if it still comes, it
        is counted as a ``late_reply`` and published for no node."""
        if self._pending is not None:
            self._pending, self._late = None, self._pending

    def feed(self, data: bytes) -> list[StreamEvent]:
        buf = self._buf
        buf += data
        out: list[StreamEvent] = []
        pos, n = 0, len(buf)
        while pos < n:
            b = buf[pos]
            if b in _SPACE:
                pos += 1
            elif not self.replies_only and FIRST_REQUEST <= b < FIRST_REQUEST + self.max_nodes:
                if self._pending is not None:
                    self._garbage.flush(out)
                    out.append(self._no_reply(self._pending))
                self._pending = b - FIRST_REQUEST + 1
                pos += 1
            elif b == _TEMPLATE[0]:
                m = _REPLY.match(buf, pos)
                if m is not None:
                    self._reply(m, out)
                    pos = m.end()
                    continue
                k = _match(buf, pos)
                if pos + k == n:
                    break  # everything so far fits a reply: wait for the rest
                else:
                    self._garbage.add(buf[pos : pos + k])
                pos += k
            elif b in _EXT_START:
                end = pos
                while end < n and buf[end] in _EXT_CHARS and end - pos < _MAX_EXTENDED:
                    end += 1
                if end == n and end - pos < _MAX_EXTENDED:
                    break  # the line may go on in the next chunk
                if end - pos < _MAX_EXTENDED and buf[end] in b"\r\n":
                    self._extended(buf[pos:end], out)
                else:
                    self._garbage.add(buf[pos:end])
                pos = end
            else:
                self._garbage.add(buf[pos : pos + 1])
                pos += 1
        del buf[:pos]
        return out

    def close(self) -> list[StreamEvent]:
        """End of input: a reply or line cut short is reported as truncated."""
        out: list[StreamEvent] = []
        self._garbage.flush(out)
        if self._buf.strip():
            out.append(Rejected(Reason.TRUNCATED, f"{len(self._buf)} bytes", bytes(self._buf)))
        self._buf.clear()
        return out

    @staticmethod
    def _no_reply(node: int) -> Rejected:
        return Rejected(Reason.NO_REPLY, f"node {node}", node=node)

    def _reply(self, m: re.Match[bytes], out: list[StreamEvent]) -> None:
        self._garbage.flush(out)
        node, self._pending = self._pending, None
        if node is not None:
            out.append(_reading(m, node))
        else:
            out.append(self._unpaired(m[0]))

    def _unpaired(self, data: bytes | bytearray) -> Rejected:
        """A reply to no request on time: late if one is overdue, else unpaired."""
        late, self._late = self._late, None
        if late is not None:
            return Rejected(Reason.LATE_REPLY, f"node {late}", bytes(data), node=late)
        return Rejected(Reason.UNPAIRED_REPLY, "reply with no request", bytes(data))

    def _extended(self, line: bytearray, out: list[StreamEvent]) -> None:
        self._garbage.flush(out)
        try:
            result = decode_extended(line)
        except DecodeError as exc:
            out.append(Rejected.of(exc, line))
            return
        if self.replies_only:
            self._extended_reply(result, line, out)
        elif isinstance(result, int):
            if self._pending is not None:
                out.append(self._no_reply(self._pending))
            self._pending = result
        else:
            self._pending = None
            if result.node > self.max_nodes:
                out.append(Rejected(Reason.UNKNOWN_NODE, f"node {result.node}", bytes(line)))
            else:
                out.append(result)

    def _extended_reply(self, result: int | OleAccel, line: bytearray,
                        out: list[StreamEvent]) -> None:  # fmt: skip
        """An extended line from the device: a reply is taken only for the node
        polled; a request line is no request from the device, but garbage."""
        if isinstance(result, int):
            out.append(Rejected(Reason.GARBAGE, "a request line from the device", bytes(line)))
        elif result.node == self._pending:
            self._pending = None
            out.append(result)
        elif result.node == self._late:
            out.append(self._unpaired(line))
        else:
            out.append(Rejected(Reason.UNPAIRED_REPLY, f"reply of node {result.node}", bytes(line)))
