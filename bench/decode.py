"""Decode rates of the codecs, each beside a bare baseline in the same run.

The baseline of each format is the least work any decoder must do (split,
unhex, unpack), with no validation, events or error handling; the ratio says
what bodynet's checks and streaming cost on top of it. Results go to
``<out>/decode.json`` and ``<out>/decode.md``.

    .venv/bin/bodynet bench --seconds 2
"""

from __future__ import annotations

import binascii
import json
import math
import platform
import struct
import time
from collections.abc import Callable
from pathlib import Path

import can

from bodynet.core.codecs import concentrator, imu_matrix, raw_sample, smartsuit_can
from bodynet.core.messages import OleAccel, Quat, RawSample, Source
from bodynet.nodes.captures import frame_of

CHUNK = 1 << 16
TARGETS = {"imu-central lines": 200_000, "CAN frames (frame codec)": 300_000}


def _rate(work: Callable[[], int], seconds: float) -> float:
    """Items per second of ``work`` (which returns how many items it did)."""
    work()  # warm up
    done, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        done += work()
    return done / elapsed


def _feed_all(make: Callable[[], object], data: bytes) -> Callable[[], int]:
    def work() -> int:
        decoder = make()
        n = 0
        for i in range(0, len(data), CHUNK):
            n += len(decoder.feed(data[i : i + CHUNK]))  # type: ignore[attr-defined]
        return n

    return work


def _quat(i: int) -> tuple[float, float, float, float]:
    a = 0.001 * i
    return (math.cos(a), 0.0, math.sin(a), 0.0)


def measure(seconds: float) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []

    def add(name: str, ours: float, base: float, unit: str) -> None:
        rows.append({"name": name, "unit": unit, "bodynet_per_s": round(ours),
                     "baseline_per_s": round(base), "ratio": round(ours / base, 3),
                     "target_per_s": TARGETS.get(name)})  # fmt: skip

    # IMU central: 15 sensors x 2000 ticks of data-matrix lines
    lines = [imu_matrix.encode_line(Quat(s, _quat(t), bytes(9))) for t in range(2000)
             for s in range(1, 16)]  # fmt: skip
    data = b"".join(lines)
    q4 = struct.Struct("<4f")

    def imu_baseline() -> int:
        for line in data.split(b"\n")[:-1]:
            q4.unpack_from(binascii.a2b_hex(line), 2)
        return len(lines)

    imu = _feed_all(imu_matrix.ImuMatrixDecoder, data)
    add("imu-central lines", _rate(imu, seconds), _rate(imu_baseline, seconds), "lines")

    # SmartSuit CAN: frames of nodes 1-12 and trunk quaternions 13-15
    readings = [OleAccel(n, 100 + i, (1, 2, 1024)) for i in range(1000) for n in range(1, 13)]
    readings += [Quat(n, _quat(i)) for i in range(250) for n in (13, 14, 15)]
    frames = [smartsuit_can.encode_reading(r) for r in readings]
    h4 = struct.Struct("<4h")

    def can_codec() -> int:
        for f in frames:
            smartsuit_can.decode_frame(f)
        return len(frames)

    def can_baseline() -> int:
        for f in frames:
            h4.unpack(f.data)
        return len(frames)

    add("CAN frames (frame codec)", _rate(can_codec, seconds), _rate(can_baseline, seconds),
        "frames")  # fmt: skip

    messages = [can.Message(arbitration_id=f.arbitration_id, data=f.data) for f in frames]

    def can_from_python_can() -> int:
        for m in messages:
            smartsuit_can.decode_frame(frame_of(m))
        return len(messages)

    def python_can_baseline() -> int:
        for m in messages:
            h4.unpack(m.data)
        return len(messages)

    add("CAN frames from python-can Messages", _rate(can_from_python_can, seconds),
        _rate(python_can_baseline, seconds), "frames")  # fmt: skip

    slcan = b"".join(smartsuit_can.encode_slcan(f) for f in frames)

    def slcan_baseline() -> int:
        for line in slcan.split(b"\r")[:-1]:
            h4.unpack(binascii.a2b_hex(line[10:]))
        return len(frames)

    add("slcan lines", _rate(_feed_all(smartsuit_can.SmartSuitSlcanDecoder, slcan), seconds),
        _rate(slcan_baseline, seconds), "lines")  # fmt: skip

    # Data Concentrator: request + short reply, round robin over 15 nodes
    exchange = b"".join(concentrator.request(r.node) + concentrator.encode_reply(r)
                        for r in readings if isinstance(r, OleAccel))  # fmt: skip
    n_replies = exchange.count(b"E")

    def conc_baseline() -> int:
        for part in exchange.split(b"\r\n")[:-1]:
            binascii.a2b_hex(part[2:6] + part[7:11] + part[12:16] + part[17:21])
        return n_replies

    conc = _feed_all(concentrator.ConcentratorDecoder, exchange)
    add("concentrator replies", _rate(conc, seconds),
        _rate(conc_baseline, seconds), "replies")  # fmt: skip

    # raw-sample messages: a batch of a full body's tick, as the gateway will see it
    samples = [RawSample(r, i, 1_700_000_000_000_000_000 + i, Source.CAN)
               for i, r in enumerate(readings)]  # fmt: skip
    batch = raw_sample.encode_batch(samples)
    header = struct.Struct("<2sBBBBHIq")

    def raw_baseline() -> int:
        pos = 0
        for s in samples:
            header.unpack_from(batch, pos)
            pos += 28 if isinstance(s.reading, OleAccel) else 53 + len(s.reading.extra)
        return len(samples)

    raw = _feed_all(raw_sample.RawSampleDecoder, batch)
    add("raw-sample messages (decode)", _rate(raw, seconds),
        _rate(raw_baseline, seconds), "messages")  # fmt: skip

    def raw_encode() -> int:
        raw_sample.encode_batch(samples)
        return len(samples)

    def raw_encode_baseline() -> int:
        b"".join(header.pack(b"BN", 1, 1, 1, 0, 1, s.seq, s.t_ns) for s in samples)
        return len(samples)

    add("raw-sample messages (encode)", _rate(raw_encode, seconds),
        _rate(raw_encode_baseline, seconds), "messages")  # fmt: skip
    return rows


def markdown(rows: list[dict[str, object]]) -> str:
    head = ("| codec | bodynet /s | bare baseline /s | ratio | target /s |\n"
            "|---|---:|---:|---:|---:|\n")  # fmt: skip
    body = "".join(
        f"| {r['name']} | {r['bodynet_per_s']:,} | {r['baseline_per_s']:,} | {r['ratio']:.2f} | "
        f"{'' if r['target_per_s'] is None else format(r['target_per_s'], ',')} |\n"
        for r in rows
    )
    return head + body


def run(seconds: float = 1.0, out_dir: Path = Path("bench-results")) -> int:
    """Run the decode benchmark, print its table, write JSON and Markdown."""
    rows = measure(seconds)
    machine = (
        f"{platform.machine()}, {platform.python_implementation()} {platform.python_version()}"
    )
    table = markdown(rows)
    print(f"Decode rates ({machine}, {seconds:g} s per measurement)\n\n{table}")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "decode.json").write_text(json.dumps({"machine": machine, "rows": rows}, indent=2))
    (out_dir / "decode.md").write_text(table)
    return 0
