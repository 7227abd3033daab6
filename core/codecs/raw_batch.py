"""Several sites' raw samples in one Zenoh message (version 1).

A bridge run with ``--batch-ms`` puts what its nodes sent within a few
milliseconds on one key, ``body/@batch/<bridge>`` (see ``keys.batch_key``),
instead of one message per sample on each site's key: Zenoh's receiving costs
per message, and one body's 1,500 lone samples a second cost a subscriber
more CPU than everything else the gateway does (docs/benchmarks.md). Layout,
little-endian::

    offset size  field
    0      2     magic  b"BB"
    2      1     version = 1
    3      2     count n (uint16), then n entries of:
           1       key length k (1..255)
           k       the sample's raw key, without a subject: body/arm/left/elbow/raw
           2       message length m (uint16)
           m       one raw-sample message (``raw_sample``), undecoded here

:func:`split` turns a message on any raw key, batch or not, into the (key,
message) pairs it carries, with the batch's subject put before each key: every
subscriber of raw samples reads a batch through it and then goes on as for
samples on their own keys. An entry whose key is not a site's raw key is
rejected (a batch cannot put a sample on a topology or on another subject's
key); a bad header or a short batch rejects what cannot be read.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from functools import lru_cache

from .. import keys
from ..errors import DecodeError, Reason, Rejected

MAGIC = b"BB"
VERSION = 1
_HEADER = struct.Struct("<2sBH")
HEADER_LEN = _HEADER.size
_LEN = struct.Struct("<H")
MAX_ENTRIES = 0xFFFF

#: What a batch carries: a raw key and one raw-sample message, or a rejection.
Entry = tuple[str, bytes]


def encode(entries: Sequence[Entry]) -> bytes:
    """One batch of ``(raw key, raw-sample message)`` pairs; ``ValueError`` for more
    than :data:`MAX_ENTRIES`, a key longer than 255 bytes or a message longer
    than 65,535."""
    if len(entries) > MAX_ENTRIES:
        raise ValueError(f"{len(entries)} entries in one batch (at most {MAX_ENTRIES})")
    out = [_HEADER.pack(MAGIC, VERSION, len(entries))]
    for key, message in entries:
        k = key.encode("ascii")
        if not 0 < len(k) <= 255:
            raise ValueError(f"key {key!r}: {len(k)} bytes (1..255)")
        out += (bytes((len(k),)), k, _LEN.pack(len(message)), message)
    return b"".join(out)


@lru_cache(maxsize=4096)  # on every batched sample's path; the key space is small
def _raw_key(key: bytes, prefix: str = "") -> str | None:
    """``key`` as text, after ``prefix``, if it is a site's raw key, else None."""
    try:
        text = key.decode("ascii")
        site, stream = keys.parse(text)
    except (UnicodeDecodeError, keys.KeySpaceError):
        return None
    if stream is not keys.Stream.RAW or keys.chunk(site.name) != site.name:
        return None
    return prefix + text


def decode(payload: bytes | bytearray, prefix: str = "") -> list[Entry | Rejected]:
    """The entries of one batch, each a ``(raw key, message)`` pair (the key after
    ``prefix``, a subject's) or, where it cannot be read, a rejection;
    ``DecodeError`` if the header is not a batch's."""
    payload = bytes(payload)  # slices of it are then the entries' bytes
    if len(payload) < _HEADER.size:
        raise DecodeError(Reason.TRUNCATED, f"{len(payload)} bytes, a batch's header is 5")
    magic, version, count = _HEADER.unpack_from(payload)
    if magic != MAGIC:
        raise DecodeError(Reason.BAD_MAGIC, f"magic {bytes(magic)!r}")
    if version != VERSION:
        raise DecodeError(Reason.BAD_VERSION, f"version {version}")
    out: list[Entry | Rejected] = []
    pos, end = _HEADER.size, len(payload)
    for index in range(count):
        if pos >= end:
            out.append(Rejected(Reason.TRUNCATED, f"entry {index} of {count}: none left"))
            return out
        k = payload[pos]
        key_end = pos + 1 + k
        if k == 0 or key_end + _LEN.size > end:
            out.append(Rejected(Reason.TRUNCATED if k else Reason.BAD_LENGTH,
                                f"entry {index} of {count}: key of {k} bytes",
                                payload[pos : pos + 64]))  # fmt: skip
            return out
        m = payload[key_end] | payload[key_end + 1] << 8  # _LEN, written out: every entry
        start = key_end + _LEN.size
        if start + m > end:
            why = f"entry {index} of {count}: message of {m} bytes, {end - start} left"
            out.append(Rejected(Reason.TRUNCATED, why, payload[pos : pos + 64]))
            return out
        entry, pos = entry_at(payload, pos, prefix, f"entry {index} of {count}")
        out.append(entry)
    if pos != end:
        out.append(Rejected(Reason.BAD_LENGTH, f"{end - pos} bytes after the {count} entries",
                            payload[pos : pos + 64]))  # fmt: skip
    return out


def entry_at(payload: bytes, pos: int, prefix: str = "",
             which: str = "entry") -> tuple[Entry | Rejected, int]:  # fmt: skip
    """The entry at byte ``pos`` of a batch, whose key and message lie whole
    within it (:func:`decode` checks that first), and where the next entry
    starts: the ``(raw key, message)`` pair, or its rejection (``which``
    names the entry in it)."""
    k = payload[pos]
    start = pos + 1 + k + _LEN.size
    m = payload[start - 2] | payload[start - 1] << 8  # _LEN, written out: every entry
    key = _raw_key(payload[pos + 1 : pos + 1 + k], prefix)
    if key is None:
        return Rejected(Reason.UNKNOWN_NODE, f"{which}: not a raw key",
                        payload[pos + 1 : pos + 1 + k][:64]), start + m  # fmt: skip
    return (key, payload[start : start + m]), start + m


@lru_cache(maxsize=4096)
def subject_of_batch(key: str) -> str | None:
    """What comes before ``body/`` in ``key`` (``"alice/"``, or ``""``) if it is a
    batch's key, else None."""
    prefix, sep, source = key.partition(f"{keys.BATCH}/")
    if not sep or "/" in source or not source:
        return None
    if prefix:
        try:
            keys.split_subject(key)  # one chunk, the subject's, before body/
        except keys.KeySpaceError:
            return None
    return prefix


def split(key: str, payload: bytes) -> list[Entry | Rejected]:
    """The ``(raw key, message)`` pairs of a message that came on ``key``: itself
    on a site's key, its entries (their keys after the batch's subject) on a
    batch's; a batch that cannot be read, rejected whole."""
    prefix = subject_of_batch(key)
    if prefix is None:
        return [(key, payload)]
    try:
        return decode(payload, prefix)
    except DecodeError as exc:
        return [Rejected.of(exc, payload[:64])]
