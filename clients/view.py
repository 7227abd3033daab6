"""``bodynet view``: the body in Rerun, live from Zenoh or from a recording.

A 3D stick figure (the segments of the 000 seed's stick figure, joints as
points), every joint angle as a time series, a gauge panel of chosen joints
(the seed's 3x3 gauge matrix: dials over each dof's range of motion) and the topology and health as
text, laid out by a default blueprint. A dof with no measurement behind its
number (``pose.is_measured``) is left out of its time series (a gap), its
gauge's needle is grey with the reason instead of a reading, and the panel
"Not measured" says for each such dof why. Poses are logged in batches (columns
of angles, the latest figure per batch), never one ``rr.log`` per sample.
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError
from bodynet.core.skeleton import Skeleton, build_skeleton, rom
from bodynet.session.outputs import OutputError, PendingOutput

GAUGES = (
    "left_shoulder_flexion_deg", "left_elbow_flexion_deg", "left_wrist_flexion_deg",
    "right_shoulder_flexion_deg", "right_elbow_flexion_deg", "right_wrist_flexion_deg",
    "left_knee_flexion_deg", "right_knee_flexion_deg", "lumbar_flexion_deg",
)  # fmt: skip
BATCH_S = 0.1
#: The gauge panel: ``GAUGES`` in three rows of three dials, each sweeping its dof's
#: range of motion over 240 degrees, from lower left (the minimum) to lower right.
GAUGE_SWEEP_DEG, GAUGE_PITCH = 240.0, 2.6


def _dial_point(i: int, fraction: float, radius: float) -> tuple[float, float]:
    """A point of gauge ``i``'s dial, ``fraction`` of the way along its range (2D, y down)."""
    cx, cy = GAUGE_PITCH * (i % 3), GAUGE_PITCH * (i // 3)
    theta = math.radians(90.0 + GAUGE_SWEEP_DEG / 2 - GAUGE_SWEEP_DEG * fraction)
    return cx + radius * math.cos(theta), cy - radius * math.sin(theta)


def gauge_faces() -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray, list[str]]:
    """The still part of the gauge panel: each dial's arc, its ticks at the ends of
    the range of motion and at 0, and where its name goes."""
    arcs, ticks, names = [], [], []
    for i, angle in enumerate(GAUGES):
        arcs.append(np.array([_dial_point(i, f, 1.0) for f in np.linspace(0.0, 1.0, 49)]))
        lo, hi = rom(angle)
        for f in {0.0, 1.0, (0.0 - lo) / (hi - lo)}:
            ticks.append(np.array([_dial_point(i, f, 0.85), _dial_point(i, f, 1.0)]))
        names.append(angle.removesuffix("_deg"))
    where = np.array([(GAUGE_PITCH * (i % 3), GAUGE_PITCH * (i // 3) + 1.15)
                      for i in range(len(GAUGES))])  # fmt: skip
    return arcs, ticks, where, names


#: The needle of a measured dof, and of one with no measurement behind it (grey).
NEEDLE, NEEDLE_UNMEASURED = (230, 90, 40), (160, 160, 160)
#: What a gauge reads instead of a number, by flag.
MARKS = {pose.UNCALIBRATED: "uncal.", pose.UNOBSERVED: "n/m", pose.HELD: "held"}


def gauge_needles(
    values: Sequence[float], flags: Sequence[str] | None = None
) -> tuple[list[np.ndarray], list[str]]:
    """Each gauge's needle at its value (held at the end of the range outside it)
    and its reading, from the values of ``GAUGES``; a gauge whose flag (``flags``,
    "" for a measured one) says no measurement reads its mark, not a number."""
    needles, readings = [], []
    for i, (angle, value) in enumerate(zip(GAUGES, values, strict=True)):
        lo, hi = rom(angle)
        fraction = min(max((value - lo) / (hi - lo), 0.0), 1.0)
        centre = (GAUGE_PITCH * (i % 3), GAUGE_PITCH * (i // 3))
        needles.append(np.array([centre, _dial_point(i, fraction, 0.8)]))
        flag = flags[i] if flags else ""
        readings.append(MARKS.get(flag, flag) if flag else f"{value:.0f}°")
    return needles, readings


def unmeasured_text(frame: pose.PoseFrame) -> str:
    """The "Not measured" panel: each dof with no measurement behind its number,
    and why (the pose's reasons in words)."""
    rows = [f"- **{n.removesuffix('_deg')}**: {frame.why(n)}"
            for n in frame.angles_deg if not pose.is_measured(frame, n)]  # fmt: skip
    return "\n".join(rows) if rows else "Every joint angle is measured."


log = logging.getLogger(__name__)


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="body", name="Body"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="angles", name="Joint angles (deg)"),
                rrb.Spatial2DView(origin="gauges", name="Gauges (degrees)"),
                rrb.Tabs(
                    rrb.TextDocumentView(origin="status", name="Topology and health"),
                    rrb.TextDocumentView(origin="unmeasured", name="Not measured"),
                ),
                rrb.TextDocumentView(origin="metrics", name="Clinical metrics"),
            ),
        ),
        collapse_panels=True,
    )  # fmt: skip


