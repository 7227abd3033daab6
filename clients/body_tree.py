"""Segment poses relative to their parent segment: what BVH and Foxglove transforms carry.

A pose message gives every segment's pose in the world (position of its frame's
origin, the joint centre where it hangs from its parent, and its orientation).
Hierarchical formats want each segment in its parent's frame instead:
``parentMchild = worldMparent^-1 * worldMchild``. The tree is the skeleton's
(``core/skeleton.py``): the pelvis is the root, every joint links its parent
segment to its child segment.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import orjson
from scipy.spatial.transform import Rotation

from bodynet.core.skeleton import Skeleton, build_skeleton

ROOT_SEGMENT = "pelvis"


def segment_parents(skeleton: Skeleton | None = None) -> dict[str, str]:
    """Parent segment of every non-root segment, parents before their children."""
    return {j.child: j.parent for j in (skeleton or build_skeleton()).joints}


def local_poses(
    positions: np.ndarray, quats_wxyz: np.ndarray, parent_index: Sequence[int]
) -> tuple[np.ndarray, Rotation]:
    """Each segment's pose in its parent's frame (the root's: in the world).

    ``positions`` (..., S, 3) and ``quats_wxyz`` (..., S, 4) are world poses of
    S segments; ``parent_index[s]`` is the index of segment s's parent, -1 for
    the root. Returns translations (..., S, 3) and rotations (flattened, in the
    same order, reshape with ``as_quat().reshape(..., S, 4)``).
    """
    shape = positions.shape
    n_seg = shape[-2]
    p = positions.reshape(-1, n_seg, 3)
    n_frames = p.shape[0]
    # one more slot per frame holds the world (origin, identity): index -1, the
    # root's parent, picks it
    p_ext = np.concatenate([p, np.zeros((n_frames, 1, 3))], axis=1)
    q_ext = np.concatenate(
        [quats_wxyz.reshape(-1, n_seg, 4), np.tile([1.0, 0.0, 0.0, 0.0], (n_frames, 1, 1))], axis=1
    )
    world = Rotation.from_quat(q_ext.reshape(-1, 4), scalar_first=True)
    parents = np.asarray(parent_index)
    rows = np.arange(n_frames)[:, None] * (n_seg + 1)
    inv = world[(rows + np.where(parents < 0, n_seg, parents)).ravel()].inv()
    translations = inv.apply((p - p_ext[:, parents]).reshape(-1, 3)).reshape(shape)
    return translations, inv * world[(rows + np.arange(n_seg)).ravel()]


def frame_transforms(
    poses: Sequence[tuple[int, Mapping[str, tuple[Sequence[float], Sequence[float]]]]],
    parents: Mapping[str, str],
    world_frame: str = "world",
) -> list[bytes]:
    """One ``foxglove.FrameTransforms`` message (JSON bytes) for each pose
    ``(t_ns, segments)``, in order: the root segment in ``world_frame``, every
    other segment in its parent segment. Segments whose parent the pose lacks
    (a branch view) are left out.

    A recorder makes one of these per whole-body pose, so the work is done for
    many poses at once: poses with the same segments go through one array pass,
    and the JSON is one template per segment set filled with numbers that orjson
    writes (building a dict per transform cost several times the maths)."""
    groups: dict[tuple[str, ...], list[int]] = {}
    for i, (_, segments) in enumerate(poses):
        names = tuple(n for n in segments if n == ROOT_SEGMENT or parents.get(n) in segments)
        groups.setdefault(names, []).append(i)
    out = [b'{"transforms":[]}'] * len(poses)
    for names, members in groups.items():
        if not names:
            continue
        pos = np.array([[poses[i][1][n][0] for n in names] for i in members], dtype=float)
        quat = np.array([[poses[i][1][n][1] for n in names] for i in members], dtype=float)
        index = {n: k for k, n in enumerate(names)}
        parent_index = [index[parents[n]] if n in parents else -1 for n in names]
        translations, rotations = local_poses(pos, quat, parent_index)
        turns = rotations.as_quat().reshape(len(members), len(names), 4)
        # 0.1 µm and 1e-9 are below what the pose carries; + 0.0 turns -0.0 into 0.0
        numbers = np.concatenate([np.round(translations, 7), np.round(turns, 9)], axis=2) + 0.0
        template = _transforms_template(names, [parents.get(n, world_frame) for n in names])
        for row, i in zip(numbers.reshape(len(members), -1).tolist(), members, strict=True):
            sec, nsec = divmod(poses[i][0], 1_000_000_000)
            stamped = template % ((b"%d" % sec, b"%d" % nsec) * len(names))
            out[i] = stamped % tuple(orjson.dumps(row)[1:-1].split(b","))
    return out


def _transforms_template(names: Sequence[str], frames_of: Sequence[str]) -> bytes:
    """The message with ``%s`` for each stamp's sec and nsec and ``%%s`` for each
    number (x, y, z of the translation, x, y, z, w of the rotation)."""

    def text(name: str) -> bytes:
        return orjson.dumps(name).replace(b"%", b"%%%%")  # through two formattings

    numbers = (
        b'"translation":{"x":%%s,"y":%%s,"z":%%s},"rotation":{"x":%%s,"y":%%s,"z":%%s,"w":%%s}}'
    )
    return (
        b'{"transforms":['
        + b",".join(
            b'{"timestamp":{"sec":%s,"nsec":%s},"parent_frame_id":'
            + text(parent)
            + b',"child_frame_id":'
            + text(name)
            + b","
            + numbers
            for name, parent in zip(names, frames_of, strict=True)
        )
        + b"]}"
    )
