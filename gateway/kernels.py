"""A solve's array maths, compiled (numba): the segments' rotations from their
sensors' quaternions, the joints' relative rotations, splitting those into dofs
and committing them, and forward kinematics with the floor, for every joint of
every body in a solve; and the whole-body pose message's text (``write_message``).

A solve of the bodies due paid some hundred numpy calls here whatever their
number (a few us each: about 150 us of one body's 420 alone, docs/benchmarks.md),
the fixed cost that made unsynchronised bodies, solved a few at a time, dear.
Compiled, split and commit cost a few microseconds a call and a quarter of one
a joint (6.5 us for twelve joints, 56 for 240: measured 2026-12-05). The maths
is ``JointAxes.split`` (gateway/solver.py) row by row, which the tests hold it
to; rows at a gimbal lock are flagged for that scalar split. The rotations
replaced scipy's ``Rotation.from_quat`` and numpy's stacked products, some 80 us
of one body's hot solve of 255 (2026-12-05); the tests hold them to scipy.
Forward kinematics replaced Pinocchio's per body with its placements read one by
one and a dozen numpy calls for the floor, some 75 us of one body's hot solve
of 172 (2026-12-05); the tests hold it to Pinocchio's ``forwardKinematics``.
The steps a tick takes one after the other are joined where nothing in
Python comes between (``aligned_segments``, ``direct_split`` and
``direct_commit``): each call into numba and numpy costs a tick more after
the time away between two ticks than its arithmetic (docs/benchmarks.md),
and these took one body's tick from 105-137 to 73-77 us (2026-12-07).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit

from bodynet.core.codecs import raw_batch, raw_sample
from bodynet.core.codecs.pose import (
    SLOT_FLAGS,
    SLOT_SEQ,
    SLOT_SOURCES,
    SLOT_STALE,
    SLOT_T_NS,
)
from bodynet.gateway.columns import (
    AFTER,
    ARRIVED,
    COUNT,
    ENDED,
    FRESH,
    HEAD,
    KEPT_AT,
    LEAD,
    LEFT,
    NODE,
    OWED,
    PENDING,
    QUAT,
    READY,
    ROUND,
    RUNS,
    SAMPLES,
    SEQ,
    SOURCE,
    T_NS,
    UNSOLVED,
    W,
)

_DEG, _RAD = 180.0 / math.pi, math.pi / 180.0


def _compiled(signature: str | None = None) -> Callable[[Callable[..., Any]], Any]:
    """numba's ``njit``, cached where numba finds a writable place (beside this
    file, ``NUMBA_CACHE_DIR`` or the user's cache), else compiled each start
    (a read-only install and home: seconds, not an error)."""

    def wrap(function: Callable[..., Any]) -> Any:
        try:
            return njit(signature, cache=True)(function)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            return njit(signature)(function)

    return wrap


@_compiled()
def _mul3(a, b, out):
    """``out = a @ b`` for 3x3 matrices."""
    for p in range(3):
        for q in range(3):
            out[p, q] = a[p, 0] * b[0, q] + a[p, 1] * b[1, q] + a[p, 2] * b[2, q]


@_compiled()
def _axis_rotation(x, y, z, angle_rad, out):
    """``out`` = the rotation by ``angle_rad`` about the unit axis ``x, y, z``
    (Rodrigues: I + s K + (1 - cos) K K, K the axis' cross-product matrix; a
    zero axis gives the identity)."""
    s, c1 = math.sin(angle_rad), 1.0 - math.cos(angle_rad)
    out[0, 0] = 1.0 - c1 * (y * y + z * z)
    out[1, 1] = 1.0 - c1 * (x * x + z * z)
    out[2, 2] = 1.0 - c1 * (x * x + y * y)
    out[0, 1] = -s * z + c1 * x * y
    out[1, 0] = s * z + c1 * x * y
    out[0, 2] = s * y + c1 * x * z
    out[2, 0] = -s * y + c1 * x * z
    out[1, 2] = -s * x + c1 * y * z
    out[2, 1] = s * x + c1 * y * z


# Typed, so they compile when imported (the gateway's start, not its first solve),
# and cached: `make` compiles them once (seconds), later imports load them.
_A3, _A2, _I1, _F1 = "float64[:, :, :]", "float64[:, :]", "int64[:]", "float64[:]"


@_compiled(f"({_A3}, {_A2}, {_I1}, {_I1}, {_I1}, {_F1}, {_A2}, {_I1}, {_A2}, {_A2}, float64, "
           f"{_A2}, float64)")  # fmt: skip
def split_rows(rel, previous, i, j, k, e, signs, n, lo, hi, gimbal_cos, unc, unc_max):
    """Angles (deg, (m, 3), absent dofs 0) of joints for relative rotations ``rel``
    (m, 3, 3), continuous with ``previous`` (m, 3); the joints' Euler axes
    ``i, j, k``, cyclic sign ``e``, dof signs, dof count ``n`` and ranges of
    motion ``lo, hi`` (m, 3). Also which rows are at a gimbal lock (three dofs,
    ``|cos b| < gimbal_cos``), for the scalar split, and each dof's uncertainty
    from the relative rotation's, ``unc`` (m, 3): a three-dof joint's outer dofs
    carry it divided by ``|cos b|`` at ``b`` moved its own uncertainty toward the
    lock, at most ``unc_max`` (``JointAxes.unc``)."""
    m = rel.shape[0]
    chosen = np.zeros((m, 3))
    gimbal = np.zeros(m, dtype=np.bool_)
    stated = unc.copy()
    first = np.empty(3)
    second = np.empty(3)
    for r in range(m):
        R = rel[r]
        ii, jj, kk, ee, nn = i[r], j[r], k[r], e[r], n[r]
        b = math.asin(min(1.0, max(-1.0, ee * R[ii, kk])))
        a = math.atan2(-ee * R[jj, kk], R[kk, kk])
        c = math.atan2(-ee * R[ii, jj], R[ii, ii])
        euler = (a * _DEG, b * _DEG, c * _DEG)
        other = (euler[0] + 180.0, 180.0 - euler[1], euler[2] + 180.0)
        for d in range(3):
            first[d] = euler[d] * signs[r, d]
            second[d] = ((other[d] + 180.0) % 360.0 - 180.0) * signs[r, d]
        if nn == 3:
            out1 = out2 = d1 = d2 = 0.0
            for d in range(3):
                out1 += max(0.0, lo[r, d] - first[d], first[d] - hi[r, d])
                out2 += max(0.0, lo[r, d] - second[d], second[d] - hi[r, d])
                d1 += abs(first[d] - previous[r, d])
                d2 += abs(second[d] - previous[r, d])
            pick = out2 < out1 or (out2 == out1 and d2 < d1)
            gimbal[r] = abs(math.cos(b)) < gimbal_cos
            for d in (0, 2):
                near = math.pi / 2 - abs(b) - unc[r, 1] * _RAD
                stated[r, d] = min(unc_max, unc[r, d] / math.sin(near)) if near > 0.0 else unc_max
        else:  # fewer dofs: the candidate whose unused angles vanish
            u1 = u2 = 0.0
            for d in range(nn, 3):
                u1 += abs(first[d])
                u2 += abs(second[d])
            pick = u2 < u1
        for d in range(nn):
            chosen[r, d] = second[d] if pick else first[d]
        if nn == 2:  # the first angle from the child's own axis (solver._two_dofs)
            a2 = math.atan2(ee * R[kk, jj], R[jj, jj])
            col_k = -ee * math.sin(a2) * R[jj, kk] + math.cos(a2) * R[kk, kk]
            b2 = math.atan2(ee * R[ii, kk], col_k)
            chosen[r, 0] = a2 * _DEG * signs[r, 0]
            chosen[r, 1] = b2 * _DEG * signs[r, 1]
    return chosen, gimbal, stated


@_compiled(f"({_A2}, {_A2}, {_A2}, {_A3}, {_A3}, {_A3})")
def commit_rows(values, lo, hi, axis, calibration_inv, relative):
    """``_SplitBatch.commit`` (gateway/solver.py) row by row: the angles clamped to
    ``lo, hi``, which were clamped, the joint rotations ``R_dof0 R_dof1 R_dof2``
    (each dof about its row of ``axis`` (m, 3, 3), a zero axis adding nothing)
    and each joint's total rotation (deg) ``calibration_inv @ relative``."""
    m = values.shape[0]
    clipped = np.empty((m, 3))
    clamped = np.zeros((m, 3), dtype=np.bool_)
    matrices = np.empty((m, 3, 3))
    total = np.empty(m)
    rot = np.empty((3, 3))
    acc = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for r in range(m):
        for p in range(3):
            for q in range(3):
                acc[p, q] = 1.0 if p == q else 0.0
        for d in range(3):
            v = values[r, d]
            clamped[r, d] = v < lo[r, d] or v > hi[r, d]
            v = min(max(v, lo[r, d]), hi[r, d])
            clipped[r, d] = v
            _axis_rotation(axis[r, d, 0], axis[r, d, 1], axis[r, d, 2], v * _RAD, rot)
            _mul3(acc, rot, tmp)
            acc[:, :] = tmp
        matrices[r] = acc
        _mul3(calibration_inv[r], relative[r], tmp)
        vx, vy, vz = tmp[2, 1] - tmp[1, 2], tmp[0, 2] - tmp[2, 0], tmp[1, 0] - tmp[0, 1]
        cos = (tmp[0, 0] + tmp[1, 1] + tmp[2, 2] - 1.0) / 2.0
        total[r] = math.atan2(math.sqrt(vx * vx + vy * vy + vz * vz) / 2.0, cos) * _DEG
    return clipped, clamped, matrices, total


