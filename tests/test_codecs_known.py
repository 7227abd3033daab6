"""Known answers: values worked out by hand from the seeds' formats."""

from __future__ import annotations

import math
import struct

import pytest

from bodynet.core.codecs import concentrator, imu_matrix, pose, raw_sample, smartsuit_can
from bodynet.core.codecs.smartsuit_can import CanFrame
from bodynet.core.errors import DecodeError, Reason, Rejected
from bodynet.core.messages import NoNewData, OleAccel, Quat, RawSample, SensorAbsent, Source, Tick


# --- SmartSuit CAN --------------------------------------------------------------------
def test_can_ids_of_the_seed() -> None:
    assert [smartsuit_can.can_id(n) for n in (1, 2, 3)] == [0x0006FFFF, 0x000AFFFF, 0x000EFFFF]
    assert smartsuit_can.node_of(0x000EFFFF) == 3
    assert smartsuit_can.can_id(15) == 0x003EFFFF


def test_can_frame_payload_is_four_int16_le() -> None:
    frame = CanFrame(0x0006FFFF, bytes.fromhex("6100BE03030096FE"))
    assert smartsuit_can.decode_frame(frame) == OleAccel(1, 97, (958, 3, -362))


def test_can_trunk_node_carries_q14_quaternion() -> None:
    # w = 0.5 * 16384 = 0x2000, x = -0.5 -> 0xE000, y = 0.5, z = -0.5
    frame = CanFrame(smartsuit_can.can_id(14), bytes.fromhex("0020 00E0 0020 00E0"))
    assert smartsuit_can.decode_frame(frame) == Quat(14, (0.5, -0.5, 0.5, -0.5))


@pytest.mark.parametrize(
    ("frame", "reason"),
    [
        (CanFrame(0x123, bytes(8), is_extended_id=False), Reason.STANDARD_ID),
        (CanFrame(0x0006FFFF, b"", is_remote_frame=True), Reason.REMOTE_FRAME),
        (CanFrame(0x0006FFFF, bytes(8), is_error_frame=True), Reason.ERROR_FRAME),
        (CanFrame(0x0006FFFF, bytes(4), dlc=4), Reason.BAD_DLC),
        (CanFrame(0x0007FFFF, bytes(8)), Reason.UNKNOWN_NODE),
        (CanFrame(0x0042FFFF, bytes(8)), Reason.UNKNOWN_NODE),  # node 16
        (CanFrame(0x0006FFFE, bytes(8)), Reason.UNKNOWN_NODE),
        (CanFrame(0x0036FFFF, bytes(8)), Reason.BAD_QUAT_NORM),  # node 13, all zero
    ],
)
def test_can_bad_frames(frame: CanFrame, reason: Reason) -> None:
    with pytest.raises(DecodeError) as err:
        smartsuit_can.decode_frame(frame)
    assert err.value.reason is reason


@pytest.mark.parametrize(
    ("frame", "kind"),
    [
        (CanFrame(0x123, bytes(8), is_extended_id=False), "standard_id"),
        (CanFrame(0x18FF0001, bytes(8)), "extended_id"),  # a J1939 device's
        (CanFrame(0x0042FFFF, bytes(8)), "extended_id"),  # no node 16
        (CanFrame(0x0006FFFF, b"", is_remote_frame=True), "remote_frame"),  # polls node 1
        (CanFrame(0x0006FFFF, bytes(8), is_error_frame=True), None),  # rejected: error_frame
        (CanFrame(0x0006FFFF, bytes(4), dlc=4), None),  # node 1's, malformed: bad_dlc
        (CanFrame(0x0036FFFF, bytes(8)), None),  # node 13's, malformed: bad_quat_norm
        (CanFrame(0x000AFFFF, bytes(8)), None),  # node 2's reading
    ],
)
def test_can_frames_of_other_devices_are_foreign(frame: CanFrame, kind: str | None) -> None:
    assert smartsuit_can.foreign(frame) == kind


