"""The gateway's output message: one body's joint angles and segment poses.

JSON (UTF-8), version 2, one object per tick, for clients in any language:

```json
{"v": 2, "seq": 118, "t_ns": 1700000000000000000,
 "angles_deg": {"left_elbow_flexion_deg": 42.1, ...},
 "rel_deg": {"left_elbow": 42.1, ...},
 "flags": {"left_elbow_pronation_deg": "held"},
 "reasons": {"left_elbow_pronation_deg": ["uncalibrated", "held"]},
 "unc_deg": {"left_elbow_flexion_deg": 0.5, "left_elbow_pronation_deg": null, ...},
 "segments": {"left_forearm": {"p": [0.0, 0.22, 1.17], "q": [0.93, 0.0, -0.36, 0.0]}, ...},
 "joints_m": {"left_elbow": [0.0, 0.22, 1.17], ...},
 "sources": {"body/arm/left/elbow/raw": 1700000000000000000, ...},
 "stale": ["body/leg/left/foot/raw"]}
```

World frame +X forward, +Y left, +Z up, metres; ``q`` is a unit quaternion
w, x, y, z. ``t_ns`` is the newest source timestamp that went into the tick;
``sources`` gives each sample's own. A branch view (``body/arm/left/pose``)
has the same shape, limited to that branch's joints and segments.

Quality of each dof (new in version 2): ``reasons`` lists every reason a dof
is not a plain measurement (``uncalibrated``, ``unobserved``, ``stale``, ``held``,
``clamped``: :data:`REASONS`); ``flags`` keeps one of them per dof, the first in
that order, as version 1 did. A dof resting on a sensor in ``stale`` has
``unobserved`` and ``stale``: its flag is ``unobserved``, one readers of
version 1 know. ``unc_deg`` is each measured dof's uncertainty
(degrees, an error bound of about two standard deviations), ``null`` where no
measurement stands behind the number. A dof is *measured* when it has no flag
or only ``clamped`` (:func:`is_measured`); any other flag means the number is
no measurement (held from the last one, a model's rest value, or uncalibrated)
and clients show a mark instead. :func:`decode` reads versions 1 and 2; a
version 1 message has no uncertainties, and its flags are its reasons.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import orjson

from ..errors import DecodeError, Reason

VERSION = 2
VERSIONS = (1, 2)  # what decode reads

#: Why a dof's number is not a plain measurement, most telling first: the flag
#: of a dof with several reasons is the first of these it has.
UNCALIBRATED = "uncalibrated"  # its sensors' calibration (the T-pose) does not exist yet
UNOBSERVED = "unobserved"  # nothing measures it: the model's rest value (or what it last was)
#: a sensor it rests on stopped delivering (always with ``unobserved``, the flag)
STALE = "stale"
HELD = "held"  # not determined now (a tilt along gravity): its last measured value, held
CLAMPED = "clamped"  # measured, then clamped to the range of motion
#: nothing measures it (always with ``unobserved``, the flag): it is the upright
#: model's, the reference a body with no trunk sensor is measured against (as the
#: pelvis at the origin is every body's), so what hangs below it is measured
UPRIGHT = "upright"
REASONS: Mapping[str, str] = {
    UNCALIBRATED: "not calibrated yet (waiting for the T-pose)",
    UNOBSERVED: "no sensor measures it now",
    STALE: "a sensor it rests on stopped delivering: the number rests on its last sample",
    HELD: "gravity cannot see it in this posture: held at its last measured value",
    CLAMPED: "measured beyond the range of motion, clamped to it",
    UPRIGHT: "no trunk sensor: the upright model's, the reference the limbs are measured against",
}


def primary(reasons: Sequence[str] | set[str] | frozenset[str]) -> str:
    """The flag of a dof with these reasons: the first of :data:`REASONS` it has
    (an unknown reason comes after them, in name order)."""
    order = list(REASONS)
    return min(reasons, key=lambda r: (order.index(r) if r in REASONS else len(order), r))


Vec3 = tuple[float, float, float]
QuatWxyz = tuple[float, float, float, float]


@dataclass(frozen=True)
class PoseFrame:
    seq: int
    t_ns: int
    angles_deg: Mapping[str, float]
    rel_deg: Mapping[str, float]
    segments: Mapping[str, tuple[Vec3, QuatWxyz]]
    joints_m: Mapping[str, Vec3]
    flags: Mapping[str, str] = field(default_factory=dict)
    sources: Mapping[str, int] = field(default_factory=dict)
    stale: Sequence[str] = ()
    #: every reason of each flagged dof (version 1: its flag)
    reasons: Mapping[str, Sequence[str]] = field(default_factory=dict)
    #: each dof's uncertainty (deg), NaN where no measurement stands behind it
    unc_deg: Mapping[str, float] = field(default_factory=dict)

    def why(self, dof: str) -> str:
        """Why a dof's number is not a measurement, in words ("" if it is one)."""
        if is_measured(self, dof):
            return ""
        reasons = self.reasons.get(dof) or [self.flags[dof]]
        return "; ".join(REASONS.get(r, r) for r in reasons if r != CLAMPED)

    def subset(self, joints: Sequence[str], segments: Sequence[str], keys_prefix: str) -> PoseFrame:
        """The view of one branch: its joints, segments and sources."""
        js = set(joints)
        return PoseFrame(
            self.seq,
            self.t_ns,
            {n: v for n, v in self.angles_deg.items() if _joint_of(n) in js},
            {j: v for j, v in self.rel_deg.items() if j in js},
            {s: self.segments[s] for s in segments if s in self.segments},
            {j: v for j, v in self.joints_m.items() if j in js},
            {n: f for n, f in self.flags.items() if _joint_of(n) in js},
            {k: t for k, t in self.sources.items() if k.startswith(keys_prefix)},
            [k for k in self.stale if k.startswith(keys_prefix)],
            {n: r for n, r in self.reasons.items() if _joint_of(n) in js},
            {n: u for n, u in self.unc_deg.items() if _joint_of(n) in js},
        )