@_compiled(f"({_A2}, {_A3}, {_A3})")
def segment_rotations(quats, lefts, mounts):
    """Segments' world rotations ``lefts @ R(q) @ mounts`` (n, 3, 3) from their
    sensors' quaternions ``quats`` (n, 4, w first, normalised here), the turns
    into the body's heading ``lefts`` and the mounts' inverses ``mounts``.
    ``ValueError`` for a quaternion of zero, infinite or NaN norm (scipy refused
    zero and NaN ones; an infinite one gave NaN rotations)."""
    n = quats.shape[0]
    out = np.empty((n, 3, 3))
    sensor = np.empty((3, 3))
    tmp = np.empty((3, 3))
    for s in range(n):
        w, x, y, z = quats[s, 0], quats[s, 1], quats[s, 2], quats[s, 3]
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        if not 0.0 < norm < math.inf:
            raise ValueError("a quaternion of zero, infinite or NaN norm")
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        sensor[0, 0] = 1.0 - 2.0 * (y * y + z * z)
        sensor[0, 1] = 2.0 * (x * y - z * w)
        sensor[0, 2] = 2.0 * (x * z + y * w)
        sensor[1, 0] = 2.0 * (x * y + z * w)
        sensor[1, 1] = 1.0 - 2.0 * (x * x + z * z)
        sensor[1, 2] = 2.0 * (y * z - x * w)
        sensor[2, 0] = 2.0 * (x * z - y * w)
        sensor[2, 1] = 2.0 * (y * z + x * w)
        sensor[2, 2] = 1.0 - 2.0 * (x * x + y * y)
        _mul3(lefts[s], sensor, tmp)
        _mul3(tmp, mounts[s], out[s])
    return out


@_compiled(f"({_A3}, {_I1}, {_I1})")
def relative_rotations(segments, parents, children):
    """``segments[p].T @ segments[c]`` (m, 3, 3) for each joint's parent and child
    rows ``parents``, ``children``; a parent row past the end is the identity
    (an unmeasured pelvis)."""
    m = parents.shape[0]
    n = segments.shape[0]
    out = np.empty((m, 3, 3))
    for r in range(m):
        c, p = children[r], parents[r]
        if p >= n:
            out[r] = segments[c]
            continue
        for a in range(3):
            for b in range(3):
                out[r, a, b] = (segments[p, 0, a] * segments[c, 0, b]
                                + segments[p, 1, a] * segments[c, 1, b]
                                + segments[p, 2, a] * segments[c, 2, b])  # fmt: skip
    return out


