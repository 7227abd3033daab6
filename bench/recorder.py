"""Recorder messages/s beside the bare ``mcap`` writer, in one run.

Baseline: the ``mcap`` library's own ``Writer`` (same 1 MiB zstd chunks, at the
library's level) storing each message's bytes as they came off the wire, no
decoding. bodynet's ``McapSink`` does what the recorder does per message: a raw
sample is decoded and stored as JSON with a schema (so generic MCAP tools can
plot it); a pose is stored as it came, with its Foxglove transforms made from
its segments at a display's rate (``mcap_store.TF_MIN_GAP_NS``: every other
pose of the 2 s of a walking body's 100 Hz poses, as the gateway publishes
them).
Both rates are per second of the thread's CPU time (the wall clock of a shared
machine counts the other processes too). A third row is the whole recorder
live: a feeder process publishes raw samples as fast as Zenoh takes them
(congestion control BLOCK, so nothing is dropped) and ``Recorder`` writes
them; its rate (wall clock) is what a recording can absorb end to end.

:func:`with_gateway` is the recording in use: ``bodynet gateway`` and
``bodynet record`` as processes on twenty bodies (15 nodes x 100 Hz each, the
realistic feed of ``bench/gateway.py``, through the node bridges' own
publishers), counting what the feeders sent and the gateway published (poses
by their sequence numbers, topology and health as a probe saw them) against
what the file holds.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from bodynet.bench import machine
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


def _rate(work: Callable[[], int], seconds: float) -> float:
    """Items per second of the thread's CPU time of ``work`` (which returns how
    many items it did), run for ``seconds`` of it: on a shared machine the wall
    clock counts the other processes' time too."""
    work()  # warm up
    done, start = 0, time.thread_time()
    while (spent := time.thread_time() - start) < seconds:
        done += work()
    return done / spent


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


def run(seconds: float = 1.0, out_dir: Path = Path("bench-results"), bodies: int = 20,
        gateway_seconds: float = 10.0) -> dict[str, Any]:  # fmt: skip
    """Run the recorder benchmark; print its table; write ``recorder.{json,md}``.
    With ``bodies`` (0: not), also :func:`with_gateway` for ``gateway_seconds``."""
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
        rows.append({"name": "whole-body poses (McapSink: as received, + transforms at 50 Hz)",
                     "bodynet_per_s": ours, "baseline_per_s": bare})  # fmt: skip
        live = _live(max(seconds, 1.0), Path(tmp) / "live.mcap")
    for r in rows:
        r["ratio"] = float(r["bodynet_per_s"]) / float(r["baseline_per_s"])  # type: ignore[arg-type]
    result = {"machine": machine.describe(), "seconds": seconds, "rows": rows,
              "recorder_live": live, "pose_bytes": len(poses[0])}  # fmt: skip
    if bodies:
        result["with_gateway"] = with_gateway(bodies, gateway_seconds)
    table = (
        "| messages (per second of the thread's CPU time) | bodynet /s | bare mcap writer /s "
        "| ratio |\n|---|---:|---:|---:|\n"
        + "".join(
            f"| {r['name']} | {r['bodynet_per_s']:,.0f} | {r['baseline_per_s']:,.0f} | "
            f"{r['ratio']:.2f} |\n"
            for r in rows
        )
        + f"| raw samples, whole recorder live through Zenoh | {live['per_s']:,.0f} | | |\n"
    )
    if bodies:
        table += "\nRecorded in the same run as the gateway:\n\n" + with_gateway_table(
            result["with_gateway"]
        )
    print(f"\nRecorder against the bare mcap writer ({machine.line(result['machine'])})\n\n{table}")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "recorder.json").write_text(json.dumps(result, indent=2))
    (out_dir / "recorder.md").write_text(table)
    return result


