"""Raw-to-pose latency of the gateway beside a bare Zenoh relay, in one run.

Parties on loopback: a router; a feeder publishing one emulated body's
raw samples (15 nodes at 100 Hz) stamped with the time of publishing; a bare
relay that republishes every raw payload unchanged (subscribe, put, no work);
the real gateway; and a probe that receives both and takes, for each relayed
sample, ``receive time - source time``, and for each pose, ``receive time -
newest source time in the tick``. Relay and gateway run at the same time on
the same feed, so the machine's noise hits both alike; the ratio is the figure
to read. On two cores each then runs on what the other leaves: ``--apart``
feeds them one after the other instead (the same feed each), rows marked
"apart", with a third phase: a subscriber whose samples never reach Python,
Zenoh's own CPU for receiving the feed (the floor under any gateway's), and
a fourth (one gateway): a Python thread that wakes as often as the gateway's
worker did and takes each sample's bytes, nothing else (the floor under a
worker that polls Zenoh's queues, as the gateway's does). Loss:
what the relay and the gateway received against what was sent. A gateway's
CPU is its process's; the part its worker thread spent (``Gateway.run``: the
Python of every sample and every tick) is beside it, the rest being Zenoh's
threads.

The ``batched`` feed is the realistic one put out as bridges run with
``--batch-ms 5`` do (``nodes.publisher``): each body's samples together on its
batch key, once all fifteen are in or 5 ms after the first, each stamped with
its send's due time (a node's stamp); the relay republishes the batches, and
a relayed sample's latency counts from its own source time, its wait in the
batch included.
"""

from __future__ import annotations

import heapq
import json
import multiprocessing as mp
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from bodynet.nodes.timing import JITTER_S, Sends, feed_schedule

RATE_HZ = 100.0
#: the batched feed's window: a bridge run with ``--batch-ms 5``
BATCH_S = 0.005


def _session(endpoint: str) -> Any:
    from bodynet.session import open_session, session_config

    return open_session(session_config("client", connect=[endpoint]))


def subject(i: int, bodies: int) -> str:
    """Key prefix of body ``i``: none for a single body, else ``s<i>/``."""
    return "" if bodies == 1 else f"s{i:02d}/"


def _feed(endpoint: str, seconds: float, sent: Any, ready: Any, bodies: range, total: int,
          rate_hz: float = RATE_HZ, feed: str = "locked", finished: Any = None,
          hold: Any = None, bridges: bool = False) -> None:  # fmt: skip
    """Publish ``bodies``' raw samples for ``seconds`` once ``ready``, counting them
    in ``sent``; with ``bridges``, through the node bridges' own publishers
    (``bodynet.nodes.publisher``: advanced, with a cache a recovering subscriber
    fetches what it missed from), else plain ones (both congestion control
    BLOCK). With ``hold``: once done, add one to ``finished`` and keep the
    session open until ``hold`` is set (closing it drops what its queues still
    hold, which a subscriber that is behind has not yet had)."""
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
    batched = feed == "batched"
    pubs = _publishers(session, _feed_keys(bodies, total, tags, batched), bridges)
    schedule = feed_schedule(bodies, len(tags), rate_hz, "realistic" if batched else feed)
    rng = np.random.default_rng(bodies.start + 1)
    jitter = 0.0 if feed == "locked" else JITTER_S
    ready.wait()
    start = time.monotonic()
    # each node's next send (nodes.timing.Sends); locked nodes all come due together
    sends = Sends(schedule, start, jitter, rng, end=start + seconds)
    if batched:
        count = _feed_batches(sends, frames, tags, _Batches(pubs, len(tags)), sent)
    else:
        count = 0
        while sends:
            now = time.monotonic()
            if (nxt := sends.next_due) > now:
                with sent.get_lock():
                    sent.value += count
                count = 0
                time.sleep(nxt - now)
                continue
            _, i, tick = sends.pop()
            reading = frames[tick % len(frames)][i % len(tags)]
            stamp = time.time_ns()
            pubs[i].put(raw_sample.encode(RawSample(reading, tick, stamp, Source.IMU_CENTRAL)))
            count += 1
    with sent.get_lock():
        sent.value += count
    if hold is not None:
        with finished.get_lock():
            finished.value += 1
        hold.wait(120)
    session.close()


