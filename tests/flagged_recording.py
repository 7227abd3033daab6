"""A recording whose poses flag some angles as not measured for a window of
frames (the exports' tests of "no number without a measurement")."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from bodynet.clients.mcap_store import McapSink, read_poses
from bodynet.core import keys

WINDOW = range(100, 121)  # frames (25 Hz) in the moving part of ``body_mcap``
FLAGS = {
    "left_elbow_pronation_deg": "unobserved",
    "left_knee_flexion_deg": "uncalibrated",
    "right_elbow_flexion_deg": "clamped",  # measured: a value at a limit
}
UNMEASURED = [a for a, f in FLAGS.items() if f != "clamped"]


def write_flagged(source: Path, out: Path) -> None:
    """``source``'s poses with FLAGS added to those of WINDOW."""
    sink = McapSink(out)
    for index, (log_time, frame) in enumerate(read_poses(source)):
        assert not set(frame.flags) & set(FLAGS)  # the flags are the test's alone
        flags = {**frame.flags, **FLAGS} if index in WINDOW else frame.flags
        sink.write_pose(keys.pose_key(), dataclasses.replace(frame, flags=flags), log_time)
    sink.close()
