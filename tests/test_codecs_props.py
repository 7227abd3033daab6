"""Property tests of every codec: round trips, chunking, and random bytes."""

from __future__ import annotations

import contextlib
import itertools
import math
import struct
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bodynet.core.codecs import concentrator, imu_matrix, raw_sample, slimevr, smartsuit_can
from bodynet.core.errors import DecodeError, Rejected
from bodynet.core.messages import (
    RESUMED,
    NodeStatus,
    NoNewData,
    OleAccel,
    Quat,
    RawSample,
    SensorAbsent,
    Source,
    Tick,
)  # fmt: skip


class StreamDecoder(Protocol):
    def feed(self, data: bytes) -> Sequence[Any]: ...
    def close(self) -> Sequence[Any]: ...


int16 = st.integers(-0x8000, 0x7FFF)
accel = st.tuples(int16, int16, int16)


@st.composite
def unit_quats(draw: st.DrawFn) -> tuple[float, float, float, float]:
    v = draw(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4))
    n = math.sqrt(sum(c * c for c in v))
    if n < 1e-3:
        return (1.0, 0.0, 0.0, 0.0)
    w, x, y, z = (c / n for c in v)
    return (w, x, y, z)


def ole(nodes: st.SearchStrategy[int]) -> st.SearchStrategy[OleAccel]:
    return st.builds(OleAccel, nodes, int16, accel)


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    edges = [0, *points, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges)]


def decode_all(make: Callable[[], StreamDecoder], chunks: list[bytes]) -> list[Any]:
    decoder = make()
    events: list[Any] = []
    for chunk in chunks:
        events += decoder.feed(chunk)
    return events + list(decoder.close())


def quats_close(a: Sequence[float], b: Sequence[float], tol: float) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


cuts = st.lists(st.integers(0, 10_000), max_size=12)

# --- round trips ----------------------------------------------------------------------


@given(ole(st.integers(1, 12)))
def test_can_roundtrip_ole(reading: OleAccel) -> None:
    assert smartsuit_can.decode_frame(smartsuit_can.encode_reading(reading)) == reading


@given(st.integers(13, 15), unit_quats())
def test_can_roundtrip_quat_within_q14(node: int, q: tuple[float, ...]) -> None:
    out = smartsuit_can.decode_frame(smartsuit_can.encode_reading(Quat(node, q)))  # type: ignore[arg-type]
    assert isinstance(out, Quat)
    assert out.node == node
    assert quats_close(out.wxyz, q, 2e-4)


@given(st.lists(ole(st.integers(1, 12)), max_size=20), cuts)
def test_slcan_stream_any_chunking(readings: list[OleAccel], cut: list[int]) -> None:
    data = b"".join(smartsuit_can.encode_slcan(smartsuit_can.encode_reading(r)) for r in readings)
    assert decode_all(smartsuit_can.SmartSuitSlcanDecoder, chunked(data, cut)) == readings


@st.composite
def exchanges(draw: st.DrawFn) -> tuple[bytes, list[OleAccel]]:
    readings = draw(st.lists(ole(st.integers(1, 15)), max_size=20))
    data = b""
    for r in readings:
        if draw(st.booleans()):
            newline = draw(st.sampled_from([b"", b"\r", b"\n", b"\r\n"]))
            upper = draw(st.booleans())
            data += concentrator.request(r.node) + concentrator.encode_reply(
                r, newline=newline, upper=upper
            )
        else:
            data += concentrator.encode_extended_request(r.node)
            data += concentrator.encode_extended_reply(r)
    return data, readings


@given(exchanges(), cuts)
def test_concentrator_roundtrip_any_chunking(
    ex: tuple[bytes, list[OleAccel]], cut: list[int]
) -> None:
    data, readings = ex
    assert decode_all(concentrator.ConcentratorDecoder, chunked(data, cut)) == readings


imu_events = st.one_of(
    st.builds(Quat, st.integers(1, 15), unit_quats(), st.binary(min_size=9, max_size=9)),
    st.builds(NoNewData, st.integers(1, 15)),
    st.builds(SensorAbsent, st.integers(1, 15)),
)


@given(imu_events)
def test_imu_line_roundtrip(event: Quat | NoNewData | SensorAbsent) -> None:
    out = imu_matrix.decode_line(imu_matrix.encode_line(event)[:-1])
    if isinstance(event, Quat):
        assert isinstance(out, Quat)
        assert (out.node, out.extra) == (event.node, event.extra)
        assert quats_close(out.wxyz, event.wxyz, 1e-6)
    else:
        assert out == event