def is_measured(frame: PoseFrame, dof: str) -> bool:
    """Whether a measurement stands behind ``frame``'s number for ``dof``: it has
    no flag, or only ``clamped`` (the team's one test of it)."""
    flag = frame.flags.get(dof)
    return flag is None or flag == CLAMPED


@lru_cache(maxsize=1024)
def _joint_of(angle_name: str) -> str:
    """``left_elbow`` of ``left_elbow_flexion_deg``."""
    return angle_name.rsplit("_", 2)[0]


def encode(frame: PoseFrame) -> bytes:
    """The message, numbers as given (the gateway rounds them to 1e-6 when it
    builds the frame, once for the body and all its branch views). orjson, not
    the standard library: at 100 Hz per body the encoder is on the hot path."""
    return orjson.dumps(
        {
            "v": VERSION,
            "seq": frame.seq,
            "t_ns": frame.t_ns,
            "angles_deg": frame.angles_deg,
            "rel_deg": frame.rel_deg,
            "flags": frame.flags,
            "segments": {s: {"p": p, "q": q} for s, (p, q) in frame.segments.items()},
            "joints_m": frame.joints_m,
            "sources": frame.sources,
            "stale": list(frame.stale),
            "reasons": frame.reasons,
            "unc_deg": frame.unc_deg,  # NaN goes out as null
        },
        option=orjson.OPT_SERIALIZE_NUMPY,
    )


#: What a slot of :attr:`WholeBodyEncoder.slots` holds when it is not a number.
SLOT_SEQ, SLOT_T_NS, SLOT_FLAGS, SLOT_SOURCES, SLOT_STALE, SLOT_REASONS = range(-1, -7, -1)


