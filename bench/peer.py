"""Against a peer: the same sample stream through Lab Streaming Layer, in the same run.

Lab Streaming Layer (liblsl through pylsl) is what motion-capture labs use to
stream samples between programs. Here one LSL outlet carries one emulated
body's samples (15 nodes, each sample ``node, seq, w, x, y, z``, pushed one by
one as bodynet's feeder publishes them, at the same rate) to one inlet in
another process: one hop, stamped with ``pylsl.local_clock()`` at the push,
latency ``local_clock() - stamp`` at the pull (the same clock on one machine).

At the same time the gateway benchmark (``bench.gateway``) runs bodynet's
two hops, raw sample -> router -> gateway (solving the body) -> router ->
client; both see the same machine noise. LSL moves the sample and nothing
else: it is the floor of a one-hop stream, not a gateway.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bodynet.bench import gateway, machine

STREAM = "bodynet-bench"
CHANNELS = 6  # node, seq, w, x, y, z


def _quiet_lsl() -> None:
    """liblsl logs at INFO on stderr; a config file turns it down to errors only."""
    cfg = Path(tempfile.gettempdir()) / "bodynet-lsl_api.cfg"
    cfg.write_text("[log]\nlevel = -3\n")
    os.environ["LSLAPICFG"] = str(cfg)


def _outlet(source_id: str, rate_hz: float, go: Any, stop: Any, sent: Any) -> None:
    _quiet_lsl()
    import pylsl

    from bodynet.nodes.emulator import BodyEmulator, imu_tags
    from bodynet.nodes.motion import ROUTINES

    tags = imu_tags()
    body = BodyEmulator(ROUTINES["walk"], tags)
    frames = [body.sample(k / rate_hz)[0] for k in range(int(rate_hz))]
    info = pylsl.StreamInfo(STREAM, "MoCap", CHANNELS, rate_hz * len(tags), pylsl.cf_double64,
                            source_id)  # fmt: skip
    outlet = pylsl.StreamOutlet(info)
    go.wait()
    start = time.monotonic()
    tick = 0
    while not stop.is_set():
        for reading in frames[tick % len(frames)]:
            outlet.push_sample([reading.node, tick, *reading.wxyz], pylsl.local_clock())
            sent.value += 1
        tick += 1
        time.sleep(max(0.0, start + tick / rate_hz - time.monotonic()))
    del outlet


def _inlet(source_id: str, connected: Any, stop: Any, out: str) -> None:
    _quiet_lsl()
    import pylsl

    streams = pylsl.resolve_byprop("source_id", source_id, timeout=30)
    if not streams:
        Path(out).write_text("[]")
        connected.set()
        return
    inlet = pylsl.StreamInlet(streams[0], max_buflen=10)
    inlet.open_stream(timeout=10)
    connected.set()
    latencies: list[float] = []
    quiet_since = None
    while True:
        sample, stamp = inlet.pull_sample(timeout=0.2)
        if sample is not None:
            latencies.append(pylsl.local_clock() - stamp)
            quiet_since = None
        elif stop.is_set():  # stopped and drained
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since > 0.5:
                break
    inlet.close_stream()
    Path(out).write_text(json.dumps(latencies))


def stats_ms(seconds: list[float] | np.ndarray) -> dict[str, float]:
    """n, p50 and p99 in milliseconds of latencies in seconds."""
    if len(seconds) == 0:
        return {"n": 0, "p50_ms": float("nan"), "p99_ms": float("nan")}
    arr = np.asarray(seconds) * 1e3
    return {"n": int(arr.size), "p50_ms": float(np.percentile(arr, 50)),
            "p99_ms": float(np.percentile(arr, 99))}  # fmt: skip


def run(
    seconds: float = 10.0, out_dir: Path = Path("bench-results"), rate_hz: float = 100.0
) -> dict[str, Any]:
    """bodynet's gateway run and an LSL stream of the same rate side by side;
    writes ``peer.json`` and ``peer.md`` (and the gateway run's ``peer-gateway.*``)."""
    ctx = mp.get_context("spawn")
    source_id = f"bodynet-bench-{os.getpid()}-{time.monotonic_ns()}"
    go, stop, connected = ctx.Event(), ctx.Event(), ctx.Event()
    sent = ctx.Value("q", 0)
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "lsl.json")
        inlet = ctx.Process(target=_inlet, args=(source_id, connected, stop, out))
        outlet = ctx.Process(target=_outlet, args=(source_id, rate_hz, go, stop, sent))
        outlet.start()
        inlet.start()
        connected.wait(timeout=60)
        go.set()
        try:
            ours = gateway.run(seconds, out_dir, (1,), rate_hz=rate_hz, name="peer-gateway")
        finally:
            stop.set()
            outlet.join(timeout=30)
            inlet.join(timeout=30)
        lsl_lat = json.loads(Path(out).read_text()) if Path(out).exists() else []
    lsl = {**stats_ms(lsl_lat), "sent": sent.value, "received": len(lsl_lat),
           "lost": sent.value - len(lsl_lat)}  # fmt: skip
    relay, gw = ours["relay"], ours["gateway"]
    result = {
        "machine": machine.describe(),
        "seconds": seconds,
        "rate_hz_per_node": rate_hz,
        "nodes": 15,
        "lsl_one_hop": lsl,
        "zenoh_relay_two_hops": {**relay, "lost": ours["sent"] - relay["received"]},
        "gateway_two_hops": {**gw, "lost": ours["sent"] - gw["samples_received"]},
        "p99_gateway_over_lsl": gw["p99_ms"] / lsl["p99_ms"] if lsl["n"] and gw["n"] else None,
    }
    table = (
        "| path | hops | messages | lost | p50 ms | p99 ms |\n"
        "|---|---:|---:|---:|---:|---:|\n"
        f"| LSL outlet -> inlet (raw -> raw) | 1 | {lsl['received']} | {lsl['lost']} | "
        f"{lsl['p50_ms']:.2f} | {lsl['p99_ms']:.2f} |\n"
        f"| bodynet bare relay (raw -> router -> relay -> router -> client) | 2 | "
        f"{relay['received']} | {ours['sent'] - relay['received']} | "
        f"{relay['p50_ms']:.2f} | {relay['p99_ms']:.2f} |\n"
        f"| bodynet gateway (raw -> router -> gateway -> router -> pose) | 2 | "
        f"{gw['poses']} poses from {gw['samples_received']} samples | "
        f"{ours['sent'] - gw['samples_received']} | {gw['p50_ms']:.2f} | {gw['p99_ms']:.2f} |\n"
    )
    print(f"\nAgainst Lab Streaming Layer, one body (15 nodes x {rate_hz:g} Hz), {seconds:g} s, "
          f"{machine.line(result['machine'])}\n\n{table}")  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "peer.json").write_text(json.dumps(result, indent=2))
    (out_dir / "peer.md").write_text(table)
    return result