@given(st.lists(imu_events, max_size=30), cuts, st.booleans())
def test_imu_stream_any_chunking(events: list[Any], cut: list[int], crlf: bool) -> None:
    lines = [imu_matrix.encode_line(e) for e in events]
    if crlf:
        lines = [line[:-1] + b"\r\n" for line in lines]
    data = b"".join(lines)
    whole = decode_all(imu_matrix.ImuMatrixDecoder, [data])
    assert decode_all(imu_matrix.ImuMatrixDecoder, chunked(data, cut)) == whole
    assert [e.node for e in whole if not isinstance(e, Tick)] == [e.node for e in events]


raw_samples = st.one_of(
    st.builds(RawSample, ole(st.integers(1, 0xFFFF)), st.integers(0, 0xFFFFFFFF),
              st.integers(-(2**63), 2**63 - 1), st.sampled_from(Source),
              st.integers(0, 0xFF)),  # a SmartSuit sample's flags: RESUMED, the rest kept
    st.builds(RawSample,
              st.builds(Quat, st.integers(1, 0xFFFF), unit_quats(), st.binary(max_size=255)),
              st.integers(0, 0xFFFFFFFF), st.integers(-(2**63), 2**63 - 1),
              st.sampled_from(Source)),
)  # fmt: skip


@given(ole(st.integers(1, 0xFFFF)), st.integers(0, 0xFFFFFFFF), st.integers(0, 2**62))
def test_raw_sample_resumed_flag_round_trips_in_its_byte_alone(
    reading: OleAccel, seq: int, t_ns: int
) -> None:
    """``RESUMED`` round-trips on a SmartSuit sample and is byte 5 alone (reserved
    before, so a gateway that ignores it reads the rest as ever); a quaternion's
    flags byte stays reserved: refused on encoding, read as 0."""
    plain = raw_sample.encode(RawSample(reading, seq, t_ns, Source.CAN))
    flagged = raw_sample.encode(RawSample(reading, seq, t_ns, Source.CAN, RESUMED))
    assert raw_sample.decode(flagged).flags == RESUMED
    assert raw_sample.decode(plain).flags == 0
    assert flagged[5] == RESUMED
    assert flagged[:5] + flagged[6:] == plain[:5] + plain[6:]
    quat = RawSample(Quat(reading.node, (1.0, 0.0, 0.0, 0.0)), seq, t_ns, Source.IMU_CENTRAL)
    with pytest.raises(ValueError, match="reserved"):
        raw_sample.encode(RawSample(quat.reading, seq, t_ns, Source.IMU_CENTRAL, RESUMED))
    sent = bytearray(raw_sample.encode(quat))
    sent[5] = RESUMED
    assert raw_sample.decode(bytes(sent)) == quat
    assert raw_sample.decode_batch(bytes(sent)) == [quat]


@given(raw_samples)
def test_raw_sample_roundtrip_exact(sample: RawSample) -> None:
    assert raw_sample.decode(raw_sample.encode(sample)) == sample


def _checked_decode(payload: bytes) -> Any:
    """What the field-by-field checks make of one message (outcome or error reason)."""
    from bodynet.core.errors import DecodeError

    try:
        length = raw_sample._length(payload, 0)
        if length != len(payload):
            return "length"
        return raw_sample._decode_at(payload, 0, length)
    except DecodeError as exc:
        return exc.reason


@settings(max_examples=400)  # mostly well-formed, so that each field's check is reached
@given(st.sampled_from([b"BN", b"BN", b"BM"]), st.sampled_from([1, 1, 2]),
       st.sampled_from([2, 2, 1, 3]), st.integers(0, 5), st.integers(0, 2),
       st.integers(0, 2**32 - 1), st.integers(-(2**63), 2**63 - 1),
       st.one_of(st.just([0.5, 0.5, -0.5, 0.5]), st.lists(st.floats(), min_size=4, max_size=4)),
       st.sampled_from([0, 0, 1]), st.sampled_from([0, 0, 1, 0xFF]))  # fmt: skip
