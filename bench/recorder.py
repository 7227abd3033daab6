"""Recorder messages/s beside the bare ``mcap`` writer, in one run.

Baseline: the ``mcap`` library's own ``Writer`` (same 1 MiB zstd chunks)
storing each message's bytes as they came off the wire, no decoding. bodynet's
``McapSink`` does what the recorder does per message: a raw sample is decoded
and stored as JSON with a schema (so generic MCAP tools can plot it); a pose
is stored as it came, with its Foxglove transforms made from its segments (2 s
of a walking body's poses, as the gateway publishes them). A third
row is the whole recorder live: a feeder process publishes raw samples as
fast as Zenoh takes them (congestion control BLOCK, so nothing is dropped) and
``Recorder`` writes them; its rate is what a recording can absorb end to end.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from bodynet.bench import machine
from bodynet.bench.decode import _rate
from bodynet.clients.mcap_store import CHUNK_BYTES, McapSink
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.messages import RawSample, Source

CHUNK = CHUNK_BYTES


def _body_samples(ticks: int) -> tuple[list[str], list[bytes]]:
    """Keys and wire payloads of ``ticks`` ticks of one emulated IMU body."""
    from bodynet.nodes.emulator import BodyEmulator, imu_tags
    from bodynet.nodes.motion import ROUTINES

    tags = imu_tags()
    body = BodyEmulator(ROUTINES["walk"], tags)
    topics, payloads = [], []
    for k in range(ticks):
        for tag, reading in zip(tags, body.sample(k / 100)[0], strict=True):
            topics.append(tag.site.raw_key)
            payloads.append(raw_sample.encode(RawSample(reading, k, k * 10_000_000, Source.CAN)))
    return topics, payloads


def _pose_payloads(ticks: int) -> list[bytes]:
    """``ticks`` whole-body pose messages of one walking body at 100 Hz, as the
    gateway publishes them."""
    from bodynet.gateway.frames import pose_frame
    from bodynet.gateway.solver import BodySolver
    from bodynet.nodes.emulator import BodyEmulator, imu_tags
    from bodynet.nodes.motion import ROUTINES

    tags = imu_tags()
    body, solver = BodyEmulator(ROUTINES["walk"], tags), BodySolver()
    out = []
    for k in range(ticks):
        t_ns = 1_700_000_000_000_000_000 + k * 10_000_000
        readings = body.sample(k / 100)[0]
        latest = {t.site: RawSample(r, k, t_ns, Source.CAN)
                  for t, r in zip(tags, readings, strict=True)}  # fmt: skip
        out.append(pose.encode(pose_frame(solver.solve(latest), k, [])))
    return out


def _bare(path: Path, topics: list[str], payloads: list[bytes]) -> Callable[[], int]:
    def work() -> int:
        with path.open("wb") as f:
            writer = Writer(f, chunk_size=CHUNK, compression=CompressionType.ZSTD)
            writer.start(profile="", library="bare")
            schema = writer.register_schema("bytes", "", b"")
            channels: dict[str, int] = {}
            for i, (topic, data) in enumerate(zip(topics, payloads, strict=True)):
                channel = channels.get(topic)
                if channel is None:
                    channel = channels[topic] = writer.register_channel(topic, "", schema)
                writer.add_message(channel, i, data, i)
            writer.finish()
        return len(payloads)

    return work


def _sink_raw(path: Path, topics: list[str], payloads: list[bytes]) -> Callable[[], int]:
    def work() -> int:
        sink = McapSink(path)
        for topic, data in zip(topics, payloads, strict=True):
            sample = raw_sample.decode(data)
            sink.write_raw(topic, sample, sample.t_ns)
        sink.close()
        return len(payloads)

    return work


def _sink_pose(path: Path, payloads: list[bytes]) -> Callable[[], int]:
    """What the recorder does with each whole-body pose message: store it as it
    came, with its Foxglove transforms (``McapSink.write_pose_message``)."""

    def work() -> int:
        sink = McapSink(path)
        for data in payloads:
            sink.write_pose_message("body/pose", data)
        sink.close()
        return len(payloads)

    return work


def _flood(endpoint: str, stop: Any) -> None:
    """Publish one body's raw samples back to back until ``stop``."""
    import zenoh

    from bodynet.bench.harness import client

    topics, payloads = _body_samples(100)
    session = client(endpoint)
    block = zenoh.CongestionControl.BLOCK
    pubs = {t: session.declare_publisher(t, congestion_control=block) for t in set(topics)}
    while not stop.is_set():
        for topic, data in zip(topics, payloads, strict=True):
            pubs[topic].put(data)
    session.close()


