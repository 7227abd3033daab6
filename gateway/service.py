"""The live gateway: raw samples in, poses and joint angles out, on Zenoh.

One process, by default with an embedded Zenoh router. A subscription to
every raw key (or a chosen subset of branches) feeds a queue; a worker thread
drains it, keeps each site's latest sample, and solves the body at most once
per tick (``rate_hz``), publishing the whole body on ``body/pose`` and each
branch's view on ``body/<limb>/<side>/pose``. Nodes are tracked through
their liveliness tokens; the topology is published on ``body/@topology``
when it changes and answered as a query there. A site that stops delivering
keeps its last sample, flagged stale; other branches carry on. Garbage on the
raw keys is counted (``body/@health/gateway``), never fatal.
``body/@calibrate/tpose`` answers a query by calibrating the IMU mounts from
the last ``seconds`` of samples (the subject standing in T-pose).
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError, Reason, RejectCounts
from bodynet.core.keys import BRANCHES, Branch, Site
from bodynet.core.messages import Quat, RawSample
from bodynet.core.subject import Profile
from bodynet.gateway import profile_file
from bodynet.gateway.solver import BodyOutput, BodySolver, tpose_mounts

log = logging.getLogger(__name__)

STALE_S = 0.5
HISTORY_S = 5.0


def branch_parts(branch: Branch) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The joints and segments of a branch."""
    if branch == keys.TRUNK:
        return ("lumbar", "neck"), ("pelvis", "thorax", "head")
    side = branch.side
    if branch.limb is keys.Limb.ARM:
        return tuple(f"{side}_{j}" for j in ("shoulder", "elbow", "wrist")), tuple(
            f"{side}_{s}" for s in ("upperarm", "forearm", "hand")
        )
    return tuple(f"{side}_{j}" for j in ("hip", "knee", "ankle")), tuple(
        f"{side}_{s}" for s in ("thigh", "shank", "foot")
    )


def branch_views(frame: pose.PoseFrame, branches: Iterable[Branch]) -> dict[Branch, pose.PoseFrame]:
    """Each branch's view of a whole-body pose: its joints, segments and sources."""
    views = {}
    for branch in branches:
        joints, segments = branch_parts(branch)
        views[branch] = frame.subset(joints, segments, branch.key + "/")
    return views


def pose_frame(output: BodyOutput, seq: int, stale: Sequence[str]) -> pose.PoseFrame:
    return pose.PoseFrame(seq, output.t_ns, output.angles_deg, output.rel_deg, output.segments,
                          output.joints_m, output.flags, output.sources, list(stale))  # fmt: skip


@dataclass
class _Site:
    sample: RawSample
    arrived: float  # monotonic
    fresh: bool = True  # not yet in a solved tick


