"""``bodynet view``: the body in Rerun, live from Zenoh or from a recording.

A 3D stick figure (the segments of the 000 seed's stick figure, joints as
points), every joint angle as a time series, a gauge panel of chosen joints
(the seed's 3x3 gauge matrix, as a bar chart) and the topology and health as
text, laid out by a default blueprint. Poses are logged in batches (columns
of angles, the latest figure per batch), never one ``rr.log`` per sample.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError
from bodynet.core.skeleton import Skeleton, build_skeleton

GAUGES = (
    "left_shoulder_flexion_deg", "left_elbow_flexion_deg", "left_wrist_flexion_deg",
    "right_shoulder_flexion_deg", "right_elbow_flexion_deg", "right_wrist_flexion_deg",
    "left_knee_flexion_deg", "right_knee_flexion_deg", "lumbar_flexion_deg",
)  # fmt: skip
BATCH_S = 0.1


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="body", name="Body"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="angles", name="Joint angles (deg)"),
                rrb.BarChartView(origin="gauges", name="Gauges: " + ", ".join(
                    g.removesuffix("_deg") for g in GAUGES)),
                rrb.TextDocumentView(origin="status", name="Topology and health"),
            ),
        ),
        collapse_panels=True,
    )  # fmt: skip


def figure(frame: pose.PoseFrame, skeleton: Skeleton) -> tuple[list[np.ndarray], np.ndarray]:
    """Line strips of the stick figure, and the joint centres, from one pose."""
    seg = {name: (np.array(p), np.array(q)) for name, (p, q) in frame.segments.items()}

    def end(segment: str) -> np.ndarray:
        p, (w, x, y, z) = seg[segment]
        rot = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        return p + rot @ (np.array(skeleton.directions[segment]) * skeleton.segment_length(segment))  # type: ignore[no-any-return]

    if not seg:
        return [], np.zeros((0, 3))
    strips = [np.array([seg["pelvis"][0], seg["thorax"][0], seg["head"][0], end("head")])]
    for side in ("left", "right"):
        arm = [seg["head"][0]] + [seg[f"{side}_{s}"][0] for s in ("upperarm", "forearm", "hand")]
        strips.append(np.array([*arm, end(f"{side}_hand")]))
        leg = [seg["pelvis"][0]] + [seg[f"{side}_{s}"][0] for s in ("thigh", "shank", "foot")]
        strips.append(np.array([*leg, end(f"{side}_foot")]))
    joints = np.array([p for p, _ in (seg[s] for s in skeleton.segments)])
    return strips, joints


def status_text(topology: object, health: Mapping[str, object]) -> str:
    """The status panel from the latest topology and health JSON, whatever their
    shape: what is not as documented shows as ``?`` rather than stopping the view."""

    def field(d: object, key: str) -> object:
        return d.get(key) if isinstance(d, dict) else None

    lines = ["## Topology"]
    branches = field(topology, "branches")
    for branch, info in sorted(branches.items() if isinstance(branches, dict) else ()):
        nodes = field(info, "nodes")
        states = ", ".join(
            f"{k.split('/')[-2] if k.count('/') >= 2 else k} {field(v, 'state') or '?'}"
            for k, v in sorted(nodes.items() if isinstance(nodes, dict) else ())
        )
        lines.append(f"- **{branch}**: {states}")
    lines.append("\n## Health")
    for source, h in sorted(health.items()):
        rejected = field(h, "rejected") or {}
        lines.append(f"- {source}: device {field(h, 'device') or '-'}, rejected {rejected}")
    return "\n".join(lines)


@dataclass
class Viewer:
    """Logs poses to Rerun, batching them; to several sinks at once if asked
    (a window or the web viewer, and a saved ``.rrd``), one stream each."""

    recs: list[rr.RecordingStream]
    skeleton: Skeleton
    address: str = ""  # the web viewer's address, in web mode

    @classmethod
    def start(cls, mode: str, save: Path | None = None, url: str | None = None,
              web_port: int | None = None, grpc_port: int | None = None) -> Viewer:  # fmt: skip
        """``mode``: ``native`` (a window), ``web`` (serve the web viewer),
        ``connect`` (to a running viewer at ``url``) or ``none``; with ``save``
        the ``.rrd`` is written as well."""
        bp = blueprint()
        recording_id = f"bodynet-{time.time_ns()}"
        recs: list[rr.RecordingStream] = []
        address = ""
        if mode != "none":
            rec = rr.RecordingStream("bodynet", recording_id=recording_id)
            if mode == "native":
                rec.spawn(default_blueprint=bp)
            elif mode == "web":
                uri = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=bp)
                rr.serve_web_viewer(open_browser=False, connect_to=uri, web_port=web_port)
                address = f"http://127.0.0.1:{web_port or 9090}/?url={uri}"
            else:
                rec.connect_grpc(url, default_blueprint=bp)
            recs.append(rec)
        if save is not None:
            rec = rr.RecordingStream("bodynet", recording_id=recording_id)
            rec.save(save, default_blueprint=bp)
            recs.append(rec)
        for rec in recs:
            rec.log("body", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        return cls(recs, build_skeleton(), address)

    def log_poses(self, frames: Sequence[pose.PoseFrame]) -> None:
        """One batch: angle columns over time, the latest figure and gauges."""
        if not frames:
            return
        times = rr.TimeColumn("time", timestamp=[f.t_ns * 1e-9 for f in frames])
        last = frames[-1]
        strips, joints = figure(last, self.skeleton)
        for rec in self.recs:
            for name in last.angles_deg:
                values = [f.angles_deg.get(name, float("nan")) for f in frames]
                rec.send_columns(f"angles/{name.removesuffix('_deg')}", indexes=[times],
                                 columns=rr.Scalars.columns(scalars=values))  # fmt: skip
            rec.set_time("time", timestamp=last.t_ns * 1e-9)
            rec.log("body/figure", rr.LineStrips3D(strips, radii=0.01))
            rec.log("body/joints", rr.Points3D(joints, radii=0.02))
            rec.log("gauges", rr.BarChart([last.angles_deg.get(g, 0.0) for g in GAUGES]))

    def log_status(self, text: str) -> None:
        for rec in self.recs:
            rec.log("status", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN))

    def close(self) -> None:
        for rec in self.recs:
            rec.flush()
            rec.disconnect()


def view_recording(path: Path, viewer: Viewer, batch: int = 100) -> int:
    """Log every pose of an MCAP recording; returns how many."""
    from bodynet.clients.mcap_store import read_poses

    frames: list[pose.PoseFrame] = []
    count = 0
    for _, frame in read_poses(path):
        frames.append(frame)
        if len(frames) >= batch:
            viewer.log_poses(frames)
            count += len(frames)
            frames = []
    viewer.log_poses(frames)
    return count + len(frames)


def view_live(session: zenoh.Session, viewer: Viewer, stop: threading.Event) -> int:
    """Log the live poses, topology and health until ``stop``; returns how many poses."""
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()

    def put(sample: zenoh.Sample) -> None:
        inbox.put((str(sample.key_expr), sample.payload.to_bytes()))

    subs = [
        session.declare_subscriber(k, put)
        for k in (keys.pose_key(), keys.TOPOLOGY, f"{keys.HEALTH}/**")
    ]
    topology: object = None
    health: dict[str, object] = {}
    count = 0
    try:
        while not stop.wait(BATCH_S):
            frames: list[pose.PoseFrame] = []
            changed = False
            while True:
                try:
                    key, data = inbox.get_nowait()
                except queue.Empty:
                    break
                try:
                    if key == keys.pose_key():
                        frames.append(pose.decode(data))
                    elif key == keys.TOPOLOGY:
                        topology, changed = json.loads(data), True
                    else:
                        health[key.rsplit("/", 1)[-1]], changed = json.loads(data), True
                except (DecodeError, ValueError):
                    continue  # a client shows what it can; the gateway counts garbage
            viewer.log_poses(frames)
            count += len(frames)
            if changed:
                viewer.log_status(status_text(topology, health))
    finally:
        for sub in subs:
            sub.undeclare()
    return count
