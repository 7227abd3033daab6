"""``bodynet export bvh``: a recording as a Biovision Hierarchy (BVH) file.

The hierarchy is the body model's (``core/skeleton.py``): one BVH joint per
segment, named after it (``pelvis`` is the ROOT, ``left_forearm`` hangs from
``left_upperarm`` at the elbow...), each placed at the joint centre where the
segment hangs from its parent. OFFSETs are measured from the recording (its
segment placements, so the subject's segment lengths the gateway
used); the End Sites of the hands, feet and head take their length from the
subject profile (defaults without one).

The rest pose (all channels 0) is the model's zero pose, anatomical neutral,
where every segment frame is aligned with the world. The ROOT has
``Xposition Yposition Zposition`` (the pelvis in the world, OFFSET 0) and three
rotations; every other joint three rotations, in the order of its anatomical
dofs (flexion first...), completed by the axis it lacks, so the channels read
as joint angles. As in every BVH reader, a joint's rotation is the product of
its channels' rotations in the order the file lists them (``Zrotation
Xrotation Yrotation`` is Rz * Rx * Ry, about the parent's axes), and a point
maps to its parent as ``offset + R p``.

Axes: ``up="y"`` (the default) writes the Biovision convention that Blender's
BVH importer and most tools expect: +Y up, the subject facing +Z, its left on
+X (bodynet's +X forward, +Y left, +Z up rotated, a proper rotation).
``up="z"`` keeps bodynet's axes as they are (import with "Z up" in Blender).
Units: metres (Blender's unit) or centimetres.

BVH has no way to say "not measured": a joint angle with no measurement
behind it (``is_measured`` false) holds the last measured value of its channel
(0, the neutral pose, before the first one), and the export counts the held
values (:class:`~bodynet.clients.exports.Written`'s note, on stderr); in a
frame inside a gap in the poses (``PoseTrack.posed``) every channel holds its
last value, the root's six too, counted likewise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.clients.body_tree import ROOT_SEGMENT, local_poses, segment_parents
from bodynet.clients.exports import Written
from bodynet.clients.exports.track import (
    PoseTrack,
    euler_deg,
    held_note,
    hold_gaps,
    hold_unmeasured,
    output_file,
)
from bodynet.core.skeleton import Skeleton, Vec3, build_skeleton

#: bodynet axes -> BVH axes: the rows are the BVH X, Y, Z axes in bodynet's frame.
AXES: Mapping[str, np.ndarray] = {
    "y": np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
    "z": np.eye(3),
}
UNITS: Mapping[str, float] = {"m": 1.0, "cm": 100.0}
#: Frames converted at a time: bounds the memory of long recordings.
CHUNK_FRAMES = 4096
#: The root turns about the vertical first (heading), then the side axis, then forward.
ROOT_ORDER_BODYNET: tuple[Vec3, ...] = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0))


def _letter(axis: Vec3, m: np.ndarray) -> str:
    return "XYZ"[int(np.argmax(np.abs(m @ np.asarray(axis))))]


def channel_orders(skeleton: Skeleton, m: np.ndarray) -> dict[str, str]:
    """Rotation order (e.g. ``"XZY"``) of every segment's BVH joint."""
    orders = {ROOT_SEGMENT: "".join(_letter(a, m) for a in ROOT_ORDER_BODYNET)}
    for joint in skeleton.joints:
        letters = [_letter(d.axis, m) for d in joint.dofs]
        letters += [c for c in "XYZ" if c not in letters]
        orders[joint.child] = "".join(letters)
    return orders


def children_of(parents: Mapping[str, str], segments: Sequence[str]) -> dict[str, list[str]]:
    """Each segment's children, in the skeleton's order."""
    children: dict[str, list[str]] = {s: [] for s in segments}
    for child, parent in parents.items():
        children[parent].append(child)
    return children


def rest_offsets(track: PoseTrack, parent_index: list[int]) -> np.ndarray:
    """(S, 3) each segment's origin in its parent's frame (bodynet's axes, m):
    constant for a rigid body; the median over the first frames evens out the
    1 µm rounding of the pose messages."""
    head = slice(0, 1000)
    translations, _ = local_poses(track.segment_p[head], track.segment_q[head], parent_index)
    return np.asarray(np.median(translations, axis=0))


