"""``bodynet export amc``: a recording as an Acclaim skeleton and motion pair
(``.asf`` + ``.amc``), the format of the CMU motion capture database and of the
000 seed's exports beside BVH.

The skeleton (``<stem>.asf``, written beside the ``.amc``) is the body model's
(``core/skeleton.py``): the root is the pelvis; every other segment is a bone
named after it (``left_thigh``, ``thorax``...) that starts at the joint centre
where the segment hangs from its parent and ends where its main child hangs
(the head's neck, the knee...; a hand, foot or the head ends at its length from
the subject profile, ``--profile``). Where a child does not hang at the end of
its parent's bone, a bone without dofs links them, named after the child's
joint: ``lumbar_link``, ``left_hip_link`` (from the root), ``left_shoulder_link``
(from the neck to the shoulder centre). Lengths are measured from the
recording, as BVH's OFFSETs.

Conventions, chosen so that every Acclaim reader agrees on them: the rest
pose is anatomical neutral, where every segment frame is the world's, so
every bone's ``axis`` is ``0 0 0 XYZ`` (its local frame is the global one); its
``direction`` is a unit vector in the global frame at rest; every bone with
motion has ``dof rx ry rz`` with ``limits`` (-180 180) for each (some readers
find the dofs by their limits). A bone's rotation relative to its parent is
``Rz(rz) Ry(ry) Rx(rx)`` (x applied first), the order of the ``dof`` line; a
bone's end is ``parent end + length * R_world direction``. The root's
``order TX TY TZ RX RY RZ``: the pelvis position, then its rotation likewise.
``:units`` has ``length 1.0`` (the file's lengths are metres, or centimetres
with ``--units cm``, as the ``:documentation`` says) and ``angle deg``.

Axes as BVH's (``--up y``, the default: +Y up, the subject facing +Z, its left
on +X, as the CMU files; ``--up z``: bodynet's).

Acclaim has no way to say "not measured": a joint angle with no measurement
behind it (``is_measured`` false) holds its last measured value (0, neutral,
before the first), the joint's rotation is rebuilt from its dofs with it, and
the export counts the held values; in a frame inside a gap in the poses every
bone holds its last rotation, and the root its place too.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.clients.body_tree import ROOT_SEGMENT, local_poses, segment_parents
from bodynet.clients.exports import Written
from bodynet.clients.exports.bvh import AXES, UNITS, children_of, rest_offsets
from bodynet.clients.exports.track import (
    PoseTrack,
    euler_deg,
    held_note,
    hold_gaps,
    hold_unmeasured,
    output_file,
)
from bodynet.clients.mcap_store import StoreError
from bodynet.core.skeleton import Skeleton, build_skeleton

#: the most a held joint angle may be to rebuild a rotation from it (a turn; a pose's
#: angles are within it, a number past it is no angle bodynet wrote)
MAX_HELD_DEG = 360.0


class Bone(NamedTuple):
    name: str
    parent: str  # "root" or a bone's name
    vector: np.ndarray  # from its start to its end, global frame at rest (bodynet axes, m)
    moves: bool  # a segment (dof rx ry rz), not a link


def bones(track: PoseTrack, skeleton: Skeleton) -> list[Bone]:
    """The skeleton's bones, parents before children."""
    parents = segment_parents(skeleton)
    index = {s: i for i, s in enumerate(track.segments)}
    offsets = rest_offsets(track, [index[parents[s]] if s in parents else -1
                                   for s in track.segments])  # fmt: skip
    children = children_of(parents, track.segments)
    joint_of = {j.child: j.name for j in skeleton.joints}
    out: list[Bone] = []

    def add(segment: str, parent_bone: str, start: np.ndarray) -> None:
        """The bones of ``segment``'s children; ``start``: where ``parent_bone``
        ends, in ``segment``'s frame at rest."""
        for child in children[segment]:
            at = parent_bone
            if not np.allclose(offsets[index[child]], start, atol=1e-6):
                at = f"{joint_of[child]}_link"
                out.append(Bone(at, parent_bone, offsets[index[child]] - start, False))
            kids = children[child]
            if kids:  # ends where its main child hangs: the one along its length
                along = np.asarray(skeleton.directions[child])
                end = max((offsets[index[k]] for k in kids),
                          key=lambda v: float(along @ v) / (np.linalg.norm(v) or 1.0))  # fmt: skip
            else:
                end = np.asarray(skeleton.directions[child]) * skeleton.segment_length(child)
            out.append(Bone(child, at, end, True))
            add(child, child, end)

    add(ROOT_SEGMENT, "root", np.zeros(3))
    return out


def asf_text(bone_list: list[Bone], m: np.ndarray, scale: float, units: str) -> str:
    """The ``.asf`` of the bones, in the file's axes ``m`` and units."""

    def vec(v: np.ndarray) -> str:
        return " ".join(f"{c + 0.0:.6f}" for c in v)

    lines = [
        "# bodynet: the body model as an Acclaim skeleton (see its .amc)",
        ":version 1.10",
        ":name bodynet",
        ":units",
        "  mass 1.0",
        "  length 1.0",
        "  angle deg",
        ":documentation",
        f"  lengths in {'metres' if units == 'm' else 'centimetres'}; rest pose: anatomical",
        "  neutral, every bone's local frame the global one; rotations Rz Ry Rx",
        ":root",
        "  order TX TY TZ RX RY RZ",
        "  axis XYZ",
        "  position 0 0 0",
        "  orientation 0 0 0",
        ":bonedata",
    ]
    for i, bone in enumerate(bone_list, start=1):
        length = float(np.linalg.norm(bone.vector))
        direction = m @ bone.vector / (length or 1.0)
        lines += ["  begin", f"    id {i}", f"    name {bone.name}",
                  f"    direction {vec(direction)}", f"    length {length * scale:.6f}",
                  "    axis 0 0 0 XYZ"]  # fmt: skip
        if bone.moves:
            lines += ["    dof rx ry rz", "    limits (-180.0 180.0)",
                      "           (-180.0 180.0)", "           (-180.0 180.0)"]  # fmt: skip
        lines.append("  end")
    lines += [":hierarchy", "  begin"]
    kids: dict[str, list[str]] = {}
    for bone in bone_list:
        kids.setdefault(bone.parent, []).append(bone.name)
    lines += [f"    {parent} {' '.join(names)}" for parent, names in kids.items()]
    lines += ["  end"]
    return "\n".join(lines) + "\n"


