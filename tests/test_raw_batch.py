"""The batch of raw samples (``core/codecs/raw_batch.py``): what goes in comes out,
and whatever bytes or key come, the answer is entries or counted rejections."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bodynet.core import keys
from bodynet.core.codecs import raw_batch, raw_sample
from bodynet.core.errors import DecodeError, Reason, Rejected
from bodynet.core.messages import OleAccel, Quat, RawSample, Source
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES

RAW_KEYS = sorted({s.raw_key for s in (*IMU_SITES.values(), *SMARTSUIT_SITES.values())})

samples = st.builds(
    RawSample,
    st.one_of(
        st.builds(
            OleAccel,
            st.integers(1, 99),
            st.integers(-0x8000, 0x7FFF),
            st.tuples(*[st.integers(-0x8000, 0x7FFF)] * 3),
        ),
        st.builds(Quat, st.integers(1, 99), st.just((1.0, 0.0, 0.0, 0.0))),
    ),
    st.integers(0, 2**32 - 1),
    st.integers(0, 2**62),
    st.just(Source.IMU_CENTRAL),
)
entries = st.lists(st.tuples(st.sampled_from(RAW_KEYS), samples.map(raw_sample.encode)),
                   max_size=40)  # fmt: skip


@given(entries)
def test_a_batch_gives_back_its_entries_in_order(pairs: list[tuple[str, bytes]]) -> None:
    assert raw_batch.decode(raw_batch.encode(pairs)) == pairs
    assert raw_batch.split(keys.batch_key("imu-0"), raw_batch.encode(pairs)) == pairs


@given(entries.filter(bool), st.data())
def test_a_cut_batch_keeps_the_entries_before_the_cut(
    pairs: list[tuple[str, bytes]], data: st.DataObject
) -> None:
    payload = raw_batch.encode(pairs)
    cut = data.draw(st.integers(5, len(payload) - 1))
    got = raw_batch.decode(payload[:cut])
    *whole, last = got
    assert whole == pairs[: len(whole)]
    assert isinstance(last, Rejected)
    assert last.reason is Reason.TRUNCATED


headed = st.tuples(st.integers(0, 40), st.binary(max_size=300)).map(
    lambda t: raw_batch.MAGIC + bytes((raw_batch.VERSION, t[0], 0)) + t[1]
)


@given(st.one_of(st.binary(max_size=300), headed))
def test_any_bytes_give_entries_or_counted_rejections(payload: bytes) -> None:
    header = (Reason.TRUNCATED, Reason.BAD_MAGIC, Reason.BAD_VERSION)
    try:
        got = raw_batch.decode(payload)
    except DecodeError as exc:
        reason = exc.reason
        got = []
    else:
        reason = None
    assert reason in (None, *header)
    for entry in got:
        assert isinstance(entry, Rejected) or keys.parse(entry[0])[1] is keys.Stream.RAW
    split = raw_batch.split(keys.batch_key("x"), payload)
    assert len(split) == (len(got) if reason is None else 1)


@pytest.mark.parametrize(
    "hostile",
    ["body/@topology", "body/arm/left/elbow/pose", "alice/body/arm/left/elbow/raw",
     "body/arm/left/*/raw", "body/arm/left/**/raw", "body/wing/left/elbow/raw", "é"],
)  # fmt: skip
def test_an_entry_on_a_key_that_is_no_sites_raw_key_is_rejected_and_the_rest_kept(
    hostile: str,
) -> None:
    good = raw_sample.encode(RawSample(Quat(1, (1.0, 0.0, 0.0, 0.0)), 0, 1, Source.SLIMEVR))
    payload = raw_batch.encode([(RAW_KEYS[0], good)]).replace(b"\x01\x00", b"\x03\x00", 1)
    payload += bytes((len(hostile.encode()),)) + hostile.encode() + b"\x02\x00ab"
    payload += bytes((len(RAW_KEYS[1]),)) + RAW_KEYS[1].encode() + bytes((len(good), 0)) + good
    first, bad, last = raw_batch.split(keys.batch_key("x"), payload)
    assert first == (RAW_KEYS[0], good)
    assert last == (RAW_KEYS[1], good)
    assert isinstance(bad, Rejected)
    assert bad.reason is Reason.UNKNOWN_NODE


def test_a_subjects_batch_puts_its_subject_before_each_key_and_others_pass_as_they_are() -> None:
    good = raw_sample.encode(RawSample(Quat(1, (1.0, 0.0, 0.0, 0.0)), 0, 1, Source.SLIMEVR))
    payload = raw_batch.encode([(RAW_KEYS[0], good)])
    assert raw_batch.split("alice/" + keys.batch_key("x"), payload) == [
        ("alice/" + RAW_KEYS[0], good)
    ]
    # not a batch's key: the message is one sample on its own key, read as such later
    for key in (RAW_KEYS[0], "a/b/" + keys.batch_key("x"), keys.BATCH + "/x/y", keys.BATCH):
        assert raw_batch.split(key, payload) == [(key, payload)]
    (bad,) = raw_batch.split(keys.batch_key("x"), b"BN" + payload)
    assert isinstance(bad, Rejected)
    assert bad.reason is Reason.BAD_MAGIC


def test_what_cannot_be_put_in_a_batch_is_refused() -> None:
    with pytest.raises(ValueError, match=r"1\.\.255"):
        raw_batch.encode([("", b"")])
    with pytest.raises(ValueError, match="at most"):
        raw_batch.encode([(RAW_KEYS[0], b"")] * (raw_batch.MAX_ENTRIES + 1))
