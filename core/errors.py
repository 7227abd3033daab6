"""The declared decode errors: the only failures a codec may report.

Single-message decoders raise :class:`DecodeError`. Streaming decoders never
raise on bad input: they turn each bad stretch of bytes into a
:class:`Rejected` event, in stream order between the good samples, so a
consumer counts it (:class:`RejectCounts`) and carries on.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from enum import StrEnum


class Reason(StrEnum):
    """Why input was rejected; the value is the stable name used in counts."""

    BAD_LENGTH = "bad_length"
    NOT_HEX = "not_hex"
    NOT_DECIMAL = "not_decimal"
    UNKNOWN_NODE = "unknown_node"
    OUT_OF_RANGE = "out_of_range"
    STANDARD_ID = "standard_id"
    REMOTE_FRAME = "remote_frame"
    ERROR_FRAME = "error_frame"
    BAD_DLC = "bad_dlc"
    NOT_FINITE = "not_finite"
    BAD_QUAT_NORM = "bad_quat_norm"
    BAD_FLAG = "bad_flag"
    GARBAGE = "garbage"
    UNPAIRED_REPLY = "unpaired_reply"
    LATE_REPLY = "late_reply"
    NO_REPLY = "no_reply"
    BAD_MAGIC = "bad_magic"
    BAD_VERSION = "bad_version"
    BAD_KIND = "bad_kind"
    TRUNCATED = "truncated"
    OUT_OF_ORDER = "out_of_order"


class DecodeError(ValueError):
    """Input that does not decode; ``reason`` says why in a countable way."""

    def __init__(self, reason: Reason, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else str(reason))
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, slots=True)
class Rejected:
    """A stream event: ``data`` could not be decoded, for ``reason``.

    ``data`` holds at most :data:`MAX_KEPT` bytes of the offending input, to
    show in a log without letting a garbage flood grow memory.
    """

    reason: Reason
    detail: str
    data: bytes = b""
    #: the node the rejected input was for, where the format says (else None); an
    #: attribution for counting, not part of what was rejected (not compared)
    node: int | None = field(default=None, compare=False)

    @classmethod
    def of(
        cls, error: DecodeError, data: bytes | bytearray = b"", node: int | None = None
    ) -> Rejected:
        return cls(error.reason, error.detail, bytes(data[:MAX_KEPT]), node)


MAX_KEPT = 64


class RejectCounts(Counter[Reason]):
    """Rejections counted per reason."""

    def summary(self) -> str:
        """``"bad_length: 1, not_hex: 2"``, most frequent first."""
        return ", ".join(f"{reason}: {n}" for reason, n in self.most_common())