class WholeBodyEncoder:
    """:func:`encode` of whole-body frames whose names are these, byte for byte,
    from the numbers as arrays: no dictionary of the message is built. The
    message's fixed text (keys, brackets) is worked out once, with a slot for
    each number; a tick fills them with orjson's text of its numbers (one call
    for all of them, so each is written exactly as :func:`encode` writes it)
    and of its few variable maps (flags, sources, stale sites, reasons).

    ``numbers`` (see :meth:`encode`) is one vector: every segment's position
    (x, y, z), then every segment's quaternion (w, x, y, z), the angles, the
    joints' total rotations, then the angles' uncertainties (NaN: null),
    unrounded: the message rounds them as the gateway's frames do (``numpy.round``,
    to 1e-6, the uncertainties to 1e-3). ``joint_segment`` names each joint's
    child segment (its position is the joint centre)."""

    def __init__(self, angles: Sequence[str], joints: Sequence[str], segments: Sequence[str],
                 joint_segment: Sequence[int]) -> None:  # fmt: skip
        def key(name: str) -> str:
            return orjson.dumps(name).decode().replace("%", "%%") + ":"

        n_s, n_a, n_j = len(segments), len(angles), len(joints)
        at_q = 3 * n_s
        at_a = at_q + 4 * n_s
        at_u = at_a + n_a + n_j  # the uncertainties
        a_rel = [*range(at_a, at_u)]
        seg = [i for s in range(n_s) for i in (*range(3 * s, 3 * s + 3),
                                               *range(at_q + 4 * s, at_q + 4 * s + 4))]  # fmt: skip
        jnt = [i for s in joint_segment for i in range(3 * s, 3 * s + 3)]
        unc = [*range(at_u, at_u + n_a)]
        #: where each slot's number sits in ``numbers``, in the message's order
        self.order = np.array(a_rel + seg + jnt + unc, dtype=np.intp)
        # numpy.round(x, d) is rint(x * 10**d) / 10**d: one pass with each slot's 10**d,
        # d being 6 (micrometres, microdegrees) and 3 for the uncertainties
        self.places = np.where(self.order >= at_u, 3, 6).astype(np.int64)
        self.scale = 10.0**self.places
        self._n_first, self._n_segs = len(a_rel), len(a_rel) + len(seg) + len(jnt)
        self.size = at_u + n_a

        def obj(names: Sequence[str], value: str) -> str:
            return "{" + ",".join(key(n) + value for n in names) + "}"

        point, quat = "[%s,%s,%s]", "[%s,%s,%s,%s]"
        text = (
            '{"v":' + str(VERSION) + ',"seq":%s,"t_ns":%s,'
            + '"angles_deg":' + obj(angles, "%s") + ',"rel_deg":' + obj(joints, "%s")
            + ',"flags":%s,"segments":'
            + obj(segments, '{"p":' + point + ',"q":' + quat + "}")
            + ',"joints_m":' + obj(joints, point)
            + ',"sources":%s,"stale":%s,"reasons":%s,"unc_deg":' + obj(angles, "%s") + "}"
        )  # fmt: skip
        self._template = text.encode()
        # the same message laid out for a compiled writer (gateway/kernels.write_message):
        # the fixed text between the slots, joined, with where each piece ends
        # (``ends``), and what each slot holds (``slots``): the k-th number of
        # ``order`` (k >= 0, rounded to ``places``), or a SLOT_* (negative)
        pieces, piece, i = [], bytearray(), 0
        template = self._template
        while i < len(template):
            if template[i] == 37:  # "%": "%%" is one, "%s" a slot
                if template[i + 1] == 37:
                    piece.append(37)
                else:
                    pieces.append(bytes(piece))
                    piece = bytearray()
                i += 2
            else:
                piece.append(template[i])
                i += 1
        pieces.append(bytes(piece))
        self.text = np.frombuffer(b"".join(pieces), dtype=np.uint8).copy()
        self.ends = np.cumsum([len(p) for p in pieces], dtype=np.int64)
        first, segs, n = self._n_first, self._n_segs, len(self.order)
        self.slots = np.array([SLOT_SEQ, SLOT_T_NS, *range(first), SLOT_FLAGS,
                               *range(first, segs), SLOT_SOURCES, SLOT_STALE, SLOT_REASONS,
                               *range(segs, n)], dtype=np.int64)  # fmt: skip
        #: what the message takes at most besides its four maps: the fixed text, 24
        #: characters a number ("-123456789.123456" and more) and two integers
        self.capacity = len(self.text) + 24 * n + 2 * 21

    def encode(self, seq: int, t_ns: int, numbers: Any, flags: Mapping[str, str],
               sources: Mapping[str, int], stale: Sequence[str],
               reasons: Mapping[str, Sequence[str]]) -> bytes:  # fmt: skip
        """The message: ``numbers`` (an array, see the class) as :func:`encode`
        writes floats, the rest as given."""
        if len(numbers) != self.size:
            raise ValueError(f"{len(numbers)} numbers, the message has {self.size}")
        picked = numbers[self.order]
        picked *= self.scale
        np.rint(picked, out=picked)
        picked /= self.scale
        texts = orjson.dumps(picked, option=orjson.OPT_SERIALIZE_NUMPY)[1:-1]
        slots = texts.split(b",")
        first, segs = self._n_first, self._n_segs
        dumps = orjson.dumps
        return self._template % (
            b"%d" % seq, b"%d" % t_ns, *slots[:first], dumps(flags), *slots[first:segs],
            dumps(sources), dumps(list(stale)), dumps(reasons), *slots[segs:],
        )  # fmt: skip