def _live(seconds: float, path: Path) -> dict[str, float]:
    """Messages/s the ``Recorder`` writes of a flood of raw samples through Zenoh."""
    from bodynet.bench.harness import client as open_client
    from bodynet.bench.harness import free_endpoint
    from bodynet.bench.harness import router as open_router
    from bodynet.clients.recorder import Recorder

    endpoint = free_endpoint()
    router = open_router(endpoint)
    client = open_client(endpoint)
    recorder = Recorder(client, path)
    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    feeder = ctx.Process(target=_flood, args=(endpoint, stop))
    feeder.start()
    wait = threading.Event()
    deadline = time.monotonic() + 60
    while recorder.messages < 1000 and time.monotonic() < deadline:
        wait.wait(0.05)
    m0, t0 = recorder.messages, time.monotonic()
    wait.wait(seconds)
    m1, t1 = recorder.messages, time.monotonic()
    stop.set()
    feeder.join(timeout=30)
    recorder.close()
    client.close()
    router.close()
    return {"messages": m1 - m0, "per_s": (m1 - m0) / (t1 - t0)}


def run(seconds: float = 1.0, out_dir: Path = Path("bench-results")) -> dict[str, Any]:
    """Run the recorder benchmark; print its table; write ``recorder.{json,md}``."""
    topics, payloads = _body_samples(200)  # 3000 raw samples
    poses = _pose_payloads(200)  # 2 s of walking
    rows: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "bench.mcap"
        bare = _rate(_bare(f, topics, payloads), seconds)
        ours = _rate(_sink_raw(f, topics, payloads), seconds)
        rows.append({"name": "raw samples (McapSink: decode, JSON, write)", "bodynet_per_s": ours,
                     "baseline_per_s": bare})  # fmt: skip
        bare = _rate(_bare(f, ["body/pose"] * len(poses), poses), seconds)
        ours = _rate(_sink_pose(f, poses), seconds)
        rows.append({"name": "whole-body poses (McapSink: as received, + transforms)",
                     "bodynet_per_s": ours, "baseline_per_s": bare})  # fmt: skip
        live = _live(max(seconds, 1.0), Path(tmp) / "live.mcap")
    for r in rows:
        r["ratio"] = float(r["bodynet_per_s"]) / float(r["baseline_per_s"])  # type: ignore[arg-type]
    result = {"machine": machine.describe(), "seconds": seconds, "rows": rows,
              "recorder_live": live, "pose_bytes": len(poses[0])}  # fmt: skip
    table = (
        "| messages | bodynet /s | bare mcap writer /s | ratio |\n|---|---:|---:|---:|\n"
        + "".join(
            f"| {r['name']} | {r['bodynet_per_s']:,.0f} | {r['baseline_per_s']:,.0f} | "
            f"{r['ratio']:.2f} |\n"
            for r in rows
        )
        + f"| raw samples, whole recorder live through Zenoh | {live['per_s']:,.0f} | | |\n"
    )
    print(f"\nRecorder against the bare mcap writer ({machine.line(result['machine'])})\n\n{table}")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "recorder.json").write_text(json.dumps(result, indent=2))
    (out_dir / "recorder.md").write_text(table)
    return result
