"""A recording's poses as arrays: what every export writer is given.

:func:`load_track` reads a recording's poses into a :class:`PoseTrack`, with
which of its joint angles were measured (``is_measured``). Formats with a
frame rate (BVH, C3D, OpenSim's tables...) want frames at a constant rate:
:func:`resample` puts a track on a regular grid (segment orientations by
slerp, positions and angles linearly; a resampled angle is measured only
where both poses around it were, and those were no more than
:data:`GAP_TICKS` tick intervals apart: a frame in a gap in the poses is
no measurement). A recording whose ticks are already regular comes out
frame for frame.

Segment orientations and joint centres carry no flag of their own: they rest
on every angle of their chain from the pelvis (``Skeleton.segment_chains``),
and are measured where all of those are, or are the upright model's, the
reference of a body with no trunk sensor (:meth:`PoseTrack.chain_measured`,
:meth:`PoseTrack.centre_measured`, ``body_tree.chain_breaks``).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm

from bodynet.clients.body_tree import chain_breaks, default_chains
from bodynet.clients.mcap_store import StoreError, count_messages, read_poses
from bodynet.core import keys
from bodynet.core.metrics import measured_angles
from bodynet.core.skeleton import build_skeleton
from bodynet.session.outputs import atomic_path

#: Frame rate of a recording with a single pose, where none can be measured.
DEFAULT_RATE_HZ = 100.0
#: How many held angles a note names (the count covers them all).
NOTE_ANGLES = 8
#: Poses further apart than this many of the recording's tick intervals (its
#: median) leave a gap: nothing measured the frames resampled between them.
#: 2.5: one tick missing (2 intervals) and some jitter still bridge; two do not.
GAP_TICKS = 2.5


@dataclass(frozen=True)
class PoseTrack:
    """A recording's whole-body poses as arrays, one row per frame.

    Segments, joints and angles are in the skeleton's order; a joint centre or
    angle a pose lacks is NaN. Positions in metres, world frame.
    """

    t_ns: np.ndarray  # (F,) int64
    segments: tuple[str, ...]
    segment_p: np.ndarray  # (F, S, 3)
    segment_q: np.ndarray  # (F, S, 4) unit quaternions w, x, y, z
    joints: tuple[str, ...]
    joint_p: np.ndarray  # (F, J, 3)
    angles: tuple[str, ...]
    angle_deg: np.ndarray  # (F, A)
    rel_deg: np.ndarray  # (F, J) each joint's total rotation from the calibration pose
    measured: np.ndarray  # (F, A) bool: a measurement is behind the angle (measured_angles)
    rate_hz: float | None = None  # set by resample: the frames are 1 / rate_hz apart
    source: str = ""  # the recording it was read from, for messages about its poses
    #: (F,) bool: the frame stands on poses (False: resampled inside a gap in them,
    #: where nothing measured even the pelvis); None: every frame does
    posed: np.ndarray | None = None
    #: (F, A) bool: the angle is not measured but the upright model's, which the
    #: segments below it stand on as on a measured one (``body_tree.chain_breaks``);
    #: None: none is
    upright: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_ns)

    def joint_measured(self) -> np.ndarray:
        """(F, J) bool: every dof of the joint is measured (its ``rel_deg`` is)."""
        names = build_skeleton().joints
        index = {a: i for i, a in enumerate(self.angles)}
        return np.stack([self.measured[:, [index[a] for a in j.angle_names()]].all(axis=1)
                         for j in names], axis=1)  # fmt: skip

    def frame_posed(self) -> np.ndarray:
        """(F,) bool: :attr:`posed`, every frame if None."""
        return np.ones(len(self), dtype=bool) if self.posed is None else self.posed

    def chain_measured(self) -> np.ndarray:
        """(F, S) bool: the segment's orientation is measured: its frame stands
        on poses and every angle from the pelvis to it is measured or the upright
        model's (the pelvis: the frame alone, it carries no flag)."""
        index = {a: i for i, a in enumerate(self.angles)}
        chains = default_chains()
        posed = self.frame_posed()
        stands = self.measured if self.upright is None else self.measured | self.upright
        return np.stack([posed & stands[:, [index[a] for a in chains[s]]].all(axis=1)
                         for s in self.segments], axis=1)  # fmt: skip

    def centre_measured(self) -> np.ndarray:
        """(F, J) bool: the joint centre's place is measured: that of the segment
        it sits on (its parent's chain; the joint's own angles do not move it)."""
        segment = {s: i for i, s in enumerate(self.segments)}
        parent = {j.name: j.parent for j in build_skeleton().joints}
        return self.chain_measured()[:, [segment[parent[j]] for j in self.joints]]

    def measured_rate_hz(self) -> float:
        """The recording's tick rate (median interval), to 0.01 Hz."""
        if len(self) < 2:
            return DEFAULT_RATE_HZ
        return round(1e9 / float(np.median(np.diff(self.t_ns))), 2)


