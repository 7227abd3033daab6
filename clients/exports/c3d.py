"""``bodynet export c3d``: a recording as a C3D file, through ezc3d.

ezc3d (pyomeca) is the maintained C++ C3D library with Python wheels, read and
written by the biomechanics tools (Vicon Nexus, Mokka, OpenSim's converters,
biorbd); it keeps every parameter group as given, so the file can declare its
angle points the way Vicon does. (The pure-Python ``c3d`` package would do as
well; ezc3d was chosen for its wider use and its strict writer.)

Content, all as 3D points at the recording's frame rate (``POINT:RATE``),
stored as floats (``POINT:SCALE`` -1), in bodynet's world frame (+X forward,
+Y left, +Z up, the usual lab frame of C3D):

- one point per joint centre, labelled with the joint's name (``left_elbow``),
  plus ``pelvis``, the root midway between the hip centres; millimetres
  (``POINT:UNITS`` = ``mm``);
- one point per joint labelled ``<joint>_angles`` holding its joint angles in
  degrees, x, y, z = the joint's dofs in order (``left_shoulder_angles``: x
  flexion, y abduction, z rotation; unused components 0). This is the
  "angles as points" convention of Vicon's Plug-in Gait: their labels are
  listed in ``POINT:ANGLES`` and their unit in ``POINT:ANGLE_UNITS`` (``deg``),
  so readers that know it plot them as angles, and ``POINT:DESCRIPTIONS``
  names each component.

The first frame's absolute time (its pose's source time, nanoseconds since the
Unix epoch, what CSV's ``t_s`` and ``.sto``'s ``bodynet_start_ns`` give) is
``BODYNET:START_NS``, a string: C3D has no parameter for it (``TRIAL`` counts
frames only) and its numbers, float32 or 16-bit integers, cannot hold it whole.
Frame ``i`` is at ``START_NS + i / POINT:RATE`` seconds.

A value the recording lacks is NaN, and so is a joint angle with no
measurement behind it (``is_measured`` false), a joint centre whose place
rests on one (``PoseTrack.centre_measured``) and any point in a frame inside a
gap in the poses: such a point is written invalid, C3D's way (residual -1,
all its coordinates NaN).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import ezc3d
import numpy as np

from bodynet.clients.body_tree import ROOT_SEGMENT
from bodynet.clients.exports import Written
from bodynet.clients.exports.track import PoseTrack, output_file
from bodynet.core.skeleton import build_skeleton
from bodynet.session.outputs import OutputError

ANGLE_SUFFIX = "_angles"


def c3d_points(track: PoseTrack) -> tuple[list[str], list[str], np.ndarray]:
    """Labels, descriptions and the (4, points, frames) array of the file."""
    skeleton = build_skeleton()
    labels = [*track.joints, ROOT_SEGMENT]
    descriptions = [f"{j} joint centre (mm)" for j in track.joints]
    descriptions.append("pelvis: root, midway between the hip centres (mm)")
    root = track.segments.index(ROOT_SEGMENT)
    places = np.concatenate([track.joint_p, track.segment_p[:, [root]]], axis=1)
    measured = np.concatenate([track.centre_measured(), track.chain_measured()[:, [root]]], axis=1)
    mm = np.where(measured[..., None], places * 1000.0, np.nan)  # (F, P, 3)
    angle_index = {name: i for i, name in enumerate(track.angles)}
    angle_points = np.zeros((len(track), len(skeleton.joints), 3))
    for k, joint in enumerate(skeleton.joints):
        names = joint.angle_names()
        for c, name in enumerate(names):
            i = angle_index[name]
            angle_points[:, k, c] = np.where(track.measured[:, i], track.angle_deg[:, i], np.nan)
        labels.append(joint.name + ANGLE_SUFFIX)
        parts = [f"{axis} {dof.name}" for axis, dof in zip("xyz", joint.dofs, strict=False)]
        descriptions.append(f"{joint.name} angles (deg): " + ", ".join(parts))
    xyz = np.concatenate([mm, angle_points], axis=1)  # (F, P, 3)
    points = np.ones((4, xyz.shape[1], len(track)))
    points[:3] = xyz.transpose(2, 1, 0)
    return labels, descriptions, points


def write(track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
    """Write ``track`` (frames at ``track.rate_hz``, see ``track.resample``) as
    C3D. No options."""
    rate_hz = track.rate_hz or track.measured_rate_hz()
    labels, descriptions, points = c3d_points(track)
    c3d = ezc3d.c3d()
    point = c3d["parameters"]["POINT"]
    point["RATE"]["value"] = [float(rate_hz)]
    point["UNITS"]["value"] = ["mm"]
    point["LABELS"]["value"] = labels
    point["DESCRIPTIONS"]["value"] = descriptions
    # C3D's own mark of a point without data: residual -1 (its coordinates NaN)
    invalid = np.isnan(points[:3]).any(axis=0)
    points[:3, invalid] = np.nan
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {"residuals": np.where(invalid, -1.0, 0.0)[None]}
    c3d.add_parameter("POINT", "ANGLES", [lab for lab in labels if lab.endswith(ANGLE_SUFFIX)])
    c3d.add_parameter("POINT", "ANGLE_UNITS", ["deg"])
    c3d.add_parameter("BODYNET", "START_NS", str(int(track.t_ns[0])),
                      "time of the first frame: ns since the Unix epoch")  # fmt: skip
    # ezc3d adds ".c3d" to a name without it: the temporary file has it already
    # (so it has a name: one a killed run leaves is removed by the next run)
    with output_file(out, ".part.c3d", named=True) as tmp:
        c3d.write(str(tmp))
        _check_written(tmp, out, len(track))
    return Written(len(track))


def _check_written(path: Path, out: Path, frames: int) -> None:
    """ezc3d says nothing when it cannot write (a full disk leaves a short
    file), and reading a short file back crashes it: the size is checked
    against the file's own C3D header (data start block, points, analog
    values, float or integer storage), the data padded to 512-byte blocks.
    ``OutputError`` naming ``out`` if the file is not whole."""
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(512)
    expected = None
    if len(head) == 512 and head[1] == 0x50:  # the C3D key
        words = struct.unpack("<256H", head)
        scale = struct.unpack_from("<f", head, 12)[0]
        values = words[1] * 4 + words[2]  # x, y, z, residual of each point; analog
        data = (words[8] - 1) * 512 + frames * values * (4 if scale < 0 else 2)
        expected = -(-data // 512) * 512
    if size == expected:
        return
    full = os.statvfs(path.parent).f_bavail == 0
    why = "No space left on device" if full else "the file came out short"
    raise OutputError(f"cannot write {out}: {why} ({size} of {expected or '?'} bytes written)")