#: Positions further than this from the origin (m), or not numbers, are not drawn.
MAX_M = 1e6


def _limb(start: str, side: str, parts: tuple[str, ...]) -> tuple[tuple[str, bool], ...]:
    return ((start, False), *((f"{side}_{p}", False) for p in parts), (f"{side}_{parts[-1]}", True))


#: The stick figure's chains: (segment, its far end rather than its origin) in
#: order; a bone is drawn between neighbours that are both there.
CHAINS: tuple[tuple[tuple[str, bool], ...], ...] = (
    (("pelvis", False), ("thorax", False), ("head", False), ("head", True)),
    *(
        chain
        for side in ("left", "right")
        for chain in (_limb("head", side, ("upperarm", "forearm", "hand")),
                      _limb("pelvis", side, ("thigh", "shank", "foot")))
    ),
)  # fmt: skip


def _point(v: object) -> np.ndarray | None:
    """A drawable position: three numbers within ``MAX_M``, else ``None``."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return None
    return a if a.shape == (3,) and bool(np.all(np.abs(a) <= MAX_M)) else None


def figure(frame: pose.PoseFrame, skeleton: Skeleton) -> tuple[list[np.ndarray], np.ndarray]:
    """Line strips of the stick figure, and the joint centres, from one pose.

    Whatever the pose holds: a bone whose segment is missing (a branch view, a
    partial pose) or not drawable (a position not a number or absurdly far, a
    quaternion of no direction) is left out, and the rest is drawn."""

    def origin(segment: str) -> np.ndarray | None:
        pq = frame.segments.get(segment)
        return None if pq is None else _point(pq[0])

    def end(segment: str) -> np.ndarray | None:
        p = origin(segment)
        q = frame.segments[segment][1] if p is not None else ()
        if p is None or len(q) != 4:
            return None
        n = math.hypot(*q)  # no overflow, unlike a sum of squares
        if not 0.0 < n < math.inf:
            return None
        w, x, y, z = (c / n for c in q)
        rot = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        direction = np.array(skeleton.directions.get(segment, (0.0, 0.0, 0.0)))
        return _point(p + rot @ (direction * skeleton.segment_length(segment)))

    strips: list[np.ndarray] = []
    for chain in CHAINS:
        run: list[np.ndarray] = []
        for segment, far in (*chain, ("", False)):  # a sentinel ends the last run
            point = (end if far else origin)(segment) if segment else None
            if point is not None:
                run.append(point)
                continue
            if len(run) >= 2:
                strips.append(np.array(run))
            run = []
    points = [p for p in (origin(s) for s in skeleton.segments) if p is not None]
    return strips, np.array(points, dtype=float).reshape(-1, 3)


def angle_path(name: str) -> str | None:
    """The entity of one joint angle's time series, ``None`` for a nameless one."""
    part = name.removesuffix("_deg")
    return f"angles/{rr.escape_entity_path_part(part)}" if part else None


def _number(v: float) -> float:
    return float(v) if math.isfinite(v) else math.nan


@dataclass(frozen=True)
class Drawing:
    """What the view logs of one pose."""

    t_ns: int  # within int64, as Rerun's timestamps are
    strips: list[np.ndarray]  # each (n >= 2, 3), finite
    joints: np.ndarray  # (n, 3), finite
    angles: dict[str, float]  # entity path -> degrees (NaN: not a number, or not measured)
    gauges: list[float]  # one per ``GAUGES``, finite (0: absent or not a number)
    gauge_flags: list[str]  # one per ``GAUGES``: "" if measured, else its flag
    unmeasured: str  # the "Not measured" panel
    origins: dict[str, np.ndarray] = field(default_factory=dict)  # segment -> its origin