def load_track(recording: Path, progress: bool = True, every_tick: bool = False) -> PoseTrack:
    """The poses on ``body/pose`` of a recording; ``StoreError`` if it has none,
    is not a complete MCAP file, or holds something else than bodynet poses.

    Ticks that carry no newer sample repeat a time: only the last pose of each
    time is kept, unless ``every_tick`` (one row per pose, as CSV gives it)."""
    skeleton = build_skeleton()
    segments, joints = skeleton.segments, tuple(j.name for j in skeleton.joints)
    angles = skeleton.angle_names()
    total = count_messages(recording, keys.pose_key())
    # arrays filled in place (a Python float per value would take 4 times the memory)
    cap = max(total, 256)
    t = np.empty(cap, dtype=np.int64)
    seg_p = np.empty((cap, len(segments), 3))
    seg_q = np.empty((cap, len(segments), 4))
    joint_p = np.empty((cap, len(joints), 3))
    angle_deg = np.empty((cap, len(angles)))
    rel_deg = np.empty((cap, len(joints)))
    measured = np.empty((cap, len(angles)), dtype=bool)
    upright = np.zeros((cap, len(angles)), dtype=bool)
    nan3 = (np.nan, np.nan, np.nan)
    n = 0
    # disable=None: no bar when stderr is not a terminal
    bar = tqdm(total=total or None, unit="pose", desc=recording.name, leave=False,
               disable=None if progress else True)  # fmt: skip
    with bar:
        for t_ns, frame in read_poses(recording):
            missing = [s for s in segments if s not in frame.segments]
            if missing:
                raise StoreError(f"{recording}: the pose at {t_ns} ns lacks segments "
                                 f"{', '.join(missing)}")  # fmt: skip
            if n == len(t):
                t, seg_p, seg_q, joint_p, angle_deg, rel_deg, measured, upright = (
                    np.concatenate([a, np.zeros_like(a)])
                    for a in (t, seg_p, seg_q, joint_p, angle_deg, rel_deg, measured, upright)
                )
            t[n] = t_ns
            seg_p[n] = [frame.segments[s][0] for s in segments]
            seg_q[n] = [frame.segments[s][1] for s in segments]
            joint_p[n] = [frame.joints_m.get(j, nan3) for j in joints]
            angle_deg[n] = [frame.angles_deg.get(a, np.nan) for a in angles]
            rel_deg[n] = [frame.rel_deg.get(j, np.nan) for j in joints]
            if frame.flags or frame.stale:
                got = measured_angles(frame)
                measured[n] = [a in got for a in angles]
                breaks = chain_breaks(frame)
                upright[n] = [not (m or a in breaks)
                              for a, m in zip(angles, measured[n], strict=True)]  # fmt: skip
            else:
                measured[n] = True
            n += 1
            bar.update()
    if not n:
        raise StoreError(f"{recording}: no poses on {keys.pose_key()} to export "
                         "(raw samples only? process the capture first)")  # fmt: skip
    measured[:n] &= ~np.isnan(angle_deg[:n])  # an angle a pose lacks was not measured either
    if every_tick:
        keep: np.ndarray | slice = slice(0, n)
    else:
        _, last_first = np.unique(t[:n][::-1], return_index=True)
        keep = n - 1 - last_first
    return PoseTrack(t[keep], segments, seg_p[keep], seg_q[keep], joints, joint_p[keep], angles,
                     angle_deg[keep], rel_deg[keep], measured[keep],
                     source=str(recording),
                     upright=upright[keep] if upright[:n].any() else None)  # fmt: skip


