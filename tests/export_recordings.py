"""The exports' tests' helpers: ``bodynet export`` in the test's process, and a
recording whose poses flag some angles as not measured for a window of frames
(for "no number without a measurement")."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

from bodynet.cli.main import main
from bodynet.clients.mcap_store import McapSink, read_poses
from bodynet.core import keys

WINDOW = range(100, 121)  # frames (25 Hz) in the moving part of ``body_mcap``
FLAGS = {
    "left_elbow_pronation_deg": "unobserved",
    "left_knee_flexion_deg": "uncalibrated",
    "right_elbow_flexion_deg": "clamped",  # measured: a value at a limit
}


def write_flagged(source: Path, out: Path) -> None:
    """``source``'s poses with FLAGS added to those of WINDOW."""
    sink = McapSink(out)
    for index, (log_time, frame) in enumerate(read_poses(source)):
        flags = {**frame.flags, **FLAGS} if index in WINDOW else frame.flags
        sink.write_pose(keys.pose_key(), dataclasses.replace(frame, flags=flags), log_time)
    sink.close()


def export(capsys: pytest.CaptureFixture[str], *args: object) -> str:
    """``bodynet export ARGS`` in this process (no interpreter to start); what
    it said on stderr. It must succeed."""
    capsys.readouterr()
    code = main(["export", *map(str, args)])
    err = capsys.readouterr().err
    assert code == 0, err
    return err


def tf_message(data: bytes) -> dict[str, Any]:
    """A ``foxglove.FrameTransforms`` message read with Foxglove's own class, laid
    out as its JSON form (time as ``sec``, ``nsec``)."""
    message = FrameTransforms()
    message.ParseFromString(data)
    return {"transforms": [
        {"timestamp": {"sec": t.timestamp.seconds, "nsec": t.timestamp.nanos},
         "parent_frame_id": t.parent_frame_id, "child_frame_id": t.child_frame_id,
         "translation": {a: getattr(t.translation, a) for a in "xyz"},
         "rotation": {a: getattr(t.rotation, a) for a in "xyzw"}}
        for t in message.transforms]}  # fmt: skip


def read_c3d(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """A C3D file read with ezc3d: its point labels, points (4, P, F) and
    residuals (P, F)."""
    c3d = ezc3d.c3d(str(path))
    labels = list(c3d["parameters"]["POINT"]["LABELS"]["value"])
    return labels, c3d["data"]["points"], c3d["data"]["meta_points"]["residuals"][0]