def _feed_batches(sends: Sends, frames: list[Any], tags: list[Any], batches: _Batches,
                  sent: Any) -> int:  # fmt: skip
    """The batched feed's sends, put out in ``batches``: each sample stamped with
    its send's due time on the wall clock and added ahead, up to when the next
    batch goes out, when the feeder wakes (see :class:`_Batches`). Counts what
    was put in ``sent``; returns what is left to count."""
    from bodynet.core.codecs import raw_sample
    from bodynet.core.messages import RawSample, Source

    wall_ns, mono = time.time_ns(), time.monotonic()
    count = 0
    while sends or batches:
        now = time.monotonic()
        count += batches.flush_due(now)
        while sends and sends.next_due <= max(now, batches.next_due):
            due, i, tick = sends.pop()
            reading = frames[tick % len(frames)][i % len(tags)]
            stamp = wall_ns + round((due - mono) * 1e9)
            payload = raw_sample.encode(RawSample(reading, tick, stamp, Source.IMU_CENTRAL))
            batches.add(i // len(tags), tags[i % len(tags)].site.raw_key, payload, due)
        if batches and (nxt := batches.next_due) > now:  # (none: the sends are done)
            with sent.get_lock():
                sent.value += count
            count = 0
            time.sleep(nxt - now)
    return count


def _feed_keys(bodies: range, total: int, tags: list[Any], batched: bool) -> list[str]:
    """Where the feed puts ``bodies``' samples: a key per body (its bridge's batch
    key) if ``batched``, else one per node (its site's raw key)."""
    from bodynet.core import keys

    if batched:
        return [subject(b, total) + keys.batch_key("bench") for b in bodies]
    return [subject(b, total) + t.site.raw_key for b in bodies for t in tags]


def _publishers(session: Any, keys: list[str], bridges: bool) -> list[Any]:
    """A publisher on each key: the bridges' own (advanced) if ``bridges``, else
    plain ones; both congestion control BLOCK."""
    import zenoh

    from bodynet.nodes.publisher import _raw_publisher

    if bridges:
        return [_raw_publisher(session, k) for k in keys]
    return [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
            for k in keys]  # fmt: skip


class _Batches:
    """Each body's samples put together as a bridge run with ``--batch-ms`` does
    (``nodes.publisher``): out on the body's publisher once every node has one
    in, or :data:`BATCH_S` after the first. The feeder adds each send ahead, at
    its due time, up to when the next batch goes (``next_due``), and wakes
    then: once a batch, not once a sample (150 nodes a feeder woke it some
    15,000 times a second, 0.4 of a core of the two the gateway is measured
    on). Counts are of samples published."""

    def __init__(self, pubs: list[Any], nodes: int) -> None:
        self.pubs, self.nodes = pubs, nodes
        # body -> its open batch's first due time and entries; batches closed, a heap by
        # when each goes out
        self.open: dict[int, tuple[float, list[tuple[str, bytes]]]] = {}
        self.closed: list[tuple[float, int, list[tuple[str, bytes]]]] = []

    def __bool__(self) -> bool:
        return bool(self.open or self.closed)

    @property
    def next_due(self) -> float:
        """When the next batch goes out (``inf``: none waits)."""
        soonest = self.closed[0][0] if self.closed else float("inf")
        return min([soonest, *(first + BATCH_S for first, _ in self.open.values())])

    def add(self, body: int, key: str, payload: bytes, due: float) -> None:
        """A send of ``body`` due at ``due`` (the sends come in the order due)."""
        if (batch := self.open.get(body)) is not None and batch[0] + BATCH_S <= due:
            self._close(body)  # its window ended before this send (a feeder running late)
        entries = self.open.setdefault(body, (due, []))[1]
        entries.append((key, payload))
        if len(entries) == self.nodes:  # every node in: out at once
            self._close(body, due)

    def _close(self, body: int, at: float | None = None) -> None:
        """``body``'s open batch closed, to go out at ``at`` (else its window's end)."""
        first, entries = self.open.pop(body)
        heapq.heappush(self.closed, (first + BATCH_S if at is None else at, body, entries))

    def flush_due(self, now: float) -> int:
        """Put every batch due by ``now``; how many samples they held."""
        from bodynet.core.codecs import raw_batch

        for body, (first, _) in list(self.open.items()):
            if first + BATCH_S <= now:
                self._close(body)
        count = 0
        while self.closed and self.closed[0][0] <= now:
            _, body, entries = heapq.heappop(self.closed)
            self.pubs[body].put(raw_batch.encode(entries))
            count += len(entries)
        return count


#: Every raw key and every bridge's batches, of the namespace-less subject and
#: of named ones.
RAW_SELECTORS = ("body/*/*/*/raw", "*/body/*/*/*/raw", "body/@batch/*", "*/body/@batch/*")


def _subscribed(session: Any, handler: Any, stop: Any, cpu: Any, serving: Any = None) -> None:
    """Subscribe ``handler`` to every raw key until ``stop``; the process's CPU
    meanwhile into ``cpu``."""
    subs = [session.declare_subscriber(sel, handler) for sel in RAW_SELECTORS]
    if serving is not None:
        serving.set()
    cpu0 = time.process_time()
    stop.wait()
    cpu.value = time.process_time() - cpu0
    for sub in subs:
        sub.undeclare()
    session.close()


def _relay(endpoint: str, stop: Any, cpu: Any) -> None:
    session = _session(endpoint)
    pubs: dict[str, Any] = {}

    def on_raw(sample: Any) -> None:
        key = str(sample.key_expr)
        pub = pubs.get(key) or pubs.setdefault(key, session.declare_publisher("bench/relay/" + key))
        pub.put(sample.payload)

    _subscribed(session, on_raw, stop, cpu)


def _floor(endpoint: str, stop: Any, cpu: Any, serving: Any) -> None:
    """Zenoh's own cost of receiving the feed: a subscriber whose samples never
    reach Python (a ring of one, never read)."""
    import zenoh

    _subscribed(_session(endpoint), zenoh.handlers.RingChannel(1), stop, cpu, serving)


def _poller(endpoint: str, stop: Any, cpu: Any, serving: Any, wakes_per_s: float) -> None:
    """The floor under a Python worker that polls Zenoh's queues as the gateway's
    does: the gateway's subscribers, and a thread that wakes ``wakes_per_s``
    times a second (as the gateway's worker did on the same feed) and takes
    each waiting sample's bytes, nothing else. Its process's CPU into ``cpu``."""
    import threading

    import zenoh

    from bodynet.gateway.service import INTAKE_DEPTH

    session = _session(endpoint)
    subs = [session.declare_subscriber(sel, zenoh.handlers.FifoChannel(INTAKE_DEPTH))
            for sel in RAW_SELECTORS]  # fmt: skip

    def poll() -> None:
        while not stop.is_set():
            for sub in subs:
                while (sample := sub.try_recv()) is not None:
                    sample.payload.to_bytes()
            time.sleep(1.0 / wakes_per_s)

    thread = threading.Thread(target=poll)
    serving.set()
    cpu0 = time.process_time()
    thread.start()
    stop.wait()
    cpu.value = time.process_time() - cpu0
    thread.join()
    session.close()


def _gateway(endpoint: str, stop: Any, samples: Any, cpu: Any, all_subjects: bool,
             share: str | None = None, serving: Any = None,
             solves: Any = None, worker: Any = None, wakes: Any = None) -> None:  # fmt: skip
    """A gateway process: its CPU while fed into ``cpu``, its worker thread's
    (``Gateway.run``: every sample's and every tick's Python) into ``worker``,
    and how often that thread woke from a sleep into ``wakes``."""
    import threading

    from bodynet.gateway.service import Gateway

    session = _session(endpoint)
    gateway = Gateway(session, all_subjects=all_subjects, share=share)
    done = threading.Event()
    thread = threading.Thread(target=gateway.run, args=(done,))
    thread.start()
    assert thread.ident is not None
    clock = time.pthread_getcpuclockid(thread.ident)
    if serving is not None:
        serving.set()
    cpu0, worker0 = time.process_time(), time.clock_gettime(clock)
    sleeps0 = gateway.rounds.sleeps
    stop.wait()
    worker_s = time.clock_gettime(clock) - worker0  # within the process's span
    if wakes is not None:
        with wakes.get_lock():
            wakes.value += gateway.rounds.sleeps - sleeps0
    with cpu.get_lock():
        cpu.value += time.process_time() - cpu0
    if worker is not None:
        with worker.get_lock():
            worker.value += worker_s
    done.set()
    thread.join()
    with samples.get_lock():
        samples.value += gateway.samples
    if solves is not None:
        with solves.get_lock():
            solves.value += gateway.solves
    gateway.close()
    session.close()


def _relayed(now_ns: int, key: str, payload: bytes) -> list[int]:
    """The latencies (ns) of the samples of one relayed message: itself, or a batch's."""
    from bodynet.core.codecs import raw_batch, raw_sample

    return [now_ns - raw_sample.source_time(m)
            for _, m in raw_batch.split(key[len("bench/relay/"):], payload)]  # fmt: skip


def _stats(lat: list[int]) -> dict[str, float]:
    if not lat:
        return {"n": 0, "p50_ms": float("nan"), "p99_ms": float("nan")}
    arr = np.array(lat) / 1e6
    return {"n": len(lat), "p50_ms": float(np.percentile(arr, 50)),
            "p99_ms": float(np.percentile(arr, 99))}  # fmt: skip


def _phase(bodies: int, seconds: float, rate_hz: float, feed: str, relay: bool,
           gateways: int, floor: bool = False, poll_hz: float = 0.0) -> dict[str, Any]:  # fmt: skip
    """Feed ``bodies`` bodies for ``seconds`` through the relay (if ``relay``) and
    ``gateways`` gateway processes at the same time (or, with ``floor``, a
    subscriber that only receives; with ``poll_hz``, :func:`_poller` waking
    that often), on a router of their own, with a probe taking each relayed
    sample's and each pose's latency (ns). What was sent, the latencies, each
    path's CPU (s), the gateways' samples taken, solves and wakes."""
    import socket

    from bodynet.core.codecs import pose, raw_sample
    from bodynet.session import open_session, session_config

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_session(session_config("router", listen=[endpoint]))
    ctx = mp.get_context("spawn")
    sent, gw_samples, gw_solves = ctx.Value("q", 0), ctx.Value("q", 0), ctx.Value("q", 0)
    relay_cpu, gw_cpu, floor_cpu = ctx.Value("d", 0.0), ctx.Value("d", 0.0), ctx.Value("d", 0.0)
    gw_worker, gw_wakes = ctx.Value("d", 0.0), ctx.Value("q", 0)
    stop, ready = ctx.Event(), ctx.Event()
    share = (lambda k: f"bench-{k}") if gateways > 1 else (lambda k: None)
    serving = [ctx.Event() for _ in range(gateways)]
    procs = [ctx.Process(target=_gateway, args=(endpoint, stop, gw_samples, gw_cpu,
                                                bodies > 1 or gateways > 1, share(k), serving[k],
                                                gw_solves, gw_worker, gw_wakes))
             for k in range(gateways)]  # fmt: skip
    if relay:
        procs.append(ctx.Process(target=_relay, args=(endpoint, stop, relay_cpu)))
    if floor:
        serving.append(ctx.Event())
        procs.append(ctx.Process(target=_floor, args=(endpoint, stop, floor_cpu, serving[-1])))
    if poll_hz:
        serving.append(ctx.Event())
        poller = (endpoint, stop, floor_cpu, serving[-1], poll_hz)
        procs.append(ctx.Process(target=_poller, args=poller))
    # one feeder process per 10 bodies, so the feed keeps its rate
    feeders = [
        ctx.Process(target=_feed, args=(endpoint, seconds, sent, ready,
                                        range(i, min(i + 10, bodies)), bodies, rate_hz, feed))
        for i in range(0, bodies, 10)
    ]  # fmt: skip
    for p in (*procs, *feeders):
        p.start()
    probe = open_session(session_config("client", connect=[endpoint]))
    relay_lat: list[int] = []
    pose_lat: list[int] = []
    source_time = raw_sample.source_time
    subs = [
        # a relayed sample on its own key read where it stands: 30,000 a second at
        # twenty bodies, in the process that hosts the router (``**`` matches no
        # batch key: an ``@`` chunk only itself)
        probe.declare_subscriber("bench/relay/**", lambda s: relay_lat.append(
            time.time_ns() - source_time(s.payload.to_bytes()))),
    ] + [
        probe.declare_subscriber(sel, lambda s: relay_lat.extend(
            _relayed(time.time_ns(), str(s.key_expr), s.payload.to_bytes())))
        for sel in ("bench/relay/body/@batch/*", "bench/relay/*/body/@batch/*")
    ] + [
        probe.declare_subscriber(keys_pose(bodies), lambda s: pose_lat.append(
            time.time_ns() - pose.source_time(s.payload.to_bytes()))),
    ]  # fmt: skip
    for event in serving:  # each gateway has imported Pinocchio and subscribed (the floor too)
        event.wait(timeout=120)
    time.sleep(1.0)  # subscriptions propagate
    ready.set()
    for f in feeders:
        f.join()
    time.sleep(0.5)  # the last samples drain
    stop.set()
    for p in procs:
        p.join(timeout=30)
    for sub in subs:
        sub.undeclare()
    probe.close()
    router.close()
    return {"sent": sent.value, "relay_lat": relay_lat, "pose_lat": pose_lat,
            "relay_cpu_s": relay_cpu.value, "gateway_cpu_s": gw_cpu.value,
            "gateway_worker_cpu_s": gw_worker.value,
            "floor_cpu_s": floor_cpu.value, "wakes": gw_wakes.value,
            "samples": gw_samples.value, "solves": gw_solves.value}  # fmt: skip


def run_once(bodies: int, seconds: float, rate_hz: float = RATE_HZ, feed: str = "realistic",
             gateways: int = 1, apart: bool = False) -> dict[str, Any]:  # fmt: skip
    """One run of relay and gateway fed ``bodies`` bodies, each node sending
    ``rate_hz`` as ``feed`` says (see :func:`feed_schedule`): side by side, or
    with ``apart`` one after the other (the same feed each). ``gateways`` > 1:
    that many gateway processes share the bodies (``gateway --share``); their
    samples and CPU are added up."""

    def floor_row(phase: dict[str, Any]) -> dict[str, Any]:
        return {"sent": phase["sent"],
                "cpu_ms_per_body_s": 1e3 * phase["floor_cpu_s"] / seconds / bodies}  # fmt: skip

    floor = poller = None
    if apart:
        relay = _phase(bodies, seconds, rate_hz, feed, True, 0)
        gw = _phase(bodies, seconds, rate_hz, feed, False, gateways)
        floor = floor_row(_phase(bodies, seconds, rate_hz, feed, False, 0, floor=True))
        if gateways == 1 and gw["wakes"]:
            poll_hz = gw["wakes"] / seconds
            poller = {**floor_row(_phase(bodies, seconds, rate_hz, feed, False, 0,
                                         poll_hz=poll_hz)), "wakes_per_s": poll_hz}  # fmt: skip
    else:
        relay = gw = _phase(bodies, seconds, rate_hz, feed, True, gateways)
    r, g = _stats(relay["relay_lat"]), _stats(gw["pose_lat"])
    expected_poses = seconds * RATE_HZ * bodies  # the gateway ticks at 100 Hz at most
    poses = len(gw["pose_lat"])
    return {
        "bodies": bodies, "feed": feed, "gateways": gateways, "apart": apart, "sent": gw["sent"],
        "relay": {**r, "sent": relay["sent"], "received": len(relay["relay_lat"]),
                  "lost": relay["sent"] - len(relay["relay_lat"]),
                  "cpu_ms_per_body_s": 1e3 * relay["relay_cpu_s"] / seconds / bodies},
        "gateway": {**g, "samples_received": gw["samples"],
                    "lost": gw["sent"] - gw["samples"], "poses": poses,
                    "pose_rate": poses / expected_poses,
                    # body-ticks per batched solve (the poses of bodies solved together)
                    "mean_batch": poses / gw["solves"] if gw["solves"] else None,
                    "cpu_ms_per_body_s": 1e3 * gw["gateway_cpu_s"] / seconds / bodies,
                    # of which its worker thread's: the Python of every sample and tick
                    "worker_cpu_ms_per_body_s":
                        1e3 * gw["gateway_worker_cpu_s"] / seconds / bodies,
                    # how often its worker woke from a sleep (each gateway's, added up)
                    "wakes_per_s": gw["wakes"] / seconds},
        # apart only: Zenoh's own cost of receiving the same feed, with no Python per sample
        "floor": floor,
        # apart, one gateway: the floor under a Python worker that polls as its worker did
        "poller": poller,
        "p50_ratio": g["p50_ms"] / r["p50_ms"] if r["n"] and g["n"] else None,
        "p99_ratio": g["p99_ms"] / r["p99_ms"] if r["n"] and g["n"] else None,
    }  # fmt: skip


#: the apart rows' floors: each one's key in a run and its path in the table
_FLOORS = (("floor", "Zenoh subscriber alone (floor: receives, no Python)"),
           ("poller", "Python worker alone (floor: polls as the gateway's did, "
                      "{wakes_per_s:.0f} wakes/s, takes each sample's bytes)"))  # fmt: skip


def _ranges(runs: dict[tuple[int, str, int, bool], list[dict[str, Any]]], repeat: int) -> str:
    """The range of each row's figures over its ``repeat`` runs, a line a row."""

    def span(values: list[float], fmt: str) -> str:
        lo, hi = min(values), max(values)
        return format(lo, fmt) if format(lo, fmt) == format(hi, fmt) else \
            f"{format(lo, fmt)}-{format(hi, fmt)}"  # fmt: skip

    lines = [
        f"\nRanges over the {repeat} runs of each row (gateway: ticks delivered, p99 "
        "ratio, CPU ms per body-second, of which the worker thread; relay: CPU):\n"
    ]
    for (n, feed, g, alone), rs in runs.items():
        gws = [r["gateway"] for r in rs]
        ratios = [r["p99_ratio"] for r in rs if r["p99_ratio"] is not None]
        who = "gateway" if g == 1 else f"{g} gateways sharing"
        lines.append(
            f"- {n} {'body' if n == 1 else 'bodies'}, {feed}{', apart' if alone else ''}, "
            f"{who}: {span([100 * x['pose_rate'] for x in gws], '.0f')}% of ticks, "
            f"p99 ratio {span(ratios, '.2f') if ratios else '-'}, "
            f"{span([x['cpu_ms_per_body_s'] for x in gws], '.0f')} ms "
            f"({span([x['worker_cpu_ms_per_body_s'] for x in gws], '.0f')}); relay "
            f"{span([r['relay']['cpu_ms_per_body_s'] for r in rs], '.0f')} ms"
        )  # fmt: skip
    return "\n".join(lines) + "\n"


def keys_pose(bodies: int) -> str:
    from bodynet.core import keys

    return keys.pose_key() if bodies == 1 else keys.ANY_SUBJECT + "/" + keys.pose_key()


TICKS_GOAL = 0.95  # a gateway sustains a load when it delivers this share of ticks


def sustained(row: dict[str, Any], path: str) -> bool:
    """No sample lost, and (for the gateway) at least 95% of the ticks delivered."""
    ok = row[path]["lost"] == 0 and row[path]["n"] > 0
    return bool(ok and (path == "relay" or row[path]["pose_rate"] >= TICKS_GOAL))


FEEDS = ("realistic", "batched", "locked")


def run(
    seconds: float = 5.0,
    out_dir: Path = Path("bench-results"),
    bodies: tuple[int, ...] = (1, 5, 10, 15, 20, 50),
    rate_hz: float = RATE_HZ,
    name: str = "gateway",
    feeds: tuple[str, ...] = FEEDS,
    gateways: tuple[int, ...] = (1,),
    apart: bool = False,
    repeat: int = 1,
) -> dict[str, Any]:
    """Run the comparison for each number of bodies and each feed (realistic
    first, see :func:`feed_schedule`), each node sending ``rate_hz``; print a
    table; write ``<name>.json`` and ``<name>.md``. The first run's figures
    (one body, the first feed) are also at the top level of the result; the
    bodies sustained are counted on the first feed. Each count in ``gateways``
    other than 1 adds a row per number of bodies: that many gateway processes
    sharing the bodies (``gateway --share``), on the first feed; ``apart`` adds
    one per number of bodies and feed (but the locked one) with relay and
    gateway fed one after the other. ``repeat``: each row that many times,
    the rows' runs interleaved (the machine's drift hits each alike), with
    the ranges of their figures after the table; a number of bodies counts
    as sustained only if every run of it is."""
    from bodynet.bench import machine

    configs = [(n, feed, 1, False) for n in bodies for feed in feeds]
    configs += [(n, feeds[0], g, False) for g in gateways if g != 1 for n in bodies]
    configs += [(n, feed, 1, True) for feed in feeds if apart and feed != "locked"
                for n in bodies]  # fmt: skip
    runs: dict[tuple[int, str, int, bool], list[dict[str, Any]]] = {c: [] for c in configs}
    for k in range(repeat):
        for n, feed, g, alone in configs:
            row = run_once(n, seconds, rate_hz, feed, g, apart=alone)
            runs[n, feed, g, alone].append({**row, "run": k + 1})
    rows = [row for c in configs for row in runs[c]]

    def most(feed: str, g: int, path: str) -> int:
        """The most bodies sustained on ``feed`` by ``g`` gateways, in every run."""
        return max((n for (n, f, gs, alone), rs in runs.items()
                    if f == feed and gs == g and not alone
                    and all(sustained(r, path) for r in rs)), default=0)  # fmt: skip

    best = {path: most(feeds[0], 1, path) for path in ("relay", "gateway")}
    by_gateways = {g: most(feeds[0], g, "gateway") for g in sorted({1, *gateways})}
    by_feed = {feed: most(feed, 1, "gateway") for feed in feeds}
    result = {
        "machine": f"{machine.cpu_model()}, {mp.cpu_count()} cores, "
        f"Python {platform.python_version()}",
        "seconds": seconds, "rate_hz_per_node": rate_hz, "nodes_per_body": 15,
        "feeds": list(feeds),
        **{k: rows[0][k] for k in ("sent", "relay", "gateway", "p50_ratio", "p99_ratio")},
        "runs": rows, "sustained_bodies": best, "sustained_by_gateways": by_gateways,
        "sustained_by_feed": by_feed,
        "sustained_ratio": best["gateway"] / best["relay"] if best["relay"] else None,
    }  # fmt: skip
    lines = [
        "| bodies | feed | path | sent | lost | poses/s per body | p50 ms | p99 ms | p99 ratio "
        "| CPU ms per body-second | of which the worker thread | bodies per solve |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        r, g = row["relay"], row["gateway"]
        f = row["feed"] + (", apart" if row["apart"] else "")
        if repeat > 1:
            f += f", run {row['run']} of {repeat}"
        lines.append(
            f"| {row['bodies']} | {f} | bare relay (raw -> raw) | {r['sent']} | {r['lost']} "
            f"| | {r['p50_ms']:.2f} | {r['p99_ms']:.2f} | | {r['cpu_ms_per_body_s']:.0f} | | |"
        )
        ratio = f"{row['p99_ratio']:.2f}" if row["p99_ratio"] else "-"
        path = "gateway" if row["gateways"] == 1 else f"{row['gateways']} gateways sharing"
        batch = f"{g['mean_batch']:.1f}" if g["mean_batch"] else "-"
        lines.append(f"| {row['bodies']} | {f} | {path} (raw -> pose) | {row['sent']} "
                     f"| {g['lost']} | {g['pose_rate'] * RATE_HZ:.0f} | {g['p50_ms']:.2f} "
                     f"| {g['p99_ms']:.2f} | {ratio} | {g['cpu_ms_per_body_s']:.0f} "
                     f"| {g['worker_cpu_ms_per_body_s']:.0f} | {batch} |")  # fmt: skip
        for key, path in _FLOORS:
            if got := row.get(key):
                lines.append(f"| {row['bodies']} | {f} | {path.format(**got)} | {got['sent']} "
                             f"| | | | | | {got['cpu_ms_per_body_s']:.0f} | | |")  # fmt: skip
    table = "\n".join(lines) + (
        f"\n\nSustained with zero loss ({feeds[0]} feed): relay {best['relay']} bodies, "
        f"gateway {best['gateway']} bodies (at least {TICKS_GOAL:.0%} of ticks delivered)"
        + "".join(f"; {g} gateways sharing: {n}" for g, n in by_gateways.items() if g != 1)
        + ". One gateway by feed: "
        + ", ".join(f"{feed} {n}" for feed, n in by_feed.items())
        + ".\n"
        + (_ranges(runs, repeat) if repeat > 1 else "")
    )
    print(f"Gateway vs bare relay (15 nodes x {rate_hz:g} Hz per body), {seconds:g} s each, "
          f"{result['machine']}\n\n{table}")  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(json.dumps(result, indent=2))
    (out_dir / f"{name}.md").write_text(table)
    return result
