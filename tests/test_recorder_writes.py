"""What the recorder writes of a pose, and how cheaply: the mcap library's
records through a leaner way in (byte for byte the library's file), a pose
stored as it came with only its header and segments read (``pose.glance``),
and its Foxglove transforms made for many poses in one array pass, as
protobuf messages that Foxglove's own schema classes and the mcap protobuf
decoder read."""

from __future__ import annotations

import io
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import pytest
from export_recordings import tf_message
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from google.protobuf import descriptor_pb2
from hypothesis import given
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from bodynet.clients import foxglove_pb
from bodynet.clients.body_tree import Transforms, local_poses, segment_parents
from bodynet.clients.mcap_store import TF_MIN_GAP_NS, McapSink, read_poses
from bodynet.clients.mcap_writer import LeanWriter
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError

TF = keys.TRANSFORMS


def _write(cls: type[Writer], lean: bool = True) -> bytes:
    """One sequence of calls: chunks that close inside a batch, a flush, two
    schemas, three channels, times out of order."""
    out = io.BytesIO()
    writer = cls(out, chunk_size=4096, compression=CompressionType.ZSTD)
    if not lean:
        writer.lean = False  # type: ignore[attr-defined]
    writer.start(profile="", library="test")
    a = writer.register_schema("a", "jsonschema", b"{}")
    b = writer.register_schema("b", "jsonschema", b'{"type": "object"}')
    one, two = writer.register_channel("one", "json", a), writer.register_channel("two", "json", b)
    rng = np.random.default_rng(3)
    for i in range(300):
        t = int(1_700_000_000_000_000_000 + rng.integers(0, 10**9))
        writer.add_message(one if i % 3 else two, t, bytes(rng.integers(0, 255, i % 97)), t)
        if i == 150:
            writer.flush()
        if i % 50 == 49:
            batch = [(t + k, b'{"k": %d}' % k * (k + 1), t + k) for k in range(40)]
            if isinstance(writer, LeanWriter):
                writer.add_messages(one, batch)
            else:
                for log_time, data, publish_time in batch:
                    writer.add_message(one, log_time, data, publish_time)
    three = writer.register_channel("three", "json", a)
    writer.add_message(three, 0, b"{}", 0)
    writer.finish()
    return out.getvalue()


def test_lean_writer_writes_what_the_library_writes() -> None:
    library = _write(Writer)
    assert LeanWriter(io.BytesIO()).lean  # this version of mcap: the lean way is taken
    assert _write(LeanWriter) == library
    assert _write(LeanWriter, lean=False) == library  # and the library's own way, if not
    reader = make_reader(io.BytesIO(library))
    assert sum(1 for _ in reader.iter_messages()) == 300 + 6 * 40 + 1


def test_lean_writer_compresses_at_its_level() -> None:
    """zstd level 1 chunks: the same messages read back, other chunk bytes than
    the library's level (so the level is applied)."""

    def write(level: int | None) -> bytes:
        out = io.BytesIO()
        writer = LeanWriter(out, chunk_size=4096, zstd_level=level)
        assert writer.leveled == (level is not None)
        writer.start()
        channel = writer.register_channel("one", "json", writer.register_schema("a", "", b""))
        for i in range(500):
            writer.add_message(channel, i, b'{"i": %d, "text": "%s"}' % (i, b"ab" * (i % 40)), i)
        writer.finish()
        return out.getvalue()

    def messages(data: bytes) -> list[tuple[int, bytes]]:
        return [(m.log_time, m.data) for _, _, m in make_reader(io.BytesIO(data)).iter_messages()]

    library, fast = write(None), write(1)
    assert fast != library
    assert messages(fast) == messages(library)
    assert len(messages(fast)) == 500