@_compiled(f"({_A2}, {_A3}, {_I1}, {_F1}, {_I1}, {_A2}, {_A3}, {_I1}, {_I1}, {_A3})")
def forward_poses(angles, segments, root_at, root_z, parents, axes, offsets, segment_joints,
                  floor_joints, floor_points):  # fmt: skip
    """Forward kinematics of every body of a solve (``BodyModel``'s Pinocchio
    model, its arrays read by ``BodyModel.chain``): each body's segment poses
    with its lowest point on the floor (z = 0), as positions (b, segments, 3)
    and unit quaternions w, x, y, z with w >= 0 (b, segments, 4).

    Body ``b`` has the angles ``angles[b]`` (deg, the skeleton's order), its root
    at height ``root_z[b]`` turned by ``segments[root_at[b]]`` (-1: upright);
    revolute joint ``r`` turns about ``axes[r]`` after its parent (``parents``,
    -1 the root) and the offset ``offsets[b, r]`` in the parent's frame.
    Segments sit on the joints ``segment_joints``; the floor points
    ``floor_points[b]`` on ``floor_joints`` (-1: the root). The quaternions
    are Eigen's of the rotation matrices (as Pinocchio's ``SE3ToXYZQUAT``)."""
    nb, nr, ns = angles.shape[0], parents.shape[0], segment_joints.shape[0]
    positions = np.empty((nb, ns, 3))
    quats = np.empty((nb, ns, 4))
    rots = np.empty((nr + 1, 3, 3))  # row 0 the root, row r + 1 revolute joint r
    pos = np.empty((nr + 1, 3))
    turn = np.empty((3, 3))
    for b in range(nb):
        a = root_at[b]
        for p in range(3):
            for q in range(3):
                rots[0, p, q] = segments[a, p, q] if a >= 0 else (1.0 if p == q else 0.0)
        pos[0, 0], pos[0, 1], pos[0, 2] = 0.0, 0.0, root_z[b]
        for r in range(nr):
            up = parents[r] + 1
            for p in range(3):
                pos[r + 1, p] = pos[up, p] + (rots[up, p, 0] * offsets[b, r, 0]
                                              + rots[up, p, 1] * offsets[b, r, 1]
                                              + rots[up, p, 2] * offsets[b, r, 2])  # fmt: skip
            _axis_rotation(axes[r, 0], axes[r, 1], axes[r, 2], angles[b, r] * _RAD, turn)
            _mul3(rots[up], turn, rots[r + 1])
        lowest = math.inf
        for f in range(floor_joints.shape[0]):
            j = floor_joints[f] + 1
            z = (rots[j, 2, 0] * floor_points[b, f, 0] + rots[j, 2, 1] * floor_points[b, f, 1]
                 + rots[j, 2, 2] * floor_points[b, f, 2] + pos[j, 2])  # fmt: skip
            lowest = min(lowest, z)
        for s in range(ns):
            lowest = min(lowest, pos[segment_joints[s] + 1, 2])
        for s in range(ns):
            j = segment_joints[s] + 1
            positions[b, s, 0], positions[b, s, 1] = pos[j, 0], pos[j, 1]
            positions[b, s, 2] = pos[j, 2] - lowest
            m = rots[j]
            t = m[0, 0] + m[1, 1] + m[2, 2]
            q4 = quats[b, s]  # w, x, y, z
            if t > 0.0:  # Eigen's conversion (Shepperd's)
                t = math.sqrt(t + 1.0)
                q4[0] = 0.5 * t
                t = 0.5 / t
                q4[1] = (m[2, 1] - m[1, 2]) * t
                q4[2] = (m[0, 2] - m[2, 0]) * t
                q4[3] = (m[1, 0] - m[0, 1]) * t
            else:
                i = 0
                if m[1, 1] > m[0, 0]:
                    i = 1
                if m[2, 2] > m[i, i]:
                    i = 2
                j2, k = (i + 1) % 3, (i + 2) % 3
                t = math.sqrt(m[i, i] - m[j2, j2] - m[k, k] + 1.0)
                q4[1 + i] = 0.5 * t
                t = 0.5 / t
                q4[0] = (m[k, j2] - m[j2, k]) * t
                q4[1 + j2] = (m[j2, i] + m[i, j2]) * t
                q4[1 + k] = (m[k, i] + m[i, k]) * t
            norm = math.sqrt(q4[0] * q4[0] + q4[1] * q4[1] + q4[2] * q4[2] + q4[3] * q4[3])
            sign = -1.0 if q4[0] < 0.0 else 1.0
            for c in range(4):
                q4[c] = sign * q4[c] / norm
    return positions, quats


_I2, _B2 = "int64[:, :]", "boolean[:, :]"


@_compiled(f"({_A3}, {_F1}, {_I1}, {_I1}, {_A2}, {_I1}, {_I2}, {_A2}, {_I1}, {_I1}, {_I1}, "
           f"{_F1}, {_A2}, {_I1}, {_A2}, {_A2}, float64, float64)")  # fmt: skip
def direct_split(segments, residual, parents, children, last, owner, index, known, i, j, k, e,
                 signs, n, lo, hi, gimbal_cos, unc_max):  # fmt: skip
    """The first half of a solve's direct joints (``BodySolver._solve_direct``) in
    one call: each joint's relative rotation (``relative_rotations``), its
    previous angles gathered from its body's row of ``last`` (``owner``, the
    dofs' columns ``index``), what its two tags give it (``known``, deg) widened
    by the residual turn of its two segments (``residual``, deg, one a segment;
    an unmeasured pelvis none) and :func:`split_rows`. Returns the relative
    rotations, the previous angles, the split, the rows at a gimbal lock (for
    the scalar split) with their count, and the dofs' uncertainties."""
    relative = relative_rotations(segments, parents, children)
    m, ns = parents.shape[0], segments.shape[0]
    previous = np.empty((m, 3))
    widened = known.copy()
    moved = False
    for s in range(ns):
        moved = moved or residual[s] != 0.0
    for r in range(m):
        for d in range(3):
            previous[r, d] = last[owner[r], index[r, d]]
        if moved:
            p = parents[r]
            off = math.hypot(residual[p] if p < ns else 0.0, residual[children[r]])
            for d in range(3):
                widened[r, d] = math.hypot(known[r, d], off)
    chosen, gimbal, stated = split_rows(relative, previous, i, j, k, e, signs, n, lo, hi,
                                        gimbal_cos, widened, unc_max)  # fmt: skip
    locked = 0
    for r in range(m):
        locked += gimbal[r]
    return relative, previous, chosen, gimbal, locked, stated