def drawing(frame: pose.PoseFrame, skeleton: Skeleton) -> Drawing | None:
    """The view of one decoded pose, ``None`` if it cannot be shown at all (a
    time Rerun cannot hold): counted as a bad message, never an exception."""
    if not -(2**63) < frame.t_ns < 2**63:  # int64, and -2**63 is NaT
        return None
    strips, joints = figure(frame, skeleton)
    angles = {}
    for name, value in frame.angles_deg.items():
        path = angle_path(name)
        if path is not None:  # no measurement: a gap in its time series
            angles[path] = _number(value) if pose.is_measured(frame, name) else math.nan
    gauges = [frame.angles_deg.get(g, 0.0) for g in GAUGES]
    flags = ["" if pose.is_measured(frame, g) else frame.flags[g] for g in GAUGES]
    origins = {name: o for name, pq in frame.segments.items()
               if (o := _point(pq[0] if len(pq) else None)) is not None}  # fmt: skip
    return Drawing(frame.t_ns, strips, joints, angles,
                   [g if math.isfinite(g) else 0.0 for g in gauges], flags,
                   unmeasured_text(frame), origins)  # fmt: skip


def _show(v: object) -> str:
    """One value of the health JSON as text; ``?`` for what is not a number or a word."""
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, bool | int | str):
        return str(v)[:40]
    return "?"


def _counts(d: object) -> str:
    """Rejections by reason, ``0`` for none."""
    if d is None or d == {}:
        return "0"
    if isinstance(d, dict):
        return ", ".join(f"{k} {_show(v)}" for k, v in sorted(d.items()))
    return _show(d)


def status_text(topology: object, health: Mapping[str, object], bad: int = 0) -> str:
    """The status panel from the latest topology and health JSON, whatever their
    shape: what is not as documented shows as ``?`` rather than stopping the view.
    Per bridge its device and rejections, and per node whether it is alive, its
    rate, samples, gaps and rejections; ``bad``: messages the view could not show."""

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
        parts = [f"device {_show(field(h, 'device'))}"] if field(h, "device") is not None else []
        parts += [f"{k} {_show(field(h, k))}" for k in ("samples", "ticks")
                  if field(h, k) is not None]  # fmt: skip
        parts.append(f"rejected {_counts(field(h, 'rejected'))}")
        if field(h, "foreign"):
            parts.append(f"other devices' frames {_counts(field(h, 'foreign'))}")
        lines.append(f"- **{source}**: " + ", ".join(parts))
        nodes = field(h, "nodes")
        # node numbers in numeric order: "2" before "10"
        for node, n in sorted(nodes.items() if isinstance(nodes, dict) else (),
                              key=lambda kv: (len(kv[0]), kv[0])):  # fmt: skip
            alive = field(n, "alive")
            state = "alive" if alive is True else "not alive" if alive is False else "alive ?"
            key = field(n, "key")
            where = f" `{_show(key)}`" if key is not None else ""
            lines.append(
                f"  - node {node}{where}: {state}, {_show(field(n, 'rate_hz'))} Hz,"
                f" {_show(field(n, 'samples'))} samples, {_show(field(n, 'gaps'))} gaps,"
                f" rejected {_counts(field(n, 'rejected'))}"
            )
    lines += calibration_lines(health)
    if bad:
        lines.append(f"- **viewer**: {bad} bad messages, not shown")
    return "\n".join(lines)


