"""`bodynet record` (with rotation) and `bodynet replay`, as processes; what the
recorder refuses, topology and health in recordings, salvage of what is no
recording (a recorder killed mid-write: test_faults)."""

from __future__ import annotations

import itertools
import json
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path

import can
import jsonschema
import pytest
import zenoh
from mcap.reader import make_reader
from zenoh_helpers import Collector, Running, client, raw_collector

from bodynet.cli.main import main
from bodynet.clients.mcap_store import (
    GAPS_TOPIC,
    MAX_TIME_NS,
    McapSink,
    count_messages,
    read_gaps,
    read_health,
    read_poses,
    read_raw,
    read_topology,
    read_truth,
    salvage,
)
from bodynet.clients.recorder import DEFAULT_KEYS, Recorder
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError, Reason
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import OleAccel, RawSample, Source
from bodynet.gateway.service import Gateway
from bodynet.nodes.can_bridge import CanBridge
from bodynet.nodes.emulator import BodyEmulator, Realism, smartsuit_sensors
from bodynet.nodes.hardware import CanNodes
from bodynet.nodes.motion import ROUTINES

BODYNET = Path(sys.executable).with_name("bodynet")


@pytest.fixture
def live_arm(zsession: zenoh.Session) -> Iterator[None]:
    """A SmartSuit left arm on a virtual bus, bridged onto the test router."""
    channel = f"rec-{time.monotonic_ns()}"
    bridge = CanBridge(zsession, "rec-test")
    running = Running(partial(bridge.run_bus, interface="virtual", channel=channel), timeout=10)
    with can.Bus(interface="virtual", channel=channel) as bus:
        nodes = CanNodes(bus, BodyEmulator(ROUTINES["elbow-slow"], smartsuit_sensors([LEFT_ARM]),
                                           realism=Realism.ideal()))  # fmt: skip
        nodes.start()
        yield
        nodes.stop()
    running.stop()
    bridge.close()