@_compiled(f"({_A2}, {_A2}, {_A3}, {_I1}, {_I2}, {_I1}, {_A2}, {_A2}, {_A3}, {_B2}, {_A3}, "
           f"{_A2}, {_A2}, {_A2})")  # fmt: skip
def direct_commit(values, stated, relative, owner, index, rows, lo, hi, axis, unused, cal_inv,
                  angles, unc, rel):  # fmt: skip
    """The second half (after any gimbal rows' scalar split): :func:`commit_rows`,
    and each body's angles, uncertainties (its row of ``angles``, ``unc``: the
    dofs' columns ``index``, the last column for absent dofs, set to 0 in
    ``angles``) and joints' total rotations (``rel``, at ``rows``) written in
    place. Returns the joint rotations, which dofs were clamped to their range
    of motion, and how many of the joints' own dofs were."""
    clipped, clamped, matrices, total = commit_rows(values, lo, hi, axis, cal_inv, relative)
    m, last = values.shape[0], angles.shape[1] - 1
    count = 0
    for r in range(m):
        b = owner[r]
        for d in range(3):
            angles[b, index[r, d]] = clipped[r, d]
            unc[b, index[r, d]] = stated[r, d]
            count += clamped[r, d] and not unused[r, d]
        rel[b, rows[r]] = total[r]
    for b in range(angles.shape[0]):
        angles[b, last] = 0.0  # the absent dofs' column
    return matrices, clamped, count


#: a site's sample time before it has one (``align_quats``'s ``times``)
NO_TIME = -(2**62)


@_compiled(
    "UniTuple(float64, 2)(int64, int64, int64, float64, float64, int64, int64, float64, float64, "
    "float64)"
)
def ahead(t_ns, previous_ns, target_ns, turned_rad, noise_rad, max_span_ns, max_ahead_ns,
          change_per_s, max_rate_deg_s, recent_rad_s):  # fmt: skip
    """How far (rad) a sensor that turned ``turned_rad`` (>= 0) from its sample at
    ``previous_ns`` to its sample at ``t_ns`` goes on turning, at that rate, to
    ``target_ns``, and how far (deg, two standard deviations) that may be off:
    :func:`align_quats`'s rule for one sensor (a tag's turn or an encoder's),
    ``noise_rad`` each sample's noise (over three axes). What may be off: the
    angle turned times ``change_per_s`` times the time from the middle of the
    span to the target; the turn the two samples showed over the time ahead that
    it was not turned for (shrunk away as noise, or beyond the horizon: it may be
    motion; as a rate at most ``max_rate_deg_s``: samples stamped a hair apart
    give none); and beside those, the two samples' noise as the turn carried it
    forward (beyond the sample's own, which the sensor's uncertainty states).
    Nothing for a target not after ``t_ns``. Without a rate (no previous sample,
    ``NO_TIME``, or a span over ``max_span_ns``: a gap) it is not turned, and
    states what its age may hold at ``recent_rad_s`` (:func:`recent_rate`; ``inf``:
    none known), at most ``max_rate_deg_s``."""
    age = target_ns - t_ns
    span = t_ns - previous_ns
    if age <= 0:
        return 0.0, 0.0
    if previous_ns == NO_TIME or span > max_span_ns:
        return 0.0, min(_DEG * recent_rad_s, max_rate_deg_s) * age * 1e-9
    step = min(age, max_ahead_ns, 2 * span)
    if step <= 0 or turned_rad <= 0.0:
        return 0.0, 0.0
    # a rate from two noisy samples: their turn is off by about sqrt(2) * noise,
    # so a turn less than twice that gives none and one not far above it is shrunk
    # (against emulated white noise of 2 deg a gain of 1 - (sqrt(2) scatter / turn)^2
    # added a tenth to the walking knees' RMS error; this one left them as unaligned)
    gain = 1.0 - 8.0 * (noise_rad / turned_rad) ** 2
    # a turn left out (to the gain, or beyond the horizon) may be motion: a foot at
    # 350 deg/s whose turn 2 deg of tag noise hid is 5 deg on 15 ms later
    shown = min(turned_rad, max_rate_deg_s * _RAD * span * 1e-9)  # over the span
    later = (target_ns - t_ns) / span
    if gain <= 0.0:
        return 0.0, _DEG * shown * later
    reach = gain * step / span  # the sample's noise goes 1 + reach forward, the other's reach
    # one axis of each sample's noise (the noise is over three), two standard deviations
    carried = 2.0 * noise_rad / math.sqrt(3.0) * math.sqrt(2.0 * reach * (1.0 + reach))
    more = shown * reach  # at most the largest rate: two samples stamped a hair apart (a
    # burst, stamped as it arrived) turned 20 deg forward 40 more over 0.2 ms
    left = max(0.0, shown * later - more)  # the turn shown but not made
    change = more * change_per_s * (0.5 * span + step) * 1e-9
    return more, _DEG * math.hypot(change + left, carried)


