"""``bodynet export``: recordings to standard formats.

CSV: one row per pose tick, ``t_s`` (the recording's time base: for a processed
capture, the same as ``bodynet decode`` gives it), then every joint angle
``<joint>_<dof>_deg``, every joint's total rotation from the calibration pose
``<joint>_rel_deg``, and every joint centre ``<joint>_x_m``, ``_y_m``, ``_z_m``.

BVH (``bvh.py``) and C3D (``c3d_export.py``) need frames at a constant rate:
:func:`load_track` reads a recording's poses into arrays and :func:`resample`
puts them on a regular grid (segment orientations by slerp, positions and
angles linearly). A recording whose ticks are already regular comes out
frame for frame.
"""

from __future__ import annotations

import contextlib
import csv
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm

from bodynet.clients.mcap_store import StoreError, count_messages, read_poses
from bodynet.core import keys
from bodynet.core.skeleton import build_skeleton
from bodynet.session.outputs import atomic_path

#: Frame rate of a recording with a single pose, where none can be measured.
DEFAULT_RATE_HZ = 100.0


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

    def __len__(self) -> int:
        return len(self.t_ns)

    def measured_rate_hz(self) -> float:
        """The recording's tick rate (median interval), to 0.01 Hz."""
        if len(self) < 2:
            return DEFAULT_RATE_HZ
        return round(1e9 / float(np.median(np.diff(self.t_ns))), 2)


def load_track(recording: Path, progress: bool = True) -> PoseTrack:
    """The poses on ``body/pose`` of a recording; ``StoreError`` if it has none,
    is not a complete MCAP file, or holds something else than bodynet poses."""
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
    nan3 = (np.nan, np.nan, np.nan)
    n = 0
    # disable=None: no bar when stderr is not a terminal
    bar = tqdm(total=total or None, unit="pose", desc=recording.name, leave=False,
               disable=None if progress else True)  # fmt: skip
    with bar:
        for log_time, frame in read_poses(recording):
            missing = [s for s in segments if s not in frame.segments]
            if missing:
                raise StoreError(f"{recording}: the pose at {log_time} ns lacks segments "
                                 f"{', '.join(missing)}")  # fmt: skip
            if n == len(t):
                t, seg_p, seg_q, joint_p, angle_deg = (
                    np.concatenate([a, np.empty_like(a)]) for a in (t, seg_p, seg_q, joint_p,
                                                                    angle_deg)
                )  # fmt: skip
            t[n] = log_time
            seg_p[n] = [frame.segments[s][0] for s in segments]
            seg_q[n] = [frame.segments[s][1] for s in segments]
            joint_p[n] = [frame.joints_m.get(j, nan3) for j in joints]
            angle_deg[n] = [frame.angles_deg.get(a, np.nan) for a in angles]
            n += 1
            bar.update()
    if not n:
        raise StoreError(f"{recording}: no poses on {keys.pose_key()} to export "
                         "(raw samples only? process the capture first)")  # fmt: skip
    t = t[:n]
    # ticks that carry no newer sample repeat a time: keep the last pose of each
    _, last_first = np.unique(t[::-1], return_index=True)
    keep = n - 1 - last_first
    return PoseTrack(t[keep], segments, seg_p[keep], seg_q[keep], joints, joint_p[keep], angles,
                     angle_deg[keep])  # fmt: skip


def resample(track: PoseTrack, rate_hz: float) -> PoseTrack:
    """``track`` at ``rate_hz`` from its first pose to its last: segment
    orientations by slerp, positions and angles linearly (gaps included)."""
    if rate_hz <= 0 or not np.isfinite(rate_hz):
        raise ValueError(f"frame rate must be positive, not {rate_hz}")
    if len(track) < 2:
        return track
    period_ns = 1e9 / rate_hz
    rel = (track.t_ns - track.t_ns[0]).astype(np.float64)
    n = int(np.floor(rel[-1] / period_ns + 1e-6)) + 1
    grid = np.minimum(np.arange(n) * period_ns, rel[-1])
    if n == len(track) and np.allclose(grid, rel, rtol=0.0, atol=period_ns * 1e-3):
        return track  # regular ticks already: frame for frame

    def linear(values: np.ndarray) -> np.ndarray:
        return np.asarray(make_interp_spline(rel, values, k=1, axis=0, check_finite=False)(grid))

    quats = np.empty((n, len(track.segments), 4))
    for s in range(len(track.segments)):
        rot = Rotation.from_quat(track.segment_q[:, s], scalar_first=True)
        quats[:, s] = Slerp(rel, rot)(grid).as_quat(scalar_first=True)
    return replace(track, t_ns=track.t_ns[0] + np.round(grid).astype(np.int64),
                   segment_p=linear(track.segment_p), segment_q=quats,
                   joint_p=linear(track.joint_p), angle_deg=linear(track.angle_deg))  # fmt: skip


@contextlib.contextmanager
def output_file(out: Path, suffix: str = ".part") -> Iterator[Path]:
    """A temporary file beside ``out`` (readable by the owner only: health
    data) that becomes ``out`` when the block ends without an exception, and
    is removed otherwise: nothing half-written is left under ``out``."""
    with atomic_path(out, suffix=suffix) as tmp:
        yield tmp


def euler_deg(rotations: Rotation, seq: str) -> np.ndarray:
    """Intrinsic Euler angles (deg) in ``seq`` order; at a gimbal lock scipy
    picks one of the equivalent triples (warning silenced): the rotation is
    still exact."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.asarray(rotations.as_euler(seq.upper(), degrees=True))


def csv_columns() -> list[str]:
    skeleton = build_skeleton()
    joints = [j.name for j in skeleton.joints]
    return (["t_s", *skeleton.angle_names(), *(f"{j}_rel_deg" for j in joints)]
            + [f"{j}_{axis}_m" for j in joints for axis in "xyz"])  # fmt: skip


def export_csv(recording: Path, out: Path, progress: bool = True) -> int:
    """Write the CSV of a recording's poses; returns the number of rows.

    The file appears complete or not at all (written aside, then renamed).
    ``progress``: a progress bar on a terminal, as :func:`load_track` shows.
    """
    columns = csv_columns()
    total = count_messages(recording, keys.pose_key())
    rows = 0
    bar = tqdm(total=total or None, unit="pose", desc=recording.name, leave=False,
               disable=None if progress else True)  # fmt: skip
    with output_file(out) as tmp:
        with bar, tmp.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(columns)
            for log_time, frame in read_poses(recording):
                row: dict[str, float] = {"t_s": round(log_time / 1e9, 9)}
                row.update(frame.angles_deg)
                row.update({f"{j}_rel_deg": v for j, v in frame.rel_deg.items()})
                for j, (x, y, z) in frame.joints_m.items():
                    row.update({f"{j}_x_m": x, f"{j}_y_m": y, f"{j}_z_m": z})
                writer.writerow([str(row["t_s"]), *(_fmt(row.get(c)) for c in columns[1:])])
                rows += 1
                bar.update()
        if not rows:
            raise StoreError(f"{recording}: no poses to export (process the capture first?)")
    return rows


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.6g}"