def test_lean_writer_refuses_a_time_before_writing_any_of_it() -> None:
    out = io.BytesIO()
    writer = LeanWriter(out)
    writer.start()
    channel = writer.register_channel("one", "json", writer.register_schema("a", "", b""))
    writer.add_message(channel, 5, b"{}", 5)
    with pytest.raises(Exception, match=r"format requires|argument out of range"):
        writer.add_message(channel, -1, b"{}", -1)
    writer.finish()
    assert [m.log_time for _, _, m in make_reader(io.BytesIO(out.getvalue())).iter_messages()] == [
        5
    ]


def _messages(path: Path, topic: str) -> list[tuple[int, bytes]]:
    """(source time, data) of the messages on ``topic``, in source-time order
    (``publish_time``; ``log_time`` is when they were written)."""
    with path.open("rb") as f:
        messages = [(m.publish_time, m.data)
                    for _, _, m in make_reader(f).iter_messages(topics=[topic])]  # fmt: skip
    return sorted(messages, key=lambda m: m[0])


def _foxglove_terms(path: Path) -> list[tuple[str, str, str, str]]:
    """Each channel's topic, message encoding, schema name and schema encoding."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted(
        (c.topic, c.message_encoding, summary.schemas[c.schema_id].name,
         summary.schemas[c.schema_id].encoding)
        for c in summary.channels.values()
    )  # fmt: skip


def test_poses_stored_as_they_came_with_the_same_transforms(
    body_mcap: Path, tmp_path: Path
) -> None:
    """The recorder's way (``write_pose_message``: the bytes as received, the
    transforms from their segments' text) gives the poses and the transforms
    `bodynet process` wrote from decoded frames, byte for byte, in the same
    channels, schemas and encodings (what Foxglove opens a file by)."""
    poses = [(t, d) for t, d in _messages(body_mcap, keys.pose_key()) if t > 0]  # 0: now
    out = tmp_path / "again.mcap"
    sink = McapSink(out)
    for t_ns, data in poses:
        seq, log_time = sink.write_pose_message(keys.pose_key(), data)
        frame = pose.decode(data)
        assert (seq, log_time) == (frame.seq, t_ns) == (frame.seq, frame.t_ns)
    sink.close()
    assert len(poses) > 2 * 64  # several batches of transforms
    assert _messages(out, keys.pose_key()) == poses
    assert _messages(out, TF) == [(t, d) for t, d in _messages(body_mcap, TF) if t > 0]
    assert [(c[0], *c[1:]) for c in _foxglove_terms(out)] == [
        c for c in _foxglove_terms(body_mcap) if c[0] in (keys.pose_key(), TF)
    ]
    assert [t for t, _ in read_poses(out)] == [t for t, _ in poses]


def test_a_pose_whose_quaternions_are_no_rotation_gets_no_transforms(
    body_mcap: Path, tmp_path: Path
) -> None:
    """A whole-body pose whose segments' quaternions are all zero (a hostile
    publisher's): stored as it came, with an empty transforms message, not
    transforms of NaN (the recorder normalised the zeros); the next poses'
    transforms are as ever. Read back with Foxglove's schema."""
    poses = [(t, d) for t, d in _messages(body_mcap, keys.pose_key()) if t > 0][:3]
    d = orjson.loads(poses[0][1])
    for seg in d["segments"].values():
        seg["q"] = [0.0, 0.0, 0.0, 0.0]
    zeroed = orjson.dumps(d)
    out = tmp_path / "zeroed.mcap"
    sink = McapSink(out)
    for data in [zeroed, *(data for _, data in poses[1:])]:
        sink.write_pose_message(keys.pose_key(), data)
    sink.close()
    tfs = _messages(out, TF)
    assert tfs[0] == (poses[0][0], foxglove_pb.NO_TRANSFORMS)
    first = FrameTransforms.FromString(tfs[0][1])
    assert len(first.transforms) == 0
    again = dict(_messages(body_mcap, TF))
    assert all(data == again[t] for t, data in tfs[1:])


