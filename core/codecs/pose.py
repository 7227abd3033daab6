"""The gateway's output message: one body's joint angles and segment poses.

JSON (UTF-8), version 1, one object per tick, for clients in any language:

```json
{"v": 1, "seq": 118, "t_ns": 1700000000000000000,
 "angles_deg": {"left_elbow_flexion_deg": 42.1, ...},
 "rel_deg": {"left_elbow": 42.1, ...},
 "flags": {"left_elbow_pronation_deg": "unobserved"},
 "segments": {"left_forearm": {"p": [0.0, 0.22, 1.17], "q": [0.93, 0.0, -0.36, 0.0]}, ...},
 "joints_m": {"left_elbow": [0.0, 0.22, 1.17], ...},
 "sources": {"body/arm/left/elbow/raw": 1700000000000000000, ...},
 "stale": ["body/leg/left/foot/raw"]}
```

World frame +X forward, +Y left, +Z up, metres; ``q`` is a unit quaternion
w, x, y, z. ``t_ns`` is the newest source timestamp that went into the tick;
``sources`` gives each sample's own. A branch view (``body/arm/left/pose``)
has the same shape, limited to that branch's joints and segments.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import orjson

from ..errors import DecodeError, Reason

VERSION = 1

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
        )


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
        },
        option=orjson.OPT_SERIALIZE_NUMPY,
    )


def source_time(payload: bytes | bytearray) -> int:
    """The ``t_ns`` of one pose message, nothing else checked: for a latency
    probe that must cost less than what it measures (a quarter of :func:`decode`)."""
    return int(orjson.loads(payload)["t_ns"])


def _floats(v: Any, n: int) -> Any:
    """Exactly ``n`` numbers, as floats (a vector or a quaternion)."""
    if not isinstance(v, list) or len(v) != n:
        raise DecodeError(Reason.BAD_LENGTH, f"expected {n} numbers, got {v!r:.60}")
    return tuple(float(c) for c in v)


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
        if d.get("v") != VERSION:
            raise DecodeError(Reason.BAD_VERSION, f"version {d.get('v')!r:.60}")
        return PoseFrame(
            _int(d["seq"]),
            _int(d["t_ns"]),
            {str(k): float(v) for k, v in d["angles_deg"].items()},
            {str(k): float(v) for k, v in d["rel_deg"].items()},
            {str(s): (_floats(v["p"], 3), _floats(v["q"], 4)) for s, v in d["segments"].items()},
            {str(j): _floats(p, 3) for j, p in d["joints_m"].items()},
            {str(k): str(v) for k, v in d.get("flags", {}).items()},
            {str(k): _int(v) for k, v in d.get("sources", {}).items()},
            [str(k) for k in d.get("stale", [])],
        )
    except DecodeError:
        raise
    # RecursionError: JSON nested deeper than the parser goes; OverflowError: int(1e999)
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError, RecursionError) as exc:
        raise DecodeError(Reason.GARBAGE, f"not a pose message: {exc!s:.200}") from None
