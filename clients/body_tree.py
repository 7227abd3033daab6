"""Segment poses relative to their parent segment: what BVH and Foxglove transforms carry.

A pose message gives every segment's pose in the world (position of its frame's
origin, the joint centre where it hangs from its parent, and its orientation).
Hierarchical formats want each segment in its parent's frame instead:
``parentMchild = worldMparent^-1 * worldMchild``. The tree is the skeleton's
(``core/skeleton.py``): the pelvis is the root, every joint links its parent
segment to its child segment.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.clients import foxglove_pb
from bodynet.core.codecs._common import QUAT_NORM_RANGE
from bodynet.core.codecs.pose import UNOBSERVED, UPRIGHT, PoseFrame
from bodynet.core.metrics import measured_angles
from bodynet.core.skeleton import Skeleton, build_skeleton

ROOT_SEGMENT = "pelvis"


def segment_parents(skeleton: Skeleton | None = None) -> dict[str, str]:
    """Parent segment of every non-root segment, parents before their children."""
    if skeleton is None:
        return dict(_default_parents())
    return {j.child: j.parent for j in skeleton.joints}


@functools.cache  # each recording file asks for it (building the skeleton: a fraction of a ms)
def _default_parents() -> dict[str, str]:
    return segment_parents(build_skeleton())


@functools.cache
def default_chains() -> Mapping[str, tuple[str, ...]]:
    """The default skeleton's ``segment_chains`` (one copy for every caller)."""
    return build_skeleton().segment_chains()


def unmeasured_segments(
    frame: PoseFrame, chains: Mapping[str, Sequence[str]] | None = None
) -> frozenset[str]:
    """The segments whose world pose rests on an angle no measurement stands
    behind: on their chain from the pelvis (``chains``: ``Skeleton.segment_chains``,
    the default skeleton's if None), one the pose lacks or one of
    :func:`chain_breaks`. Every client's test of a segment's pose."""
    breaks, angles = chain_breaks(frame), frame.angles_deg
    return frozenset(s for s, chain in (chains or default_chains()).items()
                     if not breaks.isdisjoint(chain)
                     or not all(a in angles for a in chain))  # fmt: skip


def chain_breaks(frame: PoseFrame) -> frozenset[str]:
    """The angles of ``frame`` a segment's world pose below them cannot stand on:
    those :func:`~bodynet.core.metrics.measured_angles` leaves out, but for the
    upright model's (reasons ``unobserved`` and ``upright`` only: the trunk of a
    body with no trunk sensor, the reference its limbs are measured against, as
    the pelvis at the origin is)."""
    if not frame.flags and not frame.stale:
        return frozenset()
    measured, reasons = measured_angles(frame), frame.reasons
    return frozenset(a for a in frame.angles_deg if a not in measured
                     and frozenset(reasons.get(a, ())) != _UPRIGHT)  # fmt: skip


_UPRIGHT = frozenset({UNOBSERVED, UPRIGHT})


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
    """One ``foxglove.FrameTransforms`` message (protobuf bytes) for each pose
    ``(t_ns, segments)``, in order: see :class:`Transforms`."""
    rows = [(t, tuple(segs), [[*p, *q] for p, q in segs.values()]) for t, segs in poses]
    return Transforms(parents, world_frame).messages(rows)


def _usable(values: np.ndarray) -> bool:
    """Rows ``(..., 7)`` of finite numbers whose quaternions are rotations (a
    norm near 1; a zero one made transforms of NaN)."""
    if not np.isfinite(values).all():
        return False
    norms = np.linalg.norm(values[..., 3:], axis=-1)
    return bool(((norms >= QUAT_NORM_RANGE[0]) & (norms <= QUAT_NORM_RANGE[1])).all())