@_compiled("float64(float64, int64, int64, float64, float64, float64)")
def recent_rate(recent_rad_s, previous_ns, t_ns, turned_rad, max_rate_deg_s, memory_s):
    """A sensor's recent rate (rad/s) once a sample at ``t_ns`` turned ``turned_rad``
    from its previous one at ``previous_ns`` (``NO_TIME``: none): the fastest of
    its recent turns' rates (a gap's too: its mean), each forgotten over
    ``memory_s`` (a gait cycle: a foot still now may be at heel strike a period
    later), at most ``max_rate_deg_s``; a turn within the samples' noise counts,
    as :func:`ahead` states it may be motion. What :func:`ahead` states for a
    sample with no rate of its own (after a gap); ``inf`` (none known) until
    a span gives one."""
    span = t_ns - previous_ns
    if previous_ns == NO_TIME or span <= 0:
        return recent_rad_s
    rate = min(turned_rad / (span * 1e-9), max_rate_deg_s * _RAD)
    if recent_rad_s == math.inf:
        return rate
    return max(rate, recent_rad_s * math.exp(-span * 1e-9 / memory_s))


@_compiled("float64(float64, float64, float64)")
def _taken(rate_rad_s, spread_ns, max_rate_deg_s):
    """What a sensor turning at ``rate_rad_s`` (at most ``max_rate_deg_s``) may have
    turned (deg) over ``spread_ns``: how long before its stamp it may have been
    read (a source that stamps on arrival what was read earlier)."""
    return min(_DEG * rate_rad_s, max_rate_deg_s) * spread_ns * 1e-9


@_compiled(f"({_A2}, {_I1}, int64, {_I2}, {_A3}, {_F1}, {_F1}, int64, int64, float64, float64, "
           f"float64, {_F1})")  # fmt: skip
def align_quats(quats, t_ns, target_ns, times, held, recent, scatter_rad, max_span_ns,
                max_ahead_ns, change_per_s, max_rate_deg_s, memory_s, spread_ns):  # fmt: skip
    """Orientation sensors' quaternions ``quats`` (n, 4, w first), sampled at
    ``t_ns`` (n,), brought to one time ``target_ns``: each turned on at the rate
    it turned between its previous sample and this one, for ``target_ns - t``
    but at most ``max_ahead_ns`` and twice that span (beyond, its sample is too
    old for a rate to say where it is). A span longer than ``max_span_ns`` (a
    gap) or none yet gives the quaternion as it is. ``times`` (n, 2: previous,
    latest; ``NO_TIME`` before one) and ``held`` (n, 2, 4) are each sensor's last
    two samples, updated here where ``t_ns`` is new (a time that went back starts
    over), and ``recent`` (n,) each one's recent rate (:func:`recent_rate`, over
    ``memory_s``; ``inf`` before one). A turn from two samples with
    ``scatter_rad`` (n,) of noise each is shrunk where it is not well above that
    noise. Returns the quaternions (n, 4) and how far each may be off for being
    brought forward, or for its age where it has no rate (deg, two standard
    deviations; :func:`ahead`, with ``change_per_s`` and ``max_rate_deg_s``) and,
    beside that, for having been taken up to ``spread_ns`` (n,) before its stamp
    (a source that stamps on arrival what was read earlier: its turn over that
    long at its last rate, or its recent one, at most ``max_rate_deg_s``)."""
    n = quats.shape[0]
    out = quats.copy()
    residual = np.zeros(n)
    for s in range(n):
        t = t_ns[s]
        new = t != times[s, 1]
        if new:
            times[s, 0] = times[s, 1] if t > times[s, 1] else NO_TIME
            held[s, 0, :] = held[s, 1, :]
            times[s, 1] = t
            held[s, 1, :] = quats[s, :]
        if times[s, 0] == NO_TIME:
            aged = ahead(t, NO_TIME, target_ns, 0.0, scatter_rad[s], max_span_ns, max_ahead_ns,
                         change_per_s, max_rate_deg_s, recent[s])[1]  # fmt: skip
            residual[s] = math.hypot(aged, _taken(recent[s], spread_ns[s], max_rate_deg_s))
            continue
        if t >= target_ns and not new and spread_ns[s] <= 0.0:
            continue
        pw, px, py, pz = held[s, 0, 0], held[s, 0, 1], held[s, 0, 2], held[s, 0, 3]
        w, x, y, z = quats[s, 0], quats[s, 1], quats[s, 2], quats[s, 3]
        pn = math.sqrt(pw * pw + px * px + py * py + pz * pz)
        qn = math.sqrt(w * w + x * x + y * y + z * z)
        if not (0.0 < pn < math.inf and 0.0 < qn < math.inf):
            continue  # the solve refuses the bad one (segment_rotations)
        pw, px, py, pz = pw / pn, px / pn, py / pn, pz / pn
        w, x, y, z = w / qn, x / qn, y / qn, z / qn
        # the turn from the previous sample to this one, in the sensor's frame: p^-1 q
        rw = pw * w + px * x + py * y + pz * z
        rx = pw * x - px * w - py * z + pz * y
        ry = pw * y + px * z - py * w - pz * x
        rz = pw * z - px * y + py * x - pz * w
        if rw < 0.0:
            rw, rx, ry, rz = -rw, -rx, -ry, -rz
        sin_half = math.sqrt(rx * rx + ry * ry + rz * rz)
        turned = 2.0 * math.atan2(sin_half, rw)
        span = t - times[s, 0]
        if new:
            recent[s] = recent_rate(recent[s], times[s, 0], t, turned, max_rate_deg_s, memory_s)
        rate = turned / (span * 1e-9) if span <= max_span_ns else recent[s]  # rad/s
        more, residual[s] = ahead(t, times[s, 0], target_ns, turned, scatter_rad[s], max_span_ns,
                                  max_ahead_ns, change_per_s, max_rate_deg_s,
                                  recent[s])  # fmt: skip
        residual[s] = math.hypot(residual[s], _taken(rate, spread_ns[s], max_rate_deg_s))
        if more <= 0.0 or sin_half < 1e-12:
            continue
        half = 0.5 * more
        c, k = math.cos(half), math.sin(half) / sin_half
        dw, dx, dy, dz = c, rx * k, ry * k, rz * k
        out[s, 0] = w * dw - x * dx - y * dy - z * dz
        out[s, 1] = w * dx + x * dw + y * dz - z * dy
        out[s, 2] = w * dy - x * dz + y * dw + z * dx
        out[s, 3] = w * dz + x * dy - y * dx + z * dw
    return out, residual


