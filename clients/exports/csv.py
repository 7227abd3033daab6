"""``bodynet export csv``: one row per pose tick.

Columns: ``t_s`` (the recording's time base: for a processed capture, the same
as ``bodynet decode`` gives it), then every joint angle ``<joint>_<dof>_deg``,
every joint's total rotation from the calibration pose ``<joint>_rel_deg``,
and every joint centre ``<joint>_x_m``, ``_y_m``, ``_z_m`` (world frame, the
model's).

An angle with no measurement behind it (flagged other than ``clamped``) is an
empty cell, and so is the ``rel_deg`` of a joint with such an angle, and a
joint centre whose place rests on one (an angle on the chain from the pelvis
to the segment it sits on: ``PoseTrack.centre_measured``).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from bodynet.clients.exports import Written
from bodynet.clients.exports.track import PoseTrack, output_file


def columns(track: PoseTrack) -> list[str]:
    """The header row."""
    return (["t_s", *track.angles, *(f"{j}_rel_deg" for j in track.joints)]
            + [f"{j}_{axis}_m" for j in track.joints for axis in "xyz"])  # fmt: skip


def write(track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
    """Write ``track`` (every tick, see ``load_track(every_tick=True)``) as CSV."""
    angles = np.where(track.measured, track.angle_deg, np.nan)
    rel = np.where(track.joint_measured(), track.rel_deg, np.nan)
    centres = np.where(track.centre_measured()[..., None], track.joint_p, np.nan)
    values = np.hstack([angles, rel, centres.reshape(len(track), -1)])
    with output_file(out) as tmp, tmp.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns(track))
        for t_ns, row in zip(track.t_ns.tolist(), values.tolist(), strict=True):
            writer.writerow([str(round(t_ns / 1e9, 9)), *map(_fmt, row)])
    return Written(len(track), "rows")


def _fmt(value: float) -> str:
    return "" if math.isnan(value) else f"{value:.6g}"  # NaN: an empty cell