def local_rotations(track: PoseTrack, skeleton: Skeleton) -> Rotation:
    """(F * S) each segment's rotation relative to its parent (the root's: in
    the world), with every unmeasured angle held (``hold_unmeasured``) and the
    rotation of a joint with such an angle rebuilt from its dofs."""
    parents = segment_parents(skeleton)
    index = {s: i for i, s in enumerate(track.segments)}
    parent_index = [index[parents[s]] if s in parents else -1 for s in track.segments]
    _, rotations = local_poses(track.segment_p, track.segment_q, parent_index)
    if track.measured.all():
        return rotations
    quats = rotations.as_quat().reshape(len(track), len(track.segments), 4)
    held = hold_unmeasured(track.angle_deg, track.measured, np.zeros(len(track.angles)))
    angle_index = {a: i for i, a in enumerate(track.angles)}
    for joint in skeleton.joints:
        dofs = [angle_index[a] for a in joint.angle_names()]
        rows = ~track.measured[:, dofs].all(axis=1)
        if rows.any():
            _check_held(track, held, rows, dofs)
            rebuilt = Rotation.identity(int(rows.sum()))
            for dof, column in zip(joint.dofs, dofs, strict=True):
                angle = np.radians(held[rows, column])
                rebuilt = rebuilt * Rotation.from_rotvec(np.outer(angle, dof.axis))
            quats[rows, index[joint.child]] = rebuilt.as_quat()
    return Rotation.from_quat(quats.reshape(-1, 4))


def _check_held(track: PoseTrack, held: np.ndarray, rows: np.ndarray, dofs: list[int]) -> None:
    """``StoreError`` at the first angle a joint's rotation would be rebuilt from
    that is not finite or past a turn (a pose's ``angles_deg`` of 1e308 gave
    scipy's "zero norm quaternions")."""
    values = held[np.ix_(rows, dofs)]
    bad = np.argwhere(~(np.abs(values) <= MAX_HELD_DEG))
    if len(bad):
        row, dof = bad[0]
        frame = int(np.flatnonzero(rows)[row])
        where = f"{track.source}: " if track.source else ""
        raise StoreError(
            f"{where}the pose {(track.t_ns[frame] - track.t_ns[0]) / 1e9:.3f} s into the "
            f"recording (AMC frame {frame + 1}) holds {track.angles[dofs[dof]]} = "
            f"{values[row, dof]:g} deg, no joint angle (finite, within +-{MAX_HELD_DEG:g} deg) "
            "an AMC rotation can be rebuilt from; nothing written"
        )


def write(track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
    """Write ``track`` (frames at ``track.rate_hz``) as ``out`` (the ``.amc``)
    and its ``.asf`` beside it. Options: ``up``, ``units``, ``skeleton`` (the
    lengths of the hands, feet and head), as BVH's."""
    skeleton: Skeleton = options.get("skeleton") or build_skeleton()
    units = options.get("units", "m")
    m, scale = AXES[options.get("up", "y")], UNITS[units]
    bone_list = bones(track, skeleton)
    index = {s: i for i, s in enumerate(track.segments)}
    # each rotation seen in the file's axes, M R M^T, as Rz Ry Rx: intrinsic Z-Y-X reversed
    file_axes = Rotation.from_matrix(m)
    local = file_axes * local_rotations(track, skeleton) * file_axes.inv()
    xyz = euler_deg(local, "ZYX")[:, ::-1].reshape(len(track), len(track.segments), 3)
    root = track.segment_p[:, index[ROOT_SEGMENT]] @ m.T * scale
    posed = track.frame_posed()
    root = hold_gaps(root, posed, np.zeros(3))
    xyz = hold_gaps(xyz.reshape(len(track), -1), posed, np.zeros(xyz[0].size)).reshape(xyz.shape)
    moving = [b.name for b in bone_list if b.moves]
    asf = out.with_suffix(".asf")
    rate = track.rate_hz or track.measured_rate_hz()
    # comments (AMC has no frame rate of its own): the skeleton's file, as CMU's files
    lines = [f"#!OML:ASF {asf.name}", f"# bodynet: {rate:g} frames per second",
             ":FULLY-SPECIFIED", ":DEGREES"]  # fmt: skip
    for f in range(len(track)):
        lines.append(str(f + 1))
        values = [*root[f], *xyz[f, index[ROOT_SEGMENT]]]
        lines.append("root " + " ".join(f"{v + 0.0:.6f}" for v in values))
        lines += [f"{name} " + " ".join(f"{v + 0.0:.6f}" for v in xyz[f, index[name]])
                  for name in moving]  # fmt: skip
    # both files whole, or neither: the skeleton is put in place after the motion
    with output_file(asf) as asf_tmp, output_file(out) as amc_tmp:
        with asf_tmp.open("w") as f:
            f.write(asf_text(bone_list, m, scale, units))
        with amc_tmp.open("w") as f:
            f.write("\n".join(lines) + "\n")
    notes = (f"skeleton -> {asf}", *held_note(track))
    return Written(len(track), notes=notes)