@_compiled(f"({_A2}, {_I2}, {_I1}, {_F1}, int64, {_I2}, {_A3}, {_F1}, {_F1}, int64, int64, "
           f"float64, float64, float64, {_A3}, {_A3})")  # fmt: skip
def aligned_segments(floats, ints, rows, spread_by_source, target_ns, times, held, recent,
                     scatter_rad, max_span_ns, max_ahead_ns, change_per_s, max_rate_deg_s,
                     memory_s, lefts, mounts):  # fmt: skip
    """A body's tick's orientation sensors, read from its frame's arrays (``floats``
    and ``ints``, the rows of ``gateway/columns.py``; the sensors' are ``rows``):
    their quaternions brought to ``target_ns`` (:func:`align_quats`, each stamp's
    spread by its source id from ``spread_by_source``, an id past either end
    taking that end's), how far each may be off for that (deg), and the
    segments' world rotations (n, 3, 3: :func:`segment_rotations`). In one call:
    gathering the rows in numpy took four more a tick."""
    n, last = rows.shape[0], spread_by_source.shape[0] - 1
    quats = np.empty((n, 4))
    t_ns = np.empty(n, dtype=np.int64)
    spread_ns = np.empty(n)
    for s in range(n):
        r = rows[s]
        for c in range(4):
            quats[s, c] = floats[r, W + c]
        t_ns[s] = ints[r, T_NS]
        spread_ns[s] = spread_by_source[min(max(ints[r, SOURCE], 0), last)]
    out, residual = align_quats(quats, t_ns, target_ns, times, held, recent, scatter_rad,
                                max_span_ns, max_ahead_ns, change_per_s, max_rate_deg_s,
                                memory_s, spread_ns)  # fmt: skip
    return out, residual, segment_rotations(out, lefts, mounts)


# --- the whole-body pose message's text ---------------------------------------------
_U1, _BYTES = "uint8[:]", "Bytes(uint8, 1, 'C', readonly=True)"
_ZERO, _POINT, _MINUS, _E = 48, 46, 45, 101
#: a number rounded to more than this many units of its last place goes back to
#: orjson (``write_message`` returns ``REFUSED``): below it, the text written here is
#: orjson's (its shortest round-trip text of the rounded double), which the tests
#: check over some 760,000 numbers
ROUNDED_MAX = 1e15
REFUSED, SHORT = -1, -2


#: "00" to "99", for writing an integer two digits at a time
_PAIRS = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode(), dtype=np.uint8).copy()
_TENS = np.array([10**i for i in range(19)], dtype=np.int64)


@_compiled("int64(int64)")
def _length(k):
    """How many decimal digits ``k`` (>= 0) has."""
    n = 1
    while n < 19 and k >= _TENS[n]:
        n += 1
    return n


@_compiled(f"int64({_U1}, int64, int64)")
def _integer(out, at, k):
    """``k``'s decimal digits written at ``out[at:]``; where they end."""
    if k < 0:
        out[at] = _MINUS
        at += 1
        k = -k
    end = i = at + _length(k)
    while k >= 100:
        q = k // 100
        r = 2 * (k - 100 * q)
        out[i - 2], out[i - 1] = _PAIRS[r], _PAIRS[r + 1]
        i -= 2
        k = q
    if k >= 10:
        out[i - 2], out[i - 1] = _PAIRS[2 * k], _PAIRS[2 * k + 1]
    else:
        out[i - 1] = _ZERO + k
    return end


@_compiled(f"int64({_U1}, int64, float64, float64, int64)")
def _number(out, at, x, scale, places):
    """``x`` rounded to ``places`` decimals (``numpy.round``: ``rint(x * scale) /
    scale``, ``scale`` being 10**places) written at ``out[at:]`` as orjson writes
    that float (NaN and infinities as ``null``); where it ends, or ``REFUSED``
    past ``ROUNDED_MAX``."""
    if not math.isfinite(x):
        out[at], out[at + 1], out[at + 2], out[at + 3] = 110, 117, 108, 108  # null
        return at + 4
    r = np.rint(x * scale)
    if abs(r) >= ROUNDED_MAX:
        return REFUSED
    if r < 0.0 or (r == 0.0 and math.copysign(1.0, r) < 0.0):  # -0.0 too
        out[at] = _MINUS
        at += 1
    k = int(abs(r))
    if k == 0:
        out[at], out[at + 1], out[at + 2] = _ZERO, _POINT, _ZERO
        return at + 3
    exponent = -places  # the number is k * 10**exponent, k without trailing zeros
    while k % 10 == 0:
        k //= 10
        exponent += 1
    n = _length(k)
    point = n + exponent  # how many of k's digits come before the decimal point
    if exponent >= 0:  # a whole number: 1500.0
        at = _integer(out, at, k)
        for _ in range(exponent):
            out[at] = _ZERO
            at += 1
        out[at], out[at + 1] = _POINT, _ZERO
        return at + 2
    if point > 0:  # 12.345
        end = _integer(out, at + 1, k)
        for i in range(point):
            out[at + i] = out[at + 1 + i]
        out[at + point] = _POINT
        return end
    if point > -5:  # 0.00012
        out[at], out[at + 1] = _ZERO, _POINT
        at += 2
        for _ in range(-point):
            out[at] = _ZERO
            at += 1
        return _integer(out, at, k)
    if n == 1:  # 3e-6
        out[at], out[at + 1] = _ZERO + k, _E
        return _integer(out, at + 2, point - 1)
    return REFUSED  # not reached for six places or fewer


@_compiled(f"int64({_F1}, {_I1}, {_F1}, {_I1}, {_U1}, {_I1}, {_I1}, int64, int64, {_BYTES}, "
           f"{_BYTES}, {_BYTES}, {_BYTES}, {_U1})")  # fmt: skip
