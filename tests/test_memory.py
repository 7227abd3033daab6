"""What a long recording keeps in memory (docs/benchmarks.md, "Memory over an hour")."""

from __future__ import annotations

import io
import os
import platform
import subprocess
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from bodynet.clients.mcap_store import McapSink, PackedChunkIndexes, pack_chunk_indexes, read_raw
from bodynet.core.messages import Quat, RawSample, Source


def _write(pack: bool) -> tuple[bytes, PackedChunkIndexes | None]:
    out = io.BytesIO()
    writer = Writer(out, chunk_size=400, compression=CompressionType.ZSTD)
    packed = pack_chunk_indexes(writer) if pack else None
    writer.start(profile="", library="test")
    schema = writer.register_schema("s", "jsonschema", b"{}")
    channels = [writer.register_channel(f"body/t{k}/raw", "json", schema) for k in range(5)]
    for i in range(300):
        writer.add_message(channels[i * 7 % 5], 1000 + i, b'{"n": %d}' % i, 1000 + i)
    writer.finish()
    return out.getvalue(), packed


def test_packed_chunk_indexes_write_the_same_file() -> None:
    """The summary made from packed chunk indexes is the writer's own, byte for byte."""
    plain, _ = _write(pack=False)
    packed_file, packed = _write(pack=True)
    assert packed is not None
    assert packed_file == plain
    summary = make_reader(io.BytesIO(packed_file)).get_summary()
    assert summary is not None
    assert len(summary.chunk_indexes) == len(packed) > 10
    messages = list(make_reader(io.BytesIO(packed_file)).iter_messages(log_time_order=False))
    assert len(messages) == 300


def test_packing_refuses_a_writer_that_has_started_chunks() -> None:
    out = io.BytesIO()
    writer = Writer(out, chunk_size=10)
    writer.start()
    schema = writer.register_schema("s", "jsonschema", b"{}")
    channel = writer.register_channel("t", "json", schema)
    writer.add_message(channel, 1, b"x" * 20, 1)
    writer.add_message(channel, 2, b"y" * 20, 2)  # the first chunk is closed
    assert pack_chunk_indexes(writer) is None  # its index would be lost from the summary
    writer.finish()


def test_the_recorders_sink_packs_its_chunk_indexes(tmp_path: Path) -> None:
    path = tmp_path / "a.mcap"
    sink = McapSink(path, chunk_size=1024)
    for i in range(200):
        sample = RawSample(Quat(3, (1.0, 0.0, 0.0, 0.0)), i, 10**9 + i * 10**7, Source.IMU_CENTRAL)
        sink.write_raw("body/trunk/center/sacrum/raw", sample, sample.t_ns)
    sink.close()
    assert sink.chunk_indexes is not None
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert len(summary.chunk_indexes) == len(sink.chunk_indexes) > 1
    assert [s.seq for _, _, s in read_raw(path)] == list(range(200))


def test_a_recordings_chunk_indexes_wait_on_disk_not_in_memory(tmp_path: Path) -> None:
    """The summary's chunk indexes of a file being written grow with its length (2.2
    MB an hour for one body, packed): they wait in an anonymous temporary file, so
    the recorder's heap does not grow with them, and the summary is still whole."""
    import tracemalloc

    path = tmp_path / "long.mcap"
    sink = McapSink(path, chunk_size=512)
    assert sink.chunk_indexes is not None
    sample = RawSample(Quat(3, (1.0, 0.0, 0.0, 0.0)), 0, 10**9, Source.IMU_CENTRAL)
    for i in range(200):  # warm: channels, buffers
        sink.write_raw("body/trunk/center/sacrum/raw", sample, 10**9 + i * 10**7)
    tracemalloc.start()
    before, chunks = tracemalloc.take_snapshot(), len(sink.chunk_indexes)
    for i in range(200, 20_200):
        sink.write_raw("body/trunk/center/sacrum/raw", sample, 10**9 + i * 10**7)
    grown = sum(d.size_diff for d in tracemalloc.take_snapshot().compare_to(before, "filename")
                if d.traceback[0].filename.endswith("mcap_store.py"))  # fmt: skip
    tracemalloc.stop()
    added = len(sink.chunk_indexes) - chunks
    assert added > 500
    assert sink.chunk_indexes.nbytes > 500 * 100
    assert grown < 50 * added  # in memory, packed: about 100 bytes per chunk
    sink.close()
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    assert len(summary.chunk_indexes) == len(sink.chunk_indexes)
    assert len(list(read_raw(path))) == 20_200


def _arenas_limited(env: dict[str, str]) -> str:
    code = ("from bodynet.session.memory import limit_malloc_arenas as f; "
            "print(f(), f())")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=60, check=True)  # fmt: skip
    return done.stdout.strip()


def test_services_cap_the_allocators_arenas() -> None:
    """Two glibc arenas for a gateway or recorder (once per process); a user's own
    MALLOC_ARENA_MAX stands."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    glibc = sys.platform == "linux" and platform.libc_ver()[0] == "glibc"
    assert _arenas_limited(env) == ("True True" if glibc else "False False")
    assert _arenas_limited({**env, "MALLOC_ARENA_MAX": "4"}) == "False False"