def calibration_lines(health: Mapping[str, object]) -> list[str]:
    """The calibration state per segment, from the gateway's health (its body's
    ``heading``: the state of the tags' heading, and per segment what holds its
    tag's heading against drift and how well it is known, ``unc_deg``); none
    when no health says it. Any other shape shows as ``?``."""

    def field(d: object, key: str) -> object:
        return d.get(key) if isinstance(d, dict) else None

    lines: list[str] = []
    for source, h in sorted(health.items()):
        heading = field(field(h, "body"), "heading")
        if not isinstance(heading, dict):
            continue
        deg = field(heading, "deg")
        lines.append(f"\n## Calibration ({source})")
        lines.append(f"- heading **{_show(field(heading, 'state'))}**"
                     + (f", {_show(deg)} deg" if deg is not None else ""))  # fmt: skip
        segments = field(heading, "segments")
        for segment, seg in sorted(segments.items() if isinstance(segments, dict) else ()):
            unc = field(seg, "unc_deg")
            held = field(seg, "held_by")
            lines.append(
                f"  - {segment}: {_show(field(seg, 'how'))}"
                + (f" ({_show(held)})" if held is not None else "")
                + (f", heading known to {_show(unc)} deg" if unc is not None
                   else ", heading not known")
                + f", turned {_show(field(seg, 'corrected_deg'))} deg"
            )  # fmt: skip
    return lines


#: the calibration marks' colours: a heading held by a measurement or a joint's
#: geometry, by an assumption (a three-dof joint's mean twist), or not at all
CALIBRATION_COLOURS = {"held": (60, 180, 75), "assumed": (245, 170, 30), "not": (220, 50, 47)}
_ASSUMED = ("three-dof joint's mean twist",)
_NOT_HELD = ("not held", "heading unknown")


def calibration_marks(health: Mapping[str, object]) -> dict[str, tuple[tuple[int, int, int], str]]:
    """Per segment, the colour and label of its calibration state (the gateway's
    health: what holds its tag's heading, how well it is known); any other
    shape of health gives no mark."""
    out: dict[str, tuple[tuple[int, int, int], str]] = {}
    for _, h in sorted(health.items()):
        body = h.get("body") if isinstance(h, dict) else None
        heading = body.get("heading") if isinstance(body, dict) else None
        segments = heading.get("segments") if isinstance(heading, dict) else None
        for segment, seg in segments.items() if isinstance(segments, dict) else ():
            if not isinstance(seg, dict):
                continue
            how, unc = seg.get("how"), seg.get("unc_deg")
            kind = "not" if how in _NOT_HELD or unc is None else (
                "assumed" if how in _ASSUMED else "held")  # fmt: skip
            label = f"{segment}: {_show(how)}" + (f" +/-{_show(unc)} deg" if unc is not None
                                                   else "")  # fmt: skip
            out[str(segment)] = (CALIBRATION_COLOURS[kind], label)
    return out


def metrics_text(message: object) -> str:
    """The clinical-metrics panel from a ``body/@metrics`` message (JSON): one row
    per observed dof; what is not as documented shows as ``?``."""
    dofs = message.get("dofs") if isinstance(message, dict) else None
    if not isinstance(dofs, dict) or not dofs:
        return "No measured joint angle yet."
    lines = ["| dof | min | max | range (deg) | reps | SPARC |", "|---|---|---|---|---|---|"]
    for name, d in sorted(dofs.items()):

        def get(key: str, d: object = d) -> str:
            v = d.get(key) if isinstance(d, dict) else None
            if v is None and key == "sparc":
                return ""
            return f"{v:.4g}" if isinstance(v, float) else _show(v)

        lines.append(f"| {str(name).removesuffix('_deg')[:40]} | {get('min_deg')} | "
                     f"{get('max_deg')} | {get('range_deg')} | {get('repetitions')} | "
                     f"{get('sparc')} |")  # fmt: skip
    return "\n".join(lines)


class ViewerError(OSError):
    """A viewer that cannot be started or reached (a port in use, no viewer at
    the URL); the message says which."""


#: Rerun's defaults: its gRPC server's port (and a viewer's), and the web viewer's.
GRPC_PORT, WEB_PORT = 9876, 9090


def check_free(port: int, option: str) -> None:
    """``ViewerError`` unless ``port`` can be listened on (Rerun says so only in
    its log, and fails later)."""
    try:
        socket.create_server(("0.0.0.0", port)).close()
    except OSError as exc:
        why = os.strerror(exc.errno) if exc.errno else str(exc)
        raise ViewerError(f"cannot serve on port {port} ({option}): {why}") from None


