"""MCAP files of the body network: poses, raw samples, topology and health,
readable by any tool.

Topics are the Zenoh keys. Messages are JSON with a JSON Schema, so generic
MCAP tools (Foxglove, the ``mcap`` CLI) can open and plot them:

- ``body/pose`` and ``body/<limb>/<side>/pose``: schema ``bodynet.PoseFrame``,
  the gateway's pose message as it is;
- ``body/<limb>/<side>/<site>/raw``: schema ``bodynet.RawSample``,
  ``{node, seq, t_ns, source, encoder, accel}`` or ``{..., quat_wxyz}``;
- ``body/<limb>/<side>/<site>/truth``: schema ``bodynet.Truth``, an emulator's
  ground truth as it publishes it (``t_ns``, ``angles_deg``, ``segment``,
  ``segment_quat_wxyz``), when the recording asked for it.
- ``body/tf``: schema ``foxglove.FrameTransforms`` (Foxglove's well-known
  schema, protobuf: see ``foxglove_pb``), the pelvis in frame ``world``, every
  other segment in its parent segment (``body_tree``), so Foxglove's 3D panel
  shows the skeleton's frames without any setup: one message per ``body/pose``
  at most every :data:`TF_MIN_GAP_NS` of source time (a display's rate; the
  poses themselves are all there).
- ``body/@topology``: schema ``bodynet.Topology``, the gateway's topology as it
  publishes it or answers it (``t_ns``, ``branches`` -> ``nodes`` ->
  ``state``, ``node``, ``last_t_ns``, ``clock_offset_ms``);
- ``body/@health/<source>``: schema ``bodynet.Health``, a bridge's or the
  gateway's health as published (``source``, ``t_ns``, then ``device``,
  ``rejected``, ``nodes``... or ``samples``, ``ticks``...). Log time: the
  message's ``t_ns`` (when it has none, when it was received). Another
  subject's (``alice/body/@topology``, ``alice/body/@health/...``) alike,
  when the recording asked for it.

- ``@gaps``: schema ``bodynet.Gap``, one record per jump in a topic's
  sequence numbers the recorder saw (``topic``, ``after_seq``, ``missing``,
  ``from_t_ns``, ``to_t_ns``): where the recording is incomplete.

Chunks are zstd at level 1 (:data:`ZSTD_LEVEL`): on these messages about half
the time of the library's level 3, and about as small.

Log time is the sample's source time in ns (for a processed capture, the
capture's own time base); MCAP stores it as an unsigned 64-bit number, so a
message whose time is negative or past ``2**64 - 1`` is refused
(``DecodeError``, ``out_of_range``) before it reaches the writer. Files are
created readable by the owner only: this is health data.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import io
import json
import operator
import os
import platform
import struct
import tempfile
import time
from array import array
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import IO, Any

import numpy as np
import orjson
import zstandard
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Header,
    Message,
    MessageIndex,
    Metadata,
    Schema,
)
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from bodynet.clients import foxglove_pb
from bodynet.clients.body_tree import Transforms, segment_parents, unmeasured_segments
from bodynet.clients.mcap_writer import LeanWriter
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError, Reason
from bodynet.core.messages import OleAccel, RawSample, source_name
from bodynet.core.skeleton import build_skeleton

POSE_SCHEMA = {
    "title": "bodynet.PoseFrame",
    "type": "object",
    "properties": {
        "v": {"type": "integer"},
        "seq": {"type": "integer"},
        "t_ns": {"type": "integer"},
        "angles_deg": {"type": "object", "additionalProperties": {"type": "number"}},
        "rel_deg": {"type": "object", "additionalProperties": {"type": "number"}},
        "flags": {"type": "object", "additionalProperties": {"type": "string"}},
        "segments": {"type": "object"},
        "joints_m": {"type": "object"},
        "sources": {"type": "object"},
        "stale": {"type": "array", "items": {"type": "string"}},
        "reasons": {
            "type": "object",
            "additionalProperties": {"type": "array", "items": {"type": "string"}},
        },
        "unc_deg": {"type": "object", "additionalProperties": {"type": ["number", "null"]}},
    },
}
RAW_SCHEMA = {
    "title": "bodynet.RawSample",
    "type": "object",
    "properties": {
        "node": {"type": "integer"},
        "seq": {"type": "integer"},
        "t_ns": {"type": "integer"},
        "source": {"type": "string"},
        "flags": {"type": "integer"},
        "encoder": {"type": "integer"},
        "accel": {"type": "array", "items": {"type": "integer"}},
        "quat_wxyz": {"type": "array", "items": {"type": "number"}},
    },
}
TRUTH_SCHEMA = {
    "title": "bodynet.Truth",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer"},
        "angles_deg": {"type": "object", "additionalProperties": {"type": "number"}},
        "segment": {"type": "string"},
        "segment_quat_wxyz": {"type": "array", "items": {"type": "number"}},
    },
}

_COUNTS = {"type": "object", "additionalProperties": {"type": "integer"}}
TOPOLOGY_SCHEMA = {
    "title": "bodynet.Topology",
    "type": "object",
    "properties": {
        "t_ns": {"type": "integer"},
        "branches": {
            "type": "object",
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "nodes": {
                        "type": "object",
                        "additionalProperties": {
                            "type": "object",
                            "properties": {
                                "state": {"type": "string", "enum": ["alive", "stale", "gone"]},
                                "node": {"type": ["integer", "null"]},
                                "last_t_ns": {"type": ["integer", "null"]},
                                "clock_offset_ms": {"type": ["number", "null"]},
                            },
                        },
                    }
                },
            },
        },
    },
}
METRICS_SCHEMA = {
    "title": "bodynet.Metrics",
    "description": "body/@metrics: per observed dof, range of motion so far, repetitions and "
                   "the SPARC smoothness of its current movement (core/metrics.py)",
    "type": "object",
    "properties": {
        "v": {"type": "integer"},
        "t_ns": {"type": ["integer", "null"]},
        "dofs": {
            "type": "object",
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "min_deg": {"type": "number"},
                    "max_deg": {"type": "number"},
                    "range_deg": {"type": "number"},
                    "repetitions": {"type": "integer"},
                    "sparc": {"type": ["number", "null"]},
                    "samples": {"type": "integer"},
                },
            },
        },
    },
}  # fmt: skip
HEALTH_SCHEMA = {
    "title": "bodynet.Health",
    "type": "object",
    "properties": {
        "source": {"type": "string"},
        "t_ns": {"type": "integer"},
        # a bridge's
        "kind": {"type": "string"},
        "device": {"type": "string"},
        "rejected": _COUNTS,
        "nodes": {
            "type": "object",
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "key": {"type": "string"},
                    "alive": {"type": "boolean"},
                    "rate_hz": {"type": "number"},
                    "samples": {"type": "integer"},
                    "gaps": {"type": "integer"},
                    "rejected": _COUNTS,
                },
            },
        },
        # the gateway's
        "samples": {"type": "integer"},
        "ticks": {"type": "integer"},
        "solver_errors": {"type": "integer"},
        "subjects": {"type": "integer"},
        "refused_subjects": {"type": "integer"},
        "body": {"type": "object", "properties": {"samples": {"type": "integer"},
                                                  "ticks": {"type": "integer"}}},
    },
}  # fmt: skip

WORLD_FRAME = "world"

GAP_SCHEMA = {
    "title": "bodynet.Gap",
    "type": "object",
    "properties": {
        "topic": {"type": "string"},
        "after_seq": {"type": "integer"},
        "missing": {"type": "integer"},
        "from_t_ns": {"type": "integer"},
        "to_t_ns": {"type": "integer"},
    },
}
# not a Zenoh key: a channel of the recording only (admin-like, so `body/**` never matches it)
GAPS_TOPIC = "@gaps"


@dataclass(frozen=True)
class Gap:
    """``missing`` messages of ``topic`` after sequence number ``after_seq``, between
    the source times ``from_t_ns`` (the last one before) and ``to_t_ns`` (the next)."""

    topic: str
    after_seq: int
    missing: int
    from_t_ns: int
    to_t_ns: int


class StoreError(RuntimeError):
    """An MCAP file that cannot be read as bodynet data, with the reason."""


#: The latest time an MCAP log or publish time can hold (an unsigned 64-bit ns count).
MAX_TIME_NS = 2**64 - 1


def check_time(t_ns: int) -> int:
    """``t_ns`` if MCAP can store it as a message time (an integer from 0 to
    ``MAX_TIME_NS``), else ``DecodeError``: refused before it reaches the
    writer, which would fail half-way through the message and spoil its chunk."""
    try:
        t = operator.index(t_ns)
    except TypeError:
        raise DecodeError(Reason.GARBAGE, f"time {t_ns!r} is not an integer") from None
    if not 0 <= t <= MAX_TIME_NS:
        raise DecodeError(Reason.OUT_OF_RANGE,
                          f"time {t} ns is outside what MCAP stores (0 to 2**64 - 1)")  # fmt: skip
    return t


def raw_json(sample: RawSample) -> dict[str, Any]:
    r = sample.reading
    out: dict[str, Any] = {"node": r.node, "seq": sample.seq, "t_ns": sample.t_ns,
                           "source": source_name(sample.source)}  # fmt: skip
    if sample.flags:  # RESUMED: the node may have rebooted (absent: 0)
        out["flags"] = sample.flags
    if isinstance(r, OleAccel):
        out.update(encoder=r.encoder, accel=list(r.accel))
    else:
        out["quat_wxyz"] = list(r.wxyz)
    return out


#: A chunk's size past which it is closed. The loss bound of a killed recorder is
#: the chunk's age (``max_chunk_s``), not this: the writer keeps an index entry per
#: chunk for the file's summary, so small chunks cost memory for as long as the
#: file grows (64 KiB chunks of one body's raw samples and poses: some 25,000
#: entries and tens of MB in ten minutes; 1 MiB: a chunk per 0.5 s, about 2 KB
#: of index each as the writer keeps them, 0.3 KB packed on disk by
#: :class:`PackedChunkIndexes`).
CHUNK_BYTES = 1 << 20

#: The zstd level of a recording's chunks. Level 1 against the library's 3 (thread
#: CPU time, 2026-12-04): 2 s of one walking body's poses with their transforms,
#: 11 against 16 us a pose, 3% larger (1.58 against 1.54 kB); raw samples, 0.27
#: against 0.53 us a sample, 10% smaller.
ZSTD_LEVEL = 1

#: Allocations from this size up are mapped and unmapped on their own (glibc's
#: ``M_MMAP_THRESHOLD``), see :func:`keep_large_buffers_off_heap`.
MMAP_THRESHOLD = 128 * 1024


@functools.cache  # once per process
def keep_large_buffers_off_heap() -> bool:
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD` for this process;
    True if it is (False where the C library is not glibc). Idempotent.

    Each chunk the writer closes goes through buffers of about a chunk's size
    (the chunk being built, its copy, zstd's context and output). glibc starts
    by mapping such buffers, but the first one freed raises its threshold above
    them, so from then on they come from the heap arenas, where the small
    allocations that outlive them (the chunk's index entry, Zenoh's own) keep
    the freed space from being reused whole: a live recorder's resident memory
    grew steadily, about 1.3 MB a minute for one body (0.35 with the threshold
    fixed, 0.26 with no writer at all; Python's own memory stayed flat under
    ``tracemalloc``). Fixed, the threshold no longer moves: these buffers go
    back to the system when freed, at the cost of a few ``mmap`` calls a chunk."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))


_M_MMAP_THRESHOLD = -3  # glibc's malloc.h


class PackedChunkIndexes:
    """The chunk indexes of a file being written, each kept as the bytes of its
    summary record (some 300 bytes for one body's 23 channels) instead of a
    ``ChunkIndex`` object with a dictionary of offsets (about 2 KB), in an
    anonymous temporary file until the summary is written.

    The ``mcap`` writer keeps one index per chunk for the file's summary, which
    it writes at :meth:`Writer.finish`: in memory, that grows with the file (one
    body's recording, two chunks a second: 14 MB an hour as objects, 2.2 MB
    packed), and only rotating files bounded it. On disk, the recorder's memory
    no longer grows with the file's length. The summary written is the same,
    byte for byte: the writer calls ``write`` on what it iterates, and
    :meth:`__iter__` gives one record that writes every packed index."""

    def __init__(self) -> None:
        # deleted by the system as soon as it is closed (or the process ends); in
        # memory where no temporary directory is writable (a read-only container)
        self._file: IO[bytes]
        try:
            self._file = tempfile.TemporaryFile(prefix="bodynet-chunk-indexes-")  # noqa: SIM115
        except OSError:
            self._file = io.BytesIO()
        self._count = 0
        self._nbytes = 0

    def append(self, index: ChunkIndex) -> None:
        builder = RecordBuilder()
        index.write(builder)
        data = builder.end()
        self._file.write(data)
        self._nbytes += len(data)
        self._count += 1

    def __len__(self) -> int:
        return self._count

    @property
    def nbytes(self) -> int:
        """The bytes the packed indexes take (on disk)."""
        return self._nbytes

    def __iter__(self) -> Iterator[_PackedRecords]:
        if self._count:
            self._file.seek(0)
            data = self._file.read()
            self._file.seek(0, io.SEEK_END)
            yield _PackedRecords(data)

    def close(self) -> None:
        """Delete the temporary file (the summary has been written)."""
        self._file.close()


@dataclass(frozen=True)
class _PackedRecords:
    """Summary records already encoded, written as they are."""

    data: bytes

    def write(self, stream: RecordBuilder) -> None:
        stream.write(self.data)


def pack_chunk_indexes(writer: Writer) -> PackedChunkIndexes | None:
    """Make ``writer`` keep its chunk indexes packed (:class:`PackedChunkIndexes`),
    before it writes its first chunk; None (nothing changed) if this ``mcap``
    version keeps them elsewhere than the list it has always used."""
    name = "_Writer__chunk_indices"  # mcap's Writer.__chunk_indices (1.x)
    kept = getattr(writer, name, None)
    if not isinstance(kept, list) or kept:
        return None
    packed = PackedChunkIndexes()
    setattr(writer, name, packed)
    return packed


TF_BATCH = 64  # whole-body poses whose transforms are made together

#: A whole-body pose gets its Foxglove transforms when the last ones are at least
#: this much older in source time (or newer: time went back): at most about 66 a
#: second, what a display drawing 60 frames a second uses; a 100 Hz gateway's
#: poses get them every other pose, a 60 Hz one's each. Half the transforms of
#: 100 Hz poses took a whole-body pose from 0.43 to 0.54 of the bare writer's
#: rate (docs/benchmarks.md). 0: every whole-body pose.
TF_MIN_GAP_NS = 15_000_000


@functools.cache  # every file of a recording registers them
def _schemas() -> dict[str, tuple[str, str, bytes]]:
    """Each kind of message's schema: name, encoding and data."""

    def described(schema: dict[str, Any]) -> tuple[str, str, bytes]:
        return str(schema["title"]), "jsonschema", json.dumps(schema).encode()

    return {"pose": described(POSE_SCHEMA), "raw": described(RAW_SCHEMA),
            "gap": described(GAP_SCHEMA), "truth": described(TRUTH_SCHEMA),
            "tf": (foxglove_pb.SCHEMA_NAME, foxglove_pb.SCHEMA_ENCODING,
                   foxglove_pb.FRAME_TRANSFORMS_DESCRIPTOR),
            "topology": described(TOPOLOGY_SCHEMA), "health": described(HEALTH_SCHEMA),
            "metrics": described(METRICS_SCHEMA)}  # fmt: skip


class McapSink:
    """Writes poses and raw samples to one MCAP file; each whole-body pose
    (``body/pose``) also as Foxglove frame transforms on ``body/tf``. A chunk is
    closed and flushed once it holds ``chunk_size`` bytes or is ``max_chunk_s``
    old, so a writer killed mid-file loses at most that much (see :func:`salvage`).

    A message it cannot store (a time MCAP cannot hold, see :func:`check_time`)
    raises ``DecodeError`` before anything of it is written: the file goes on
    and closes complete.

    Each message's ``publish_time`` is its source time (the ``t_ns`` it
    carries, the time given to ``write_*``); its ``log_time`` is when it was
    written (``receive_time``: the recorder's clock, ``time.time_ns()``) or,
    without a receive time (``bodynet process``), its source time. Either way
    the log time never goes back in file order (the MCAP spec's order, what
    ``mcap doctor --strict-message-order`` checks): a message that would is
    logged at the latest log time so far. Readers take the source time from
    ``publish_time`` (:func:`read_poses` ...)."""

    def __init__(self, path: Path, chunk_size: int = CHUNK_BYTES, max_chunk_s: float = 0.5,
                 tf_min_gap_ns: int = TF_MIN_GAP_NS, exclusive: bool = False,
                 receive_time: bool = False) -> None:  # fmt: skip
        # exclusive: FileExistsError rather than a file of that name emptied
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | (os.O_EXCL if exclusive else os.O_TRUNC),
                     0o600)  # fmt: skip
        self._stream = os.fdopen(fd, "wb")
        zstd = CompressionType.ZSTD
        self._writer = LeanWriter(self._stream, chunk_size, zstd, zstd_level=ZSTD_LEVEL)
        #: the writer's chunk indexes for the summary, packed (None: as the writer keeps them)
        self.chunk_indexes = pack_chunk_indexes(self._writer)
        self._writer.start(profile="", library="bodynet")
        self._schemas = {kind: self._writer.register_schema(name, encoding, data)
                          for kind, (name, encoding, data) in _schemas().items()}  # fmt: skip
        self._transforms = Transforms(segment_parents(), WORLD_FRAME)
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.messages = 0
        self._max_chunk_s = max_chunk_s
        self._chunk_opened = time.monotonic()
        # whole-body poses awaiting their transforms: (time, the message or None, its
        # segments' text or (names, rows))
        self._tf_pending: list[tuple[int, bytes | None, Any]] = []
        # and the segments of each whose transform is left out (resting on an unmeasured angle)
        self._tf_unmeasured: list[frozenset[str]] = []
        self._segments_at = 0  # where the last pose's segments began: looked at first
        self._tf_min_gap_ns = tf_min_gap_ns
        self._tf_last: int | None = None  # the time of the last pose given transforms
        self._receive_time = receive_time
        self._log_last = 0  # the latest log time written: the next is no earlier

    def _log_time(self, t_ns: int) -> int:
        """The log time of a message written now whose source time is ``t_ns``:
        now (``receive_time``) or ``t_ns``, never before the last one written."""
        t = time.time_ns() if self._receive_time else t_ns
        if t < self._log_last:
            return self._log_last
        self._log_last = t
        return t

    def _next(self, channel: int) -> int:
        """The channel's next message sequence number (1, 2, 3...): salvage
        counts the messages a damaged part of the file held by its gaps."""
        seq = self._sequence[channel] = self._sequence.get(channel, 0) + 1
        return seq

    def _channel(self, topic: str, kind: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            encoding = foxglove_pb.MESSAGE_ENCODING if kind == "tf" else "json"
            channel = self._channels[topic] = self._writer.register_channel(
                topic, encoding, self._schemas[kind]
            )
        return channel

    def write_pose(self, topic: str, frame: pose.PoseFrame, t_ns: int,
                   data: bytes | None = None) -> None:  # fmt: skip
        """``data``: the frame's message as received, stored as it is (encoding a
        pose again costs twice as much as decoding it)."""
        check_time(t_ns)  # before the pose: its transforms share its time
        data = pose.encode(frame) if data is None else data
        if topic == keys.pose_key() and self._tf_due(t_ns):
            rows = [[*p, *q] for p, q in frame.segments.values()]
            self._pending(t_ns, None, (tuple(frame.segments), rows), unmeasured_segments(frame))
        self._add(self._channel(topic, "pose"), t_ns, data)

    def write_pose_message(self, topic: str, data: bytes) -> tuple[int, int]:
        """A pose message as received, stored as it is; returns its sequence
        number and its source time, the message's publish time (its ``t_ns``;
        when that is 0, now).

        Only what the file needs is read of it: the header (``pose.glance``)
        and, for a whole-body pose due its transforms (:data:`TF_MIN_GAP_NS`),
        its segments, read with the next ones' (see
        :class:`~bodynet.clients.body_tree.Transforms`).
        A message laid out otherwise than the gateway lays it out is decoded
        whole (``DecodeError`` if it is no pose). So a message that starts as a
        pose does but is none past its header is stored as it came (a reader
        then names it, see :func:`read_poses`), and a whole-body pose whose
        segments do not read gets no transforms (an empty message); a whole-body
        pose whose segments are not laid out so is decoded whole when its
        transforms are due."""
        head = pose.glance(data)
        frame: pose.PoseFrame | None = None
        if head is None:
            frame = pose.decode(data)
            seq, t_ns = frame.seq, frame.t_ns
        else:
            seq, t_ns = head.seq, head.t_ns
        t = check_time(t_ns or time.time_ns())
        if topic == keys.pose_key() and self._tf_due(t):  # its segments, for its transforms
            if frame is None:
                head = pose.glance(data, segments=True, hint=self._segments_at)
                unmeasured = None if head is None else _unmeasured_before(data, head.at)
                if head is not None and unmeasured is not None:
                    self._segments_at = head.at
                    self._pending(t, data, head.segments, unmeasured)
                else:  # not laid out as the gateway lays it out past its header
                    frame = pose.decode(data)
            if frame is not None:
                rows = [[*p, *q] for p, q in frame.segments.values()]
                self._pending(t, None, (tuple(frame.segments), rows), unmeasured_segments(frame))
        self._add(self._channel(topic, "pose"), t, data)
        return seq, t

    def _tf_due(self, t_ns: int) -> bool:
        """Whether a whole-body pose at ``t_ns`` gets transforms (see
        :data:`TF_MIN_GAP_NS`)."""
        last = self._tf_last
        return last is None or not last <= t_ns < last + self._tf_min_gap_ns

    def _pending(self, t_ns: int, data: bytes | None, segments: Any,
                 unmeasured: frozenset[str]) -> None:  # fmt: skip
        # its transforms are made with the next ones' (at most TF_BATCH), and
        # before the writer closes a chunk on time, so salvage keeps them
        self._tf_last = t_ns
        self._tf_pending.append((t_ns, data, segments))
        self._tf_unmeasured.append(unmeasured)
        if len(self._tf_pending) >= TF_BATCH:
            self._write_transforms()

    def _write_transforms(self) -> None:
        pending, self._tf_pending = self._tf_pending, []
        unmeasured, self._tf_unmeasured = self._tf_unmeasured, []
        texts = [s for _, _, s in pending if isinstance(s, bytes)]
        try:
            names, flat = pose.segment_numbers(texts)
        except DecodeError:  # one of them holds no numbers: each on its own
            names, flat = [], []
            for text in texts:
                try:
                    one, numbers = pose.segment_numbers([text])
                except DecodeError:
                    one, numbers = [None], []
                names += one
                flat += numbers
        rows = np.asarray(flat, dtype=float).reshape(-1, 7)
        times = [t for t, _, _ in pending]
        if (
            len(texts) == len(pending)
            and not any(unmeasured)
            and names
            and names[0]
            and names.count(names[0]) == len(names)
        ):
            # the usual batch: every pose as the gateway writes it, the same segments
            messages = self._transforms.alike(times, names[0], rows.reshape(len(times), -1, 7))
        else:
            read, at = iter(names), 0
            poses: list[tuple[int, Any, Any]] = []
            for t_ns, data, given in pending:
                segments = given
                if isinstance(given, bytes):
                    these = next(read)
                    if these is None:  # not as the gateway writes them: the whole message
                        segments = _decoded_rows(data)
                    else:
                        segments = (these, rows[at : at + len(these)])
                        at += len(these)
                poses.append((t_ns, *segments))
            messages = self._transforms.messages(
                [_without(p, u) for p, u in zip(poses, unmeasured, strict=True)]
            )
        channel = self._channel(keys.TRANSFORMS, "tf")
        first = self._sequence.get(channel, 0) + 1  # numbered as _next numbers them
        self._sequence[channel] = first + len(messages) - 1
        self._writer.add_messages(
            channel,
            [(self._log_time(t), m, t) for t, m in zip(times, messages, strict=True)],
            first,
        )
        self.messages += len(messages)

    def write_raw(self, topic: str, sample: RawSample, t_ns: int) -> None:
        try:
            data = orjson.dumps(raw_json(sample))  # the recorder's hot path: orjson is ~5x json
        except orjson.JSONEncodeError as exc:  # a number past 64 bits
            raise DecodeError(Reason.OUT_OF_RANGE, f"raw sample not storable: {exc}") from None
        self._add(self._channel(topic, "raw"), t_ns, data)

    def _add(self, channel: int, t_ns: int, data: bytes) -> None:
        t = check_time(t_ns)  # the publish time: a uint64 field
        self._writer.add_message(channel, self._log_time(t), data, t, self._next(channel))
        self.messages += 1
        now = time.monotonic()
        if now - self._chunk_opened >= self._max_chunk_s:
            if self._tf_pending:
                self._write_transforms()
            self._writer.flush()  # closes the open chunk: on disk, salvageable
            self._chunk_opened = now

    def write_truth(self, topic: str, truth_json: bytes, t_ns: int) -> None:
        """An emulator's ground-truth message, as published (JSON bytes)."""
        self._add(self._channel(topic, "truth"), t_ns, truth_json)

    def write_topology(self, topic: str, data: bytes, t_ns: int) -> None:
        """A topology message (``body/@topology``), as published (JSON bytes)."""
        self._add(self._channel(topic, "topology"), t_ns, data)

    def write_health(self, topic: str, data: bytes, t_ns: int) -> None:
        """A health message (``body/@health/<source>``), as published (JSON bytes)."""
        self._add(self._channel(topic, "health"), t_ns, data)

    def write_metrics(self, topic: str, data: bytes, t_ns: int) -> None:
        """A metrics message (``body/@metrics``), as published (JSON bytes)."""
        self._add(self._channel(topic, "metrics"), t_ns, data)

    def write_gap(self, gap: Gap) -> None:
        data = orjson.dumps(asdict(gap))
        self._add(self._channel(GAPS_TOPIC, "gap"), gap.to_t_ns, data)

    def close(self) -> None:
        if self._tf_pending:
            self._write_transforms()
        try:
            self._writer.finish()
        finally:
            if self.chunk_indexes is not None:
                self.chunk_indexes.close()
        self._stream.close()


_FLAGS = b',"flags":'
_REASONS, _UNC = b',"reasons":', b',"unc_deg":'


def _unmeasured_before(data: bytes, at: int) -> frozenset[str] | None:
    """``unmeasured_segments`` of a pose message laid out as the gateway lays
    it out, from its ``flags``: the member just before its ``segments`` (found
    at ``at`` by ``pose.glance``), and where a dof is ``unobserved`` (which the
    upright model's are), its ``reasons``, between its ``stale`` and
    ``unc_deg``; None if it is not there so (then decode the message)."""
    start = data.rfind(_FLAGS, 0, at)
    if start < 0:
        return None
    flags = data[start + len(_FLAGS) : at]
    if pose.UNOBSERVED.encode() not in flags:
        return _unmeasured(flags, b"{}")
    begin = data.rfind(_REASONS, at)
    end = data.find(_UNC, begin)
    if begin < 0 or end < 0:
        return None
    return _unmeasured(flags, data[begin + len(_REASONS) : end])


@functools.lru_cache(maxsize=256)  # a recording's poses repeat a few sets of flags
def _unmeasured(flags_text: bytes, reasons_text: bytes) -> frozenset[str] | None:
    if flags_text == b"{}":
        return frozenset()
    try:
        flags, reasons = orjson.loads(flags_text), orjson.loads(reasons_text)
    except orjson.JSONDecodeError:
        return None
    if not isinstance(flags, dict) or not all(isinstance(v, str) for v in flags.values()):
        return None
    if not isinstance(reasons, dict) or not all(isinstance(v, list) for v in reasons.values()):
        return None
    return unmeasured_segments(pose.PoseFrame(0, 0, _every_angle(), {}, {}, {}, flags,
                                              reasons=reasons))  # fmt: skip


@functools.cache
def _every_angle() -> Mapping[str, float]:
    """Every angle of the default skeleton, for :func:`_unmeasured`'s pose of
    flags alone (the gateway's whole-body pose carries them all)."""
    return MappingProxyType(dict.fromkeys(build_skeleton().angle_names(), 0.0))


def _without(given: tuple[int, Any, Any], unmeasured: frozenset[str]) -> tuple[int, Any, Any]:
    """A pose ``(t_ns, segment names, rows)`` for ``Transforms.messages``
    without the ``unmeasured`` segments (names may be UTF-8 bytes)."""
    if not unmeasured:
        return given
    t_ns, names, rows = given
    text = [n.decode("utf-8", "replace") if isinstance(n, bytes) else n for n in names]
    keep = [i for i, n in enumerate(text) if n not in unmeasured]
    return t_ns, tuple(names[i] for i in keep), [rows[i] for i in keep]


def _decoded_rows(data: bytes | None) -> tuple[tuple[str, ...], list[list[float]]]:
    """The segment names and rows of a pose message (none if it is no pose)."""
    try:
        segments = pose.decode(data or b"").segments
    except DecodeError:
        return (), []
    return tuple(segments), [[*p, *q] for p, q in segments.values()]


def read_poses(path: Path, topic: str = "body/pose") -> Iterator[tuple[int, pose.PoseFrame]]:
    """(source time ns, pose) of every message on ``topic``, in source-time order;
    ``StoreError`` at a message that is not a pose."""
    for _, _, message in _messages(path, [topic]):
        try:
            frame = pose.decode(message.data)
        except DecodeError as exc:
            raise StoreError(
                f"{path}: the message on {topic} at {message.publish_time} ns is not a bodynet "
                f"pose ({exc})"
            ) from None
        yield message.publish_time, frame


_READ_ERRORS = (McapError, ValueError, EOFError, OSError, struct.error, zstandard.ZstdError,
                MemoryError, OverflowError)  # fmt: skip


def _damaged(path: Path, f: IO[bytes], exc: BaseException) -> StoreError:
    """The error of a recording that breaks off or is damaged: where, and how
    to recover what is intact (not salvage, for a file that is no recording)."""
    try:
        stop = f.tell()
        f.seek(0)
        head = f.read(len(MCAP_MAGIC))
        if not (head.startswith(MCAP_MAGIC) or MCAP_MAGIC.startswith(head)):
            return StoreError(f"{path}: not an MCAP recording (it does not start as MCAP files "
                              "do); `bodynet process` makes one of a capture")  # fmt: skip
        where = f" (reading stopped at byte {stop})"
        f.seek(0)
        summary = make_reader(f).get_summary()
        for ci in summary.chunk_indexes if summary is not None else ():
            if ci.chunk_start_offset < stop <= ci.chunk_start_offset + ci.chunk_length:
                where = f" (in the chunk at byte {ci.chunk_start_offset})"
    except (*_READ_ERRORS, OSError, ValueError):
        pass
    # a read that fails (not a seek before the start of a file cut short: EINVAL)
    if isinstance(exc, OSError) and exc.errno is not None and exc.errno != errno.EINVAL:
        return StoreError(f"{path}: cannot read it ({exc.strerror}){where}")
    return StoreError(
        f"{path}: not a complete MCAP file ({_short(exc)}){where}; "
        f"`bodynet record --salvage {path} -o <new file>` recovers the messages that are intact"
    )


#: how much of a recording's messages a reader holds (their bytes, and about
#: :data:`_HELD_OVERHEAD` more each) to put them in source-time order as it reads
#: the file once; a larger recording is read twice: its source times, then its
#: messages, held only as long as one comes before others it came after
SORT_IN_MEMORY_BYTES = 32 << 20
_HELD_OVERHEAD = 256


def _messages(path: Path, topics: Iterable[str] | None) -> Iterator[Any]:
    """(schema, channel, message) of a recording's messages on ``topics`` (None:
    all), in source-time order: by ``publish_time``, messages of the same time
    in the order they were recorded. The recorder logs each message at the time
    it came (``log_time``, see :class:`McapSink`), the order of the file; a
    recording written before it did had ``log_time == publish_time``."""
    topics = None if topics is None else list(topics)
    held: list[Any] | None = []
    size = 0
    times = array("Q")
    error: StoreError | None = None
    try:
        for item in _file_messages(path, topics):
            times.append(item[2].publish_time)
            if held is not None:
                held.append(item)
                size += len(item[2].data) + _HELD_OVERHEAD
                if size > SORT_IN_MEMORY_BYTES:
                    held = None
    except StoreError as exc:  # what was read before the damage, then the error
        error = exc
    if held is not None:
        held.sort(key=lambda item: item[2].publish_time)  # stable: same times as recorded
        yield from held
        if error is not None:
            raise error
        return
    yield from _in_order(_file_messages(path, topics), times)


def _in_order(items: Iterator[Any], times: array[int]) -> Iterator[Any]:
    """``items`` (whose publish times are ``times``) by publish time, each held
    only until the ones before it in that order have come."""
    order = np.argsort(np.frombuffer(times, dtype=np.uint64), kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    waiting: dict[int, Any] = {}
    due = 0
    for i, item in enumerate(items):
        if i >= len(rank):
            break
        if rank[i] != due:
            waiting[int(rank[i])] = item
            continue
        yield item
        due += 1
        while due in waiting:
            yield waiting.pop(due)
            due += 1


def _file_messages(path: Path, topics: list[str] | None) -> Iterator[Any]:
    """A recording's messages in log-time order (the order of the file)."""
    try:
        f = path.open("rb")
    except OSError as exc:
        raise StoreError(f"{path}: cannot read it ({exc.strerror})") from None
    with f:
        try:
            yield from make_reader(f).iter_messages(topics=topics)
        # the mcap reader raises struct.error, not an McapError, on some truncated files, and
        # zstandard's error on a corrupt chunk
        except _READ_ERRORS as exc:
            raise _damaged(path, f, exc) from None


def raw_from_json(data: bytes) -> RawSample:
    """The raw sample a ``bodynet.RawSample`` message holds (see :func:`raw_json`)."""
    from bodynet.core.messages import Quat, source_of

    try:
        d = json.loads(data)
        if "quat_wxyz" in d:
            w, x, y, z = (float(c) for c in d["quat_wxyz"])
            reading: OleAccel | Quat = Quat(int(d["node"]), (w, x, y, z))
        else:
            ax, ay, az = (int(c) for c in d["accel"])
            reading = OleAccel(int(d["node"]), int(d["encoder"]), (ax, ay, az))
        flags = int(d.get("flags", 0)) if "quat_wxyz" not in d else 0
        if not 0 <= flags <= 0xFF:  # the raw-sample message holds it in one byte
            raise ValueError(f"flags {flags} is not a byte (0 to 255)")
        return RawSample(reading, int(d["seq"]), int(d["t_ns"]), source_of(str(d["source"])),
                         flags)  # fmt: skip
    except (ValueError, KeyError, TypeError) as exc:
        raise StoreError(f"not a raw-sample message: {exc}") from None


def read_raw(
    path: Path, topics: Iterable[str] | None = None
) -> Iterator[tuple[str, int, RawSample]]:
    """(topic, source time ns, sample) of the raw samples of a recording, in
    source-time order."""
    for schema, channel, message in _messages(path, topics):
        if schema is not None and schema.name == "bodynet.RawSample":
            try:
                sample = raw_from_json(message.data)
            except StoreError as exc:
                raise StoreError(f"{path}: {channel.topic}: {exc}") from None
            yield channel.topic, message.publish_time, sample


def read_gaps(path: Path) -> list[Gap]:
    """The gap records of a recording (see :class:`Gap`), in source-time order."""
    try:
        return [Gap(**json.loads(m.data)) for _, _, m in _messages(path, [GAPS_TOPIC])]
    except (ValueError, TypeError) as exc:
        raise StoreError(f"{path}: a gap record that is not one ({exc})") from None


def read_truth(path: Path) -> Iterator[tuple[str, int, dict[str, float]]]:
    """(topic, source time ns, true joint angles) of the ground truth a recording holds."""
    for schema, channel, message in _messages(path, None):
        if schema is not None and schema.name == "bodynet.Truth":
            try:
                angles = json.loads(message.data)["angles_deg"]
                values = {str(k): float(v) for k, v in angles.items()}
            except (ValueError, KeyError, TypeError, AttributeError) as exc:
                raise StoreError(f"{path}: not a ground-truth message: {exc}") from None
            yield channel.topic, message.publish_time, values


def read_topology(path: Path) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """(topic, source time ns, message) of the topology messages of a recording."""
    return _read_json(path, "bodynet.Topology")


def read_health(path: Path) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """(topic, source time ns, message) of the health messages of a recording
    (every source's: ``body/@health/<source>``)."""
    return _read_json(path, "bodynet.Health")


def read_metrics(path: Path) -> Iterator[tuple[str, int, dict[str, Any]]]:
    """(topic, source time ns, message) of the clinical metrics of a recording
    (``body/@metrics``, see ``core/metrics.py``)."""
    return _read_json(path, "bodynet.Metrics")


def _read_json(path: Path, schema_name: str) -> Iterator[tuple[str, int, dict[str, Any]]]:
    for schema, channel, message in _messages(path, None):
        if schema is not None and schema.name == schema_name:
            try:
                d = json.loads(message.data)
            except ValueError as exc:
                raise StoreError(f"{path}: a {schema_name} message that is not JSON "
                                 f"({exc})") from None  # fmt: skip
            if not isinstance(d, dict):
                raise StoreError(f"{path}: a {schema_name} message that is not a JSON object")
            yield channel.topic, message.publish_time, d


@dataclass(frozen=True)
class ChannelCount:
    """One channel of a recording's summary: its topic, schema and message count."""

    topic: str
    schema: str | None
    messages: int


def channel_counts(path: Path) -> list[ChannelCount] | None:
    """The channels of a recording with their message counts, from its summary
    (``None`` if it has none, or no statistics)."""
    try:
        f = path.open("rb")
    except OSError as exc:
        raise StoreError(f"{path}: cannot read it ({exc.strerror})") from None
    with f:
        try:
            summary = make_reader(f).get_summary()
        except _READ_ERRORS as exc:
            raise _damaged(path, f, exc) from None
    stats = summary.statistics if summary is not None else None
    if stats is None or summary is None:
        return None
    out = []
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        out.append(ChannelCount(ch.topic, schema.name if schema is not None else None,
                                int(stats.channel_message_counts.get(cid, 0))))  # fmt: skip
    return out


def count_messages(path: Path, topic: str | None = None) -> int:
    """Messages in a recording (or on one topic), from its summary (0 if it has none)."""
    counts = channel_counts(path)
    if counts is None:
        return 0
    return sum(c.messages for c in counts if topic is None or c.topic == topic)


#: The first bytes of every MCAP file.
MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class Loss:
    """A part of a recording salvage could not read: where it starts (byte
    offset) and where reading went on (``end``), how many messages it held
    and how that is known (``counted``), and why it could not be read.

    ``counted`` is "exact" (a chunk's message index, or the file's summary),
    "at least" (the gaps in the message sequence numbers of the channels read
    after it: a channel heard of only inside it cannot be seen), "at most" (a
    cut chunk's size, over the smallest message a chunk can hold) or
    "unknown" (``messages`` None; ``unknown`` says why)."""

    offset: int
    messages: int | None
    why: str
    end: int | None = None
    counted: str = "exact"
    unknown: str = ""

    def told(self) -> str:
        """``byte X to Y (N messages: why)``."""
        where = f"byte {self.offset}" + (
            f" to {self.end}" if self.end is not None and self.end > self.offset + 1 else ""
        )
        if self.messages is None:
            count = "an unknown number of messages: " + (self.unknown or "not counted")
        else:
            bound = "" if self.counted == "exact" else f"{self.counted} "
            count = bound + _n_messages(self.messages)
        return f"{where} ({count}; {self.why})"


def _n_messages(n: int) -> str:
    return f"{n} message{'' if n == 1 else 's'}"


@dataclass(frozen=True)
class Salvaged:
    """What :func:`salvage_report` kept and lost."""

    messages: int
    losses: tuple[Loss, ...]
    #: messages read whose channel no record defines (its record lost): channel -> count
    orphans: Mapping[int, int] = field(default_factory=dict)
    #: the messages read carry no sequence numbers (a recording made before
    #: bodynet's recorder numbered them, 2026-12-03, or by another tool)
    unnumbered: bool = False

    def uncounted(self) -> str | None:
        """One line saying that the losses of an unnumbered file could not be
        counted by sequence numbers, where that left one of them unknown or
        bounded only by its size (None otherwise)."""
        if not self.unnumbered or all(loss.counted == "exact" for loss in self.losses):
            return None
        return ("its messages carry no sequence numbers (recorded before bodynet's recorder "
                "numbered them, 2026-12-03, or by another tool): what its damaged parts held "
                "cannot be counted by them")  # fmt: skip

    def summary(self) -> str:
        """``lost N messages: byte X (n messages; why); ...``, "at least N" where
        a part's count is a bound or unknown."""
        if not self.losses and not self.orphans:
            return "nothing lost"
        orphans = sum(self.orphans.values())
        low = orphans + sum(loss.messages or 0 for loss in self.losses
                            if loss.counted != "at most")  # fmt: skip
        high = low + sum(loss.messages or 0 for loss in self.losses if loss.counted == "at most")
        open_ended = any(loss.counted in ("at least", "unknown") or loss.messages is None
                         or _CUT in loss.why for loss in self.losses)  # fmt: skip
        if open_ended and not low and all(loss.messages is None for loss in self.losses):
            lost = "an unknown number of messages"
        elif open_ended:
            lost = f"at least {_n_messages(low)}"
        elif high > low:
            lost = f"{low} to {high} messages"
        else:
            lost = _n_messages(low)
        told = [loss.told() for loss in self.losses]
        if orphans:
            told.insert(0, f"{_n_messages(orphans)} of channel(s) "
                        f"{', '.join(map(str, sorted(self.orphans)))}, whose channel record "
                        "was lost with the part that held it")  # fmt: skip
        more = f"; and {len(told) - 10} more" if len(told) > 10 else ""
        return f"lost {lost}: {'; '.join(told[:10])}{more}"


def salvage(src: Path, dst: Path) -> int:
    """Copy every message of an unfinished or damaged file into a complete
    one (see :func:`salvage_report`); returns how many."""
    return salvage_report(src, dst).messages


def salvage_report(src: Path, dst: Path) -> Salvaged:
    """Copy every message of an unfinished file (a recorder killed mid-write)
    or a damaged one (a corrupt chunk) into a complete file: each chunk that
    cannot be read is skipped, counted (from its message index) and the
    chunks after it are read; a file cut short keeps everything before the
    cut. A part whose count its own index does not give is counted from the
    file's summary (chunk and message indexes, statistics) when the file has
    one, else bounded by the message sequence numbers around it, else by a
    cut chunk's size; :class:`Loss` says which.

    ``StoreError`` if ``src`` cannot be read or is no MCAP file at all; then,
    as on any other failure, nothing is left at ``dst`` (written aside and
    renamed into place last)."""
    from bodynet.session.outputs import atomic_file

    try:
        f = src.open("rb")
    except OSError as exc:
        raise StoreError(f"{src}: cannot read it ({exc.strerror})") from None
    with f:
        try:
            head = f.read(len(MCAP_MAGIC))
        except OSError as exc:
            raise StoreError(f"{src}: cannot read it ({exc.strerror})") from None
        if head != MCAP_MAGIC:
            if MCAP_MAGIC.startswith(head):
                raise StoreError(f"{src}: ends before its MCAP header ({len(head)} bytes): "
                                 "nothing to salvage")  # fmt: skip
            raise StoreError(f"{src}: not an MCAP recording (it does not start as MCAP files "
                             "do): nothing to salvage")  # fmt: skip
        losses: list[Loss] = []
        size = os.fstat(f.fileno()).st_size
        summary = _summary_counts(f, size)
        gaps = _SequenceGaps()
        read_chunks: set[int] = set()
        with atomic_file(dst, [src], "wb") as out:
            indexed = (
                {c.chunk_start_offset: c.chunk_length for c in summary.chunks} if summary else None
            )
            records = _walk(f, size, losses, read_chunks, indexed,
                            set(summary.channels) if summary else None)  # fmt: skip
            count, orphans = _copy_complete(gaps.watch(records, losses), out, summary)
        losses = _counted(f, size, losses, gaps, count + sum(orphans.values()), summary,
                          read_chunks)  # fmt: skip
    return Salvaged(count, tuple(losses), orphans, unnumbered=count > 0 and not gaps.numbered)


class _SequenceGaps:
    """The message sequence numbers on either side of each loss, channel by
    channel (a writer that numbers its messages, as bodynet's recorder does,
    1, 2, 3... per channel): how many messages are missing between them."""

    def __init__(self) -> None:
        self.last: dict[int, int] = {}  # channel -> the last sequence number read
        self.before: dict[int, dict[int, int]] = {}  # loss -> channel -> last before it
        self.after: dict[int, dict[int, int]] = {}  # loss -> channel -> first after it
        self._open: list[int] = []  # losses still waiting for a channel's first number
        self.numbered = True

    def watch(self, records: Iterator[Any], losses: list[Loss]) -> Iterator[Any]:
        seen = 0
        for record in records:
            if seen < len(losses):  # losses found before this record: the ones before
                self._open = []  # them are closed (a gap past a later loss is not theirs)
            while seen < len(losses):
                self.before[seen] = dict(self.last)
                self.after[seen] = {}
                self._open.append(seen)
                seen += 1
            if isinstance(record, Message):
                self._message(record.channel_id, record.sequence)
            yield record
        while seen < len(losses):
            self.before[seen], self.after[seen] = dict(self.last), {}
            seen += 1

    def _message(self, channel: int, seq: int) -> None:
        if seq == 0:
            self.numbered = False
        for i in list(self._open):
            after = self.after[i]
            if channel not in after:
                after[channel] = seq
                if set(self.before[i]) <= set(after):  # every channel heard again
                    self._open.remove(i)
        self.last[channel] = seq

    def missing(self, i: int) -> int | None:
        """Messages missing at loss ``i``, of the channels read after it (None:
        none read after it, or the messages are not numbered)."""
        if not self.numbered or not self.after.get(i):
            return None
        before = self.before[i]
        return sum(max(0, first - before.get(ch, 0) - 1) for ch, first in self.after[i].items())


def _counted(f: IO[bytes], size: int, losses: list[Loss], gaps: _SequenceGaps,
             read: int, summary: _Summary | None, read_chunks: set[int]) -> list[Loss]:  # fmt: skip
    """The losses, each unknown count made exact from the file's summary where
    it has one, else bounded by sequence numbers or a cut chunk's size, else
    said why not."""
    from dataclasses import replace

    out = []
    by_summary = summary.unread(f, read_chunks, losses, size) if summary is not None else {}
    for i, loss in enumerate(losses):
        if loss.messages is not None:
            out.append(loss)
            continue
        end = size if loss.end is None else loss.end
        n = by_summary.get(i, 0 if summary is not None and summary.chunks else None)
        if n is not None:
            out.append(replace(loss, messages=n, counted="exact"))
            continue
        n = gaps.missing(i)
        if n is not None:
            out.append(replace(loss, messages=n, counted="at least"))
            continue
        most = _cut_chunk_bound(f, loss.offset, size) if loss.end is None else None
        if most is not None:
            out.append(replace(loss, messages=most, counted="at most"))
            continue
        if loss.end is None and loss.offset + 9 > size:
            why = "nothing is left of the file to count by"
        else:
            why = ("the file ends inside it, and " if loss.end is None else
                   f"its {end - loss.offset} bytes hide where records begin, and ")  # fmt: skip
            why += ("the file has no summary to count it by"
                    + ("" if gaps.numbered else ", nor message sequence numbers"))  # fmt: skip
        out.append(replace(loss, counted="unknown", unknown=why))
    if summary is not None and summary.total is not None:  # the statistics: all but one known
        unknown = [i for i, loss in enumerate(out) if loss.counted != "exact"]
        if len(unknown) == 1:
            others = sum(loss.messages or 0 for loss in out if loss.counted == "exact")
            lost = summary.total - read - others
            if lost >= 0:
                out[unknown[0]] = replace(out[unknown[0]], messages=lost, counted="exact",
                                          unknown="")  # fmt: skip
    return out


@dataclass
class _Summary:
    """A damaged file's summary section, if it kept one: its chunk indexes and
    the total of its statistics."""

    chunks: list[ChunkIndex]
    total: int | None
    schemas: dict[int, Schema]
    channels: dict[int, Channel]

    def unread(self, f: IO[bytes], read: set[int], losses: list[Loss],
               size: int) -> dict[int, int | None]:  # fmt: skip
        """For each loss (by index) whose count is not known, the messages of
        the indexed chunks that were not read and that lie in it (or after it,
        before the next one), from their message indexes (None: one of them
        cannot be read)."""
        counts: dict[int, int | None] = {}
        open_losses = [i for i, loss in enumerate(losses) if loss.messages is None]
        # a chunk that did not read, counted already from the message indexes after it
        counted = {loss.offset for loss in losses if loss.messages is not None}
        for chunk in self.chunks:
            if chunk.chunk_start_offset in read or chunk.chunk_start_offset in counted:
                continue
            start, end = chunk.chunk_start_offset, chunk.chunk_start_offset + chunk.chunk_length
            at = [i for i in open_losses if losses[i].offset < end]
            if not at:
                continue
            over = [i for i in at if (losses[i].end or size) > start]
            i = over[0] if over else at[-1]
            n = _indexed_messages(f, chunk)
            counts[i] = None if n is None or counts.get(i, 0) is None else (counts.get(i) or 0) + n
        return counts


def _indexed_messages(f: IO[bytes], chunk: ChunkIndex) -> int | None:
    """A chunk's messages, from its message index records (None if one of them
    does not read)."""
    count = 0
    for offset in chunk.message_index_offsets.values():
        try:
            f.seek(offset)
            if f.read(1) != bytes([Opcode.MESSAGE_INDEX]):
                return None
            length = int.from_bytes(f.read(8), "little")
            index = MessageIndex.read(ReadDataStream(io.BytesIO(f.read(length))))
        except (McapError, ValueError, EOFError, struct.error, OSError, OverflowError,
                MemoryError):  # fmt: skip
            return None
        count += len(index.records)
    return count


def _summary_counts(f: IO[bytes], size: int) -> _Summary | None:
    """The file's summary, if its footer and summary read (a file damaged in
    the middle keeps them), else None."""
    from mcap.reader import SeekingReader

    try:
        f.seek(0)
        summary = SeekingReader(f).get_summary()
    except (McapError, ValueError, EOFError, struct.error, OSError, StopIteration,
            zstandard.ZstdError, UnicodeDecodeError, MemoryError):  # fmt: skip
        return None
    if summary is None:
        return None
    stats = summary.statistics
    return _Summary(list(summary.chunk_indexes), stats.message_count if stats else None,
                    dict(summary.schemas), dict(summary.channels))  # fmt: skip


#: The smallest message record (opcode, length, channel id, sequence, two
#: times; no data): a chunk of N bytes holds at most N // this many.
_SMALLEST_MESSAGE = 1 + 8 + 2 + 4 + 8 + 8


def _cut_chunk_bound(f: IO[bytes], offset: int, size: int) -> int | None:
    """At most how many messages a chunk the file ends inside held (from its
    header's uncompressed size), None if it is no chunk or its header is cut."""
    f.seek(offset)
    head = f.read(9 + 8 * 3)
    if len(head) < 9 + 24 or head[0] != Opcode.CHUNK:
        return None
    uncompressed = int.from_bytes(head[9 + 16 : 9 + 24], "little")
    return uncompressed // _SMALLEST_MESSAGE


def _cut_chunk(f: IO[bytes], pos: int, size: int) -> tuple[list[Any], int] | None:
    """The whole records at the start of a chunk the file ends inside (its
    compression undone as far as the bytes go; no CRC to check them by: they
    are the writer's, only fewer), and at most how many messages the rest
    held; None if its header is cut or its compression unknown."""
    f.seek(pos + 9)
    raw = f.read(size - pos - 9)
    stream = ReadDataStream(io.BytesIO(raw))
    try:
        stream.read8()  # message start time
        stream.read8()  # message end time
        uncompressed = stream.read8()
        stream.read4()  # the CRC of what is not all here
        compression = stream.read_prefixed_string()
        stream.read8()  # the records' length
        data = raw[stream.count :]  # what the file holds of them
        if compression == "zstd":
            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif compression == "lz4":
            import lz4.frame

            data = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif compression:
            return None
    except (McapError, ValueError, EOFError, struct.error, UnicodeDecodeError, OverflowError,
            MemoryError, zstandard.ZstdError, RuntimeError):  # fmt: skip
        return None
    records: list[Any] = []
    at = 0
    while at + 9 <= len(data):
        opcode, length = data[at], int.from_bytes(data[at + 1 : at + 9], "little")
        if at + 9 + length > len(data):
            break
        body = ReadDataStream(io.BytesIO(data[at + 9 : at + 9 + length]))
        try:
            if opcode == Opcode.MESSAGE:
                records.append(Message.read(body, length))
            elif opcode == Opcode.SCHEMA:
                records.append(Schema.read(body))
            elif opcode == Opcode.CHANNEL:
                records.append(Channel.read(body))
        except (McapError, ValueError, EOFError, struct.error, UnicodeDecodeError):
            break
        at += 9 + length
    return records, max(0, uncompressed - at) // _SMALLEST_MESSAGE


_KNOWN_OPCODES = {int(op) for op in Opcode}
#: Records whose fields each carry their own length (all but a message, whose data
#: runs to its end, and a chunk, see :func:`_chunk_framing`): one whose fields end
#: before its record does has a garbled length, which would swallow the records after it.
_SELF_DELIMITED = {
    Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
    Opcode.MESSAGE_INDEX: MessageIndex, Opcode.ATTACHMENT: Attachment,
    Opcode.METADATA: Metadata, Opcode.DATA_END: DataEnd,
}  # fmt: skip


def _fills(opcode: int, body: bytes) -> bool:
    """Whether a record's fields fill its ``body`` (records not self-delimited,
    and ones that do not read at all, are left to their own checks)."""
    kind = _SELF_DELIMITED.get(opcode)  # type: ignore[call-overload]
    if kind is None:
        return True
    stream = ReadDataStream(io.BytesIO(body))
    try:
        kind.read(stream)
    except (McapError, ValueError, EOFError, struct.error, UnicodeDecodeError, OverflowError):
        return True
    return stream.count == len(body)


def _chunk_framing(f: IO[bytes], pos: int, opcode: int, length: int, given: int | None,
                   size: int) -> tuple[int, int]:  # fmt: skip
    """The opcode and length to read the record at ``pos`` by, when it says it
    is a chunk or the file's summary (``given``: the record's whole length) says
    so: the first of its own length and the summary's whose body the chunk's
    fields fill (either may be the garbled one); else the part of one that its
    fields take (a length garbled upward, which would swallow the records after
    it); else its own, left to the checks that follow."""
    tries = [length] if opcode == Opcode.CHUNK else []
    if given is not None and given - 9 not in tries:
        tries.append(given - 9)
    part = None
    for n in tries:
        span = _chunk_span(f, pos, n, size)
        if span == n:
            return Opcode.CHUNK, n
        if span is not None and part is None:
            part = span
    return (opcode, length) if part is None else (Opcode.CHUNK, part)


def _chunk_span(f: IO[bytes], pos: int, length: int, size: int) -> int | None:
    """How many bytes of a ``length``-byte body the fields of a chunk record at
    ``pos`` take (its compression's name and its records carry their lengths);
    None if they do not fit in it or in the file."""
    if length < 0 or pos + 9 + length > size:
        return None
    f.seek(pos + 9)
    head = f.read(32)  # times, uncompressed size and CRC, the compression's length
    if len(head) < 32:
        return None
    at = 32 + int.from_bytes(head[28:32], "little")
    if at + 8 > length:
        return None
    f.seek(pos + 9 + at)
    span = at + 8 + int.from_bytes(f.read(8), "little")
    return span if span <= length else None


def _walk(f: IO[bytes], size: int, losses: list[Loss],  # noqa: PLR0915
          read_chunks: set[int] | None = None,
          indexed: Mapping[int, int] | None = None,
          channels: set[int] | None = None) -> Iterator[Any]:  # fmt: skip
    """The schemas, channels and messages of an MCAP file's data section, record
    by record; a chunk that does not read is added to ``losses`` (with the
    messages its index lists) and skipped; framing that makes no sense is
    skipped up to the next chunk that reads. ``indexed``: the chunks the file's
    summary lists (start -> length), read by their index where their own
    framing is garbled, and where reading goes on after garbled bytes.
    ``channels``: the ids the summary lists, with those of the channel records
    read: a message record outside a chunk on a channel neither defines is
    garbled framing (a message's data runs to its record's end, so a garbled
    opcode makes one of any bytes, and a garbled length swallows what follows)."""
    pos = len(MCAP_MAGIC)
    bad: Loss | None = None  # the last unreadable chunk, until its indexes are counted
    starts = sorted(indexed or ())
    while pos + 9 <= size:
        f.seek(pos)
        opcode, length = f.read(1)[0], int.from_bytes(f.read(8), "little")
        given = indexed.get(pos) if indexed else None
        if opcode == Opcode.CHUNK or given is not None:
            opcode, length = _chunk_framing(f, pos, opcode, length, given, size)
        end = pos + 9 + length
        framed = opcode in _KNOWN_OPCODES and end <= size
        if opcode == Opcode.FOOTER:  # the end of reading: only where the closing magic follows
            framed = end + len(MCAP_MAGIC) == size
        f.seek(pos + 9)
        body = f.read(length) if framed else b""
        stray = (opcode == Opcode.MESSAGE and channels is not None and len(body) >= 2
                 and int.from_bytes(body[:2], "little") not in channels)  # fmt: skip
        if not framed or stray or not _fills(opcode, body):
            if bad is not None:
                losses.append(bad)
                bad = None
            nxt = _next_chunk(f, pos + 1, size)
            later = [at for at in starts if at > pos]
            if later and (nxt is None or later[0] < nxt):
                nxt = later[0]
            if opcode in _KNOWN_OPCODES and end > size and nxt is None:
                cut = _cut_chunk(f, pos, size) if opcode == Opcode.CHUNK else None
                if cut is not None and cut[0]:  # the records of its start that were written
                    records, most = cut
                    yield from records
                    n = sum(isinstance(r, Message) for r in records)
                    losses.append(
                        Loss(
                            pos,
                            most,
                            f"the file ends inside this chunk (its first "
                            f"{_n_messages(n)} read); {_CUT}",
                            counted="at most",
                        )
                    )
                    return
                losses.append(Loss(pos, None, f"the file ends inside this record; {_CUT}"))
                return
            losses.append(Loss(pos, None, "not a record (garbled bytes)", nxt))
            if nxt is None:
                return
            pos = nxt
            continue
        if opcode == Opcode.MESSAGE_INDEX and bad is not None:
            try:
                index = MessageIndex.read(ReadDataStream(io.BytesIO(body)))
                bad = Loss(bad.offset, (bad.messages or 0) + len(index.records), bad.why,
                           bad.end)  # fmt: skip
            except (McapError, ValueError, struct.error, OverflowError):
                pass
            pos = end
            continue
        if bad is not None:
            losses.append(bad)
            bad = None
        if opcode == Opcode.FOOTER:
            return  # (a footer is framed only as the file's last record, see above)
        try:
            if opcode == Opcode.CHUNK:
                chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
                records: list[Any] = breakup_chunk(chunk, validate_crc=True)
                if read_chunks is not None:
                    read_chunks.add(pos)
            elif opcode == Opcode.SCHEMA:
                records = [Schema.read(ReadDataStream(io.BytesIO(body)))]
            elif opcode == Opcode.CHANNEL:
                records = [Channel.read(ReadDataStream(io.BytesIO(body)))]
            elif opcode == Opcode.MESSAGE:
                records = [Message.read(ReadDataStream(io.BytesIO(body)), length)]
            else:
                records = []
        except (McapError, ValueError, EOFError, struct.error, zstandard.ZstdError,
                UnicodeDecodeError, MemoryError, OverflowError) as exc:  # fmt: skip
            what = "a chunk that does not read" if opcode == Opcode.CHUNK else "a bad record"
            # a chunk's count: from the message indexes after it; any other record's
            # as garbled framing's (its opcode or length may be what is garbled, and
            # the length may have swallowed records): by the summary or the numbers
            bad = Loss(pos, None, f"{what}: {_short(exc)}", end)
            if opcode != Opcode.CHUNK:
                losses.append(bad)
                bad = None
            pos = end
            continue
        if channels is not None:
            channels.update(r.id for r in records if isinstance(r, Channel))
        yield from records
        pos = end
    if bad is not None:
        losses.append(bad)
    # no footer: the file was cut short here (a recorder killed, a copy cut)
    losses.append(Loss(pos, None, f"the file ends here, before its footer; {_CUT}"))


#: What a file cut short says of what came after the cut.
_CUT = "whatever came after it is not in the file"


def _short(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:120] or type(exc).__name__


def _next_chunk(f: IO[bytes], start: int, size: int) -> int | None:
    """The offset of the next chunk record from ``start`` that reads as one."""
    step = 1 << 20
    at = start
    while at < size:
        f.seek(at)
        block = f.read(step + 64)
        i = block.find(b"\x06")
        while 0 <= i < step:
            here = at + i
            f.seek(here + 1)
            length = int.from_bytes(f.read(8), "little")
            if here + 9 + length <= size:
                f.seek(here + 9)
                try:
                    chunk = Chunk.read(ReadDataStream(io.BytesIO(f.read(min(length, 1 << 26)))))
                    known = chunk.compression in ("zstd", "lz4", "")
                    if known and chunk.uncompressed_size < 1 << 31:
                        return here
                except (
                    McapError,
                    ValueError,
                    EOFError,
                    struct.error,
                    UnicodeDecodeError,
                    OverflowError,
                    MemoryError,
                ):
                    pass
            i = block.find(b"\x06", i + 1)
        at += step
    return None


def _copy_complete(records: Iterator[Any], out: IO[bytes],
                   summary: _Summary | None = None) -> tuple[int, dict[int, int]]:  # fmt: skip
    """Schemas, channels and messages of ``records`` into a new file on ``out``
    until the records end; a channel whose record was lost is taken from the
    file's summary (which repeats them) if it has one. Returns how many
    messages, and how many of each channel that no record defines (lost)."""
    count = 0
    orphans: dict[int, int] = {}
    writer = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
    writer.start(profile="", library="bodynet salvage")
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}

    def schema(record: Schema) -> None:
        if record.id not in schemas:
            schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)

    def channel(record: Channel) -> None:
        if record.id in channels:
            return
        known = summary.schemas.get(record.schema_id) if summary is not None else None
        if record.schema_id not in schemas and known is not None:
            schema(known)
        channels[record.id] = writer.register_channel(
            record.topic, record.message_encoding, schemas.get(record.schema_id, 0),
            dict(record.metadata),
        )  # fmt: skip

    for record in records:
        # the summary section repeats schemas and channels: once each is enough
        if isinstance(record, Schema):
            schema(record)
        elif isinstance(record, Channel):
            channel(record)
        elif isinstance(record, Message):
            if record.channel_id not in channels and summary is not None:
                known_channel = summary.channels.get(record.channel_id)
                if known_channel is not None:
                    channel(known_channel)
            if record.channel_id not in channels:
                orphans[record.channel_id] = orphans.get(record.channel_id, 0) + 1
                continue
            writer.add_message(channels[record.channel_id], record.log_time, record.data,
                               record.publish_time, record.sequence)  # fmt: skip
            count += 1
    writer.finish()
    return count, orphans
