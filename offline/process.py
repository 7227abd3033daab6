"""``bodynet process``: exactly the gateway's solver, run over a capture.

The input is any capture ``bodynet decode`` reads (any format of a registered
source, ``nodes.sources``). Samples are taken in the
capture's time order and grouped into ticks of ``1 / tick_hz`` (a data-matrix
frame, or a concentrator reply, is always one tick); after each tick the body
is solved as the live gateway would and the pose written to MCAP at the
tick's time, together with the raw samples. Orientation sensors are first
calibrated from the first ``tpose_s`` seconds (the subject in T-pose), unless
the profile already holds their mounts.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bodynet.clients.mcap_store import McapSink
from bodynet.core import keys
from bodynet.core.keys import BRANCHES, Site
from bodynet.core.messages import Quat, RawSample
from bodynet.core.subject import Profile
from bodynet.gateway.frames import branch_views, pose_frame
from bodynet.gateway.solver import BodySolver, tpose_mounts
from bodynet.nodes import sources
from bodynet.nodes.sources.base import CapturedSample, CaptureStats


@dataclass
class ProcessResult:
    ticks: int
    samples: int
    calibrated: list[str]
    stats: CaptureStats


def _ticks(samples: Iterator[CapturedSample], period_s: float) -> Iterator[list[CapturedSample]]:
    tick: list[CapturedSample] = []
    for s in samples:
        if tick and s.t_s >= tick[0].t_s + period_s - 1e-9:
            yield tick
            tick = []
        tick.append(s)
    if tick:
        yield tick


def process(path: Path, fmt: str, out: Path, profile: Profile | None = None,
            rate_hz: float | None = None, tick_hz: float = 100.0,
            tpose_s: float = 3.0,
            options: Mapping[str, Any] | None = None) -> ProcessResult:  # fmt: skip
    """Solve every tick of a capture and write poses and raw samples to ``out``
    (``options``: the source's capture options, e.g. an orientation file's ``map``)."""
    source = sources.by_format(fmt).from_options(options or {})
    profile = profile or Profile()
    window: dict[Site, list[tuple[float, float, float, float]]] = {}
    start: float | None = None
    for s in source.read(path, fmt, CaptureStats(), rate_hz):
        start = s.t_s if start is None else start
        if s.t_s - start >= tpose_s:
            break
        if isinstance(s.reading, Quat) and s.site.raw_key not in profile.imu_mounts:
            window.setdefault(s.site, []).append(s.reading.wxyz)
    mounts = tpose_mounts(window, profile) if window else {}
    solver = BodySolver(profile.with_mounts(mounts))
    stats = CaptureStats()
    sink = McapSink(out)
    latest: dict[Site, RawSample] = {}
    seqs: dict[Site, int] = {}
    ticks = 0
    try:
        for tick in _ticks(source.read(path, fmt, stats, rate_hz), 1.0 / tick_hz):
            for s in tick:
                seq = seqs[s.site] = seqs.get(s.site, -1) + 1
                sample = RawSample(s.reading, seq, round(s.t_s * 1e9), source.wire_id)
                latest[s.site] = sample
                sink.write_raw(s.site.raw_key, sample, sample.t_ns)
            ticks += 1
            t_ns = round(tick[-1].t_s * 1e9)
            frame = pose_frame(solver.solve(latest), ticks, [])
            sink.write_pose(keys.pose_key(), frame, t_ns)
            for branch, view in branch_views(frame, BRANCHES).items():
                sink.write_pose(keys.pose_key(branch), view, t_ns)
    finally:
        sink.close()
    return ProcessResult(ticks, stats.decoded, sorted(mounts), stats)