def test_glance_reads_what_decode_reads(body_mcap: Path) -> None:
    messages = [data for _, data in _messages(body_mcap, keys.pose_key())][:100]
    texts = []
    for data in messages:
        head = pose.glance(data, segments=True)
        frame = pose.decode(data)
        assert head is not None
        assert (head.version, head.seq, head.t_ns) == (pose.VERSION, frame.seq, frame.t_ns)
        texts.append(head.segments)
        assert pose.glance(data) == pose.Glance(head.version, head.seq, head.t_ns)
        # the place of the segments given (or a wrong one): the same
        assert pose.glance(data, segments=True, hint=head.at) == head
        assert pose.glance(data, segments=True, hint=7) == head
    names, numbers = pose.segment_numbers(texts)
    rows = iter(np.asarray(numbers).reshape(-1, 7).tolist())
    for data, these in zip(messages, names, strict=True):
        segments = pose.decode(data).segments
        assert these is not None
        assert [n.decode() for n in these] == list(segments)
        for p, q in segments.values():
            assert next(rows) == [*p, *q]
    # another layout of the same message (a JSON library's spaces, keys in another
    # order): not read here (it is decoded whole)
    d = json.loads(messages[0])
    assert pose.glance(json.dumps(d).encode(), segments=True) is None
    assert pose.glance(orjson.dumps({"seq": d["seq"], **d}), segments=True) is None
    moved = dict(d)
    moved["segments"] = {s: {"q": v["q"], "p": v["p"]} for s, v in d["segments"].items()}
    head = pose.glance(orjson.dumps(moved), segments=True)
    assert head is not None
    assert pose.segment_numbers([head.segments])[0] == [None]


def test_glance_refuses_what_is_no_number() -> None:
    with pytest.raises(DecodeError):
        pose.glance(b'{"v":2,"seq":1,"t_ns":%d,"angles_deg":{}}' % 2**64)
    assert pose.segment_numbers([b'{"a":{"p":[1,2,"x"],"q":[1,0,0,0]}}']) == ([None], [])
    with pytest.raises(DecodeError):
        pose.segment_numbers([b'{"a":{"p":[1,2,x],"q":[1,0,0,0]}}'])
    with pytest.raises(DecodeError):
        pose.segment_numbers([b'{"a":{"p":[1,2],"q":[1,0,0,0]}}'])


@st.composite
def canonical_pose_like(draw: st.DrawFn) -> bytes:
    """A pose message as the gateway lays it out, with parts replaced by random JSON."""
    segments = {
        name: {"p": draw(st.lists(st.floats(-3, 3), min_size=3, max_size=3)),
               "q": draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4))}
        for name in draw(st.lists(st.sampled_from(["pelvis", "thorax", "head", "a\\b", "%s"]),
                                  max_size=4, unique=True))
    }  # fmt: skip
    d: dict[str, Any] = {"v": 2, "seq": draw(st.integers(0, 2**64 - 1)),
                         "t_ns": draw(st.integers(-5, 2**64 - 1)), "angles_deg": {},
                         "rel_deg": {}, "flags": {}, "segments": segments,
                         "joints_m": {}}  # fmt: skip
    odd = (st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.text(max_size=4)
           | st.just([1, 2]))  # fmt: skip
    for _ in range(draw(st.integers(0, 2))):
        if segments and draw(st.booleans()):
            name = draw(st.sampled_from(sorted(segments)))
            segments[name][draw(st.sampled_from(["p", "q"]))] = draw(odd)
        else:
            d[draw(st.sampled_from(["seq", "t_ns", "segments", "v"]))] = draw(odd)
    return orjson.dumps(d)


@given(canonical_pose_like())
def test_glance_agrees_with_decode_or_declines(data: bytes) -> None:
    try:
        head = pose.glance(data, segments=True)
    except DecodeError:
        return
    if head is None:
        return
    try:
        frame = pose.decode(data)
    except DecodeError:
        return  # stored as it came: glance does not check the rest
    assert (head.seq, head.t_ns) == (frame.seq, frame.t_ns)
    try:
        names, numbers = pose.segment_numbers([head.segments])
    except DecodeError:
        return
    if names[0] is not None:
        assert [n.decode() for n in names[0]] == list(frame.segments)
        assert numbers == [v for p, q in frame.segments.values() for v in (*p, *q)]