def resample(track: PoseTrack, rate_hz: float) -> PoseTrack:
    """``track`` at ``rate_hz`` from its first pose to its last: segment
    orientations by slerp, positions and angles linearly. An angle is measured
    where both poses around it were and were no more than :data:`GAP_TICKS`
    of the recording's tick intervals apart; a frame between poses further
    apart is no pose at all (``posed`` False, no angle measured)."""
    if rate_hz <= 0 or not np.isfinite(rate_hz):
        raise ValueError(f"frame rate must be positive, not {rate_hz}")
    if len(track) < 2:
        return replace(track, rate_hz=rate_hz)
    period_ns = 1e9 / rate_hz
    rel = (track.t_ns - track.t_ns[0]).astype(np.float64)
    n = int(np.floor(rel[-1] / period_ns + 1e-6)) + 1
    grid = np.minimum(np.arange(n) * period_ns, rel[-1])
    if n == len(track) and np.allclose(grid, rel, rtol=0.0, atol=period_ns * 1e-3):
        return replace(track, rate_hz=rate_hz)  # regular ticks already: frame for frame

    def linear(values: np.ndarray) -> np.ndarray:
        return np.asarray(make_interp_spline(rel, values, k=1, axis=0, check_finite=False)(grid))

    quats = np.empty((n, len(track.segments), 4))
    for s in range(len(track.segments)):
        rot = Rotation.from_quat(track.segment_q[:, s], scalar_first=True)
        quats[:, s] = Slerp(rel, rot)(grid).as_quat(scalar_first=True)
    # 1.0 only where every pose the value is drawn from was measured
    measured = linear(track.measured.astype(np.float64)) > 1.0 - 1e-9
    posed = linear(track.frame_posed().astype(np.float64)) > 1.0 - 1e-9
    posed &= ~in_gaps(rel, grid, period_ns)
    measured &= posed[:, None]
    upright = None
    if track.upright is not None:
        upright = (linear(track.upright.astype(np.float64)) > 1.0 - 1e-9) & posed[:, None]
    return replace(track, t_ns=track.t_ns[0] + np.round(grid).astype(np.int64),
                   segment_p=linear(track.segment_p), segment_q=quats,
                   joint_p=linear(track.joint_p), angle_deg=linear(track.angle_deg),
                   rel_deg=linear(track.rel_deg), measured=measured, posed=posed,
                   upright=upright, rate_hz=rate_hz)  # fmt: skip


def in_gaps(rel: np.ndarray, grid: np.ndarray, period_ns: float) -> np.ndarray:
    """(G,) bool: the grid time falls strictly between two poses (times ``rel``)
    more than :data:`GAP_TICKS` median intervals apart (a grid time on a pose,
    within a thousandth of the grid's period, stands on it)."""
    steps = np.diff(rel)
    limit = GAP_TICKS * float(np.median(steps))
    after = np.clip(np.searchsorted(rel, grid, side="right") - 1, 0, len(rel) - 2)
    near = period_ns * 1e-3
    on_pose = (np.abs(grid - rel[after]) <= near) | (np.abs(rel[after + 1] - grid) <= near)
    return (steps[after] > limit) & ~on_pose


@contextlib.contextmanager
def output_file(out: Path, suffix: str = ".part", named: bool = False) -> Iterator[Path]:
    """A temporary file beside ``out`` (readable by the owner only: health
    data) that becomes ``out`` when the block ends without an exception, and
    is removed otherwise: nothing half-written is left under ``out`` (see
    :func:`~bodynet.session.outputs.atomic_path`)."""
    with atomic_path(out, suffix=suffix, named=named) as tmp:
        yield tmp


def euler_deg(rotations: Rotation, seq: str) -> np.ndarray:
    """Intrinsic Euler angles (deg) in ``seq`` order; at a gimbal lock scipy
    picks one of the equivalent triples (warning silenced): the rotation is
    still exact."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.asarray(rotations.as_euler(seq.upper(), degrees=True))


def hold_unmeasured(values: np.ndarray, measured: np.ndarray, last: np.ndarray) -> np.ndarray:
    """``values`` (F, C) where ``measured``, else the last measured value of the
    column (from ``last`` (C,), the value before the first row; updated)."""
    # for each row and column, the last measured row up to it (-1: none yet)
    rows = np.where(measured, np.arange(len(values))[:, None], -1)
    upto = np.maximum.accumulate(rows, axis=0)
    cols = np.arange(values.shape[1])
    out = np.where(upto >= 0, values[np.maximum(upto, 0), cols], last)
    if len(out):
        last[:] = out[-1]
    return out


def held_note(track: PoseTrack) -> tuple[str, ...]:
    """What a format without an absent value says of the values it held."""
    held = ~track.measured
    if not held.any():
        return ()
    per_angle = held.sum(axis=0)
    names = [f"{track.angles[i]} ({per_angle[i]})" for i in np.flatnonzero(per_angle)]
    shown = ", ".join(names[:NOTE_ANGLES])
    if len(names) > NOTE_ANGLES:
        shown += f" and {len(names) - NOTE_ANGLES} more"
    notes = [f"{int(held.sum())} values of {len(names)} joint angles had no measurement behind "
             f"them and hold their last measured value: {shown}"]  # fmt: skip
    gap = int((~track.frame_posed()).sum())
    if gap:
        notes.append(f"{gap} frames fall in gaps in the poses (more than {GAP_TICKS:g} ticks "
                     "apart): nothing measured them, they hold the last frame, the root's "
                     "place and orientation too")  # fmt: skip
    return tuple(notes)


def hold_gaps(values: np.ndarray, posed: np.ndarray, last: np.ndarray) -> np.ndarray:
    """``values`` (F, C) (a frame's channels, the root's place and orientation
    among them) held over the frames in a gap in the poses (``posed`` (F,)
    False), as :func:`hold_unmeasured` holds (``last``: those before the first row)."""
    return hold_unmeasured(values, np.repeat(posed[:, None], values.shape[1], axis=1), last)