def _check_reachable(url: str | None) -> None:
    """``ViewerError`` unless something listens where the viewer at ``url``
    should (Rerun would only say so when it gives up flushing)."""
    url = url or f"rerun+http://127.0.0.1:{GRPC_PORT}/proxy"
    parts = urlsplit(url)
    try:
        port = parts.port or (443 if parts.scheme == "rerun+https" else GRPC_PORT)
        socket.create_connection((parts.hostname or "", port), timeout=5.0).close()
    except (OSError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise ViewerError(f"cannot reach the viewer at {url}: {why} (is it running?)") from None


@dataclass
class Viewer:
    """Logs poses to Rerun, batching them; to several sinks at once if asked
    (a window or the web viewer, and a saved ``.rrd``), one stream each."""

    recs: list[rr.RecordingStream]
    skeleton: Skeleton
    address: str = ""  # the web viewer's address, in web mode
    save: Path | None = None  # the .rrd, there once complete
    part: PendingOutput | None = None  # the .rrd, until it is whole
    bad: int = 0  # messages not shown: not a pose, or a pose that cannot be drawn
    shown: int = 0  # poses logged
    #: segment -> (colour, label): the calibration state per segment (health), drawn
    #: at each segment's origin in the 3D view
    calibration: dict[str, tuple[tuple[int, int, int], str]] = field(default_factory=dict)
    url: str | None = None  # the viewer connected to, in connect mode
    stuck: bool = False  # a sink that did not take what it was given (Rerun would wait)

    @classmethod
    def start(cls, mode: str, save: Path | None = None, url: str | None = None,
              web_port: int | None = None, grpc_port: int | None = None) -> Viewer:  # fmt: skip
        """``mode``: ``native`` (a window), ``web`` (serve the web viewer),
        ``connect`` (to a running viewer at ``url``) or ``none``; with ``save``
        the ``.rrd`` is written as well: aside (owner-only, as health data is),
        renamed into place by :meth:`close`. ``OSError`` if it cannot be."""
        bp = blueprint()
        recording_id = f"bodynet-{time.time_ns()}"
        recs: list[rr.RecordingStream] = []
        address = ""
        part = None
        if save is not None:  # a fresh file, mode 0600, nameless until it is whole
            part = PendingOutput(save)
        try:
            if mode != "none":
                rec, uri = _sink(mode, bp, recording_id, url, web_port, grpc_port)
                recs.append(rec)
                if uri:
                    address = f"http://127.0.0.1:{web_port or WEB_PORT}/?url={uri}"
            if part is not None:
                rec = rr.RecordingStream("bodynet", recording_id=recording_id)
                rec.save(part.path, default_blueprint=bp)
                recs.append(rec)
            arcs, ticks, where, names = gauge_faces()
            for rec in recs:
                rec.log("body", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
                rec.log(
                    "gauges/faces",
                    rr.LineStrips2D([*arcs, *ticks], radii=0.03, colors=(150, 150, 150)),
                    static=True,
                )
                rec.log("gauges/names", rr.Points2D(where, radii=0.01, labels=names,
                                                    show_labels=True), static=True)  # fmt: skip
        except BaseException:
            if part is not None:
                part.discard()
            raise
        return cls(recs, build_skeleton(), address, save, part, url=url)

    def log_poses(self, frames: Sequence[pose.PoseFrame]) -> int:
        """One batch: angle columns over time, the latest figure and gauges.
        Returns how many poses were shown; the others count as ``bad``."""
        drawn = [d for d in (drawing(f, self.skeleton) for f in frames) if d is not None]
        self.bad += len(frames) - len(drawn)
        if not drawn:
            return 0
        t_ns = np.array([d.t_ns for d in drawn], dtype=np.int64).astype("datetime64[ns]")
        times = rr.TimeColumn("time", timestamp=t_ns)
        last = drawn[-1]
        for rec in self.recs:
            for path in last.angles:
                values = [d.angles.get(path, math.nan) for d in drawn]
                rec.send_columns(path, indexes=[times],
                                 columns=rr.Scalars.columns(scalars=values))  # fmt: skip
            rec.set_time("time", timestamp=t_ns[-1])
            rec.log("body/figure", rr.LineStrips3D(last.strips, radii=0.01))
            rec.log("body/joints", rr.Points3D(last.joints, radii=0.02))
            marks = [(last.origins[seg], *mark) for seg, mark in sorted(self.calibration.items())
                     if seg in last.origins]  # fmt: skip
            if marks:
                rec.log("body/calibration", rr.Points3D(
                    [m[0] for m in marks], radii=0.03, colors=[m[1] for m in marks],
                    labels=[m[2] for m in marks], show_labels=False))  # fmt: skip
            needles, readings = gauge_needles(last.gauges, last.gauge_flags)
            colors = [NEEDLE_UNMEASURED if f else NEEDLE for f in last.gauge_flags]
            rec.log(
                "gauges/needles",
                rr.LineStrips2D(
                    needles, radii=0.05, colors=colors, labels=readings, show_labels=True
                ),
            )
            rec.log(
                "unmeasured", rr.TextDocument(last.unmeasured, media_type=rr.MediaType.MARKDOWN)
            )
        self.shown += len(drawn)
        return len(drawn)

    def log_status(self, text: str) -> None:
        for rec in self.recs:
            rec.log("status", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN))

    def log_metrics(self, text: str) -> None:
        for rec in self.recs:
            rec.log("metrics", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN))

    def close(self, keep: bool = True, patience_s: float | None = None) -> None:
        """Flush and close every sink. The ``.rrd`` first (a viewer that takes nothing
        costs it nothing): into place if ``keep`` (and it was all written), else
        removed, leaving an older file of that name as it was. Then the viewer, waited
        for at most ``patience_s`` (default :data:`FLUSH_S`; a view stopped by Ctrl-C
        or SIGTERM: :data:`STOPPED_FLUSH_S`)."""
        patience = FLUSH_S if patience_s is None else patience_s
        viewer = f"the viewer{f' at {self.url}' if self.url else ''}"
        failure: OSError | None = None
        try:
            if self.part is not None:  # the .rrd: the last sink
                try:
                    self._close_rrd(self.recs[-1], keep)
                except OutputError as exc:
                    failure = exc
            for rec in self.recs[:-1] if self.part is not None else self.recs:
                self.stuck = True  # until it is closed: Rerun may wait on a viewer for ever
                log.info("waiting up to %g s for %s to take the poses", patience, viewer)
                try:
                    _flush(rec, patience)
                except RuntimeError as exc:  # it stopped, or did not take it all in time
                    raise ViewerError(f"{viewer} did not take the poses: {exc}") from None
                if not _ends(rec.disconnect, patience):
                    raise ViewerError(f"{viewer} did not take the poses within {patience:g} s")
                self.stuck = False
        except ViewerError as exc:
            failure = failure or exc
        finally:
            if self.part is not None:
                self.part.discard()
            if self.stuck:  # nor at exit: Rerun would wait there too
                rr.unregister_shutdown()
        if failure is not None:
            raise failure

    def _close_rrd(self, rec: rr.RecordingStream, keep: bool) -> None:
        """Write the rest of the ``.rrd`` and put it into place if ``keep``."""
        try:
            _flush(rec, FLUSH_S)
        except RuntimeError as exc:  # its writer stopped (a full disk) or hung: not whole
            raise OutputError(f"cannot write {self.save}: Rerun could not write "
                              f"it ({exc}; a full disk?)") from None  # fmt: skip
        finally:
            rec.disconnect()
        if keep and self.part is not None:
            self.part.commit()