def _admin_counter(seen: Counter[str], ticks: dict[str, int]) -> Callable[[Any], None]:
    """A probe's callback: each topology and health message counted by topic with
    its time, each body's ticks (its per-subject gateway health) kept."""

    def on_sample(sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            message = json.loads(sample.payload.to_bytes())
            t_ns = int(message["t_ns"])
        except (ValueError, KeyError, TypeError):
            return
        seen[f"{key} {t_ns}"] += 1
        body = message.get("body") if key.endswith("/@health/gateway") else None
        if isinstance(body, dict):
            ticks[key.split("/", 1)[0]] = int(body.get("ticks", 0))

    return on_sample


def _in_file(path: Path, topics: set[str], since_ns: int, until_ns: int) -> dict[str, Any]:
    """What a recording holds: raw samples per count, the sequence numbers of each
    pose topic, the topology and health messages (topic and time) whose time
    lies in ``[since_ns, until_ns]``, and how many raw samples its gap records
    say are missing between the ones it holds."""
    from mcap.reader import make_reader

    from bodynet.clients.mcap_store import GAPS_TOPIC, channel_counts, read_gaps

    counts = channel_counts(path) or []
    raw = sum(c.messages for c in counts if c.schema == "bodynet.RawSample")
    seqs: dict[str, list[int]] = {}
    admin: Counter[str] = Counter()
    wanted = [c.topic for c in counts if c.schema in ("bodynet.PoseFrame", "bodynet.Topology",
                                                      "bodynet.Health")]  # fmt: skip
    with path.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(topics=wanted):
            if schema is not None and schema.name == "bodynet.PoseFrame":
                head = pose.glance(message.data)
                seq = head.seq if head is not None else pose.decode(message.data).seq
                seqs.setdefault(channel.topic, []).append(seq)
            elif since_ns <= message.log_time <= until_ns and channel.topic in topics:
                admin[f"{channel.topic} {message.log_time}"] += 1
    gaps = sum(c.messages for c in counts if c.topic == GAPS_TOPIC)
    raw_between = sum(g.missing for g in read_gaps(path) if g.topic.endswith("/raw"))
    return {"raw": raw, "seqs": seqs, "admin": admin, "gaps": gaps, "raw_between": raw_between}


def with_gateway(bodies: int = 20, seconds: float = 10.0, feed: str = "realistic",
                 rate_hz: float = 100.0) -> dict[str, Any]:  # fmt: skip
    """``bodies`` bodies' raw samples, poses, topology and health recorded by
    ``bodynet record`` in the same run as ``bodynet gateway`` (processes, on
    loopback), each body's 15 nodes at ``rate_hz`` as ``feed`` says
    (``nodes.timing.feed_schedule``); what was sent and published against what
    the file holds. Lost: raw samples sent and not in the file, poses missing from
    their topic's run of sequence numbers (1 to the last the gateway published:
    its ticks, from each body's health), topology and health messages a probe saw
    in the measured window and the file lacks."""
    from bodynet.core import keys

    with tempfile.TemporaryDirectory() as tmp:
        run = _record_with_gateway(Path(tmp), bodies, seconds, feed, rate_hz)
    ticks, held = run["ticks"], run["held"]
    whole = [keys.pose_key(), *(keys.pose_key(b) for b in keys.BRANCHES)]
    poses_published = poses_held = poses_lost = 0
    for who, published in ticks.items():
        prefix = "" if bodies == 1 else f"{who}/"
        for topic in whole:
            seq = set(held["seqs"].get(prefix + topic, ()))
            last = max(published, *seq) if seq else published
            poses_published += last
            poses_held += len(seq)
            poses_lost += last - len(seq & set(range(1, last + 1)))
    admin_seen, admin_held = run["admin_seen"], held["admin"]
    result = {
        "bodies": bodies, "seconds": seconds, "feed": feed, "rate_hz_per_node": rate_hz,
        "raw_sent": run["sent"], "raw_recorded": held["raw"],
        "raw_lost": run["sent"] - held["raw"],
        # of those, missing between samples the file holds (its gap records); the
        # rest before a topic's first or after its last
        "raw_lost_between": held["raw_between"],
        "poses_published": poses_published, "poses_recorded": poses_held,
        "poses_lost": poses_lost,
        "ticks_delivered": sum(ticks.values()) / (bodies * seconds * rate_hz),
        "admin_seen": sum(admin_seen.values()), "admin_recorded": sum(admin_held.values()),
        "admin_lost": sum((admin_seen - admin_held).values()), "gap_records": held["gaps"],
        "cpu_ms_per_body_s": {k: 1e3 * v / seconds / bodies for k, v in run["cpu_s"].items()},
    }  # fmt: skip
    result["lost"] = result["raw_lost"] + poses_lost + result["admin_lost"]
    return result


def _record_with_gateway(tmp: Path, bodies: int, seconds: float, feed: str,
                         rate_hz: float) -> dict[str, Any]:  # fmt: skip
    import signal

    import psutil

    from bodynet.bench.faults import loopback
    from bodynet.bench.gateway import _feed
    from bodynet.clients.recorder import DEFAULT_KEYS
    from bodynet.core import keys

    ctx = mp.get_context("spawn")
    sent, ready = ctx.Value("q", 0), ctx.Event()
    finished, hold = ctx.Value("i", 0), ctx.Event()  # the feeders done; may close
    seen: Counter[str] = Counter()
    ticks: dict[str, int] = {}
    waiting = threading.Event()
    with loopback(tmp) as (endpoint, probe, procs, _):
        on_admin = _admin_counter(seen, ticks)
        subs = [probe.declare_subscriber(k, on_admin)
                for k in (keys.TOPOLOGY, keys.all_health())
                for k in (k, f"{keys.ANY_SUBJECT}/{k}")]  # fmt: skip
        gw = procs.start("gateway", "--mode", "client", "-e", endpoint,
                         *(["--all-subjects"] if bodies > 1 else []))  # fmt: skip
        path = tmp / "bodies.mcap"
        rec = procs.start("record", "-o", str(path), "-e", endpoint, *DEFAULT_KEYS,
                          *(f"{keys.ANY_SUBJECT}/{k}" for k in DEFAULT_KEYS))  # fmt: skip
        # the gateway says it serves; the recorder's pose subscription reaches the router
        log, poses = tmp / "processes.log", probe.declare_publisher(f"s00/{keys.pose_key()}")
        _wait(lambda: log.exists() and "serving on" in log.read_text()
              and poses.matching_status.matching, 120, "the gateway and the recorder")  # fmt: skip
        poses.undeclare()
        feeders = [ctx.Process(target=_feed, args=(endpoint, seconds, sent, ready,
                                                   range(i, min(i + 10, bodies)), bodies,
                                                   rate_hz, feed, finished, hold, True))
                   for i in range(0, bodies, 10)]  # fmt: skip
        for f in feeders:
            f.start()
        waiting.wait(2.0)  # the feeders have imported and declared their publishers
        watched = {"gateway": psutil.Process(gw.pid), "recorder": psutil.Process(rec.pid)}
        cpu0 = {name: sum(p.cpu_times()[:2]) for name, p in watched.items()}
        since_ns = time.time_ns()
        ready.set()
        _wait(lambda: finished.value >= len(feeders), seconds + 120, "the feeders")
        # a recorder that is behind holds the feeders back (congestion control BLOCK):
        # they keep their sessions until it has caught up, or what their queues
        # hold would be dropped with them
        _wait(_quiet(path), 120, "the recorder to catch up")
        hold.set()
        for f in feeders:
            f.join()
        # the last (stale) ticks made, each body's count of them in its next health
        waiting.wait(1.0)
        ticks.clear()
        _wait(lambda: len(ticks) >= bodies, 60, "every body's health")
        waiting.wait(2.0)  # the last poses reach the recorder
        cpu_s = {name: sum(p.cpu_times()[:2]) - cpu0[name] for name, p in watched.items()}
        published = dict(ticks)
        until_ns = time.time_ns() - 1_000_000_000  # what the probe saw had a second to arrive
        for p in (rec, gw):
            p.send_signal(signal.SIGINT)
            p.wait(timeout=60)
        for sub in subs:
            sub.undeclare()
    admin_seen = Counter({k: n for k, n in seen.items()
                          if since_ns <= int(k.rsplit(" ", 1)[1]) <= until_ns})  # fmt: skip
    topics = {k.rsplit(" ", 1)[0] for k in admin_seen}
    return {"sent": sent.value, "ticks": published, "cpu_s": cpu_s, "admin_seen": admin_seen,
            "held": _in_file(path, topics, since_ns, until_ns)}  # fmt: skip


def _quiet(path: Path, bytes_per_s: float = 64_000, for_s: float = 1.5) -> Callable[[], bool]:
    """A test that ``path`` (a recording) has grown by less than ``bytes_per_s``
    for ``for_s`` (its chunks close every 0.5 s: a recorder writing a backlog of
    raw samples adds megabytes a second, one that has caught up a few kB)."""
    last = [path.stat().st_size if path.exists() else 0, time.monotonic(), time.monotonic()]

    def done() -> bool:
        size, now = path.stat().st_size if path.exists() else 0, time.monotonic()
        if size - last[0] > bytes_per_s * max(now - last[1], 0.1):
            last[2] = now  # still growing: quiet from now on, maybe
        last[0], last[1] = size, now
        return now - last[2] >= for_s

    return done


def _wait(done: Callable[[], bool], timeout: float, what: str) -> None:
    deadline, waiting = time.monotonic() + timeout, threading.Event()
    while not done():
        if time.monotonic() > deadline:
            raise RuntimeError(f"waited {timeout:g} s for {what}")
        waiting.wait(0.1)


def with_gateway_table(r: dict[str, Any]) -> str:
    """The row of :func:`with_gateway` as a Markdown table."""
    cpu = r["cpu_ms_per_body_s"]
    return (
        "| bodies | feed | raw samples sent / in file | poses published / in file "
        "| topology + health seen / in file | lost | gateway ticks delivered "
        "| CPU ms per body-second, gateway / recorder |\n"
        "|---:|---|---:|---:|---:|---:|---:|---:|\n"
        f"| {r['bodies']} | {r['feed']} | {r['raw_sent']} / {r['raw_recorded']} "
        f"| {r['poses_published']} / {r['poses_recorded']} "
        f"| {r['admin_seen']} / {r['admin_recorded']} | {r['lost']} "
        f"| {100 * r['ticks_delivered']:.0f}% | {cpu['gateway']:.0f} / {cpu['recorder']:.0f} |\n"
    )
