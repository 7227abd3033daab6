"""Soak: one full body (15 nodes x 100 Hz) through the gateway and the recorder for minutes.

The parts run as the user runs them: a router, ``bodynet gateway`` and
``bodynet record`` as processes, fed by a feeder process that publishes as
the bridges do (:func:`_feed`: one ``SitePublisher``, so Zenoh advanced
publishers with their cache and heartbeat, congestion control BLOCK,
liveliness tokens and the bridge's health each second; the recorder's
advanced subscribers then run their recovery as in use). Passing means zero
loss (every sample sent is counted by the gateway, ``body/@health/gateway``,
and is in the recording) and memory growth under 5%: the resident set size of
the gateway and of the recorder, sampled each second, at the end (median of
the last 10 samples) against the end of the warm-up (median of its last 10),
and the growth of their anonymous memory (``RssAnon``: what the process itself
allocated) over the same resident set at the warm-up. Both must stay under the
limit: the resident set also holds pages of the shared libraries, which the
kernel drops and maps again as other work needs memory (on a busy machine it
can halve while the heap grows).
A feed that sent nothing, or whose process failed, does not pass. The machine's
load average is sampled with the memory (``load_1min``): on a shared machine a
loss may be the load's, and the result says how loaded it was.

    .venv/bin/bodynet bench --only soak --minutes 10
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import signal
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import psutil

from bodynet.bench import machine
from bodynet.bench.faults import FaultError, Inbox, _subscribe, loopback
from bodynet.core import keys

GROWTH_LIMIT = 0.05
RATE_HZ = 100.0


def _feed(endpoint: str, seconds: float, sent: Any, ready: Any, rate_hz: float = RATE_HZ) -> None:
    """One emulated body's 15 IMU tags at ``rate_hz`` through a bridge's
    ``SitePublisher`` (as ``bodynet node imu``), for ``seconds`` once ``ready``
    is set; ``sent`` counts the samples published."""
    from bodynet.core.messages import Source
    from bodynet.nodes.emulator import BodyEmulator, imu_tags
    from bodynet.nodes.motion import ROUTINES
    from bodynet.nodes.publisher import SitePublisher
    from bodynet.session import open_session, session_config

    session = open_session(session_config("client", connect=[endpoint]))
    tags = imu_tags()
    body = BodyEmulator(ROUTINES["walk"], tags)
    frames = [body.sample(k / rate_hz)[0] for k in range(int(rate_hz))]  # a second, looped
    publisher = SitePublisher(session, {t.node: t.site for t in tags}, Source.IMU_CENTRAL,
                              "soak", 1.0 / rate_hz)  # fmt: skip
    ready.wait()
    start = time.monotonic()
    tick = 0
    while time.monotonic() - start < seconds:
        for reading in frames[tick % len(frames)]:
            publisher.publish(reading, tick)
        with sent.get_lock():
            sent.value += len(frames[0])
        tick += 1
        time.sleep(max(0.0, start + tick / rate_hz - time.monotonic()))
    publisher.close()
    session.close()


def anon_bytes(pid: int) -> int:
    """The process's resident anonymous memory (``RssAnon`` of ``/proc/PID/status``)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no RssAnon in /proc/{pid}/status")


def _sample_memory(watched: dict[str, psutil.Process], rss: dict[str, list[int]],
                   anon: dict[str, list[int]]) -> None:  # fmt: skip
    for name, p in watched.items():
        rss[name].append(p.memory_info().rss)
        anon[name].append(anon_bytes(p.pid))


def _owned_growth(rss: list[int], anon: list[int], warmup: int) -> float:
    """Anonymous memory's growth (end against warm-up, medians as :func:`_growth`)
    over the resident set at the warm-up."""
    a, r = _growth(anon, warmup), _growth(rss, warmup)
    return (a["end_mb"] - a["baseline_mb"]) / r["baseline_mb"]


def _growth(rss: list[int], warmup: int) -> dict[str, float]:
    base = statistics.median(rss[max(0, warmup - 10) : warmup] or rss[:1])
    end = statistics.median(rss[-10:])
    return {"baseline_mb": base / 2**20, "end_mb": end / 2**20, "max_mb": max(rss) / 2**20,
            "growth": (end - base) / base}  # fmt: skip