def test_raw_sample_quaternion_shortcut_agrees_with_the_checks(
    magic: bytes, version: int, kind: int, source: int, node: int, seq: int, t_ns: int,
    q: list[float], extra: int, flags: int,
) -> None:  # fmt: skip
    """53-byte messages take a one-unpack path; it accepts exactly what the
    field-by-field checks accept, with the same result, and leaves the rest to them."""
    import struct

    from bodynet.core.errors import DecodeError

    payload = struct.pack("<2sBBBBHIq4dB", magic, version, kind, source, flags, node, seq,
                          t_ns, *q, extra)  # fmt: skip
    try:
        got: Any = raw_sample.decode(payload)
    except DecodeError as exc:
        got = "length" if exc.reason.name in ("TRUNCATED", "BAD_LENGTH") else exc.reason
    assert got == _checked_decode(payload)
    # the gateway's intake takes the numbers alone: exactly the good messages without extra
    fields = raw_sample.quat_fields(payload)
    good = isinstance(got, RawSample) and not got.reading.extra
    assert (fields is not None) == good
    if fields is not None:
        assert raw_sample.of_fields(fields) == got


@given(st.lists(raw_samples, max_size=20), cuts)
def test_raw_sample_batch_any_chunking(samples: list[RawSample], cut: list[int]) -> None:
    data = raw_sample.encode_batch(samples)
    assert decode_all(raw_sample.RawSampleDecoder, chunked(data, cut)) == samples


# --- random bytes: only declared events, whatever the chunking --------------------------

DECLARED = {
    "slcan": (smartsuit_can.SmartSuitSlcanDecoder, (OleAccel, Quat, Rejected)),
    "concentrator": (concentrator.ConcentratorDecoder, (OleAccel, Rejected)),
    "imu": (imu_matrix.ImuMatrixDecoder, (Quat, NoNewData, SensorAbsent, Tick, Rejected)),
    "raw": (raw_sample.RawSampleDecoder, (RawSample, Rejected)),
}

# Bytes that look like each format, so the fuzzing reaches past the first check.
noisy = st.lists(
    st.one_of(
        st.binary(max_size=40),
        st.sampled_from([b"\r", b"\n", b"\x07", b"I", b"E", b"BN\x01", b"T0006FFFF8", b"0101"]),
        st.text("0123456789abcdefEXYZ \r\n-", max_size=30).map(str.encode),
    ),
    max_size=30,
).map(b"".join)


@given(st.sampled_from(sorted(DECLARED)), noisy, cuts)
def test_random_bytes_only_declared_events(name: str, data: bytes, cut: list[int]) -> None:
    make, types = DECLARED[name]
    whole = decode_all(make, [data])
    assert all(isinstance(e, types) for e in whole)
    assert decode_all(make, chunked(data, cut)) == whole


@given(noisy)
def test_good_imu_line_after_garbage_still_decodes(garbage: bytes) -> None:
    good = Quat(7, (1.0, 0.0, 0.0, 0.0), bytes(9))
    events = decode_all(
        imu_matrix.ImuMatrixDecoder, [garbage + b"\n" + imu_matrix.encode_line(good)]
    )
    assert events[-1] == good


@given(noisy)
def test_good_concentrator_reply_after_garbage_still_decodes(garbage: bytes) -> None:
    good = OleAccel(4, 12, (1, 2, 3))
    data = garbage + concentrator.request(4) + concentrator.encode_reply(good)
    assert decode_all(concentrator.ConcentratorDecoder, [data])[-1] == good


@given(noisy, st.integers(1, 15))
def test_polled_concentrator_attributes_replies_only_to_the_node_polled(
    noise: bytes, node: int
) -> None:
    """Whatever the device sends (request letters, replies, banners, noise), a
    reading is only ever the polled node's, at most one per poll, and the good
    reply to the next poll still decodes."""
    dec = concentrator.ConcentratorDecoder(replies_only=True)
    events = dec.poll(node) + dec.feed(noise)
    events += dec.poll(4) + dec.feed(concentrator.encode_reply(OleAccel(4, 12, (1, 2, 3))))
    readings = [e for e in events if isinstance(e, OleAccel)]
    assert readings[-1] == OleAccel(4, 12, (1, 2, 3))
    assert all(r.node == node for r in readings[:-1])
    assert len(readings) <= 2


@given(noisy)
def test_good_slcan_frame_after_garbage_still_decodes(garbage: bytes) -> None:
    good = OleAccel(4, 12, (1, 2, 3))
    data = garbage + b"\r" + smartsuit_can.encode_slcan(smartsuit_can.encode_reading(good))
    assert decode_all(smartsuit_can.SmartSuitSlcanDecoder, [data])[-1] == good