def channel_angles(
    track: PoseTrack, skeleton: Skeleton, written: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """The MOTION columns that are joint angles (a joint's first channels are
    its dofs, in order; the root's six and the completing axes are not), and
    the index in ``track.angles`` of each."""
    angle_index = {a: i for i, a in enumerate(track.angles)}
    column_angle: list[int] = [-1] * 6
    joint_of = {j.child: j for j in skeleton.joints}
    for seg in written[1:]:
        dofs = [angle_index[a] for a in joint_of[seg].angle_names()]
        column_angle += dofs + [-1] * (3 - len(dofs))
    columns = np.array([c for c, a in enumerate(column_angle) if a >= 0])
    return columns, np.array([column_angle[c] for c in columns])


def write(track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
    """Write ``track`` (frames at ``track.rate_hz``, see ``track.resample``) as
    BVH. Options: ``up`` ("y" or "z"), ``units`` ("m" or "cm"), ``skeleton``
    (the End Site lengths; default: the model's)."""
    skeleton: Skeleton = options.get("skeleton") or build_skeleton()
    m, scale = AXES[options.get("up", "y")], UNITS[options.get("units", "m")]
    rate_hz = track.rate_hz or track.measured_rate_hz()
    parents = segment_parents(skeleton)
    segs = track.segments
    index = {s: i for i, s in enumerate(segs)}
    parent_index = [index[parents[s]] if s in parents else -1 for s in segs]
    offsets = np.round(rest_offsets(track, parent_index) @ m.T * scale, 6) + 0.0  # -0.0: 0.0
    orders = channel_orders(skeleton, m)
    children = children_of(parents, segs)
    lines = ["HIERARCHY"]
    written: list[str] = []  # segments in the order the file lists them

    def vec(v: np.ndarray) -> str:
        return " ".join(f"{c:.6f}" for c in v)

    def emit(seg: str, depth: int) -> None:
        pad = "\t" * depth
        is_root = seg == ROOT_SEGMENT
        written.append(seg)
        lines.append(f"{pad}{'ROOT' if is_root else 'JOINT'} {seg}")
        lines.append(f"{pad}{{")
        rot_channels = [f"{c}rotation" for c in orders[seg]]
        if is_root:
            lines.append(f"{pad}\tOFFSET {vec(np.zeros(3))}")
            lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition "
                         + " ".join(rot_channels))  # fmt: skip
        else:
            lines.append(f"{pad}\tOFFSET {vec(offsets[index[seg]])}")
            lines.append(f"{pad}\tCHANNELS 3 " + " ".join(rot_channels))
        for child in children[seg]:
            emit(child, depth + 1)
        if not children[seg]:
            tip = np.asarray(skeleton.directions[seg]) * skeleton.segment_length(seg)
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{",
                          f"{pad}\t\tOFFSET {vec(m @ tip * scale)}", f"{pad}\t}}"])  # fmt: skip
        lines.append(f"{pad}}}")

    emit(ROOT_SEGMENT, 0)
    lines += ["MOTION", f"Frames: {len(track)}", f"Frame Time: {1.0 / rate_hz:.8f}"]
    angle_columns, column_angles = channel_angles(track, skeleton, written)
    # each angle column's held value before a chunk, and the last row before it (gaps)
    held_from, row_from = np.zeros(len(angle_columns)), np.zeros(6 + 3 * (len(segs) - 1))

    def motion(frames: slice) -> np.ndarray:
        """The MOTION rows of some frames: root position, then every joint's channels."""
        _, rotations = local_poses(track.segment_p[frames], track.segment_q[frames], parent_index)
        # the same rotations seen in the file's axes, M R M^T: M being a rotation,
        # that turns each quaternion's axis part (x, y, z) by M
        xyzw = rotations.as_quat().reshape(-1, len(segs), 4)
        xyzw[..., :3] = xyzw[..., :3] @ m.T
        columns = [track.segment_p[frames, index[ROOT_SEGMENT]] @ m.T * scale]
        for seg in written:
            local = Rotation.from_quat(xyzw[:, index[seg]])
            columns.append(euler_deg(local, orders[seg]))
        table = np.hstack(columns)
        measured = track.measured[frames][:, column_angles]
        table[:, angle_columns] = hold_unmeasured(table[:, angle_columns], measured, held_from)
        return hold_gaps(table, track.frame_posed()[frames], row_from)

    with output_file(out) as tmp, tmp.open("w") as f:
        f.write("\n".join(lines) + "\n")
        for start in range(0, len(track), CHUNK_FRAMES):
            np.savetxt(f, motion(slice(start, start + CHUNK_FRAMES)), fmt="%.6f")
    return Written(len(track), notes=held_note(track))