def test_transforms_are_the_rotation_algebra_of_scipy() -> None:
    """Each segment in its parent's frame: the quaternion algebra on arrays gives
    what scipy's rotations give (``local_poses``, which the exports use)."""
    parents = segment_parents()
    names = ["pelvis", *parents]
    rng = np.random.default_rng(5)
    n = 50
    p = rng.normal(0, 0.5, (n, len(names), 3))
    q = Rotation.random(n * len(names), random_state=6).as_quat(scalar_first=True)
    q = q.reshape(n, len(names), 4) * rng.uniform(0.9, 1.1, (n, len(names), 1))  # not unit
    values = np.concatenate([p, q], axis=2)
    times = [10**18 + k for k in range(n)]
    messages = Transforms(parents).messages(
        [(t, names, v) for t, v in zip(times, values, strict=True)]
    )
    index = {s: k for k, s in enumerate(names)}
    translations, rotations = local_poses(p, q, [index.get(parents.get(s, ""), -1) for s in names])
    turns = rotations.as_quat().reshape(n, len(names), 4)
    for k, message in enumerate(messages):
        transforms = tf_message(message)["transforms"]
        assert [t["child_frame_id"] for t in transforms] == names
        for s, t in enumerate(transforms):
            assert t["parent_frame_id"] == parents.get(names[s], "world")
            assert t["timestamp"] == {"sec": 1_000_000_000, "nsec": k}
            got_t = [t["translation"][a] for a in "xyz"]
            got_r = [t["rotation"][a] for a in "xyzw"]
            np.testing.assert_allclose(got_t, translations[k, s], atol=1e-7)
            np.testing.assert_allclose(got_r, turns[k, s], atol=1e-9)


def test_a_pose_not_laid_out_as_the_gateway_does_is_decoded(tmp_path: Path) -> None:
    """Another layout is decoded whole (and refused if it is no pose); a message
    that starts as a gateway pose is stored as it came, its transforms made from
    what of its segments reads (none: an empty transforms message)."""
    frame = pose.PoseFrame(4, 2_000, {}, {}, {"pelvis": ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))},
                           {})  # fmt: skip
    spaced = json.dumps(json.loads(pose.encode(frame))).encode()
    broken = pose.encode(frame).replace(b"[1.0,0.0,0.0,0.0]", b'[1.0,"x",0.0,0.0]')
    out = tmp_path / "odd.mcap"
    sink = McapSink(out, tf_min_gap_ns=0)  # each pose its transforms (the same time)
    assert sink.write_pose_message(keys.pose_key(), spaced) == (4, 2_000)
    with pytest.raises(DecodeError):
        sink.write_pose_message(keys.pose_key(), b'{"v": 2, "seq": 1}')
    assert sink.write_pose_message(keys.pose_key(), broken) == (4, 2_000)
    assert sink.write_pose_message(keys.pose_key(), pose.encode(frame)) == (4, 2_000)
    sink.close()
    assert [d for _, d in _messages(out, keys.pose_key())] == [spaced, broken, pose.encode(frame)]
    transforms = [tf_message(d)["transforms"] for _, d in _messages(out, TF)]
    assert [len(t) for t in transforms] == [1, 0, 1]
    assert transforms[0] == transforms[2]
    assert transforms[0][0]["translation"] == {"x": 0.0, "y": 0.0, "z": 1.0}


def _fields(descriptor: Any) -> list[tuple[str, int, int, str]]:
    return [(f.name, f.number, f.type, f.message_type.full_name if f.message_type else "")
            for f in descriptor.fields]  # fmt: skip