def write_message(numbers, order, scale, places, text, ends, slots, seq, t_ns, flags, sources,
                  stale, reasons, out):  # fmt: skip
    """A whole-body pose message written into ``out`` in one pass
    (``core.codecs.pose.WholeBodyEncoder``'s layout: the fixed ``text`` cut at
    ``ends``, and what each slot between two pieces holds: the ``k``-th number
    of ``order`` for ``k >= 0``, rounded to ``places``; else, by ``SLOT_*``, the
    tick, its time, or one of the four maps already in JSON). Returns its
    length, ``REFUSED`` for a number this writer does not spell as orjson does,
    or ``SHORT`` if ``out`` is too small."""
    at, start = 0, 0
    size = out.shape[0]
    for s in range(ends.shape[0]):
        end = ends[s]
        if at + end - start + 32 > size:
            return SHORT
        for i in range(end - start):
            out[at + i] = text[start + i]
        at += end - start
        start = end
        if s == slots.shape[0]:
            break
        what = slots[s]
        if what >= 0:
            at = _number(out, at, numbers[order[what]], scale[what], places[what])
            if at < 0:
                return REFUSED
            continue
        if what == SLOT_SEQ:
            at = _integer(out, at, seq)
            continue
        if what == SLOT_T_NS:
            at = _integer(out, at, t_ns)
            continue
        given = flags if what == SLOT_FLAGS else sources if what == SLOT_SOURCES else \
            stale if what == SLOT_STALE else reasons  # fmt: skip
        if at + len(given) + 32 > size:
            return SHORT
        for i in range(len(given)):  # (bytes take no slice assignment here)
            out[at + i] = given[i]
        at += len(given)
    return at


# --- the intake: samples into a body's rows (gateway/columns.py) --------------------
_RO = "Array(uint8, 1, 'C', readonly=True)"
_M0, _M1 = raw_sample.MAGIC
_QV, _QK, _QLEN = raw_sample.VERSION, raw_sample.KIND_QUAT, raw_sample.QUAT_MESSAGE_LEN
_B0, _B1 = raw_batch.MAGIC
_BV, _BATCH_HEAD = raw_batch.VERSION, raw_batch.HEADER_LEN  # (its magic, version, count)
_ROWS = "int64[:, :]"
_INTAKE = f"{_ROWS}, {_A2}, {_A3}, {_I1}, float64, int64, int64, float64, float64, float64"


@_compiled(f"void({_ROWS}, {_A2}, {_I1}, int64, float64, int64)")
def _count(ints, floats, tally, row, now, rnd):
    """A new sample of row ``row`` came in round ``rnd``: the frame's accounting
    (``_Body``'s), its arrival and its Rhythm's countdown."""
    tally[SAMPLES] += 1
    if ints[row, FRESH] == 0:
        tally[UNSOLVED] += 1
        ints[row, FRESH] = 1
    owed = ints[row, OWED]
    if owed < 2:  # at most 2: see _Body.snapshot
        if owed == 0:
            tally[READY] += 1
        ints[row, OWED] = owed + 1
    floats[row, ARRIVED] = now
    ints[row, LEFT] -= 1
    if ints[row, LEFT] < 0 and ints[row, ENDED] == 0:  # Python ends the run (_Body._taken)
        ints[row, ENDED] = 1
        tally[RUNS] += 1
    ints[row, ROUND] = rnd


@_compiled(f"void({_ROWS}, {_A2}, {_A3}, {_I1}, int64, int64, int64, int64, int64, float64, "
           "float64, float64, float64, float64, int64, float64)")  # fmt: skip
def take_fields(ints, floats, history, tally, row, node, seq, t_ns, source, w, x, y, z, now, rnd,
                step_s):  # fmt: skip
    """A quaternion sample's numbers into row ``row``: counted (``_count``), kept
    as its latest (PENDING: no sample made of them yet), and in its ring of
    orientations if ``step_s`` of sample time has passed since the last kept
    (by the sample's own time: a round's samples all arrive at once)."""
    _count(ints, floats, tally, row, now, rnd)
    ints[row, T_NS], ints[row, NODE], ints[row, SEQ], ints[row, SOURCE] = t_ns, node, seq, source
    ints[row, PENDING], ints[row, QUAT] = 1, 1
    floats[row, W], floats[row, W + 1], floats[row, W + 2], floats[row, W + 3] = w, x, y, z
    t = t_ns / 1e9
    if t - floats[row, KEPT_AT] >= step_s:
        head = ints[row, HEAD]
        history[row, head, 0], history[row, head, 1], history[row, head, 2] = t, w, x
        history[row, head, 3], history[row, head, 4] = y, z
        ints[row, HEAD] = (head + 1) % history.shape[1]
        ints[row, COUNT] = min(ints[row, COUNT] + 1, history.shape[1])
        floats[row, KEPT_AT] = t


@_compiled(f"void({_ROWS}, {_A2}, {_I1}, int64, int64, float64, int64)")
def take_other(ints, floats, tally, row, t_ns, now, rnd):
    """A sample that is not a quaternion into row ``row``: counted, its time
    kept (the clock's lead); the sample itself is Python's (``_Body.objects``)."""
    _count(ints, floats, tally, row, now, rnd)
    ints[row, T_NS], ints[row, QUAT] = t_ns, 0


@_compiled(f"boolean({_RO}, int64, int64, {_INTAKE})")
def _take_quat(buf, at, row, ints, floats, history, tally, now, rnd, ahead_ns, sq_lo, sq_hi,
               step_s):  # fmt: skip
    """The quaternion message at ``buf[at:]`` (``raw_sample.QUAT_MESSAGE_LEN`` bytes)
    into row ``row`` if ``raw_sample.quat_fields`` would read it and its time is
    within 0..``ahead_ns``; False (nothing written) for anything else, which
    Python then decodes or rejects; else ``take_fields``."""
    if ints[row, QUAT] == 0:
        return False
    if (buf[at] != _M0 or buf[at + 1] != _M1 or buf[at + 2] != _QV or buf[at + 3] != _QK
            or buf[at + _QLEN - 1] != 0):  # fmt: skip
        return False
    node = np.int64(buf[at + 6]) | np.int64(buf[at + 7]) << 8
    t_ns = buf[at + 12 : at + 20].view(np.int64)[0]
    q = buf[at + 20 : at + 52].view(np.float64)
    sq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    if node == 0 or not (sq_lo <= sq <= sq_hi) or t_ns < 0 or t_ns > ahead_ns:
        return False
    seq = np.int64(buf[at + 8 : at + 12].view(np.uint32)[0])
    take_fields(ints, floats, history, tally, row, node, seq, t_ns, np.int64(buf[at + 4]),
                q[0], q[1], q[2], q[3], now, rnd, step_s)  # fmt: skip
    return True