@given(st.one_of(st.binary(max_size=80), noisy))
def test_single_message_decoders_raise_only_declared_errors(data: bytes) -> None:
    from bodynet.core.codecs import pose
    from bodynet.core.errors import DecodeError

    decoders = (
        raw_sample.decode,
        pose.decode,
        imu_matrix.decode_line,
        smartsuit_can.decode_slcan,
        concentrator.decode_extended,
        lambda d: concentrator.decode_reply(d, 1),
    )
    for decode in decoders:
        with contextlib.suppress(DecodeError):  # anything else fails the test
            decode(data)
    for frame_data in (data[:8], data):
        with contextlib.suppress(DecodeError):
            smartsuit_can.decode_frame(
                smartsuit_can.CanFrame(0x0006FFFF, frame_data, dlc=len(frame_data))
            )


# --- SlimeVR: one datagram is one packet --------------------------------------------------

MAC = bytes.fromhex("02b0d1000001")
HANDSHAKE = slimevr.encode_handshake(0, slimevr.Handshake(MAC, 2, 10, 2, 17, "fw"))

# Datagrams that look like the protocol: right-sized bodies of every packet type,
# with the bytes of the body and the number drawn at random.
slimevr_like = st.builds(
    lambda kind, number, body: struct.pack(">iq", kind, number) + body,
    st.sampled_from([0, 1, 3, 4, 10, 12, 15, 17, 19, 22, 23, 99, 200, -1]),
    st.integers(-(2**63), 2**63 - 1),
    st.binary(max_size=40),
)


@given(st.one_of(st.binary(max_size=60), slimevr_like, noisy))
def test_slimevr_packets_raise_only_declared_errors(data: bytes) -> None:
    with contextlib.suppress(DecodeError):
        slimevr.decode_packet(data)
    with contextlib.suppress(DecodeError):
        slimevr.decode_server_packet(data)


@given(st.lists(st.tuples(st.one_of(st.binary(max_size=60), slimevr_like),
                          st.sampled_from(["a", "b"])), max_size=30))  # fmt: skip
def test_slimevr_server_gives_only_declared_events(datagrams: list[tuple[bytes, str]]) -> None:
    """Random datagrams from a tracker that shook hands and from one that did not:
    only declared events, and state only for the one that did."""
    server = slimevr.SlimeVRServer()
    server.receive(HANDSHAKE, "a")
    for data, sender in datagrams:
        for event in server.receive(data, sender):
            assert isinstance(event, Quat | Tick | NodeStatus | Rejected)
            if isinstance(event, Quat):
                assert math.isclose(sum(c * c for c in event.wxyz), 1.0, rel_tol=1e-9)
    assert set(server.connections) <= {"a", "b"}


@given(st.integers(0, 254), unit_quats(), st.integers(1, 2**40))
def test_slimevr_rotation_roundtrip(sensor: int, q: tuple[float, ...], number: int) -> None:
    w, x, y, z = q
    server = slimevr.SlimeVRServer()
    server.receive(HANDSHAKE, "t")
    events = server.receive(slimevr.encode_rotation(number, sensor, (x, y, z, w)), "t")
    first, quat = events[-2:]
    assert isinstance(quat, Quat)
    assert quats_close(quat.wxyz, q, 1e-6)  # float32 on the wire
    events = server.receive(slimevr.encode_rotation_accel(number + 1, sensor, (x, y, z, w)), "t")
    assert isinstance(events[-1], Quat)
    assert quats_close(events[-1].wxyz, q, 1e-4)  # Q15 on the wire
    assert isinstance(first, Tick)
    assert events[-2] == Tick(first.index + 1, quat.node)  # the packet after: the next sample


@given(st.lists(st.integers(1, 50), min_size=1, max_size=20))
def test_slimevr_sequence_counts_every_lost_packet(steps: list[int]) -> None:
    """Sequence numbers rise by one plus the packets lost before each sample,
    from the first packet after the handshake (the firmware's counter does not
    start at its handshake: the numbers before the first are no loss)."""
    server = slimevr.SlimeVRServer()
    server.receive(HANDSHAKE, "t")
    number, seqs = 0, []
    for step in steps:
        number += step
        events = server.receive(slimevr.encode_rotation(number, 0, (0, 0, 0, 1.0)), "t")
        seqs.append(next(e.index for e in events if isinstance(e, Tick)))
    assert seqs == [sum(steps[1 : i + 1]) for i in range(len(steps))]
