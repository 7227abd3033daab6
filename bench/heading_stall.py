"""How long a calibrated body's poses stall while another body's heading is searched.

``.venv/bin/python -m bodynet.bench.heading_stall [MODE [SECONDS]]``, MODE ``aside`` (the gateway's
own: the searches' fits in a thread), ``process`` (in a process of their own),
``inline`` (in the worker, as before) or ``none`` (no search: the floor). Live on
loopback Zenoh: a router and the real gateway (this process, all subjects), a
feeder process publishing the bodies' raw samples at 50 Hz (15 tags each), a
probe process taking every pose's arrival time. Body ``a``: 6-axis tags of their
own calibrated in an N-pose, then walking and reaching, a bow at 6 s
(``heading_protocol``: every kind of search); ``NB`` bodies (environment, default
1) ``b0``...: calibrated, heading fixed. Prints, over the time a's search runs,
the longest and p99 gap between consecutive poses of a ``b`` body, and the
longest ``BodyHeading.step`` of a (wall time in the worker)."""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import threading
import time
from typing import Any

import numpy as np

RATE_HZ = 50.0
#: the calibrated bodies beside the searching one (environment ``NB``)
OTHERS = int(os.environ.get("NB", "1"))


def _emulators() -> dict[str, Any]:
    from bodynet.nodes.emulator import BodyEmulator, Headings, Realism, imu_tags
    from bodynet.nodes.motion import heading_protocol

    own = Realism(headings=Headings.INDEPENDENT, quat_noise_deg=1.0)
    protocol = heading_protocol(bow_at_s=6.0)
    others = {f"b{i}": BodyEmulator(protocol, imu_tags(), seed=2 + i) for i in range(OTHERS)}
    return {"a": BodyEmulator(protocol, imu_tags(), realism=own, seed=1), **others}


def _feed(endpoint: str, seconds: float, go: Any, started: Any) -> None:
    import zenoh

    from bodynet.bench.harness import client
    from bodynet.core.codecs import raw_sample
    from bodynet.core.messages import RawSample, Source

    emulators = _emulators()
    session = client(endpoint)
    block = zenoh.CongestionControl.BLOCK
    pubs = {(n, t.site): session.declare_publisher(f"{n}/{t.site.raw_key}",
                                                   congestion_control=block)
            for n, e in emulators.items() for t in e.sensors}  # fmt: skip
    ticks = int(seconds * RATE_HZ)  # the readings first: the emulator must not pace the feed
    frames = {n: [e.sample(1.0 + k / RATE_HZ)[0] for k in range(ticks)]
              for n, e in emulators.items()}  # fmt: skip
    go.wait()
    start = started.value = time.monotonic()
    for k in range(ticks):
        time.sleep(max(0.0, start + k / RATE_HZ - time.monotonic()))
        for name, emulator in emulators.items():
            for tag, reading in zip(emulator.sensors, frames[name][k], strict=True):
                sample = RawSample(reading, k, time.time_ns(), Source.IMU_CENTRAL)
                pubs[(name, tag.site)].put(raw_sample.encode(sample))
    time.sleep(0.5)
    session.close()


def _probe(endpoint: str, ready: Any, stop: Any, out: Any) -> None:
    from bodynet.bench.harness import client

    session = client(endpoint)
    seen: dict[str, list[float]] = {}
    sub = session.declare_subscriber(
        "*/body/pose",
        lambda s: seen.setdefault(str(s.key_expr).split("/")[0], []).append(time.monotonic()),
    )
    ready.set()
    stop.wait()
    sub.undeclare()
    out.put(seen)
    session.close()


