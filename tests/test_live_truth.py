"""The live path against the truth: emulated tags on their real transports, their
bridge, Zenoh on loopback and the gateway's rounds and ticks, the subject walking.

``bench --only truth`` checks the poses of ``bodynet process`` (the samples
stamped with the truth's own times); here the samples are stamped as the
bridges stamp them, each tag on a timer of its own, and a tick takes what its
round found. Every measured dof of each pose is compared with the emulator's
truth at the pose's time (``bench.truth.compare_frames``): what the gateway's
rounds and alignment make of the live timing must stay within the pose's
stated ``unc_deg``.

Nothing is timed, and the machine's load is not the gateway's error: a pose is
judged only when each of its samples was stamped by its bridge within
``HOST_S`` of going out of its device (the emulator hands each reading's truth
as it goes out; the IMU central's lines carry their tick, a SlimeVR datagram is
stamped by the kernel as its tracker sends it). A loaded host gives fewer poses
to judge, and the walk goes on until there are enough.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import defaultdict
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import pytest
import zenoh
from zenoh_helpers import Collector, Running, client, raw_collector

from bodynet.bench.drift import _calibrated
from bodynet.bench.truth import compare_frames
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.messages import RawSample
from bodynet.core.subject import Profile
from bodynet.gateway.service import Gateway
from bodynet.nodes import sources
from bodynet.nodes.emulator import BodyEmulator, Realism, Truth
from bodynet.nodes.motion import ROUTINES
from bodynet.nodes.timing import Clock, LinkTiming, Timers

SEED = 3
#: tags of 0.3 deg noise mounted at random, one shared frame, the subject facing 37 deg
REALISM = Realism(quat_noise_deg=0.3, facing_deg=37.0)
#: poses compared from this long into the walk (every site's rhythm learnt)
FROM_S = 1.5
#: a pose is judged when each of its samples was stamped within this of going out
HOST_S = 0.005
#: the walk goes on for this long, and then until this many measured values were
#: judged (or ``MAX_WALK_S`` of it): several strides each way
MIN_WALK_S, ENOUGH, MAX_WALK_S = 12.0, 10_000, 60.0
SLACK_DEG = 0.3  # a dof within twice its uncertainty and this
#: at most this share of the judged values beyond (``bodynet process`` of such
#: walks: 0-0.04 %, docs/benchmarks.md)
MAX_BEYOND = 0.005

Row = tuple[Any, ...]


def told_profile(sensors: list[Any]) -> Profile:
    """The subject calibrated in a T-pose before the walk (the same suit: the
    emulator's seed gives its mounts), each tag's heading told, as ``process``'s
    ``given`` truth scenarios: no heading search to wait for."""
    still = BodyEmulator(ROUTINES["tpose"], sensors, realism=REALISM, seed=SEED)
    told = {s.site.raw_key: still.headings_deg[s.node] for s in sensors}
    profile = Profile(pose="tpose", heading="auto", imu_headings=told)
    return _calibrated(still, profile, 0.2, 2.0, 50.0)


class Outgoing:
    """A truth sink keeping, per node, when each reading went out of its device
    and when it was taken (wall clock, ns), to find each published sample's."""

    def __init__(self, via: str, sensors: list[Any]) -> None:
        self.via = via
        self.emulator: Any = None
        # a sample's node is its bridge's (a SlimeVR bridge numbers its trackers
        # as they shake hands): its key says whose it is
        self.node_of = {s.site.raw_key: s.node for s in sensors}
        self.by_tick: dict[tuple[int, int], tuple[int, int]] = {}  # (node, tick) -> (out, taken)
        self.out: dict[int, list[tuple[int, int]]] = defaultdict(list)  # node -> [(out, taken)]

    def __call__(self, node: int, truth: Truth, t_ns: int) -> None:
        now = time.time_ns()
        if self.via == "imu-central":  # a line of this tick, printed now
            self.by_tick[(node, self.emulator.ticks & 0xFFFF)] = (now, t_ns)
        else:  # a tracker's datagram, about to be sent: stamped by the kernel after now
            self.out[node].append((now, t_ns))

    def host_delay_ns(self, key: str, sample: RawSample) -> int | None:
        """How long after going out of its device ``sample`` (published on ``key``)
        was stamped (None: unknown)."""
        node = self.node_of[key]
        if self.via == "imu-central":
            tick = int.from_bytes(sample.reading.extra[:2], "little")  # type: ignore[union-attr]
            got = self.by_tick.get((node, tick))
            return None if got is None else sample.t_ns - got[0]
        # the kernel stamps a datagram in its tracker's ``sendto``, after the sink
        # heard of it and before the sink hears of the tracker's next: its send is
        # the last the sink heard of before the stamp
        sends = self.out[node]
        i = bisect.bisect_right(sends, (sample.t_ns, math.inf)) - 1
        return None if i < 0 else sample.t_ns - sends[i][1]


def walk_live(router_endpoint: str, zsession: zenoh.Session, tmp_path: Path, via: str,
              timing: LinkTiming,
              period_s: float | None) -> tuple[list[Row], int, int]:  # fmt: skip
    """``bodynet node``'s emulated ``via`` (all fifteen tags, as its source makes
    them, sending every ``period_s`` or its own period) walking, through its
    bridge and a gateway: the rows of ``compare_frames`` of the poses judged,
    and the poses judged and not."""
    routine = ROUTINES["walk"]
    source = sources.by_device(via)(period_s=period_s)
    sensors = source.emulated_sensors()
    session = client(router_endpoint)
    gateway = Gateway(session, profile=told_profile(sensors))
    running = Running(gateway.run)
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    raw = raw_collector(zsession, "body/*/*/*/raw")
    node_session = client(router_endpoint)
    outgoing = Outgoing(via, sensors)
    body = BodyEmulator(routine, sensors, realism=REALISM, seed=SEED)
    clock = Clock()
    t0_ns = clock.wall_ns(0.0)  # the emulator's time 0 on the wall clock the bridges stamp with
    emulator, bridge, kwargs = source.node(via, body, tmp_path, clock, outgoing, sensors,
                                           "live-truth", timing=timing)  # fmt: skip
    outgoing.emulator = emulator
    emulator.start()
    node = Running(lambda stop: bridge(node_session, stop, "live-truth", **kwargs))
    judge = Judge(outgoing, routine.angles, t0_ns)
    try:
        start = time.monotonic()
        while (time.monotonic() - start < MIN_WALK_S or len(judge.rows) < ENOUGH) and (
            time.monotonic() - start < MAX_WALK_S
        ):
            poses.wait_for(partial(more_than, len(poses.seen) + 50), timeout=30)
            judge.update(poses.seen, raw.drained())
    finally:
        node.stop()
        emulator.stop()
        node_session.close()
        running.stop()
        gateway.close()
        session.close()
    return judge.rows, judge.judged, judge.skipped


def more_than(count: int, seen: list[Any]) -> bool:
    return len(seen) >= count


class Judge:
    """``compare_frames`` rows of the poses each of whose samples was stamped
    within ``HOST_S`` of going out, taken as the walk goes (each sample and pose
    once: the judging must not load the host whose delays it measures)."""

    #: poses this close to the newest wait (their samples may not be in yet)
    SETTLING = 50

    def __init__(self, outgoing: Outgoing, truth: Callable[[float], dict[str, float]],
                 t0_ns: int) -> None:  # fmt: skip
        self.outgoing, self.truth, self.t0_ns = outgoing, truth, t0_ns
        self.delay: dict[tuple[str, int], int | None] = {}
        self.raw_done = self.poses_done = self.judged = self.skipped = 0
        self.rows: list[Row] = []

    def update(self, poses: list[tuple[str, Any]], raw: list[tuple[str, RawSample]]) -> None:
        for key, s in raw[self.raw_done :]:
            self.delay[(key, s.t_ns)] = self.outgoing.host_delay_ns(key, s)
        self.raw_done = len(raw)
        settled = max(self.poses_done, len(poses) - self.SETTLING)
        frames = []
        for _, frame in poses[self.poses_done : settled]:
            late = [self.delay.get((key, t)) for key, t in frame.sources.items()]
            if all(d is not None and 0 <= d <= HOST_S * 1e9 for d in late):
                frames.append((frame.t_ns, frame))
            else:
                self.skipped += 1
        self.poses_done = settled
        self.judged += len(frames)
        rows, _ = compare_frames(frames, self.truth, FROM_S, self.t0_ns)
        self.rows += [r for r in rows if not r[5]]  # a shoulder near 90 apart


def beyond(rows: list[Row]) -> tuple[float, float]:
    """The share of ``rows`` beyond twice their uncertainty and ``SLACK_DEG``, and
    the same with the pose's lag allowed."""
    out = sum(abs(r[2]) > 2 * r[4] + SLACK_DEG for r in rows)
    lag = sum(r[3] > 2 * r[4] + SLACK_DEG for r in rows)
    return out / max(1, len(rows)), lag / max(1, len(rows))


@pytest.mark.parametrize(
    ("via", "timing", "period_s"),
    [
        # the tags on their own timers every 30 ms, notifications late by up to 3 ms
        # and 5% lost (the central's lines of no new data), a line each 40 ms
        ("imu-central", LinkTiming(Timers.INDEPENDENT, jitter_s=3e-3, drop=0.05, seed=SEED),
         None),
        # each tracker on its own timer at 50 Hz, Wi-Fi-like: late by up to 20 ms,
        # 2% lost (at 100 Hz, samples a tick apart are too close for a tick that
        # does not align them to show)
        ("slimevr", LinkTiming(Timers.INDEPENDENT, jitter_s=20e-3, drop=0.02, seed=SEED), 0.02),
    ],
)  # fmt: skip
def test_live_poses_of_walking_tags_are_within_their_uncertainty_of_the_truth(
    router_endpoint: str, zsession: zenoh.Session, tmp_path: Path, via: str,
    timing: LinkTiming, period_s: float | None,
) -> None:  # fmt: skip
    """All fifteen tags of a walking subject live, through their device, bridge,
    Zenoh and the gateway: of thousands of measured dofs of its poses, at most
    0.5% are beyond twice their ``unc_deg`` (and 0.3 deg) of the truth at the
    pose's time. As it is: 0.00-0.01% (SlimeVR, about 20,000 values) and
    0.02-0.03% (IMU central, 11,000). The gateway not aligning a tick's samples and
    stating nothing for it (``kernels.ahead`` returning nothing) gave 1.01% for
    SlimeVR; the IMU central's tags stating nothing for the time their readings
    may have been taken before their line's arrival, 1.5-1.7%."""
    rows, judged, skipped = walk_live(router_endpoint, zsession, tmp_path, via, timing, period_s)
    share, lag_share = beyond(rows)
    worst = sorted(rows, key=lambda r: -(abs(r[2]) - 2 * r[4]))[:5]
    print(f"\n{via}: poses judged {judged}, skipped {skipped}; beyond 2x unc {share:.2%} "
          f"(lag allowed {lag_share:.2%}) of {len(rows)}; worst {worst}")  # fmt: skip
    assert len(rows) >= ENOUGH
    assert share <= MAX_BEYOND, worst
