"""The compiled intake (gateway/kernels.py: take_batch, take_messages) against the
codecs' own reading of the same bytes, and the frame a solve takes."""

from __future__ import annotations

import math
import random
import struct

import numpy as np

from bodynet.core.codecs import raw_batch, raw_sample
from bodynet.core.codecs._common import _SQ_HI, _SQ_LO
from bodynet.core.errors import DecodeError, Rejected
from bodynet.core.messages import Quat, RawSample, Source
from bodynet.gateway import columns, kernels
from bodynet.gateway.columns import Columns, Frame
from bodynet.gateway.solver import BodySolver
from bodynet.nodes.emulator import imu_tags

TAGS = imu_tags()
AHEAD = 2_000_000_000_000_000_000
STEP_S = 0.02


def _rows() -> Columns:
    cols = Columns(depth=8)
    for tag in TAGS:  # a row each, its first sample a quaternion (as _Body.take makes them)
        row = cols.add(tag.site.raw_key, 1.0)
        kernels.take_fields(cols.ints, cols.floats, cols.history, cols.tally, row, tag.node,
                            0, 0, 3, 1.0, 0.0, 0.0, 0.0, 0.0, 0, STEP_S)  # fmt: skip
    return cols


def _quat(rng: random.Random) -> tuple[float, float, float, float]:
    q = [rng.gauss(0, 1) for _ in range(4)]
    n = math.sqrt(sum(v * v for v in q))
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _sample(rng: random.Random, node: int, t_ns: int) -> RawSample:
    return RawSample(Quat(node, _quat(rng)), rng.randrange(2**32), t_ns,
                     rng.choice(list(Source)))  # fmt: skip


def _take(cols: Columns, payload: bytes, pos: int = raw_batch.HEADER_LEN, now: float = 5.0,
          rnd: int = 7) -> int:  # fmt: skip
    return int(kernels.take_batch(np.frombuffer(payload, np.uint8), pos, cols.keys, cols.ends,
                                  cols.n, cols.ints, cols.floats, cols.history, cols.tally, now,
                                  rnd, AHEAD, _SQ_LO, _SQ_HI, STEP_S))  # fmt: skip


def test_a_batch_taken_compiled_holds_what_the_codec_reads() -> None:
    """Batches of every tag in random order (some tags twice), random quaternions,
    sequence numbers, times and sources: each row's latest sample is the one
    ``raw_sample.decode`` reads from the last entry of its key, bit for bit;
    the tally counts every entry; each row's ring holds the samples a step of
    sample time apart, oldest dropped past its depth."""
    rng = random.Random(5)
    cols = _rows()
    last: dict[int, RawSample] = {}
    kept: dict[int, list[tuple[float, ...]]] = {row: [(0.0, 1.0, 0.0, 0.0, 0.0)]
                                                for row in range(len(TAGS))}  # fmt: skip
    t0 = 1_700_000_000_000_000_000
    taken = 0
    for k in range(40):
        rows = [rng.randrange(len(TAGS)) for _ in range(rng.randrange(1, 30))]
        entries = []
        for i, row in enumerate(rows):
            sample = _sample(rng, TAGS[row].node, t0 + k * 10_000_000 + i)
            entries.append((TAGS[row].site.raw_key, raw_sample.encode(sample)))
            last[row] = raw_sample.decode(entries[-1][1])
            ring = kept[row]
            t = sample.t_ns / 1e9
            if not ring or t - ring[-1][0] >= STEP_S:
                ring.append((t, *sample.reading.wxyz))  # type: ignore[union-attr]
        payload = raw_batch.encode(entries)
        assert _take(cols, payload) == len(payload)
        taken += len(entries)
    assert cols.tally[columns.SAMPLES] == taken + len(TAGS)
    for row, sample in last.items():
        assert cols.made(row) == sample
        assert cols.ints[row, columns.PENDING] == 1
        assert cols.floats[row, columns.ARRIVED] == 5.0
        assert cols.recent(row, math.inf) == [tuple(e) for e in kept[row][-cols.depth :]]