def _gateway(endpoint: str, mode: str) -> tuple[Any, Any, list[tuple[float, float, bool]]]:
    """The gateway (not running yet), its session, and a's steps as they come
    (start, wall time, heading still unknown)."""
    from concurrent.futures import ProcessPoolExecutor

    from bodynet.bench.drift import _calibrated
    from bodynet.bench.harness import client
    from bodynet.core.subject import Profile
    from bodynet.gateway import heading
    from bodynet.gateway.aside import AsideFits
    from bodynet.gateway.service import Gateway

    emulators = _emulators()
    steps: list[tuple[float, float, bool]] = []
    step = heading.BodyHeading.step
    session = client(endpoint)
    gw = Gateway(session, all_subjects=True)

    def timed(self: heading.BodyHeading, *args: Any) -> Any:
        start = time.perf_counter()
        out = step(self, *args)
        if self is gw._bodies["a"].heading:
            steps.append((start, time.perf_counter() - start, bool(self.unknown)))
        return out

    heading.BodyHeading.step = timed  # type: ignore[method-assign]
    if mode == "process":  # spawned: a fork would copy Zenoh's threads mid-flight
        gw.fits = AsideFits(lambda: ProcessPoolExecutor(1, mp.get_context("spawn")))
    elif mode == "inline":
        gw.fits = AsideFits(_Inline)  # type: ignore[arg-type]
    for name in emulators:
        how = "independent" if name == "a" and mode != "none" else "fixed"
        body = gw._body(name)
        assert body is not None
        body.set_profile(_calibrated(emulators[name], Profile(heading=how), 0.2, 0.95, RATE_HZ,
                                     "npose"))  # fmt: skip
    return gw, session, steps


def _serve(gw: Any, endpoint: str, seconds: float) -> tuple[dict[str, list[float]], Any, int]:
    """The gateway serving the feed: the poses' arrival times by subject, when the
    feed started (monotonic, shared), and how many of a's tags are unknown at the end."""
    ctx = mp.get_context("spawn")
    go, ready, stop, seen = ctx.Event(), ctx.Event(), ctx.Event(), ctx.Queue()
    started = ctx.Value("d", 0.0)
    probe = ctx.Process(target=_probe, args=(endpoint, ready, stop, seen))
    feeder = ctx.Process(target=_feed, args=(endpoint, seconds, go, started))
    probe.start()
    feeder.start()
    ready.wait(60)
    done = threading.Event()
    worker = threading.Thread(target=gw.run, args=(done,))
    worker.start()
    time.sleep(3.0)  # the feeder's readings made, the subscriptions matched
    go.set()
    feeder.join()
    stop.set()
    arrivals = seen.get(timeout=60)
    probe.join()
    done.set()
    worker.join()
    return arrivals, started, len(gw._bodies["a"].heading.unknown)


def run(mode: str, seconds: float) -> str:
    """One run; its line."""
    from bodynet.bench.harness import free_endpoint, router
    from bodynet.gateway.heading import BodyHeading

    endpoint = free_endpoint()
    the_router = router(endpoint)
    step = BodyHeading.step  # _gateway times it
    gw, session, steps = _gateway(endpoint, mode)
    try:
        arrivals, started, unknown = _serve(gw, endpoint, seconds)
    finally:
        BodyHeading.step = step  # type: ignore[method-assign]
        gw.close()
        session.close()
        the_router.close()
    start = started.value
    until = max((t for t, _, searching in steps if searching), default=start + seconds) + 0.1
    if mode == "none":
        until = start + seconds
    gaps = np.concatenate([np.diff([t for t in arrivals[f"b{i}"] if start + 0.5 <= t <= until])
                           for i in range(OTHERS)]) * 1e3  # fmt: skip
    walls = np.array([d for _, d, _ in steps]) * 1e3
    return (
        f"{mode}, {OTHERS} other bodies: over {until - start:.1f} s of a's search, their gaps "
        f"{len(gaps)}, gap max "
        f"{gaps.max():.1f} ms, p99 {np.percentile(gaps, 99):.1f}, p50 "
        f"{np.percentile(gaps, 50):.1f}, over 40 ms {(gaps > 40).sum()}; a's step max "
        f"{walls.max():.1f} ms; a's tags unknown at the end {unknown}; load "
        f"{os.getloadavg()[0]:.1f}"
    )


class _Inline:
    """The fits in the worker, as before they ran aside."""

    def submit(self, fn: Any, /, *args: Any) -> Any:
        from bodynet.gateway.heading import INLINE

        return INLINE.submit(fn, *args)

    def shutdown(self, **_: Any) -> None:
        pass


if __name__ == "__main__":
    print(run(sys.argv[1] if len(sys.argv) > 1 else "aside",
              float(sys.argv[2]) if len(sys.argv) > 2 else 14.0))  # fmt: skip
