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
    p = positions.reshape(-1, shape[-2], 3)
    q = quats_wxyz.reshape(-1, shape[-2], 4)
    parents = np.asarray(parent_index)
    is_child = (parents >= 0)[None, :, None]
    above = np.maximum(parents, 0)
    # the root's parent is the world: origin, identity rotation
    parent_p = np.where(is_child, p[:, above], 0.0)
    parent_q = np.where(is_child, q[:, above], np.array([1.0, 0.0, 0.0, 0.0]))
    inv = Rotation.from_quat(parent_q.reshape(-1, 4), scalar_first=True).inv()
    translations = inv.apply((p - parent_p).reshape(-1, 3)).reshape(shape)
    return translations, inv * Rotation.from_quat(q.reshape(-1, 4), scalar_first=True)


def frame_transforms_json(
    segments: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    t_ns: int,
    parents: Mapping[str, str],
    world_frame: str = "world",
) -> dict[str, object]:
    """A ``foxglove.FrameTransforms`` message (JSON form) for one pose: the root
    segment in ``world_frame``, every other segment in its parent segment.
    Segments whose parent the pose lacks (a branch view) are left out."""
    names = [n for n in segments if n == ROOT_SEGMENT or parents.get(n) in segments]
    if not names:
        return {"transforms": []}
    pos = np.array([segments[n][0] for n in names], dtype=float)
    quat = np.array([segments[n][1] for n in names], dtype=float)
    index = {n: i for i, n in enumerate(names)}
    parent_index = [index[parents[n]] if n in parents else -1 for n in names]
    translations, rotations = local_poses(pos, quat, parent_index)
    xyzw = rotations.as_quat()
    stamp = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
    return {
        "transforms": [
            {
                "timestamp": stamp,
                "parent_frame_id": parents.get(n, world_frame),
                "child_frame_id": n,
                "translation": _named("xyz", translations[i], 7),
                "rotation": _named("xyzw", xyzw[i], 9),
            }
            for i, n in enumerate(names)
        ]
    }


def _named(axes: str, values: np.ndarray, digits: int) -> dict[str, float]:
    return {a: round(float(v), digits) for a, v in zip(axes, values, strict=True)}