def test_transforms_schema_is_foxglove_s() -> None:
    """The hand-written descriptors define what Foxglove's own .proto files
    define (messages, fields, numbers, types), under Foxglove's schema name."""
    files = descriptor_pb2.FileDescriptorSet()
    files.ParseFromString(foxglove_pb.FRAME_TRANSFORMS_DESCRIPTOR)
    ours = {f"{file.package}.{m.name}": [(fd.name, fd.number, fd.type, fd.type_name.lstrip("."))
                                         for fd in m.field]
            for file in files.file for m in file.message_type}  # fmt: skip
    theirs = FrameTransforms.DESCRIPTOR
    frame = theirs.fields_by_name["transforms"].message_type
    want = {d.full_name: _fields(d) for d in (
        theirs, frame, frame.fields_by_name["translation"].message_type,
        frame.fields_by_name["rotation"].message_type,
        frame.fields_by_name["timestamp"].message_type)}  # fmt: skip
    assert ours == want
    assert theirs.full_name == foxglove_pb.SCHEMA_NAME


@given(st.integers(0, 2**64 - 1), st.lists(st.floats(-1e3, 1e3), min_size=7, max_size=7))
def test_a_transform_record_reads_back(t_ns: int, numbers: list[float]) -> None:
    stamp = foxglove_pb.timestamp(t_ns)
    record, stamp_at, at = foxglove_pb.transform_layout("world", "päd", len(stamp))
    data = bytearray(record)
    data[stamp_at : stamp_at + len(stamp)] = stamp
    for offset, value in zip(at, numbers, strict=True):
        data[offset : offset + 8] = np.float64(value).tobytes()
    (t,) = tf_message(bytes(data))["transforms"]
    assert t["timestamp"]["sec"] * 1_000_000_000 + t["timestamp"]["nsec"] == t_ns
    assert (t["parent_frame_id"], t["child_frame_id"]) == ("world", "päd")
    assert [*t["translation"].values(), *t["rotation"].values()] == numbers


def test_the_recording_s_transforms_decode_with_their_schema(body_mcap: Path) -> None:
    """A reader that knows only what the file says (its schema, its encoding)
    decodes every transforms message: the mcap protobuf decoder."""
    with body_mcap.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [(schema.encoding, channel.message_encoding, message.publish_time, proto)
                   for schema, channel, message, proto in reader.iter_decoded_messages(
                       topics=[TF])]  # fmt: skip
    assert len(decoded) > 100
    for schema_encoding, message_encoding, log_time, proto in decoded:
        assert (schema_encoding, message_encoding) == ("protobuf", "protobuf")
        assert type(proto).DESCRIPTOR.full_name == "foxglove.FrameTransforms"
        assert len(proto.transforms) == 15
        assert proto.transforms[0].parent_frame_id == "world"
        stamp = proto.transforms[0].timestamp
        if log_time:
            assert stamp.seconds * 1_000_000_000 + stamp.nanos == log_time


def test_transforms_at_a_display_s_rate(body_mcap: Path, tmp_path: Path) -> None:
    """Whole-body poses get transforms when the last are at least
    ``TF_MIN_GAP_NS`` older: every other pose at 100 Hz, each at 60 Hz, again at
    once when time goes back; every pose is stored."""
    data = next(d for t, d in _messages(body_mcap, keys.pose_key()) if t > 0)
    frame = pose.decode(data)
    times = [10_000_000 * k for k in range(1, 11)]  # 100 Hz
    times += [times[-1] + 16_666_667 * k for k in range(1, 7)]  # 60 Hz
    times += [5_000_000, 10_000_000]  # back in time
    out = tmp_path / "rate.mcap"
    sink = McapSink(out)
    for t in times:
        sink.write_pose_message(keys.pose_key(), pose.encode(replace(frame, t_ns=t)))
    sink.close()
    assert [t for t, _ in _messages(out, keys.pose_key())] == sorted(times)
    given = [t for t, _ in _messages(out, TF)]
    assert given == sorted([*times[0:10:2], *times[10:16], 5_000_000])
    assert TF_MIN_GAP_NS == 15_000_000  # the rates above
