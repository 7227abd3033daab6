"""The ``mcap`` library's ``Writer`` with a cheaper way in for messages.

The library's ``add_message`` makes a ``Message`` record object per message,
writes it field by field (a ``struct.pack`` and a buffer write each) and, when
the chunk closes, writes the chunk's message index two numbers at a time: about
8 us of Python per message, as much as a recorder's whole budget for a message.
:class:`LeanWriter` writes the same records, byte for byte (its test writes one
sequence of calls through both and compares the files), with one ``pack`` per
message and one per message index. Everything else (schemas, channels, chunks,
their compression and indexes, the summary, the footer) is the library's own.

It also takes a zstd level for its chunks (the library compresses at zstd's
default, 3): the library's own code closes each chunk, run with a compressor
of that level in place of the ``zstandard`` module it calls.

It reaches into the library's writer state (the chunk being built and the
statistics, private names of mcap 1.x). Where that state is not what it
expects (another version of the library), it says so in :attr:`LeanWriter.lean`
and every message goes through the library's ``add_message``: slower, the same
file; likewise :attr:`LeanWriter.leveled` for the level (else the library's).
"""

from __future__ import annotations

import struct
import types
from collections.abc import Iterable
from typing import IO, Any

import mcap.writer
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import MessageIndex
from mcap.writer import CompressionType, Writer

# opcode, record length, channel id, sequence, log time, publish time (MCAP's Message)
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIELDS = 2 + 4 + 8 + 8


class _Index(MessageIndex):
    """A chunk's message index written in one ``pack`` (the library writes each
    time and offset on its own): the same bytes."""

    def write(self, stream: RecordBuilder) -> None:
        n = len(self.records)
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write(struct.pack(f"<HI{2 * n}Q", self.channel_id, 16 * n,
                                 *[v for record in self.records for v in record]))  # fmt: skip
        stream.finish_record()


class _Zstd:
    """What the library's chunk code calls of the ``zstandard`` module
    (``compress``), at a chosen level; one per writer (a compressor is not
    shared between threads)."""

    def __init__(self, level: int) -> None:
        self.compress = zstandard.ZstdCompressor(level=level).compress


def _finalize_chunk_at(level: int) -> Any:
    """The library's ``Writer.__finalize_chunk``, its ``zstandard`` a compressor
    at ``level``; None if that method is not there or compresses otherwise."""
    library = getattr(Writer, "_Writer__finalize_chunk", None)
    code = getattr(library, "__code__", None)
    if code is None or "zstandard" not in code.co_names or library.__closure__:
        return None
    scope = {**vars(mcap.writer), "zstandard": _Zstd(level)}
    return types.FunctionType(code, scope, library.__name__, library.__defaults__)


class LeanWriter(Writer):
    """``mcap.writer.Writer`` (same arguments) whose :meth:`add_message` and
    :meth:`add_messages` write the library's records with less Python per message;
    ``zstd_level``: the level of its zstd chunks (None: the library's)."""

    def __init__(
        self,
        output: IO[Any],
        chunk_size: int = 1024 * 1024,
        compression: CompressionType = CompressionType.ZSTD,
        zstd_level: int | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(output, chunk_size=chunk_size, compression=compression, **kwargs)
        finalize_at = None if zstd_level is None else _finalize_chunk_at(zstd_level)
        if finalize_at is not None:  # what the library's flush, finish and add_message call
            self._Writer__finalize_chunk = types.MethodType(finalize_at, self)
        #: whether chunks are compressed at ``zstd_level``
        self.leveled = finalize_at is not None
        state = vars(self)
        self._chunks = state.get("_Writer__chunk_builder")
        self._stats = state.get("_Writer__statistics")
        self._limit = state.get("_Writer__chunk_size")
        finalize = getattr(self, "_Writer__maybe_finalize_chunk", None)
        self._close_if_full = finalize
        chunk_fields = ("record_writer", "message_indices", "num_messages",
                        "message_start_time", "message_end_time")  # fmt: skip
        stats_fields = ("message_count", "message_start_time", "message_end_time",
                        "channel_message_counts")  # fmt: skip
        #: whether messages take the lean way (False: the library's own ``add_message``)
        self.lean = (
            self._chunks is not None
            and all(hasattr(self._chunks, a) for a in chunk_fields)
            and hasattr(self._chunks.record_writer, "_buffer")
            and all(hasattr(self._stats, a) for a in stats_fields)
            and isinstance(self._limit, int)
            and callable(finalize)
        )

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int = 0) -> None:  # fmt: skip
        """One message, as the library's ``add_message`` writes it."""
        if not self.lean:
            super().add_message(channel_id, log_time, data, publish_time, sequence)
            return
        self._put(channel_id, ((log_time, data, publish_time),), sequence)

    def add_messages(self, channel_id: int, messages: Iterable[tuple[int, bytes, int]],
                     first_sequence: int = 0) -> None:  # fmt: skip
        """Messages of one channel ``(log_time, data, publish_time)``, in order, as
        that many ``add_message`` calls write them; numbered from
        ``first_sequence`` on, one by one (0: all 0, not numbered)."""
        if not self.lean:
            for i, (log_time, data, publish_time) in enumerate(messages):
                sequence = first_sequence + i if first_sequence else 0
                super().add_message(channel_id, log_time, data, publish_time, sequence)
            return
        self._put(channel_id, messages, first_sequence)

    def _put(self, channel_id: int, messages: Iterable[tuple[int, bytes, int]],
             sequence: int) -> None:  # fmt: skip
        chunk, stats = self._chunks, self._stats
        counts = stats.channel_message_counts
        pack = _MESSAGE_HEAD.pack
        records = None  # the chunk's index of this channel, made at its first message
        for log_time, data, publish_time in messages:
            # first, as it may refuse a field (struct.error): nothing is changed then
            head = pack(
                Opcode.MESSAGE,
                _MESSAGE_FIELDS + len(data),
                channel_id,
                sequence,
                log_time,
                publish_time,
            )
            if sequence:  # numbered: the next one's number
                sequence += 1
            # the statistics and the chunk's times, as the library keeps them
            if stats.message_count == 0 or log_time < stats.message_start_time:
                stats.message_start_time = log_time
            stats.message_end_time = max(stats.message_end_time, log_time)
            counts[channel_id] += 1
            stats.message_count += 1
            if chunk.num_messages == 0 or log_time < chunk.message_start_time:
                chunk.message_start_time = log_time
            chunk.message_end_time = max(chunk.message_end_time, log_time)
            chunk.num_messages += 1
            if records is None:
                index = chunk.message_indices.get(channel_id)
                if index is None:
                    index = chunk.message_indices[channel_id] = _Index(channel_id, [])
                records = index.records
            buffer = chunk.record_writer._buffer  # a new one after each chunk closes
            records.append((log_time, buffer.tell()))
            buffer.write(head)
            buffer.write(data)
            if buffer.tell() > self._limit:
                self._close_if_full()  # the chunk and its indexes are written
                records = None