class Transforms:
    """``foxglove.FrameTransforms`` messages (protobuf bytes, see
    ``foxglove_pb``) of whole-body poses: the root segment in ``world_frame``,
    every other segment in its parent segment (``parents``). Segments whose
    chain to the root the pose lacks (a branch view) are left out.

    A recorder makes one of these per whole-body pose, so the work is done for
    many poses at once: poses with the same segments are one numpy pass
    (quaternion algebra on arrays, no rotation objects), and their messages one
    array filled from a template per segment set (and stamp length): the
    numbers are doubles at fixed places, put there as bytes, with no Python
    per message but its time stamp. (As JSON, formatting the 105 numbers of a
    pose cost more than the maths, and the text twice the bytes to compress.)"""

    def __init__(self, parents: Mapping[str, str], world_frame: str = "world") -> None:
        self._parents = dict(parents)
        self._world = world_frame
        self._plans: dict[tuple[str | bytes, ...], _Plan | None] = {}

    def messages(self, poses: Sequence[tuple[int, Sequence[str | bytes], Any]]) -> list[bytes]:
        """One message per pose ``(t_ns, segment names, rows)``, in order; a row is
        a segment's world pose ``[x, y, z, qw, qx, qy, qz]`` (the rows: a sequence
        of them or an array); ``t_ns`` from 0 to ``2**64 - 1``. Names may be UTF-8
        bytes. A pose whose rows are not that (not finite numbers, or a
        quaternion that is no rotation) gets a message with no transforms."""
        groups: dict[tuple[str | bytes, ...], list[int]] = {}
        for i, (_, names, _) in enumerate(poses):
            groups.setdefault(tuple(names), []).append(i)
        out = [_NO_TRANSFORMS] * len(poses)
        for names, members in groups.items():
            plan = self._plan(names)
            if plan is None:
                continue
            try:
                values = np.array([poses[i][2] for i in members], dtype=float)
                good = values.shape == (len(members), len(names), 7) and _usable(values)
            except (ValueError, TypeError):
                good = False
            if not good:  # one bad pose spoils the group's array: each on its own
                if len(members) > 1:
                    for i in members:
                        out[i] = self.messages([poses[i]])[0]
                continue
            times = [poses[i][0] for i in members]
            for i, message in zip(members, plan.fill(times, values), strict=True):
                out[i] = message
        return out

    def alike(self, times: Sequence[int], names: Sequence[str | bytes],
              values: np.ndarray) -> list[bytes]:  # fmt: skip
        """What :meth:`messages` gives for poses at ``times`` that all have the
        segments ``names``, their rows ``values`` (B, S, 7), without sorting the
        poses into groups first (a recording's poses: the same segments each)."""
        plan = self._plan(tuple(names))
        if plan is None:
            return [_NO_TRANSFORMS] * len(times)
        if values.shape == (len(times), len(names), 7) and _usable(values):
            return plan.fill(list(times), values)
        return self.messages([(t, names, v) for t, v in zip(times, values, strict=True)])

    def _plan(self, names: tuple[str | bytes, ...]) -> _Plan | None:
        if names not in self._plans:
            try:
                text = tuple(n.decode() if isinstance(n, bytes) else n for n in names)
            except UnicodeDecodeError:
                self._plans[names] = None
            else:
                if len(self._plans) >= 64:  # a stream of odd segment sets: keep a few
                    self._plans.clear()
                self._plans[names] = _Plan.make(text, self._parents, self._world)
        return self._plans[names]


_NO_TRANSFORMS = foxglove_pb.NO_TRANSFORMS


