"""Raw-to-pose latency of the gateway beside a bare Zenoh relay, in one run.

Five parties on loopback: a router; a feeder publishing one emulated body's
raw samples (15 nodes at 100 Hz) stamped with the time of publishing; a bare
relay that republishes every raw payload unchanged (subscribe, put, no work);
the real gateway; and a probe that receives both and takes, for each relayed
sample, ``receive time - source time``, and for each pose, ``receive time -
newest source time in the tick``. Relay and gateway run at the same time on
the same feed, so the machine's noise hits both alike; the ratio is the figure
to read. Loss: what the relay and the gateway received against what was sent.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

RATE_HZ = 100.0


def _session(endpoint: str) -> Any:
    from bodynet.session import open_session, session_config

    return open_session(session_config("client", connect=[endpoint]))


def _feed(endpoint: str, seconds: float, sent: Any, ready: Any, rate_hz: float = RATE_HZ) -> None:
    import zenoh

    from bodynet.core.codecs import raw_sample
    from bodynet.core.messages import RawSample, Source
    from bodynet.nodes.emulator import BodyEmulator, imu_tags
    from bodynet.nodes.motion import ROUTINES

    session = _session(endpoint)
    tags = imu_tags()
    body = BodyEmulator(ROUTINES["walk"], tags)
    frames = [
        body.sample(k / rate_hz)[0] for k in range(int(rate_hz))
    ]  # a second of motion, looped
    block = zenoh.CongestionControl.BLOCK
    pubs = [session.declare_publisher(t.site.raw_key, congestion_control=block) for t in tags]
    ready.wait()
    start = time.monotonic()
    tick = 0
    while time.monotonic() - start < seconds:
        for pub, reading in zip(pubs, frames[tick % len(frames)], strict=True):
            pub.put(raw_sample.encode(RawSample(reading, tick, time.time_ns(), Source.IMU_CENTRAL)))
            sent.value += 1
        tick += 1
        time.sleep(max(0.0, start + tick / rate_hz - time.monotonic()))
    session.close()


def _relay(endpoint: str, stop: Any) -> None:
    session = _session(endpoint)
    pubs: dict[str, Any] = {}

    def on_raw(sample: Any) -> None:
        key = str(sample.key_expr)
        pub = pubs.get(key) or pubs.setdefault(key, session.declare_publisher("bench/relay/" + key))
        pub.put(sample.payload)

    sub = session.declare_subscriber("body/*/*/*/raw", on_raw)
    stop.wait()
    sub.undeclare()
    session.close()


def _gateway(endpoint: str, stop: Any, samples: Any) -> None:
    import threading

    from bodynet.gateway.service import Gateway

    session = _session(endpoint)
    gateway = Gateway(session)
    done = threading.Event()
    thread = threading.Thread(target=gateway.run, args=(done,))
    thread.start()
    stop.wait()
    done.set()
    thread.join()
    samples.value = gateway.samples
    gateway.close()
    session.close()


def run(
    seconds: float = 5.0,
    out_dir: Path = Path("bench-results"),
    rate_hz: float = RATE_HZ,
    name: str = "gateway",
) -> dict[str, Any]:
    """Run the comparison, each node sending ``rate_hz``; print a table; write
    ``<name>.json`` and ``<name>.md``."""
    import socket

    from bodynet.core.codecs import pose, raw_sample
    from bodynet.session import open_session, session_config

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_session(session_config("router", listen=[endpoint]))
    ctx = mp.get_context("spawn")
    sent, gw_samples = ctx.Value("q", 0), ctx.Value("q", 0)
    stop, ready = ctx.Event(), ctx.Event()
    relay = ctx.Process(target=_relay, args=(endpoint, stop))
    gateway = ctx.Process(target=_gateway, args=(endpoint, stop, gw_samples))
    feeder = ctx.Process(target=_feed, args=(endpoint, seconds, sent, ready, rate_hz))
    for p in (relay, gateway, feeder):
        p.start()
    probe = open_session(session_config("client", connect=[endpoint]))
    relay_lat: list[int] = []
    pose_lat: list[int] = []
    subs = [
        probe.declare_subscriber("bench/relay/**", lambda s: relay_lat.append(
            time.time_ns() - raw_sample.decode(s.payload.to_bytes()).t_ns)),
        probe.declare_subscriber("body/pose", lambda s: pose_lat.append(
            time.time_ns() - pose.decode(s.payload.to_bytes()).t_ns)),
    ]  # fmt: skip
    time.sleep(2.0)  # subscriptions propagate; the gateway process has imported Pinocchio
    ready.set()
    feeder.join()
    time.sleep(0.5)  # the last samples drain
    stop.set()
    for p in (relay, gateway):
        p.join(timeout=30)
    for sub in subs:
        sub.undeclare()
    probe.close()
    router.close()

    def stats(lat: list[int]) -> dict[str, float]:
        if not lat:
            return {"n": 0, "p50_ms": float("nan"), "p99_ms": float("nan")}
        arr = np.array(lat) / 1e6
        return {
            "n": len(lat),
            "p50_ms": float(np.percentile(arr, 50)),
            "p99_ms": float(np.percentile(arr, 99)),
        }

    r, g = stats(relay_lat), stats(pose_lat)
    result = {
        "machine": f"{platform.machine()}, {mp.cpu_count()} cores, "
        f"Python {platform.python_version()}",
        "seconds": seconds, "rate_hz_per_node": rate_hz, "nodes": 15, "sent": sent.value,
        "relay": {**r, "received": len(relay_lat)},
        "gateway": {**g, "samples_received": gw_samples.value, "poses": len(pose_lat)},
        "p50_ratio": g["p50_ms"] / r["p50_ms"] if r["n"] and g["n"] else None,
        "p99_ratio": g["p99_ms"] / r["p99_ms"] if r["n"] and g["n"] else None,
    }  # fmt: skip
    table = (
        "| path | messages | lost | p50 ms | p99 ms |\n|---|---:|---:|---:|---:|\n"
        f"| bare relay (raw -> raw) | {len(relay_lat)} | {sent.value - len(relay_lat)} | "
        f"{r['p50_ms']:.2f} | {r['p99_ms']:.2f} |\n"
        f"| gateway (raw -> pose) | {len(pose_lat)} poses from {gw_samples.value} samples | "
        f"{sent.value - gw_samples.value} | {g['p50_ms']:.2f} | {g['p99_ms']:.2f} |\n"
    )
    print(
        f"Gateway vs bare relay, one body (15 nodes x {rate_hz:g} Hz), {seconds:g} s, "
        f"{result['machine']}\n\n{table}\n"
        f"p50 ratio {result['p50_ratio']}, p99 ratio {result['p99_ratio']}"
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(json.dumps(result, indent=2))
    (out_dir / f"{name}.md").write_text(table)
    return result