def run(minutes: float = 10.0, out_dir: Path = Path("bench-results"),
        warmup_s: float = 20.0) -> dict[str, Any]:  # fmt: skip
    """Soak for ``minutes``; print the verdict; write ``soak.json`` and ``soak.md``."""
    from bodynet.clients.mcap_store import read_raw

    seconds = minutes * 60.0
    ctx = mp.get_context("spawn")
    sent, ready = ctx.Value("q", 0), ctx.Event()
    with tempfile.TemporaryDirectory() as tmp, loopback(Path(tmp)) as (endpoint, probe, procs, _):
        inbox = Inbox()
        health = _subscribe(probe, inbox, keys.health_key("gateway"), json.loads)
        gw = procs.start("gateway", "--mode", "client", "-e", endpoint)
        record = Path(tmp) / "soak.mcap"
        rec = procs.start("record", "-o", str(record), "-e", endpoint)
        inbox.wait(lambda k, v: True, 120, "the gateway's health")  # it has started
        feeder = ctx.Process(target=_feed, args=(endpoint, seconds, sent, ready))
        feeder.start()
        watched = {"gateway": psutil.Process(gw.pid), "recorder": psutil.Process(rec.pid)}
        rss: dict[str, list[int]] = {name: [] for name in watched}
        anon: dict[str, list[int]] = {name: [] for name in watched}
        load: list[float] = []
        tick = threading.Event()
        threading.Event().wait(2.0)  # the feeder has imported and declared its publishers
        ready.set()
        start = time.monotonic()
        cpu0 = {name: sum(p.cpu_times()[:2]) for name, p in watched.items()}
        while feeder.is_alive():
            _sample_memory(watched, rss, anon)
            load.append(os.getloadavg()[0])
            if len(load) % 60 == 0:  # a long soak says how it goes, a line a minute
                print(f"soak: {len(load) // 60} min, RSS (anonymous) gateway "
                      f"{rss['gateway'][-1] / 2**20:.1f} ({anon['gateway'][-1] / 2**20:.1f}) MB, "
                      f"recorder {rss['recorder'][-1] / 2**20:.1f} "
                      f"({anon['recorder'][-1] / 2**20:.1f}) MB, {sent.value} samples sent, "
                      f"load average {load[-1]:.1f}", flush=True)  # fmt: skip
            tick.wait(max(0.0, start + len(rss["gateway"]) - time.monotonic()))
        feeder.join()
        fed_s = time.monotonic() - start
        cpu = {name: (sum(p.cpu_times()[:2]) - cpu0[name]) / fed_s for name, p in watched.items()}
        counted = 0

        def all_counted(key: str, value: Any) -> bool:
            nonlocal counted
            counted = int(value.get("samples", 0))
            return counted >= sent.value

        with contextlib.suppress(FaultError):  # loss: reported below
            inbox.wait(all_counted, 30, "the gateway counting every sample")
        health.undeclare()
        for p in (rec, gw):
            p.send_signal(signal.SIGINT)
            p.wait(timeout=60)
        recorded = sum(1 for _ in read_raw(record))
    warmup = int(warmup_s)
    result = {
        "machine": machine.describe(),
        "minutes": minutes,
        "warmup_s": warmup_s,
        "sent": sent.value,
        "feeder_exitcode": feeder.exitcode,
        "gateway_counted": counted,
        "recorded": recorded,
        "lost_gateway": sent.value - counted,
        "lost_recorder": sent.value - recorded,
        "memory": {name: _growth(v, warmup) for name, v in rss.items()},
        "anon_memory": {name: _growth(v, warmup) for name, v in anon.items()},
        # what the process itself allocated since the warm-up, as a share of its resident
        # set then: a leak shows here even while the kernel drops library pages from RSS
        "owned_growth": {name: _owned_growth(rss[name], anon[name], warmup) for name in rss},
        "cpu_s_per_s": {name: round(v, 3) for name, v in cpu.items()},
        "load_1min": {"median": statistics.median(load or [0.0]), "max": max(load or [0.0])},
        "rss_mb": {name: [round(x / 2**20, 2) for x in v] for name, v in rss.items()},
        "anon_mb": {name: [round(x / 2**20, 2) for x in v] for name, v in anon.items()},
    }
    result["pass"] = (
        sent.value > 0
        and feeder.exitcode == 0
        and result["lost_gateway"] == 0
        and result["lost_recorder"] == 0
        and all(m["growth"] < GROWTH_LIMIT for m in result["memory"].values())
        and all(g < GROWTH_LIMIT for g in result["owned_growth"].values())
    )
    table = _table(result)
    print(f"\nSoak, one body (15 nodes x 100 Hz) through gateway and recorder "
          f"({machine.line(result['machine'])})\n\n{table}")  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "soak.json").write_text(json.dumps(result, indent=2))
    (out_dir / "soak.md").write_text(table)
    return result


def _table(result: dict[str, Any]) -> str:
    """The soak's result as one Markdown table row, with its header."""
    mem, anon_mem = result["memory"], result["anon_memory"]

    def warm_end(m: dict[str, float]) -> str:
        return f"{m['baseline_mb']:.1f} -> {m['end_mb']:.1f} ({100 * m['growth']:+.1f}%)"

    return (
        "| minutes | samples sent | lost at gateway | lost in recording | gateway RSS MB "
        "(warm -> end) | gateway anonymous MB | recorder RSS MB (warm -> end) | "
        "recorder anonymous MB | load average (median, max) | pass |\n"
        "|---:|---:|---:|---:|---|---|---|---|---|---|\n"
        f"| {result['minutes']:g} | {result['sent']} | {result['lost_gateway']} | "
        f"{result['lost_recorder']} | "
        f"{warm_end(mem['gateway'])} | {warm_end(anon_mem['gateway'])} | "
        f"{warm_end(mem['recorder'])} | {warm_end(anon_mem['recorder'])} | "
        f"{result['load_1min']['median']:.1f}, {result['load_1min']['max']:.1f} | "
        f"{'yes' if result['pass'] else 'NO'} |\n"
    )