#: How long closing waits for Rerun to write what it was given, in steps
#: between which a signal (Ctrl-C, SIGTERM) is handled.
FLUSH_S, FLUSH_STEP_S = 60.0, 0.25
#: How long a view stopped by Ctrl-C or SIGTERM waits for its viewer to take the
#: rest: one that is there takes it in milliseconds, one that is not would hold
#: the stop for a minute (the .rrd, a file, is still written whole).
STOPPED_FLUSH_S = 2.0


def _flush(rec: rr.RecordingStream, timeout_s: float) -> None:
    """``rec.flush`` for up to ``timeout_s``, in short waits: Rerun's own wait
    blocks signals (``RuntimeError`` if it fails or times out)."""
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        try:
            rec.flush(timeout_sec=max(min(FLUSH_STEP_S, left), 0.01))
            return
        except RuntimeError as exc:
            if "timed out" not in str(exc) or left <= FLUSH_STEP_S:
                raise


def _ends(call: Callable[[], object], timeout_s: float) -> bool:
    """Run ``call`` in a helper thread and wait for it up to ``timeout_s``, in
    short waits (Rerun's own waits block signals); whether it ended."""
    thread = threading.Thread(target=call, name="rerun-close", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout_s
    while thread.is_alive() and time.monotonic() < deadline:
        thread.join(FLUSH_STEP_S)
    return not thread.is_alive()


def _sink(mode: str, bp: rrb.Blueprint, recording_id: str, url: str | None,
          web_port: int | None, grpc_port: int | None,
          ) -> tuple[rr.RecordingStream, str]:  # fmt: skip
    """The recording stream of the live view, and in web mode the URI it is
    served on (``ViewerError`` if it cannot be)."""
    rec = rr.RecordingStream("bodynet", recording_id=recording_id)
    uri = ""
    try:
        if mode == "native":
            rec.spawn(default_blueprint=bp)
        elif mode == "web":
            check_free(web_port or WEB_PORT, "--web-port")
            check_free(grpc_port or GRPC_PORT, "--grpc-port")
            uri = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=bp)
            rr.serve_web_viewer(open_browser=False, connect_to=uri, web_port=web_port)
        else:
            _check_reachable(url)
            rec.connect_grpc(url, default_blueprint=bp)
    except RuntimeError as exc:  # Rerun's: an endpoint it refuses, a server it cannot make
        raise ViewerError(f"Rerun: {exc}") from None
    return rec, uri