#: a deferred message's row, before it (``take_messages``)
ROW_TAG = 2


@_compiled(f"int64({_RO}, int64, {_INTAKE})")
def take_messages(buf, pos, ints, floats, history, tally, now, rnd, ahead_ns, sq_lo, sq_hi,
                  step_s):  # fmt: skip
    """Quaternion messages (``raw_sample.QUAT_MESSAGE_LEN`` bytes each) end to end
    in ``buf``, each after its row (``ROW_TAG`` bytes, little-endian), from byte
    ``pos``: each as ``_take_quat``, until one it does not take. Returns where
    that one's row starts (``len(buf)``: all were taken), for Python to take it
    and go on after it."""
    size, step = buf.shape[0], ROW_TAG + _QLEN
    p = pos
    while p + step <= size:
        row = np.int64(buf[p]) | np.int64(buf[p + 1]) << 8
        if not _take_quat(buf, p + ROW_TAG, row, ints, floats, history, tally, now, rnd,
                          ahead_ns, sq_lo, sq_hi, step_s):  # fmt: skip
            return p
        p += step
    return p


@_compiled(f"int64({_RO}, int64, int64, {_U1}, {_I1}, int64)")
def _row_of(buf, at, k, keys, ends, n):
    """The row whose key is ``buf[at:at + k]``, -1 if none."""
    start = 0
    for row in range(n):
        end = ends[row]
        if end - start == k:
            i = k - 1  # from the end: keys differ in their site, not in "body/"
            while i >= 0 and keys[start + i] == buf[at + i]:
                i -= 1
            if i < 0:
                return row
        start = end
    return -1


@_compiled(f"int64({_RO}, int64, {_U1}, {_I1}, int64, {_INTAKE})")
def take_batch(buf, pos, keys, ends, n, ints, floats, history, tally, now, rnd, ahead_ns, sq_lo,
               sq_hi, step_s):  # fmt: skip
    """A bridge's batch (core/codecs/raw_batch.py) into a body's rows (``keys``
    and ``ends``: theirs, ``n`` of them), from the entry at byte ``pos``: each
    entry as ``_take_quat``, until one it does not take (a key with no row
    yet, or a message that is not a plain quaternion). Returns where that
    entry starts (``len(buf)``: all were taken), for Python to take it and go
    on after it; -1 if the batch is not well formed (read from its start,
    ``pos`` = ``raw_batch.HEADER_LEN``, only), nothing taken then: ``raw_batch.split`` says what is
    wrong with it."""
    size = buf.shape[0]
    if pos == _BATCH_HEAD:
        if size < _BATCH_HEAD or buf[0] != _B0 or buf[1] != _B1 or buf[2] != _BV:
            return -1
        p = _BATCH_HEAD
        for _ in range(np.int64(buf[3]) | np.int64(buf[4]) << 8):
            if p >= size:
                return -1
            k = np.int64(buf[p])
            if k == 0 or p + 1 + k + 2 > size:
                return -1
            p += 1 + k + 2 + (np.int64(buf[p + 1 + k]) | np.int64(buf[p + 2 + k]) << 8)
            if p > size:
                return -1
        if p != size:
            return -1
    p = pos
    while p < size:
        k = np.int64(buf[p])
        at = p + 1 + k + 2
        m = np.int64(buf[p + 1 + k]) | np.int64(buf[p + 2 + k]) << 8
        row = _row_of(buf, p + 1, k, keys, ends, n)
        if row < 0 or m != _QLEN:
            return p
        if not _take_quat(buf, at, row, ints, floats, history, tally, now, rnd, ahead_ns, sq_lo,
                          sq_hi, step_s):  # fmt: skip
            return p
        p = at + m
    return p


@_compiled(f"void({_ROWS}, {_A2}, int64, int64, float64)")
def fold_leads(ints, floats, n, rnd, wall):
    """The clock lead of each row whose latest sample came in round ``rnd``, which
    emptied the queues at ``wall`` (s): its time against that, the most so far."""
    for row in range(n):
        if ints[row, ROUND] == rnd:
            lead = ints[row, T_NS] / 1e9 - wall
            floats[row, LEAD] = max(floats[row, LEAD], lead)


@_compiled(f"UniTuple(int64, 2)({_ROWS}, {_A2}, int64, float64, {_U1})")
def settle_rows(ints, floats, n, now, stale):
    """A solve takes the rows (``_Body.snapshot``): which are stale (``stale``, 1
    each; past their Rhythm's ``after_s``), and the frame's accounting carried
    on (a row owed twice counts for the next frame; a body a whole frame
    behind starts afresh). Returns the rows ready for the next frame and how
    many are stale."""
    behind, n_stale = True, 0
    for row in range(n):
        if now - floats[row, ARRIVED] > floats[row, AFTER]:
            stale[row] = 1
            n_stale += 1
        else:
            stale[row] = 0
            behind = behind and ints[row, OWED] > 1
    ready = 0
    for row in range(n):
        ints[row, FRESH] = 0
        owed = ints[row, OWED]
        if owed:
            owed = 0 if behind else owed - 1
            ints[row, OWED] = owed
            ready += owed
    return ready, n_stale


@_compiled(f"boolean({_ROWS}, {_A2}, int64, float64)")
def all_delivered(ints, floats, n, now):
    """Has every row delivered for the next frame, or gone stale?"""
    for row in range(n):
        if ints[row, OWED] == 0 and now - floats[row, ARRIVED] <= floats[row, AFTER]:
            return False
    return True