def source_time(payload: bytes | bytearray) -> int:
    """The ``t_ns`` of one pose message, nothing else checked: for a latency
    probe that must cost less than what it measures (a quarter of :func:`decode`)."""
    return int(orjson.loads(payload)["t_ns"])


def _floats(v: Any, n: int) -> Any:
    """Exactly ``n`` numbers, as floats (a vector or a quaternion)."""
    if not isinstance(v, list) or len(v) != n:
        raise DecodeError(Reason.BAD_LENGTH, f"expected {n} numbers, got {v!r:.60}")
    return tuple(map(float, v))


def _float_map(m: Any) -> dict[str, float]:
    """A JSON object of numbers, as floats (JSON keys are strings already)."""
    return dict(zip(m, map(float, m.values()), strict=True))


def _strings(v: Any) -> list[str]:
    if not isinstance(v, list):
        raise DecodeError(Reason.GARBAGE, f"expected a list of reasons, got {v!r:.60}")
    return [str(r) for r in v]


def _int(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise DecodeError(Reason.GARBAGE, f"expected an integer, got {v!r:.60}")
    n = int(v)  # OverflowError (inf) and ValueError (nan) are caught by decode
    if not -(2**63) <= n < 2**64:  # what a 64-bit field (and orjson) can carry
        raise DecodeError(Reason.GARBAGE, f"integer out of 64-bit range: {v!r:.60}")
    return n


def decode(payload: bytes | bytearray) -> PoseFrame:
    """One pose message; ``DecodeError`` if it is not one."""
    try:
        d: dict[str, Any] = orjson.loads(payload)
        if not isinstance(d, dict):
            raise DecodeError(Reason.GARBAGE, "not a JSON object")
        version = d.get("v")
        if isinstance(version, bool) or version not in VERSIONS:
            raise DecodeError(Reason.BAD_VERSION, f"version {version!r:.60}")
        flags = {str(k): str(v) for k, v in d.get("flags", {}).items()}
        if version == 1:
            reasons: dict[str, tuple[str, ...]] = {k: (f,) for k, f in flags.items()}
            unc: dict[str, float] = {}
        else:
            reasons = {str(k): tuple(_strings(v)) for k, v in d.get("reasons", {}).items()}
            unc = {k: math.nan if v is None else float(v) for k, v in d.get("unc_deg", {}).items()}
        return PoseFrame(
            _int(d["seq"]),
            _int(d["t_ns"]),
            _float_map(d["angles_deg"]),
            _float_map(d["rel_deg"]),
            {s: (_floats(v["p"], 3), _floats(v["q"], 4)) for s, v in d["segments"].items()},
            {j: _floats(p, 3) for j, p in d["joints_m"].items()},
            flags,
            {str(k): _int(v) for k, v in d.get("sources", {}).items()},
            [str(k) for k in d.get("stale", [])],
            reasons,
            unc,
        )
    except DecodeError:
        raise
    # RecursionError: JSON nested deeper than the parser goes; OverflowError: int(1e999)
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError, RecursionError) as exc:
        raise DecodeError(Reason.GARBAGE, f"not a pose message: {exc!s:.200}") from None