def test_slcan_line_as_python_can_sends_it() -> None:
    frame = smartsuit_can.encode_reading(OleAccel(2, -5, (1, -1024, 300)))
    assert smartsuit_can.encode_slcan(frame) == b"T000AFFFF8FBFF010000FC2C01\r"
    decoder = smartsuit_can.SlcanDecoder()
    events = decoder.feed(b"V1013\rT000AFFFF8FBFF010000FC2C01\r\r\x07r1230\r")
    assert events == [
        smartsuit_can.SlcanReply("V1013"),
        frame,
        smartsuit_can.SlcanReply(""),
        smartsuit_can.SlcanReply("", ok=False),
        CanFrame(0x123, b"", is_extended_id=False, is_remote_frame=True, dlc=0),
    ]


# --- Data Concentrator ----------------------------------------------------------------
def test_request_characters() -> None:
    assert [concentrator.request(n) for n in (1, 2, 3, 15)] == [b"I", b"J", b"K", b"W"]


def test_reply_pairs_with_request_either_case() -> None:
    dec = concentrator.ConcentratorDecoder()
    events = dec.feed(b"IE0061X03BEY0003ZFE96\r\nKE00f8X026aY0003Zfcd0")
    assert events == [OleAccel(1, 97, (958, 3, -362)), OleAccel(3, 248, (618, 3, -816))]
    assert dec.close() == []


def test_reply_encoding() -> None:
    assert concentrator.encode_reply(OleAccel(1, -1, (0, 1024, -1024))) == (
        b"EFFFFX0000Y0400ZFC00\r\n"
    )


def test_extended_form() -> None:
    dec = concentrator.ConcentratorDecoder()
    assert dec.feed(b"1 1 2\r\n1 1 2 -5 1 -1024 300\r\n") == [OleAccel(2, -5, (1, -1024, 300))]
    assert concentrator.encode_extended_reply(OleAccel(5, 1, (2, 3, 4))) == b"1 2 5 1 2 3 4\r\n"


def test_resynchronises_after_garbage() -> None:
    dec = concentrator.ConcentratorDecoder()
    events = dec.feed(b"\x00\x01zzIE0012X00JE0001X0002Y0003Z0004") + dec.close()
    assert events == [
        # the request 'I' is no garbage, but its cut reply is: one run of 12 bytes
        Rejected(Reason.GARBAGE, "12 bytes", b"\x00\x01zzE0012X00"),
        Rejected(Reason.NO_REPLY, "node 1"),
        OleAccel(2, 1, (2, 3, 4)),
    ]


def test_unpaired_reply_and_unknown_node() -> None:
    dec = concentrator.ConcentratorDecoder()
    events = dec.feed(b"E0001X0002Y0003Z0004\r\n1 1 16 0 0 0 0\n1 1 2 0 0 0 70000\n")
    assert [e.reason for e in events if isinstance(e, Rejected)] == [
        Reason.UNPAIRED_REPLY, Reason.UNKNOWN_NODE, Reason.OUT_OF_RANGE,
    ]  # fmt: skip


# a bridge polling the device decodes only what the device sends (replies_only)
REPLY = b"E0001X0002Y0003Z0004\r\n"


def test_polled_letters_from_the_device_are_garbage_not_requests() -> None:
    dec = concentrator.ConcentratorDecoder(replies_only=True)
    assert dec.poll(2) == []
    assert dec.feed(b"RESET\r\n" + REPLY) == [
        Rejected(Reason.GARBAGE, "5 bytes", b"RESET"),
        OleAccel(2, 1, (2, 3, 4)),
    ]
    assert not dec.waiting
    assert dec.feed(REPLY) == [Rejected(Reason.UNPAIRED_REPLY, "reply with no request", REPLY[:20])]


def test_polled_late_reply_is_counted_once_and_not_paired_with_the_next() -> None:
    dec = concentrator.ConcentratorDecoder(replies_only=True)
    dec.poll(1)
    dec.overdue()
    assert dec.waiting
    assert dec.feed(REPLY) == [Rejected(Reason.LATE_REPLY, "node 1", REPLY[:20])]
    assert dec.poll(2) == []  # answered, late: no no_reply as well
    assert dec.feed(b"E0005X0006Y0007Z0008") == [OleAccel(2, 5, (6, 7, 8))]
    assert [e.node for e in dec.feed(REPLY) if isinstance(e, Rejected)] == [None]  # unpaired