def test_what_the_compiled_intake_does_not_take_it_leaves_to_python() -> None:
    """The batch stops, nothing of the entry written, at an entry whose key has no
    row, a quaternion with extra bytes, one that is not unit, a time before 1970
    or past ``ahead``, a node 0, and a row whose latest is not a quaternion;
    the entries before it are taken. A batch that is not well formed is
    refused whole (-1), nothing taken, and ``raw_batch.decode`` says why."""
    rng = random.Random(2)
    good = (TAGS[0].site.raw_key, raw_sample.encode(_sample(rng, TAGS[0].node, 10)))
    extra = raw_sample.encode(RawSample(Quat(TAGS[1].node, (1.0, 0, 0, 0), b"x"), 1, 10,
                                        Source.SLIMEVR))  # fmt: skip
    unit = bytearray(raw_sample.encode(_sample(rng, TAGS[1].node, 10)))
    struct.pack_into("<d", unit, 20, 2.0)
    past = bytearray(raw_sample.encode(_sample(rng, TAGS[1].node, 10)))
    struct.pack_into("<q", past, 12, AHEAD + 1)
    before = bytearray(past)
    struct.pack_into("<q", before, 12, -1)
    node0 = bytearray(raw_sample.encode(_sample(rng, TAGS[1].node, 10)))
    struct.pack_into("<H", node0, 6, 0)
    refused = {"no row": ("body/leg/left/toe/raw", raw_sample.encode(_sample(rng, 9, 10))),
               "extra bytes": (TAGS[1].site.raw_key, extra),
               "not unit": (TAGS[1].site.raw_key, bytes(unit)),
               "ahead": (TAGS[1].site.raw_key, bytes(past)),
               "before 1970": (TAGS[1].site.raw_key, bytes(before)),
               "node 0": (TAGS[1].site.raw_key, bytes(node0))}  # fmt: skip
    for why, entry in refused.items():
        cols = _rows()
        before_t = cols.ints[1].copy()
        payload = raw_batch.encode([good, entry, good])
        stop = _take(cols, payload)
        assert stop == raw_batch.entry_at(payload, raw_batch.HEADER_LEN)[1], why
        assert cols.tally[columns.SAMPLES] == len(TAGS) + 1, why
        assert (cols.ints[1] == before_t).all(), why
        # Python takes it (or rejects it) and the kernel goes on after it
        after = raw_batch.entry_at(payload, stop)[1]
        assert _take(cols, payload, after) == len(payload), why
        assert cols.tally[columns.SAMPLES] == len(TAGS) + 2, why
    cols = _rows()
    kernels.take_other(cols.ints, cols.floats, cols.tally, 1, 10, 1.0, 1)  # a module's sample
    plain = (TAGS[1].site.raw_key, raw_sample.encode(_sample(rng, TAGS[1].node, 10)))
    payload = raw_batch.encode([good, plain])
    assert _take(cols, payload) == raw_batch.entry_at(payload, raw_batch.HEADER_LEN)[1]
    for bad in (b"BB\x02\x01\x00", raw_batch.encode([good])[:-1], raw_batch.encode([good]) + b"x",
                b"XB\x01\x00\x00", b"BB"):  # fmt: skip
        cols = _rows()
        assert _take(cols, bad) == -1
        assert cols.tally[columns.SAMPLES] == len(TAGS)
        assert _rejected(bad)


def _rejected(payload: bytes) -> bool:
    try:
        return any(isinstance(e, Rejected) for e in raw_batch.decode(payload))
    except DecodeError:
        return True


def test_messages_taken_compiled_up_to_one_left_to_python() -> None:
    """``take_messages``: messages end to end, each after its row, taken as the
    batch's entries are, up to the first it does not take (here one not unit):
    where it starts is returned, nothing of it written, and the call goes on
    after it."""
    rng = random.Random(1)
    cols = _rows()
    first, last = _sample(rng, TAGS[3].node, 123), _sample(rng, TAGS[4].node, 124)
    bad = bytearray(raw_sample.encode(_sample(rng, TAGS[5].node, 200)))
    struct.pack_into("<d", bad, 20, 0.5)
    rows = (3, 5, 4)
    messages = (raw_sample.encode(first), bytes(bad), raw_sample.encode(last))
    buf = np.frombuffer(b"".join(row.to_bytes(kernels.ROW_TAG, "little") + message
                                 for row, message in zip(rows, messages, strict=True)),
                        np.uint8)  # fmt: skip
    step = kernels.ROW_TAG + raw_sample.QUAT_MESSAGE_LEN

    def take(pos: int) -> int:
        stop = kernels.take_messages(buf, pos, cols.ints, cols.floats, cols.history, cols.tally,
                                     2.0, 9, AHEAD, _SQ_LO, _SQ_HI, STEP_S)  # fmt: skip
        return int(stop)

    ints = cols.ints[5].copy()
    assert take(0) == step
    assert cols.made(3) == first
    assert (cols.ints[5] == ints).all()
    assert take(2 * step) == 3 * step
    assert cols.made(4) == last
    assert cols.tally[columns.SAMPLES] == len(TAGS) + 2


def test_a_frame_reads_as_its_samples() -> None:
    """A frame of a mapping reads back as that mapping; its arrays hold the
    quaternions and times the solver takes."""
    rng = random.Random(3)
    samples = {tag.site: _sample(rng, tag.node, 1000 + i) for i, tag in enumerate(TAGS)}
    frame = Frame.of(samples)
    assert dict(frame) == samples
    assert TAGS[0].site in frame
    assert list(frame.t_ns) == [s.t_ns for s in samples.values()]
    quats = [list(s.reading.wxyz) for s in samples.values()]  # type: ignore[union-attr]
    assert frame.floats[:, columns.W : columns.W + 4].tolist() == quats


def test_a_source_id_the_wire_cannot_carry_still_solves() -> None:
    """A sample made in Python may carry any source id, where the wire carries a
    byte: the solver's table of stamp spreads takes it as one it does not know."""
    samples = {tag.site: RawSample(Quat(tag.node, (1.0, 0.0, 0.0, 0.0)), 0, 10, 300 + i)
               for i, tag in enumerate(TAGS)}  # fmt: skip
    out = BodySolver().solve(samples)
    assert out.sources == {tag.site.raw_key: 10 for tag in TAGS}
