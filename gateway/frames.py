"""The pose message of a tick, built from the solver's output: pure, no Zenoh.

:func:`pose_frame` turns one body's :class:`~bodynet.gateway.solver.BodyOutput`
into the whole-body message; :func:`branch_views` cuts it into each branch's
view (``body/<limb>/<side>/pose``). The live gateway (``gateway/service.py``)
and offline processing both build their messages here, so the two stay
byte-identical for the same samples.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import orjson

from bodynet.core.codecs import pose
from bodynet.core.keys import Branch
from bodynet.core.skeleton import part
from bodynet.gateway import kernels

if TYPE_CHECKING:
    from bodynet.gateway.solver import BodyOutput


def branch_parts(branch: Branch) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The joints and segments of a branch (``core/skeleton.py`` names them)."""
    return part(str(branch.limb), str(branch.side))


def branch_views(frame: pose.PoseFrame, branches: Iterable[Branch]) -> dict[Branch, pose.PoseFrame]:
    """Each branch's view of a whole-body pose: its joints, segments and sources."""
    views = {}
    for branch in branches:
        joints, segments = branch_parts(branch)
        views[branch] = frame.subset(joints, segments, branch.key + "/")
    return views


def whole_body_message(output: BodyOutput, seq: int, stale: Sequence[str]) -> bytes:
    """``pose.encode(pose_frame(output, seq, stale))``, byte for byte, with no
    frame or dictionary built: the gateway's message for the whole body, 100
    times a second per body (``tests/test_frames.py`` holds them equal). Its
    numbers are written in one compiled pass (``kernels.write_message``; the
    encoder's orjson for a number beyond it), its four maps by orjson."""
    numbers = np.concatenate([output.positions.ravel(), output.quats.ravel(), output.angles,
                              output.rel, output.unc])  # fmt: skip
    encoder = output.names.encoder
    if len(numbers) == encoder.size:  # else the encoder says what is wrong
        dumps = orjson.dumps
        flags, sources = dumps(output.flags), dumps(output.sources)
        gone, reasons = dumps(list(stale)), dumps(output.reasons)
        out = np.empty(encoder.capacity + len(flags) + len(sources) + len(gone) + len(reasons),
                       dtype=np.uint8)  # fmt: skip
        n = kernels.write_message(numbers, encoder.order, encoder.scale, encoder.places,
                                  encoder.text, encoder.ends, encoder.slots, seq, output.t_ns,
                                  flags, sources, gone, reasons, out)  # fmt: skip
        if n >= 0:
            return out[:n].tobytes()
    return encoder.encode(seq, output.t_ns, numbers, output.flags, output.sources, stale,
                          output.reasons)  # fmt: skip


def pose_frame(output: BodyOutput, seq: int, stale: Sequence[str]) -> pose.PoseFrame:
    """The message of one tick, numbers rounded to 1e-6 (microdegrees, micrometres)."""
    names = output.names
    # one rounding and one conversion to Python floats for every number of the tick,
    # cut back into vectors by zip (a body's message is built 100 times a second)
    n_p, n_q = output.positions.size, output.quats.size
    flat = np.round(np.concatenate([output.positions.ravel(), output.quats.ravel(),
                                    output.angles, output.rel]), 6).tolist()  # fmt: skip
    unc = np.round(output.unc, 3).tolist()  # NaN: no measurement (null in the message)
    p, q = iter(flat[:n_p]), iter(flat[n_p : n_p + n_q])
    positions = list(zip(p, p, p, strict=True))
    segments = zip(positions, zip(q, q, q, q, strict=True), strict=True)
    return pose.PoseFrame(
        seq,
        output.t_ns,
        dict(zip(names.angles, flat[n_p + n_q : n_p + n_q + len(names.angles)], strict=True)),
        dict(zip(names.joints, flat[n_p + n_q + len(names.angles) :], strict=True)),
        dict(zip(names.segments, segments, strict=True)),
        dict(zip(names.joints, map(positions.__getitem__, names.joint_segment), strict=True)),
        output.flags,
        output.sources,
        list(stale),
        output.reasons,
        dict(zip(names.angles, unc, strict=True)),
    )