def test_polled_unanswered_and_cut_short_end_at_the_next_poll() -> None:
    dec = concentrator.ConcentratorDecoder(replies_only=True)
    dec.poll(1)
    assert dec.feed(b"E0001X00") == []  # may go on
    dec.overdue()
    assert dec.poll(2) == [
        Rejected(Reason.GARBAGE, "8 bytes", b"E0001X00"),
        Rejected(Reason.NO_REPLY, "node 1"),
    ]
    assert dec.feed(b"02Y0003Z0004" + REPLY) == [  # its rest: garbage, not node 2's
        Rejected(Reason.GARBAGE, "12 bytes", b"02Y0003Z0004"),
        OleAccel(2, 1, (2, 3, 4)),
    ]


def test_polled_extended_reply_only_for_the_node_polled() -> None:
    dec = concentrator.ConcentratorDecoder(replies_only=True)
    dec.poll(2)
    events = dec.feed(b"1 1 2\r\n1 1 3 0 0 0 0\r\n1 1 2 -5 1 -1024 300\r\n")
    assert [getattr(e, "reason", e) for e in events] == [
        Reason.GARBAGE, Reason.UNPAIRED_REPLY, OleAccel(2, -5, (1, -1024, 300)),
    ]  # fmt: skip
    dec.poll(3)
    dec.overdue()
    assert dec.feed(b"1 1 3 0 0 0 0\r\n") == [
        Rejected(Reason.LATE_REPLY, "node 3", b"1 1 3 0 0 0 0")
    ]


# --- IMU central ----------------------------------------------------------------------
def _line(sensor: int, flag: int, payload: bytes) -> bytes:
    return b"%02x%02x" % (sensor, flag) + payload.hex().encode()


def test_imu_line_float32_little_endian() -> None:
    # Appendix B reads w from characters 5..12 with byte pairs reversed: little-endian.
    payload = struct.pack("<4f", 0.0, 1.0, 0.0, 0.0) + bytes(range(1, 10))
    line = _line(4, 1, payload)
    assert line[4:12] == b"00000000"
    assert line[12:20] == b"0000803f"
    assert imu_matrix.decode_line(line) == Quat(4, (0.0, 1.0, 0.0, 0.0), bytes(range(1, 10)))


def test_imu_flags_00_and_ff_are_events_not_errors() -> None:
    dec = imu_matrix.ImuMatrixDecoder()
    events = dec.feed(_line(1, 0, bytes(25)) + b"\n" + _line(2, 0xFF, bytes(25)) + b"\r\n")
    assert events == [Tick(0), NoNewData(1), SensorAbsent(2)]


def test_imu_quaternion_normalised_inside_tolerance() -> None:
    q = imu_matrix.decode_line(_line(1, 1, struct.pack("<4f", 1.05, 0, 0, 0) + bytes(9)))
    assert isinstance(q, Quat)
    assert q.wxyz == (1.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        (b"0101abc", Reason.BAD_LENGTH),
        (b"zz" + b"0" * 52, Reason.NOT_HEX),
        (_line(16, 1, bytes(25)), Reason.UNKNOWN_NODE),
        (_line(0, 1, bytes(25)), Reason.UNKNOWN_NODE),
        (_line(3, 7, bytes(25)), Reason.BAD_FLAG),
        (_line(3, 1, struct.pack("<4f", math.inf, 0, 0, 0) + bytes(9)), Reason.NOT_FINITE),
        (_line(3, 1, struct.pack("<4f", math.nan, 0, 0, 0) + bytes(9)), Reason.NOT_FINITE),
        (_line(3, 1, struct.pack("<4f", 0.8, 0, 0, 0) + bytes(9)), Reason.BAD_QUAT_NORM),
        (_line(3, 1, struct.pack("<4f", 1.2, 0, 0, 0) + bytes(9)), Reason.BAD_QUAT_NORM),
    ],
)
def test_imu_bad_lines(line: bytes, reason: Reason) -> None:
    with pytest.raises(DecodeError) as err:
        imu_matrix.decode_line(line)
    assert err.value.reason is reason


def test_imu_ticks_follow_sensor_numbers() -> None:
    q = struct.pack("<4f", 1, 0, 0, 0) + bytes(9)
    data = b"".join(_line(s, 1, q) + b"\n" for s in (1, 2, 3, 1, 2, 2))
    ticks = [e.index for e in imu_matrix.ImuMatrixDecoder().feed(data) if isinstance(e, Tick)]
    assert ticks == [0, 1, 2]