def start_recorder(endpoint: str, out: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([str(BODYNET), "record", "-o", str(out), *extra, "-e", endpoint],
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def wait_for_size(path: Path, size: int, timeout: float = 20) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and path.stat().st_size >= size):
        assert time.monotonic() < deadline, f"{path} never reached {size} bytes"
        threading.Event().wait(0.05)


def test_record_stops_cleanly_into_a_complete_private_file(
    live_arm: None, zsession: zenoh.Session, router_endpoint: str, tmp_path: Path
) -> None:
    out = tmp_path / "session.mcap"
    raw = raw_collector(zsession, "body/*/*/*/raw")
    rec = start_recorder(router_endpoint, out)
    raw.wait_for(lambda s: len(s) >= 300)  # about a second of the arm
    wait_for_size(out, 2000)
    rec.send_signal(signal.SIGINT)
    assert rec.wait(timeout=20) == 0
    assert out.stat().st_mode & 0o777 == 0o600
    samples = list(read_raw(out))
    assert len(samples) > 100
    assert {topic for topic, _, _ in samples} == {
        "body/arm/left/shoulder/raw",
        "body/arm/left/elbow/raw",
        "body/arm/left/wrist/raw",
    }


def test_rotation_by_time(live_arm: None, router_endpoint: str, tmp_path: Path) -> None:
    out = tmp_path / "rot.mcap"
    rec = start_recorder(router_endpoint, out, "--rotate-s", "0.5")
    wait_for_size(tmp_path / "rot-002.mcap", 1)
    rec.send_signal(signal.SIGINT)
    assert rec.wait(timeout=20) == 0
    assert len(list(read_raw(out))) > 0
    assert len(list(read_raw(tmp_path / "rot-001.mcap"))) > 0


def test_a_recording_never_empties_an_earlier_one(
    live_arm: None, router_endpoint: str, tmp_path: Path
) -> None:
    """``record -o`` a name taken (run twice, a recorder service started again):
    the earlier files are kept whole; it goes on at the next free name."""
    out = tmp_path / "rec.mcap"
    earlier = {out: b"an earlier recording\n", tmp_path / "rec-001.mcap": b"its next file\n"}
    for path, data in earlier.items():
        path.write_bytes(data)
    rec = start_recorder(router_endpoint, out, "--rotate-s", "0.5")
    wait_for_size(tmp_path / "rec-003.mcap", 1)  # rotated past the taken names too
    rec.send_signal(signal.SIGINT)
    _, err = rec.communicate(timeout=20)
    assert rec.returncode == 0, err
    assert {path: path.read_bytes() for path in earlier} == earlier
    assert f"{out} exists (kept); recording to {tmp_path / 'rec-002.mcap'}" in err
    assert len(list(read_raw(tmp_path / "rec-002.mcap"))) > 0


def processed_arm(tmp_path: Path, data_dir: Path) -> Path:
    """The golden SmartSuit arm capture through ``bodynet process``: 400 raw samples
    with their poses and transforms."""
    mcap = tmp_path / "arm.mcap"
    subprocess.run([str(BODYNET), "process", str(data_dir / "smartsuit_arm.log"), "-o", str(mcap)],
                   check=True, capture_output=True, timeout=60)  # fmt: skip
    return mcap


def test_replay_republishes_a_recording(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path, data_dir: Path
) -> None:
    mcap = processed_arm(tmp_path, data_dir)
    raw = raw_collector(zsession, "body/*/*/*/raw")
    result = subprocess.run([str(BODYNET), "replay", str(mcap), "--speed", "4", "-q",
                             "-e", router_endpoint], capture_output=True, text=True, timeout=60,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "400 samples published" in result.stderr
    seen = raw.wait_for(lambda s: len(s) >= 400)
    assert len(seen) == 400
    assert seen[0][1].reading == next(read_raw(mcap))[2].reading


def test_replay_bar_counts_what_it_replays_and_keys_choose_topics(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path, data_dir: Path
) -> None:
    mcap = processed_arm(tmp_path, data_dir)
    assert count_messages(mcap) > 400  # poses and transforms beside the 400 raw samples
    # every raw sample: the bar ends at its total (not at 400 of every message in the file)
    raw = raw_collector(zsession, "body/*/*/*/raw")
    result = subprocess.run([str(BODYNET), "replay", str(mcap), "--speed", "8", "-e",
                             router_endpoint], capture_output=True, text=True, timeout=60,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "400/400" in result.stderr, result.stderr  # not 400/1100
    assert len(raw.wait_for(lambda s: len(s) >= 400)) == 400
    raw.close()
    # key expressions: one exact topic and a wildcard one, received over Zenoh
    raw = raw_collector(zsession, "body/**")
    result = subprocess.run([str(BODYNET), "replay", str(mcap), "--speed", "8", "-e",
                             router_endpoint, "--keys", "body/trunk/mid/head/raw",
                             "body/*/left/elbow/**"], capture_output=True, text=True,
                            timeout=60, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "200/200" in result.stderr, result.stderr
    assert "200 samples published" in result.stderr
    raw.wait_for(lambda s: len(s) >= 200)
    threading.Event().wait(0.5)  # nothing else comes
    seen = raw.wait_for(lambda s: raw.queue.empty())
    assert len(seen) == 200
    assert {k for k, _ in seen} == {"body/trunk/mid/head/raw", "body/arm/left/elbow/raw"}
    elbow = [s for t, _, s in read_raw(mcap) if t == "body/arm/left/elbow/raw"]
    assert [s.seq for k, s in seen if k == "body/arm/left/elbow/raw"] == [s.seq for s in elbow]
    raw.close()
    # a key expression Zenoh does not take: a message, no traceback
    result = subprocess.run([str(BODYNET), "replay", str(mcap), "-q", "-e", router_endpoint,
                             "--keys", "body//raw"], capture_output=True, text=True, timeout=60,
                            check=False)  # fmt: skip
    assert result.returncode == 2
    assert "argument --keys: 'body//raw': a key expression has no empty chunk" in result.stderr
    assert "Traceback" not in result.stderr


def test_a_key_expression_zenoh_refuses_is_told_whole_without_zenohs_source() -> None:
    """replay's filter (its Python API: `--keys` is checked by argparse first) says
    Zenoh's refusal through the session's one-line rule: a key with " at " in it is
    quoted whole (a split at " at " cut it), and no Rust file of Zenoh's is named."""
    from bodynet.clients.replay import topic_filter

    with pytest.raises(ValueError, match="is not a key expression") as refused:
        topic_filter(["body/sat at home//raw"])
    said = str(refused.value)
    assert "Invalid Key Expr `body/sat at home//raw`: empty chunks are forbidden" in said
    assert ".rs:" not in said


# -- what MCAP cannot store is refused, the file goes on --------------------------


def _raw(seq: int, t_ns: int) -> RawSample:
    return RawSample(OleAccel(2, 1000 + seq, (1, 2, 3)), seq, t_ns, Source.CAN)


@pytest.mark.parametrize("flags", [256, -1])
def test_replay_refuses_a_raw_sample_whose_flags_are_not_a_byte(
    flags: int, router_endpoint: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording's raw sample with ``flags`` the message's one byte cannot hold:
    replay says which recording and why, exit 2 (it was a ValueError of the
    encoder, a traceback, after the samples before it went out)."""
    from mcap.writer import Writer

    from bodynet.clients.mcap_store import RAW_SCHEMA, raw_json

    path = tmp_path / "flags.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema(str(RAW_SCHEMA["title"]), "jsonschema",
                                        json.dumps(RAW_SCHEMA).encode())  # fmt: skip
        channel = writer.register_channel("body/arm/left/elbow/raw", "json", schema)
        for i in range(3):
            t_ns = 1_700_000_000_000_000_000 + i * 10_000_000
            message = raw_json(_raw(i, t_ns)) | ({"flags": flags} if i == 2 else {})
            writer.add_message(channel, t_ns, json.dumps(message).encode(), t_ns)
        writer.finish()
    assert main(["replay", str(path), "-q", "-e", router_endpoint]) == 2
    err = capsys.readouterr().err
    said = f"{path}: body/arm/left/elbow/raw: not a raw-sample message: flags {flags} is not a"
    assert f"bodynet replay: {said} byte (0 to 255)\n" in err
    assert "Traceback" not in err


def test_sink_refuses_times_mcap_cannot_hold_before_writing(tmp_path: Path) -> None:
    out = tmp_path / "times.mcap"
    sink = McapSink(out)
    topic = "body/arm/left/elbow/raw"
    frame = pose.PoseFrame(1, 0, {"left_elbow_flexion_deg": 1.0}, {}, {}, {})
    for bad, reason in [(-1, Reason.OUT_OF_RANGE), (-(2**63), Reason.OUT_OF_RANGE),
                        (2**64, Reason.OUT_OF_RANGE), (1.5e18, Reason.GARBAGE)]:  # fmt: skip
        with pytest.raises(DecodeError) as err:
            sink.write_raw(topic, _raw(0, 0), bad)  # type: ignore[arg-type]
        assert err.value.reason is reason
        with pytest.raises(DecodeError):
            sink.write_pose(keys.pose_key(), frame, bad)  # type: ignore[arg-type]
        with pytest.raises(DecodeError):
            sink.write_health(keys.health_key("x"), b"{}", bad)  # type: ignore[arg-type]
    for t in (0, 2**63 - 1, MAX_TIME_NS):  # the edges MCAP holds
        sink.write_raw(topic, _raw(0, 0), t)
        sink.write_pose(keys.pose_key(), frame, t)
    sink.close()
    assert sink.messages == 9  # raw, pose and its transforms, three times
    assert [t for _, t, _ in read_raw(out)] == [0, 2**63 - 1, MAX_TIME_NS]
    assert [t for t, _ in read_poses(out)] == [0, 2**63 - 1, MAX_TIME_NS]
    assert count_messages(out) == 9


def _wait(done: Callable[[], bool], timeout: float = 20) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, "timed out"
        threading.Event().wait(0.02)


def _subscribed(recorder: Recorder, probe: Callable[[int], None]) -> int:
    """``probe(n)`` until the recorder has one more message (its subscriptions
    reach the router); how many messages it holds once the probes in flight are in."""
    before, n = recorder.messages, 0
    while recorder.messages == before:
        probe(n)
        n += 1
        assert n < 400, "the recorder never got a probe"
        threading.Event().wait(0.05)
    threading.Event().wait(0.3)
    return recorder.messages


def _burst(source: zenoh.Session, key: str, n: int, t0: int) -> None:
    """``n`` raw samples on ``key`` back to back, as a node bridge sends them
    (congestion control BLOCK: held back, never dropped)."""
    pub = source.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    for seq in range(n):
        pub.put(raw_sample.encode(_raw(seq, t0 + seq)))
    pub.undeclare()


def test_recorder_keeps_a_burst_whole_and_writes_its_backlog_at_close(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path
) -> None:
    """A burst far deeper than a plain callback's queue, held up behind a busy
    writer, is in the file whole when the recorder closes: nothing dropped on
    the way in, nothing left in its FIFOs at close."""
    out = tmp_path / "burst.mcap"
    recorder = Recorder(zsession, out, DEFAULT_KEYS)
    source = client(router_endpoint)
    wrist, elbow = keys.raw_key("arm", "left", "wrist"), keys.raw_key("arm", "left", "elbow")
    # a second subscriber in the recorder's session: it gets each sample when the
    # recorder's FIFO does
    seen = zsession.declare_subscriber(elbow, zenoh.handlers.FifoChannel(1 << 15))
    t0, n, got = 1_700_000_000_000_000_000, 5000, [0]

    def all_seen() -> bool:
        while seen.try_recv() is not None:
            got[0] += 1
        return got[0] >= n

    closing = threading.Thread(target=recorder.close)
    try:
        probes = _subscribed(
            recorder, lambda k: source.put(wrist, raw_sample.encode(_raw(k, t0 + k)))
        )
        with recorder._lock:  # the writer busy: the burst waits in the FIFO
            _burst(source, elbow, n, t0)
            _wait(all_seen)
            closing.start()  # close while the whole burst is still to write
            threading.Event().wait(0.2)
        closing.join(timeout=30)
        assert not closing.is_alive()
    finally:
        seen.undeclare()
        source.close()
    assert [s.seq for k, _, s in read_raw(out) if k == elbow] == list(range(n))
    assert read_gaps(out) == []
    assert count_messages(out) >= probes + n


def test_recorder_refuses_what_mcap_cannot_store_and_closes_complete(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path
) -> None:
    out = tmp_path / "odd.mcap"
    recorder = Recorder(zsession, out, [*DEFAULT_KEYS, keys.all_truth()])
    source = client(router_endpoint)
    elbow = keys.raw_key("arm", "left", "elbow")
    truth = LEFT_ARM.key + "/elbow/" + keys.Stream.TRUTH
    probe_key = LEFT_ARM.key + "/wrist/" + keys.Stream.TRUTH
    t0 = 1_700_000_000_000_000_000
    try:
        # on the subscription declared last (the truth): the router has the others by then
        probes = _subscribed(
            recorder, lambda n: source.put(probe_key, f'{{"t_ns": {t0 + n}, "angles_deg": {{}}}}')
        )
        raw_times = [t0, -1, t0 + 2, -(2**63), t0 + 4, 2**63 - 1]
        for seq, t in enumerate(raw_times):
            source.put(elbow, raw_sample.encode(_raw(seq, t)))
        pose_times = [t0, -5, MAX_TIME_NS]
        for seq, t in enumerate(pose_times):
            frame = pose.PoseFrame(seq, t, {"left_elbow_flexion_deg": 1.0}, {}, {}, {})
            source.put(keys.pose_key(LEFT_ARM), pose.encode(frame))
        for t in ("1", str(2**64), "-1", "Infinity"):
            source.put(truth, f'{{"t_ns": {t}, "angles_deg": {{"a": 1.0}}}}')
        # stored: 4 raw, 2 poses, 1 truth and 3 gap records (the refused raw and pose
        # seq); refused: 2 raw, 1 pose, 2 truth out of range, 1 truth garbage
        # at least: a probe still in flight may come too (they are counted in the file)
        _wait(lambda: recorder.messages + sum(recorder.rejected.values()) >= probes + 16)
        source.put(elbow, raw_sample.encode(_raw(6, t0 + 6)))  # and the recording goes on
        _wait(lambda: recorder.messages >= probes + 11)
    finally:
        source.close()
        recorder.close()  # the writer was never handed what it cannot store: this completes
    assert recorder.rejected == {Reason.OUT_OF_RANGE: 5, Reason.GARBAGE: 1}
    probes = sum(1 for k, _, _ in read_truth(out) if k == probe_key)
    assert count_messages(out) == probes + 11
    # in log-time order
    assert [t for k, t, _ in read_raw(out) if k == elbow] == [t0, t0 + 2, t0 + 4, t0 + 6,
                                                              2**63 - 1]  # fmt: skip
    assert [t for t, _ in read_poses(out, keys.pose_key(LEFT_ARM))] == [t0, MAX_TIME_NS]
    assert [t for k, t, _ in read_truth(out) if k == truth] == [1]
    # what was refused shows as missing sequence numbers, at times the file holds
    gaps = [(g.after_seq, g.missing) for g in read_gaps(out) if g.topic == elbow]
    assert gaps == [(0, 1), (2, 1)]
    # the recorder counts them; the records themselves are only in the file
    assert (recorder.gaps, recorder.missing) == (3, 3) == (len(read_gaps(out)), 3)


def test_recorder_fixes_the_mmap_threshold_for_the_writers_buffers(
    zsession: zenoh.Session, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A recorder keeps the writer's per-chunk buffers off the heap (see
    ``mcap_store.keep_large_buffers_off_heap``), where the C library allows it."""
    from bodynet.clients import mcap_store
    from bodynet.clients import recorder as recorder_module

    calls: list[bool] = []
    monkeypatch.setattr(recorder_module, "keep_large_buffers_off_heap",
                        lambda: calls.append(True) or True)  # fmt: skip
    Recorder(zsession, tmp_path / "a.mcap").close()
    assert calls == [True]
    glibc = sys.platform == "linux" and platform.libc_ver()[0] == "glibc"
    assert mcap_store.keep_large_buffers_off_heap() is glibc
    assert mcap_store.keep_large_buffers_off_heap() is glibc  # again: the same, once


# -- salvage: only of MCAP recordings; nothing left behind --------------------------


def _record(cmdline: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        code = main(["record", *cmdline])
    except SystemExit as exc:  # argparse's refusal of an argument, where it enters
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


def test_salvage_refuses_what_is_not_a_recording_and_leaves_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "src"
    src.mkdir()
    (src / "random.mcap").write_bytes(os.urandom(4096))
    (src / "notes.mcap").write_text("not a recording\n" * 100)
    (src / "empty.mcap").write_bytes(b"")
    (src / "short.mcap").write_bytes(b"\x89MCA")
    (src / "folder.mcap").mkdir()
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "fixed.mcap"
    cases = [
        ("random.mcap", "not an MCAP recording"),
        ("notes.mcap", "not an MCAP recording"),
        ("empty.mcap", "ends before its MCAP header (0 bytes): nothing to salvage"),
        ("short.mcap", "ends before its MCAP header (4 bytes)"),
        ("missing.mcap", "argument --salvage: cannot read"),  # refused at parse
        ("folder.mcap", "argument --salvage: cannot read"),
    ]
    for name, message in cases:
        code, err = _record(["--salvage", str(src / name), "-o", str(out)], capsys)
        assert code == 2, (name, err)
        assert err.startswith("bodynet record: ") or "bodynet record: error: " in err, err
        assert message in err, (name, err)
        assert list(out_dir.iterdir()) == [], name  # no fixed.mcap, no fixed.mcap.part
    # an -o where nothing can be written: a message, and nothing either
    good = tmp_path / "good.mcap"
    sink = McapSink(good)
    sink.write_raw("body/arm/left/elbow/raw", _raw(0, 1), 1)
    sink.close()
    code, err = _record(["--salvage", str(good), "-o", str(tmp_path / "no" / "x.mcap")], capsys)
    assert code == 2
    assert "does not exist" in err
    assert not (tmp_path / "no").exists()
    # an earlier file of that name stays as it was
    out.write_text("an earlier file\n")
    assert _record(["--salvage", str(src / "notes.mcap"), "-o", str(out)], capsys)[0] == 2
    assert out.read_text() == "an earlier file\n"
    assert sorted(p.name for p in out_dir.iterdir()) == ["fixed.mcap"]
    # as a user runs it
    result = subprocess.run([str(BODYNET), "record", "--salvage", str(src / "random.mcap"), "-o",
                             str(out_dir / "other.mcap")], capture_output=True, text=True,
                            timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2
    assert "not an MCAP recording" in result.stderr
    assert "Traceback" not in result.stderr
    assert sorted(p.name for p in out_dir.iterdir()) == ["fixed.mcap"]


def test_salvage_keeps_a_cut_recording_up_to_its_last_chunk(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    whole = tmp_path / "whole.mcap"
    sink = McapSink(whole, chunk_size=4096)
    for seq in range(3000):
        sink.write_raw("body/arm/left/elbow/raw", _raw(seq, 1000 + seq), 1000 + seq)
    sink.close()
    size = whole.stat().st_size // 2
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[:size])
    with whole.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    # the messages of the chunks that end before the cut (log times 1000 + seq)
    kept = sum(c.message_end_time - c.message_start_time + 1 for c in summary.chunk_indexes
               if c.chunk_start_offset + c.chunk_length <= size)  # fmt: skip
    assert 1000 < kept < 2000
    fixed = tmp_path / "fixed.mcap"
    code, err = _record(["--salvage", str(cut), "-o", str(fixed)], capsys)
    assert code == 0, err
    seqs = [s.seq for _, _, s in read_raw(fixed)]
    assert seqs == list(range(kept))  # every message of the complete chunks, in order
    assert f"{len(seqs)} messages salvaged" in err
    assert fixed.stat().st_mode & 0o777 == 0o600
    # a complete file salvages to itself, one channel and schema as before
    again = tmp_path / "again.mcap"
    assert salvage(whole, again) == 3000
    with again.open("rb") as f:
        copy = make_reader(f).get_summary()
    assert copy is not None
    assert len(copy.channels) == len(summary.channels) == 1
    assert sorted(s.name for s in copy.schemas.values()) == sorted(
        s.name for s in summary.schemas.values()
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.mcap", "cut.mcap", "fixed.mcap",
                                                          "whole.mcap"]  # fmt: skip


# -- topology and health --------------------------------------------------------------


def _schemas(path: Path) -> dict[str, dict[str, object]]:
    """topic -> the JSON Schema of its channel, as a generic tool finds it (the
    Foxglove transforms are protobuf, see ``test_recorder_writes``)."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = {}
    for ch in summary.channels.values():
        schema = summary.schemas[ch.schema_id]
        if ch.topic == keys.TRANSFORMS:
            assert (schema.name, schema.encoding, ch.message_encoding) == (
                "foxglove.FrameTransforms", "protobuf", "protobuf")  # fmt: skip
            continue
        assert (schema.encoding, ch.message_encoding) == ("jsonschema", "json")
        out[ch.topic] = json.loads(schema.data)
    return out


def test_record_keeps_topology_and_health_by_default(
    live_arm: None,
    gateway: Gateway,
    zsession: zenoh.Session,
    router_endpoint: str,
    tmp_path: Path,
) -> None:
    """The left arm through its CAN bridge, a gateway, and `bodynet record` with no
    keys: raw samples, poses, the topology and every health, each readable with
    the schema its channel names."""
    out = tmp_path / "all.mcap"
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    poses.wait_for(lambda s: len(s) >= 10, timeout=20)  # the gateway has its topology
    health = Collector(zsession, keys.all_health(), json.loads)
    rec = start_recorder(router_endpoint, out)
    wait_for_size(out, 1)
    mark = time.time_ns() + 500_000_000  # the recorder subscribes as it creates its file

    def rounds(seen: list[tuple[str, dict[str, int]]], source: str) -> int:
        return sum(k == keys.health_key(source) and m["t_ns"] > mark for k, m in seen)

    # two rounds of health after the recorder came (each source: every second)
    health.wait_for(lambda s: rounds(s, "gateway") >= 2 and rounds(s, "rec-test") >= 2,
                    timeout=20)  # fmt: skip
    rec.send_signal(signal.SIGINT)
    assert rec.wait(timeout=20) == 0
    topology = list(read_topology(out))
    assert topology, "no topology recorded"
    assert [t for t, _, _ in topology] == [keys.TOPOLOGY] * len(topology)
    _, log_time, first = topology[0]
    assert log_time == first["t_ns"]
    nodes = first["branches"]["left-arm"]["nodes"]
    assert {k: v["state"] for k, v in nodes.items()} == {
        f"body/arm/left/{site}/raw": "alive" for site in ("shoulder", "elbow", "wrist")
    }
    healths = list(read_health(out))
    assert {t for t, _, _ in healths} == {keys.health_key("gateway"), keys.health_key("rec-test")}
    assert all(t == m["t_ns"] for _, t, m in healths)
    bridge = [m for t, _, m in healths if t == keys.health_key("rec-test")][-1]
    assert bridge["source"] == "rec-test"
    assert {n["key"] for n in bridge["nodes"].values()} == set(nodes)
    assert any(m.get("ticks", 0) > 0 for t, _, m in healths if t == keys.health_key("gateway"))
    # every message valid against its channel's schema (what Foxglove and co. go by)
    schemas = _schemas(out)
    assert schemas[keys.TOPOLOGY]["title"] == "bodynet.Topology"
    assert schemas[keys.health_key("gateway")]["title"] == "bodynet.Health"
    for topic, _, message in [*topology, *healths]:
        jsonschema.validate(message, schemas[topic])
    # the other readers see what they saw before
    assert {t for t, _, _ in read_raw(out)} == set(nodes)
    assert sum(1 for _ in read_poses(out)) > 0
    assert list(read_truth(out)) == []


def test_recorder_refuses_admin_messages_that_are_not_json_objects(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path
) -> None:
    """Health and topology, a subject's too; what is not a JSON object on those
    keys is counted (garbage), never stored, and never taken for a raw sample."""
    source = client(router_endpoint)
    topo = {"t_ns": 1_700_000_000_000_000_000, "branches": {}}
    alice_topology = "alice/" + keys.TOPOLOGY
    queryable = source.declare_queryable(
        alice_topology, lambda q: q.reply(alice_topology, json.dumps(topo).encode())
    )
    _wait(lambda: any(r.ok for r in zsession.get(alice_topology, timeout=1)))  # it is in place
    out = tmp_path / "admin.mcap"
    recorder = Recorder(zsession, out, [*DEFAULT_KEYS, keys.ANY_SUBJECT + "/" + keys.TOPOLOGY,
                                        keys.ANY_SUBJECT + "/" + keys.all_health()])  # fmt: skip
    try:
        _wait(lambda: recorder.messages == 1)  # the subject's topology, asked for at the start
        # on the subscription declared last: the router has the others by then
        probe_key = "alice/" + keys.health_key("probe")
        probe = json.dumps({"source": "probe"}).encode()
        base = _subscribed(recorder, lambda n: source.put(probe_key, probe))
        good = {"source": "pose", "t_ns": 5, "nodes": {}}
        bad = [b"not json", b"[1, 2]", b'"text"', b"\xff\xfe", b'{"t_ns": NaN}',
               b'{"t_ns": "soon"}', b'{"t_ns": -1}', b"[" * 100_000]  # fmt: skip
        # BLOCK: a 100 kB message goes in fragments, which Zenoh's default congestion
        # control may drop on a busy machine
        put = partial(source.put, congestion_control=zenoh.CongestionControl.BLOCK)
        for data in bad:
            put(keys.TOPOLOGY, data)
        # a bridge named "pose": its health is health, not a pose
        put(keys.health_key("pose"), json.dumps(good))
        put("alice/" + keys.health_key("x"), json.dumps({"source": "x"}))
        put(keys.health_key("y"), b"[]")
        put(keys.TOPOLOGY, json.dumps({"branches": {}}))  # no t_ns: when it came
        # at least: a probe still in flight may come too (each is counted below)
        _wait(lambda: recorder.messages + sum(recorder.rejected.values()) >= base + 3 + len(bad)
              + 1)  # fmt: skip
    finally:
        queryable.undeclare()
        source.close()
        recorder.close()
    assert recorder.rejected == {Reason.GARBAGE: len(bad), Reason.OUT_OF_RANGE: 1}
    got = {(t, json.dumps(m, sort_keys=True)) for t, _, m in read_topology(out)}
    assert got == {(alice_topology, json.dumps(topo, sort_keys=True)),
                   (keys.TOPOLOGY, json.dumps({"branches": {}}))}  # fmt: skip
    [(_, received, _)] = [m for m in read_topology(out) if m[0] == keys.TOPOLOGY]
    assert abs(received - time.time_ns()) < 60e9
    assert [(t, lt) for t, lt, _ in read_health(out) if t == keys.health_key("pose")] == [
        (keys.health_key("pose"), 5)
    ]
    topics = {keys.health_key("pose"), probe_key, "alice/" + keys.health_key("x")}
    assert {t for t, _, _ in read_health(out)} == topics
    assert list(read_raw(out)) == []
    assert _schemas(out)[keys.health_key("pose")]["title"] == "bodynet.Health"


def _file_times(path: Path) -> list[tuple[str, int, int, bytes]]:
    """(topic, log_time, publish_time, data) of every message, in file order, as
    the mcap library reads them (not bodynet's readers)."""
    with path.open("rb") as f:
        return [(c.topic, m.log_time, m.publish_time, m.data)
                for _, c, m in make_reader(f).iter_messages(log_time_order=False)]  # fmt: skip


def _source_time(topic: str, data: bytes) -> int | None:
    """The ``t_ns`` a message carries (None: transforms, which carry theirs in protobuf)."""
    if topic == keys.TRANSFORMS:
        return None
    if topic.endswith(f"/{keys.POSE}"):
        return pose.decode(data).t_ns
    d = json.loads(data)  # raw samples, topology, health, gaps
    t_ns = d.get("to_t_ns") if topic == GAPS_TOPIC else d.get("t_ns")
    return None if t_ns is None else int(t_ns)


def _check_times(path: Path) -> list[tuple[str, int, int, bytes]]:
    """Log times never go back in file order (``mcap doctor --strict-message-order``)
    and each message's publish time is the source time it carries."""
    messages = _file_times(path)
    assert messages
    logs = [log_time for _, log_time, _, _ in messages]
    back = [(a, b) for a, b in itertools.pairwise(logs) if b < a]
    assert not back, f"{len(back)} log times go back in file order, first {back[0]}"
    for topic, _, publish_time, data in messages:
        t_ns = _source_time(topic, data)
        assert t_ns is None or publish_time == t_ns, (topic, publish_time, t_ns)
    return messages


def test_a_live_recording_logs_when_messages_came_and_publishes_their_source_time(
    live_arm: None, gateway: Gateway, zsession: zenoh.Session, tmp_path: Path
) -> None:
    """Raw samples, poses, transforms, topology and health of several sources in one
    file: log_time the recorder's receive time, in file order; publish_time each
    message's t_ns; on one host a message is never logged before it was made."""
    out = tmp_path / "times.mcap"
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    poses.wait_for(lambda s: len(s) >= 10, timeout=20)
    recorder = Recorder(zsession, out, DEFAULT_KEYS)
    _wait(lambda: recorder.messages >= 1500, timeout=30)
    recorder.close()
    messages = _check_times(out)
    topics = {topic for topic, _, _, _ in messages}
    assert {keys.pose_key(), keys.TRANSFORMS, "body/arm/left/elbow/raw"} <= topics
    assert any(t.startswith("body/@health/") for t in topics)
    lag = [log_time - publish_time for _, log_time, publish_time, _ in messages]
    assert min(lag) >= -1_000_000, f"a message logged {-min(lag)} ns before it was made"
    # bodynet's readers: source times (not when they came), poses in source-time order
    times = [t for t, _ in read_poses(out)]
    assert times == sorted(times)
    assert all(t == frame.t_ns for t, frame in read_poses(out))
    assert all(t == s.t_ns for _, t, s in read_raw(out))


def test_a_processed_capture_logs_in_file_order(tmp_path: Path, data_dir: Path) -> None:
    """``bodynet process``: no receive time, log times still never go back in file
    order (its transforms come after later raw samples); publish_time the t_ns."""
    mcap = processed_arm(tmp_path, data_dir)
    messages = _check_times(mcap)
    assert any(topic == keys.TRANSFORMS for topic, _, _, _ in messages)


def _pose_bytes(seq: int, t_ns: int) -> bytes:
    frame = pose.PoseFrame(seq=seq, t_ns=t_ns, segments={}, joints_m={}, angles_deg={"x": seq},
                           rel_deg={}, flags={})  # fmt: skip
    return pose.encode(frame)


@pytest.mark.parametrize("held", [32 << 20, 0])  # sorted in memory; read twice
def test_readers_give_source_times_of_old_and_new_recordings_alike(
    tmp_path: Path, held: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same poses and raw samples, written as bodynet wrote them before
    (log_time == publish_time == t_ns, file order not time order) and as it does now
    (log_time when they came, publish_time the t_ns): bodynet's readers give the
    same source times, in source-time order, from both."""
    from mcap.writer import Writer

    from bodynet.clients import mcap_store
    from bodynet.clients.mcap_store import POSE_SCHEMA, RAW_SCHEMA, raw_json

    monkeypatch.setattr(mcap_store, "SORT_IN_MEMORY_BYTES", held)
    t0 = 1_700_000_000_000_000_000
    # as they came: a source 2 s behind, another on time, poses in between
    came = []
    for i in range(30):
        came.append(("raw", "body/arm/left/elbow/raw", t0 + i * 10_000_000))
        came.append(("raw", "body/arm/right/elbow/raw", t0 - 2_000_000_000 + i * 10_000_000))
        came.append(("pose", keys.pose_key(), t0 + i * 10_000_000 - (5_000_000 if i % 3 else 0)))
    files = {}
    for style in ("old", "new"):
        path = files[style] = tmp_path / f"{style}.mcap"
        with path.open("wb") as f:
            writer = Writer(f)
            writer.start()
            schemas = {k: writer.register_schema(str(s["title"]), "jsonschema",
                                                 json.dumps(s).encode())
                       for k, s in (("raw", RAW_SCHEMA), ("pose", POSE_SCHEMA))}  # fmt: skip
            channels: dict[str, int] = {}
            for i, (kind, topic, t_ns) in enumerate(came):
                if topic not in channels:
                    channels[topic] = writer.register_channel(topic, "json", schemas[kind])
                data = (_pose_bytes(i, t_ns) if kind == "pose"
                        else json.dumps(raw_json(_raw(i, t_ns))).encode())  # fmt: skip
                log_time = t_ns if style == "old" else t0 + 1_000_000_000 + i * 1000
                writer.add_message(channels[topic], log_time, data, t_ns)
            writer.finish()
    poses = {style: [(t, f.seq, f.t_ns) for t, f in read_poses(p)] for style, p in files.items()}
    raws = {style: [(k, t, s.seq) for k, t, s in read_raw(p)] for style, p in files.items()}
    assert poses["new"] == poses["old"]
    assert raws["new"] == raws["old"]
    assert [t for t, _, _ in poses["new"]] == sorted(t for k, _, t in came if k == "pose")
    assert all(t == t_ns for t, _, t_ns in poses["new"])
    assert [t for _, t, _ in raws["new"]] == sorted(t for k, _, t in came if k == "raw")


def test_record_warns_once_when_its_keys_match_no_admin_key(
    router_endpoint: str, tmp_path: Path
) -> None:
    """``record 'body/**'``: Zenoh's wildcards never match ``@`` chunks, so topology,
    health and metrics are left out; told once at the start (and in ``--help``), not
    when an admin key is named too, nor with the default keys."""
    warning = "match no admin key"
    told = {}
    for name, extra in {"wild": ["body/**"], "named": ["body/**", "body/@topology"],
                        "default": []}.items():  # fmt: skip
        out = tmp_path / f"{name}.mcap"
        rec = start_recorder(router_endpoint, out, *extra)
        _wait(out.exists)  # recording: the warning comes before
        rec.send_signal(signal.SIGINT)
        _, err = rec.communicate(timeout=20)
        assert rec.returncode == 0, err
        told[name] = err.count(warning)
    assert told == {"wild": 1, "named": 0, "default": 0}
    helped = subprocess.run([str(BODYNET), "record", "--help"], capture_output=True,
                            text=True, check=True, timeout=30)  # fmt: skip
    assert "leaves out topology, health and metrics" in " ".join(helped.stdout.split())
