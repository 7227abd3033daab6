"""``bodynet export``: recordings to standard formats.

CSV: one row per pose tick, ``t_s`` (the recording's time base: for a processed
capture, the same as ``bodynet decode`` gives it), then every joint angle
``<joint>_<dof>_deg``, every joint's total rotation from the calibration pose
``<joint>_rel_deg``, and every joint centre ``<joint>_x_m``, ``_y_m``, ``_z_m``.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

from bodynet.clients.mcap_store import StoreError, read_poses
from bodynet.core.skeleton import build_skeleton


def csv_columns() -> list[str]:
    skeleton = build_skeleton()
    joints = [j.name for j in skeleton.joints]
    return (["t_s", *skeleton.angle_names(), *(f"{j}_rel_deg" for j in joints)]
            + [f"{j}_{axis}_m" for j in joints for axis in "xyz"])  # fmt: skip


def export_csv(recording: Path, out: Path) -> int:
    """Write the CSV of a recording's poses; returns the number of rows.

    The file appears complete or not at all (written aside, then renamed).
    """
    columns = csv_columns()
    tmp = out.with_name(out.name + ".part")
    rows = 0
    try:
        with tmp.open("w", newline="") as f:
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
        if not rows:
            raise StoreError(f"{recording}: no poses to export (process the capture first?)")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return rows


def _fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.6g}"