# -- what a recorder reads of a pose: its header and segments, not the rest --------------

#: The start of a message as :func:`encode` lays it out: version, sequence number, time.
_HEAD = re.compile(
    rb'\{"v":([12]),"seq":(-?(?:0|[1-9][0-9]{0,19})),"t_ns":(-?(?:0|[1-9][0-9]{0,19})),'
)
_SEGMENTS = b',"segments":{'
_SEGMENTS_END = b"]}}"  # the last segment's "q", the segment, the segments


@dataclass(frozen=True, slots=True)
class Glance:
    """What :func:`glance` reads of a pose message: its version, sequence
    number and time, and the JSON text of its ``segments`` object as it stands
    in the message (``b""`` where it was not asked for), found at ``at``."""

    version: int
    seq: int
    t_ns: int
    segments: bytes = b""
    at: int = 0


def glance(payload: bytes, segments: bool = False, hint: int = 0) -> Glance | None:
    """The header of a pose message laid out as :func:`encode` lays it out
    (``{"v":2,"seq":..,"t_ns":..,``), and with ``segments`` the text of its
    ``segments`` object (``hint``: where it started in the last message, the
    place looked at first); ``None`` for any other layout (then :func:`decode`
    it). Nothing else of the message is read, so nothing else is checked: what
    stores a message as it came reads this much of it, at a fraction of
    :func:`decode`'s cost. The numbers in the header are checked as decode
    checks them (``DecodeError`` past 64 bits)."""
    m = _HEAD.match(payload)
    if m is None:
        return None
    seq, t_ns = int(m[2]), int(m[3])
    for n in (seq, t_ns):
        if not -(2**63) <= n < 2**64:
            raise DecodeError(Reason.GARBAGE, f"integer out of 64-bit range: {n}")
    if not segments:
        return Glance(int(m[1]), seq, t_ns)
    at = hint if payload.startswith(_SEGMENTS, hint) else payload.find(_SEGMENTS, m.end())
    if at < 0:
        return None
    start = at + len(_SEGMENTS) - 1
    if payload.startswith(b"{}", start):
        end = start + 2
    else:
        end = payload.find(_SEGMENTS_END, start)
        if end < 0:
            return None
        end += len(_SEGMENTS_END)
    return Glance(int(m[1]), seq, t_ns, payload[start:end], at)


def segment_numbers(texts: Sequence[bytes]) -> tuple[list[tuple[bytes, ...] | None], list[float]]:
    """The segments texts of :func:`glance` read in one pass of the JSON parser:
    each text's segment names (as they stand in the JSON text, escapes
    included), ``None`` for a text not laid out as :func:`encode` lays it
    out, and the numbers of the others one after another, seven per segment
    (``p`` x, y, z then ``q`` w, x, y, z), in the order of the texts and of
    their segments. ``DecodeError`` if a text that looked so holds something
    else than numbers where they stand."""
    names: list[tuple[bytes, ...] | None] = []
    numbers: list[bytes] = []
    for text in texts:
        # {"name":{"p":[x,y,z],"q":[w,x,y,z]},...}: between the quotes, the names,
        # the "p" and "q", and between those the numbers with their brackets
        parts = text.split(b'"')
        n = len(parts) // 6
        if (len(parts) != 6 * n + 1 or parts[3::6].count(b"p") != n
                or parts[5::6].count(b"q") != n or b"\\" in text):  # fmt: skip
            names.append(None)
            continue
        names.append(tuple(parts[1::6]))
        if n:
            numbers.append(b"".join(parts[2::2]))
    if not numbers:
        return names, []
    try:
        flat = orjson.loads(b"[" + b",".join(numbers).translate(None, b":{}[]") + b"]")
    except orjson.JSONDecodeError as exc:
        raise DecodeError(Reason.GARBAGE, f"segments that are not numbers: {exc}") from None
    if len(flat) != 7 * sum(len(n) for n in names if n is not None):
        raise DecodeError(Reason.BAD_LENGTH, "segments without 3 + 4 numbers each")
    return names, flat