class _Plan:
    """The transforms of one set of segment names: which columns, their parents'
    columns, and the message's layout for each length of time stamp (where the
    stamps and the numbers go in a template of the whole message)."""

    def __init__(
        self, columns: list[int], parent_of: list[int], frames: list[tuple[str, str]]
    ) -> None:
        self.columns = np.asarray(columns)
        parent = np.asarray(parent_of)
        self.root = parent < 0
        self.parent = np.where(self.root, 0, parent)
        self.frames = tuple(frames)  # (parent frame, child frame) of each transform

    @staticmethod
    def make(names: tuple[str, ...], parents: Mapping[str, str], world: str) -> _Plan | None:
        present = set(names)

        def rooted(name: str) -> bool:
            seen = set()
            while name != ROOT_SEGMENT:
                name = parents.get(name, "")
                if name not in present or name in seen:
                    return False
                seen.add(name)
            return True

        kept = [n for n in names if rooted(n)]
        if not kept:
            return None
        where = {n: k for k, n in enumerate(kept)}
        parent_of = [where[parents[n]] if n != ROOT_SEGMENT else -1 for n in kept]
        columns = [names.index(n) for n in kept]
        frames = [(parents[n] if n != ROOT_SEGMENT else world, n) for n in kept]
        return _Plan(columns, parent_of, frames)

    def fill(self, times: list[int], values: np.ndarray) -> list[bytes]:
        """The messages of poses at ``times`` whose rows are ``values`` (B, S, 7)."""
        v = values[:, self.columns]
        p, q = v[..., :3], v[..., 3:]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        # each segment's parent pose (the world's for the root): a = parent^-1
        aw = np.where(self.root[:, None], 1.0, q[:, self.parent, :1])
        av = np.where(self.root[:, None], 0.0, -q[:, self.parent, 1:])
        d = p - np.where(self.root[:, None], 0.0, p[:, self.parent])
        bw, bv = q[..., :1], q[..., 1:]
        # rotation a * b (Hamilton product), translation a applied to d
        w = aw * bw - (av * bv).sum(axis=-1, keepdims=True)
        vec = aw * bv + bw * av + _cross(av, bv)
        c = _cross(av, d)
        t = d + 2.0 * (aw * c + _cross(av, c))
        # 0.1 um and 1e-9 are below what the pose carries; + 0.0 turns -0.0 into 0.0;
        # translation x, y, z then rotation x, y, z, w: the message's order
        numbers = np.concatenate([np.round(t, 7), np.round(vec, 9), np.round(w, 9)], axis=2) + 0.0
        raw = numbers.astype("<f8").reshape(len(times), -1).view(np.uint8)
        stamps = [foxglove_pb.timestamp(t_ns) for t_ns in times]
        out: list[bytes] = [b""] * len(times)
        for stamp_len in sorted({len(s) for s in stamps}):  # a layout each (a few lengths)
            members = [i for i, s in enumerate(stamps) if len(s) == stamp_len]
            template, at_stamps, at_numbers = _layout(self.frames, stamp_len)
            rows = np.empty((len(members), template.size), np.uint8)
            rows[:] = template
            given = np.frombuffer(b"".join(stamps[i] for i in members), np.uint8)
            rows[:, at_stamps] = np.tile(given.reshape(len(members), stamp_len), len(self.frames))
            rows[:, at_numbers] = raw[members]
            blob, size = rows.tobytes(), template.size
            for k, i in enumerate(members):
                out[i] = blob[k * size : (k + 1) * size]
        return out


@functools.lru_cache(maxsize=64)  # a few segment sets, a few stamp lengths each
def _layout(frames: tuple[tuple[str, str], ...],
            stamp_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """A message of these transforms ``(parent, child)`` with stamps of
    ``stamp_len`` bytes: its template (bytes as an array), the places of its
    stamps' bytes and of its numbers' bytes."""
    template, stamps, numbers = bytearray(), [], []
    for parent, child in frames:
        record, stamp_at, at = foxglove_pb.transform_layout(parent, child, stamp_len)
        stamps.append(len(template) + stamp_at)
        numbers += [len(template) + a for a in at]
        template += record
    return (
        np.frombuffer(bytes(template), np.uint8),
        (np.asarray(stamps)[:, None] + np.arange(stamp_len)).ravel(),
        (np.asarray(numbers)[:, None] + np.arange(8)).ravel(),
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (np.cross costs more for these small vectors)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)