def view_recording(path: Path, viewer: Viewer, batch: int = 100) -> int:
    """Log every pose of an MCAP recording, and its last clinical metrics;
    returns how many poses were shown."""
    from bodynet.clients.mcap_store import read_metrics, read_poses

    frames: list[pose.PoseFrame] = []
    count = 0
    for _, frame in read_poses(path):
        frames.append(frame)
        if len(frames) >= batch:
            count += viewer.log_poses(frames)
            frames = []
    count += viewer.log_poses(frames)
    last = deque(read_metrics(path), maxlen=1)  # the clinical metrics as they stood at the end
    if last:
        viewer.log_metrics(metrics_text(last[0][2]))
    return count


def view_live(session: zenoh.Session, viewer: Viewer, stop: threading.Event,
              on_live: Callable[[], object] | None = None) -> int:  # fmt: skip
    """Log the live poses, topology, health and metrics until ``stop``; returns how many
    poses were shown, calling ``on_live`` once the first are. No message stops it:
    what cannot be shown is counted in ``viewer.bad`` (and in the status panel) and
    the view goes on."""
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()

    def put(sample: zenoh.Sample) -> None:
        inbox.put((str(sample.key_expr), sample.payload.to_bytes()))

    subs = [
        session.declare_subscriber(k, put)
        for k in (keys.pose_key(), keys.TOPOLOGY, f"{keys.HEALTH}/**", keys.METRICS)
    ]
    topology: object = None
    health: dict[str, object] = {}
    count = 0
    failures = 0
    try:
        while not stop.wait(BATCH_S):
            frames: list[pose.PoseFrame] = []
            bad = viewer.bad
            changed = False
            while True:
                try:
                    key, data = inbox.get_nowait()
                except queue.Empty:
                    break
                try:
                    if key == keys.pose_key():
                        frames.append(pose.decode(data))
                    elif key == keys.METRICS:
                        viewer.log_metrics(metrics_text(json.loads(data)))
                    elif key == keys.TOPOLOGY:
                        topology, changed = json.loads(data), True
                    else:
                        health[key.rsplit("/", 1)[-1]], changed = json.loads(data), True
                # RecursionError: JSON nested deeper than the parser goes
                except (DecodeError, ValueError, RecursionError):
                    viewer.bad += 1  # a client shows what it can; the gateway counts garbage
            try:
                count += viewer.log_poses(frames)
            except Exception:  # a batch Rerun refused: counted, and the view goes on
                viewer.bad += len(frames)
                failures += 1
                if failures <= 3:
                    log.exception("bodynet view: a batch of %d poses failed", len(frames))
            if count and on_live is not None:
                on_live()
                on_live = None
            if changed or viewer.bad != bad:
                viewer.log_status(status_text(topology, health, viewer.bad))
                viewer.calibration = calibration_marks(health)
    finally:
        for sub in subs:
            sub.undeclare()
    return count
