"""Small checks shared by the codecs."""

from __future__ import annotations

import math
from typing import Any

from ..errors import MAX_KEPT, DecodeError, Reason, Rejected
from ..messages import OleAccel

#: Quaternions whose norm falls outside this range are rejected, not repaired.
QUAT_NORM_RANGE = (0.9, 1.1)
_SQ_LO, _SQ_HI = QUAT_NORM_RANGE[0] ** 2, QUAT_NORM_RANGE[1] ** 2

INT16_MIN, INT16_MAX = -0x8000, 0x7FFF
HEX_DIGITS = frozenset(b"0123456789abcdefABCDEF")


def unit_quat(
    w: float, x: float, y: float, z: float, *, normalise: bool = True
) -> tuple[float, float, float, float]:
    """Check a quaternion is finite with a norm near 1; return it normalised.

    Raises ``DecodeError`` (``not_finite`` or ``bad_quat_norm``).
    """
    sq = w * w + x * x + y * y + z * z
    if _SQ_LO <= sq <= _SQ_HI:  # the common case first: NaN fails both comparisons
        if not normalise:
            return (w, x, y, z)
        norm = math.sqrt(sq)
        return (w / norm, x / norm, y / norm, z / norm)
    if not math.isfinite(sq):
        if all(map(math.isfinite, (w, x, y, z))):
            raise DecodeError(Reason.BAD_QUAT_NORM, "norm overflows")
        raise DecodeError(Reason.NOT_FINITE, f"quaternion ({w}, {x}, {y}, {z})")
    lo, hi = QUAT_NORM_RANGE
    raise DecodeError(Reason.BAD_QUAT_NORM, f"norm {math.sqrt(sq):.4g} outside {lo}..{hi}")


def check_int16(value: int, what: str) -> int:
    if not INT16_MIN <= value <= INT16_MAX:
        raise DecodeError(Reason.OUT_OF_RANGE, f"{what} {value} is not a 16-bit value")
    return value


def ole_values(reading: OleAccel) -> tuple[int, int, int, int]:
    """Encoder and accelerometer x, y, z of a reading, each checked to fit int16."""
    values = (reading.encoder, *reading.accel)
    for what, v in zip(("encoder", "x", "y", "z"), values, strict=True):
        check_int16(v, what)
    return values


class GarbageRun:
    """Collects consecutive bad bytes so a run is reported as one event.

    A run only ends when something decodes (or the input ends), which keeps a
    decoder's events independent of how its input was chunked.
    """

    __slots__ = ("head", "size")

    def __init__(self) -> None:
        self.head = bytearray()
        self.size = 0

    def add(self, data: bytes | bytearray) -> None:
        room = MAX_KEPT - len(self.head)
        if room > 0:
            self.head += data[:room]
        self.size += len(data)

    def flush(self, out: list[Any], reason: Reason = Reason.GARBAGE) -> None:
        """Append the run, if any, to ``out`` as one ``Rejected`` event."""
        if self.size:
            out.append(Rejected(reason, f"{self.size} bytes", bytes(self.head)))
            self.head.clear()
            self.size = 0