class Gateway:
    """See the module docstring. ``run(stop)`` serves until ``stop`` is set."""

    def __init__(self, session: zenoh.Session, profile: Profile | None = None,
                 profile_path: Path | None = None, branches: Sequence[Branch] | None = None,
                 rate_hz: float = 100.0) -> None:  # fmt: skip
        self.session = session
        self.profile_path = profile_path
        self.solver = BodySolver(profile)
        self.branches = tuple(branches) if branches else BRANCHES
        self.period_s = 1.0 / rate_hz
        self.rejected = RejectCounts()
        self.samples = 0
        self.ticks = 0
        self.solver_errors = 0
        # raw samples, or None: "the topology changed, publish again"
        self._queue: queue.SimpleQueue[tuple[Site, RawSample] | None] = queue.SimpleQueue()
        self._latest: dict[Site, _Site] = {}
        self._history: dict[Site, deque[tuple[float, RawSample]]] = {}
        self._alive: set[str] = set()
        self._gone: set[str] = set()  # keys whose token went away
        self._published_stale: set[str] = set()
        self._topology = ""
        self._lock = threading.Lock()
        selectors = [keys.all_raw()] if branches is None else [f"{b.key}/*/raw" for b in branches]
        self._subs = [session.declare_subscriber(sel, self._on_raw) for sel in selectors]
        self._live = session.liveliness().declare_subscriber(
            keys.all_raw(), self._on_token, history=True
        )
        cc = zenoh.CongestionControl.BLOCK
        self._body_pub = session.declare_publisher(keys.pose_key(), congestion_control=cc)
        self._branch_pubs = {
            b: session.declare_publisher(keys.pose_key(b), congestion_control=cc)
            for b in self.branches
        }
        self._topology_pub = session.declare_publisher(keys.TOPOLOGY)
        self._health_pub = session.declare_publisher(keys.health_key("gateway"))
        self._queryables = [
            session.declare_queryable(keys.TOPOLOGY, self._on_topology_query),
            session.declare_queryable(keys.CALIBRATE_TPOSE, self._on_tpose_query),
        ]

    # --- input (Zenoh's threads) ---------------------------------------------------
    def _on_raw(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            site, _ = keys.parse(key)
            raw = raw_sample.decode(sample.payload.to_bytes())
        except DecodeError as exc:
            self.rejected[exc.reason] += 1
            return
        except keys.KeySpaceError:
            self.rejected[Reason.UNKNOWN_NODE] += 1
            return
        self._queue.put((site, raw))

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(key)
                self._gone.discard(key)
            else:
                self._alive.discard(key)
                self._gone.add(key)
        self._publish_topology()
        self._queue.put(None)

    # --- topology ------------------------------------------------------------------
    def topology(self) -> dict[str, object]:
        now = time.monotonic()
        with self._lock:
            alive = set(self._alive)
            latest = dict(self._latest)
        branches: dict[str, dict[str, object]] = {}
        for key in sorted(alive | {s.raw_key for s in latest}):
            try:
                site, _ = keys.parse(key)
            except keys.KeySpaceError:
                continue
            seen = latest.get(site)
            state = "alive" if key in alive else "gone"
            if seen is None or now - seen.arrived > STALE_S:
                state = "stale" if key in alive else state
            branch = branches.setdefault(str(site.branch), {"nodes": {}})
            nodes = branch["nodes"]
            assert isinstance(nodes, dict)
            nodes[key] = {"state": state, "node": seen.sample.reading.node if seen else None,
                          "last_t_ns": seen.sample.t_ns if seen else None}  # fmt: skip
        return {"t_ns": time.time_ns(), "branches": branches}

    def _publish_topology(self) -> None:
        topo = self.topology()
        text = json.dumps({k: v for k, v in topo.items() if k != "t_ns"}, sort_keys=True)
        if text != self._topology:
            self._topology = text
            self._topology_pub.put(json.dumps(topo).encode())

    def _on_topology_query(self, query: zenoh.Query) -> None:
        query.reply(keys.TOPOLOGY, json.dumps(self.topology()).encode())

    # --- T-pose calibration ----------------------------------------------------------
    def calibrate_tpose(self, seconds: float = 1.0) -> dict[str, object]:
        """Mounts of every orientation sensor from its last ``seconds`` of samples."""
        now = time.monotonic()
        with self._lock:
            window = {
                site: [
                    s.reading.wxyz
                    for t, s in hist
                    if now - t <= seconds and isinstance(s.reading, Quat)
                ]
                for site, hist in self._history.items()
            }
        mounts = tpose_mounts({s: q for s, q in window.items() if q}, self.solver.profile)
        if not mounts:
            return {"ok": False, "error": "no orientation samples in the window"}
        profile = self.solver.profile.with_mounts(mounts)
        with self._lock:
            self.solver = BodySolver(profile)
        if self.profile_path is not None:
            profile_file.save(profile, self.profile_path)
        log.info("T-pose calibration of %d sensors", len(mounts))
        return {"ok": True, "calibrated": sorted(mounts), "profile": str(self.profile_path or "")}

    def _on_tpose_query(self, query: zenoh.Query) -> None:
        try:
            seconds = float(query.parameters.get("seconds") or 1.0)
        except ValueError:
            seconds = 1.0
        result = self.calibrate_tpose(seconds)
        query.reply(keys.CALIBRATE_TPOSE, json.dumps(result).encode())

    # --- the work loop -----------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        """Solve when every live site has delivered since the last solve (a whole
        frame of the sources is in: the lowest latency), or else ``period_s``
        after the first new sample (sources of different rates)."""
        first_new: float | None = None  # when the oldest unsolved sample came
        force = False
        last_health = time.monotonic()
        while not stop.is_set():
            wait = 0.1 if first_new is None else first_new + self.period_s - time.monotonic()
            try:
                item = self._queue.get(timeout=max(0.0, wait))
                while True:  # take what else has come: one solve for the lot
                    if item is None:
                        force = True
                    else:
                        self._take(item)
                        first_new = first_new or time.monotonic()
                    item = self._queue.get_nowait()
            except queue.Empty:
                pass
            now = time.monotonic()
            due = first_new is not None and (
                now - first_new >= self.period_s or self._frame_complete(now)
            )
            if due or force:
                try:
                    self._solve_and_publish(now)
                except Exception:  # one bad tick must not end the service
                    self.solver_errors += 1
                    if self.solver_errors <= 3:
                        log.exception("gateway: a tick failed (%d so far)", self.solver_errors)
                first_new, force = None, False
            if now - last_health >= 1.0:
                last_health = now
                force = self._newly_stale(now)
                self._publish_topology()
                self._health_pub.put(json.dumps(self.health()).encode())

    def _frame_complete(self, now: float) -> bool:
        """Has every site that is not stale delivered since the last solve?"""
        with self._lock:
            return all(v.fresh or now - v.arrived > STALE_S for v in self._latest.values())

    def _newly_stale(self, now: float) -> bool:
        with self._lock:
            return any(now - v.arrived > STALE_S and s.raw_key not in self._published_stale
                       for s, v in self._latest.items())  # fmt: skip

    def _take(self, item: tuple[Site, RawSample]) -> None:
        """Keep a sample as its site's latest (and, for T-pose, its recent history)."""
        site, sample = item
        now = time.monotonic()
        self.samples += 1
        with self._lock:
            self._latest[site] = _Site(sample, now)
            if isinstance(sample.reading, Quat):
                hist = self._history.setdefault(site, deque())
                hist.append((now, sample))
                while hist and now - hist[0][0] > HISTORY_S:
                    hist.popleft()

    def _solve_and_publish(self, now: float) -> None:
        with self._lock:
            latest = {site: s.sample for site, s in self._latest.items()}
            for s in self._latest.values():
                s.fresh = False
            stale = sorted(
                s.raw_key for s, v in self._latest.items()
                if now - v.arrived > STALE_S or s.raw_key in self._gone
            )  # fmt: skip
            self._published_stale = set(stale)
            solver = self.solver
        output = solver.solve(latest)
        self.ticks += 1
        frame = pose_frame(output, self.ticks, stale)
        self._body_pub.put(pose.encode(frame))
        for branch, view in branch_views(frame, self._branch_pubs).items():
            self._branch_pubs[branch].put(pose.encode(view))

    def health(self) -> dict[str, object]:
        return {"source": "gateway", "t_ns": time.time_ns(), "samples": self.samples,
                "ticks": self.ticks, "solver_errors": self.solver_errors,
                "rejected": dict(self.rejected)}  # fmt: skip

    def close(self) -> None:
        for q in self._queryables:
            q.undeclare()
        for sub in self._subs:
            sub.undeclare()
        self._live.undeclare()
        for pub in (
            self._body_pub,
            self._topology_pub,
            self._health_pub,
            *self._branch_pubs.values(),
        ):
            pub.undeclare()