def test_imu_noise_glued_to_a_line_costs_only_the_noise() -> None:
    good = _line(5, 1, struct.pack("<4f", 1, 0, 0, 0) + bytes(9))
    events = imu_matrix.ImuMatrixDecoder().feed(b"\x00\xff\x80" + good + b"\n")
    assert events[0] == Rejected(Reason.GARBAGE, "3 bytes", b"\x00\xff\x80" + good[:61])
    assert events[2] == Quat(5, (1.0, 0.0, 0.0, 0.0), bytes(9))


# --- raw-sample message ---------------------------------------------------------------
def test_raw_sample_layout() -> None:
    sample = RawSample(OleAccel(2, -5, (1, -1024, 300)), 7, 1_000_000_000_000_000_000, Source.CAN)
    expected = (
        b"BN" + bytes([1, 1, 1, 0]) + bytes.fromhex("0200") + bytes.fromhex("07000000")
        + (10**18).to_bytes(8, "little") + bytes.fromhex("fbff 0100 00fc 2c01")
    )  # fmt: skip
    assert raw_sample.encode(sample) == expected
    assert len(expected) == 28
    assert raw_sample.decode(expected) == sample


def test_raw_sample_quaternion_layout() -> None:
    sample = RawSample(Quat(9, (0.0, 0.0, 0.0, 1.0), b"\x01\x02"), 1, -5, Source.IMU_CENTRAL)
    data = raw_sample.encode(sample)
    assert data[3] == 2  # kind: quaternion
    assert data[4] == 3  # source: IMU central
    assert data[20:52] == struct.pack("<4d", 0.0, 0.0, 0.0, 1.0)
    assert data[52:] == b"\x02\x01\x02"
    assert raw_sample.decode(data) == sample


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda b: b"XX" + b[2:], Reason.BAD_MAGIC),
        (lambda b: b[:2] + b"\x02" + b[3:], Reason.BAD_VERSION),
        (lambda b: b[:3] + b"\x09" + b[4:], Reason.BAD_KIND),
        (lambda b: b[:10], Reason.TRUNCATED),
        (lambda b: b + b"\x00", Reason.BAD_LENGTH),
        (lambda b: b[:6] + b"\x00\x00" + b[8:], Reason.UNKNOWN_NODE),
    ],
)
def test_raw_sample_rejects(mutate: object, reason: Reason) -> None:
    good = raw_sample.encode(RawSample(OleAccel(1, 0, (0, 0, 0)), 0, 0))
    with pytest.raises(DecodeError) as err:
        raw_sample.decode(mutate(good))  # type: ignore[operator]
    assert err.value.reason is reason


def test_raw_sample_rejects_nan_quaternion() -> None:
    bad = bytearray(raw_sample.encode(RawSample(Quat(1, (1.0, 0.0, 0.0, 0.0)), 0, 0)))
    bad[20:28] = struct.pack("<d", math.nan)
    with pytest.raises(DecodeError) as err:
        raw_sample.decode(bytes(bad))
    assert err.value.reason is Reason.NOT_FINITE


def test_raw_sample_source_time_is_the_t_ns_field() -> None:
    """The latency probe's shortcut reads the same timestamp the full decoder does."""
    for reading in (OleAccel(3, -120, (5, -6, 1000)), Quat(7, (0.5, 0.5, -0.5, 0.5), b"xy")):
        t_ns = -(2**62) + 12345
        payload = raw_sample.encode(RawSample(reading, 9, t_ns, Source.CAN))
        assert raw_sample.source_time(payload) == raw_sample.decode(payload).t_ns == t_ns


def test_pose_source_time_is_the_t_ns_field() -> None:
    pelvis = ((0.0, 0.0, 0.95), (1.0, 0.0, 0.0, 0.0))
    frame = pose.PoseFrame(7, 1_700_000_000_123_456_789, {"left_elbow_flexion_deg": 42.0},
                           {"left_elbow": 42.0}, {"pelvis": pelvis},
                           {"left_elbow": (0.0, 0.2, 1.2)})  # fmt: skip
    payload = pose.encode(frame)
    assert pose.source_time(payload) == pose.decode(payload).t_ns == 1_700_000_000_123_456_789
