"""``bodynet vmc``: the live body over the VMC protocol (performer -> marionette).

VMC is OSC over UDP (spec 3.x; the marionette, e.g. EVMC4U in Unity,
VSeeFace, Blender's VMC add-ons, listens on port 39539). At ``rate_hz`` the
newest pose of the subject goes out as ONE OSC bundle (python-osc builds it):

- ``/VMC/Ext/OK`` (int loaded, int calibration state, int calibration mode,
  int tracking status; the spec's V2.7 form): loaded 1 once a pose came, else
  0; calibration state 3 (Calibrated) or 0 (Uncalibrated: some dof of the pose
  is flagged ``uncalibrated``, or no pose yet); calibration mode 0 (Normal: the
  spec's modes are 0 Normal, 1 MR Normal, 2 MR Floor fix, and bodynet's T-pose
  calibration is no mixed-reality one); tracking status 1 (OK) while poses
  arrive (the newest is under 0.5 s old and no source of it is stale), else 0 (Bad);
- ``/VMC/Ext/T`` (float): seconds since the output started;
- ``/VMC/Ext/Root/Pos`` ("root", position, quaternion): the origin, identity;
- ``/VMC/Ext/Bone/Pos`` (name, local position x, y, z, local rotation x, y,
  z, w) for each Unity ``HumanBodyBones`` bone bodynet has a segment for
  (:data:`BONES`): Hips, Spine, Chest, Neck, Head, Left/Right UpperArm,
  LowerArm, Hand, UpperLeg, LowerLeg, Foot. There are no shoulder (clavicle)
  segments, so LeftShoulder/RightShoulder are not sent: the avatar keeps them at
  rest, and the upper arms' rotations are local to the Chest, which is the same.

Frames. bodynet: right-handed, +X forward, +Y left, +Z up. Unity:
left-handed, +X right, +Y up, +Z forward. A vector maps as
``u = M v`` with ``M = [[0, -1, 0], [0, 0, 1], [1, 0, 0]]`` (right = -left,
up = up, forward = forward); ``det M = -1``, the change of handedness. A
rotation ``R`` maps as ``M R M^T``; since ``M (a x b) = det(M) (Ma x Mb)``,
rotating by angle t about axis ``a`` becomes rotating by t about ``-M a``,
so the quaternion (w, x, y, z) becomes (w, -M (x, y, z)) =
(w, y, -z, -x), sent in Unity's order x, y, z, w as (y, -z, -x, w).

Rest pose. A humanoid avatar's bones have identity rotations in its T-pose
(arms horizontal, palms down); bodynet's segment orientations are rotations
from anatomical neutral (arms at the sides). So each bone's world rotation is
the segment's times its rest offset (:data:`REST`): the rotation taking the
T-pose bone onto the neutral one, Rx(-90 deg) for the left arm's bones,
Rx(+90 deg) for the right's, identity elsewhere. The local rotation sent is
``W(parent)^-1 W(bone)`` in Unity's frame; the local position is the bone's
joint centre from its parent's, in the parent's frame.

VMC has no mark for "not measured" on a bone (``/VMC/Ext/OK``'s tracking
status is the whole body's): a bone whose local rotation rests on an angle
the pose does not measure (``is_measured`` false on the joint between it and
its parent bone: :func:`unmeasured_bones`) is sent with its last measured
local rotation, as BVH holds a channel (the pose's own value until one was
measured), and :class:`HeldBones` counts those sends; the tracking status
tells a stale body.
"""

from __future__ import annotations

import functools
import math
import socket
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from bodynet.clients.body_tree import default_chains
from bodynet.clients.live import LiveOutput
from bodynet.core.codecs import pose

DEFAULT_PORT = 39539
DEFAULT_RATE_HZ = 60.0
STALE_S = 0.5
#: ``/VMC/Ext/OK`` values (the spec's lists): calibration state and mode.
UNCALIBRATED, CALIBRATED = 0, 3
MODE_NORMAL = 0

#: Unity HumanBodyBones name -> (bodynet segment, parent bone), parents first.
BONES: dict[str, tuple[str, str | None]] = {
    "Hips": ("pelvis", None),
    "Spine": ("thorax", "Hips"),
    "Chest": ("thorax", "Spine"),
    "Neck": ("head", "Chest"),
    "Head": ("head", "Neck"),
}
for _S, _s in (("Left", "left"), ("Right", "right")):
    BONES.update({
        f"{_S}UpperArm": (f"{_s}_upperarm", "Chest"),
        f"{_S}LowerArm": (f"{_s}_forearm", f"{_S}UpperArm"),
        f"{_S}Hand": (f"{_s}_hand", f"{_S}LowerArm"),
        f"{_S}UpperLeg": (f"{_s}_thigh", "Hips"),
        f"{_S}LowerLeg": (f"{_s}_shank", f"{_S}UpperLeg"),
        f"{_S}Foot": (f"{_s}_foot", f"{_S}LowerLeg"),
    })  # fmt: skip

Quat = tuple[float, float, float, float]  # w, x, y, z (bodynet's order)

_H = math.sqrt(0.5)
#: Rest offsets (w, x, y, z, bodynet's frame): the T-pose bone onto the neutral one.
REST: dict[str, Quat] = {
    **{f"left_{s}": (_H, -_H, 0.0, 0.0) for s in ("upperarm", "forearm", "hand")},
    **{f"right_{s}": (_H, _H, 0.0, 0.0) for s in ("upperarm", "forearm", "hand")},
}


# --- conversions (pure) -------------------------------------------------------------------


def qmul(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Hamilton product ``a b`` of quaternions w, x, y, z."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def qconj(q: Sequence[float]) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def qrotate(q: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    _, x, y, z = qmul(qmul(q, (0.0, *v)), qconj(q))
    return (x, y, z)


def unity_vector(v: Sequence[float]) -> tuple[float, float, float]:
    """bodynet's (forward, left, up) as Unity's (right, up, forward)."""
    return (-v[1], v[2], v[0])


def unity_quat(q: Sequence[float]) -> Quat:
    """A rotation (w, x, y, z) of bodynet's frame as the same rotation in Unity's
    frame, w, x, y, z (see the module docstring)."""
    return (q[0], q[2], -q[3], -q[1])


@dataclass(frozen=True, slots=True)
class Bone:
    """One ``/VMC/Ext/Bone/Pos``: Unity's frame, rotation w, x, y, z."""

    name: str
    position: tuple[float, float, float]
    rotation: Quat


def world_rotations(frame: pose.PoseFrame) -> dict[str, Quat]:
    """Each bone's world rotation in Unity's frame (rest offset included), for the
    bones whose segment the pose has."""
    out: dict[str, Quat] = {}
    for bone, (segment, _) in BONES.items():
        got = frame.segments.get(segment)
        if got is not None:
            out[bone] = unity_quat(qmul(got[1], REST.get(segment, (1.0, 0.0, 0.0, 0.0))))
    return out


def bones(frame: pose.PoseFrame) -> list[Bone]:
    """The local rotation and position of every bone the pose can place: its
    segment and all its parents' are in the pose."""
    world = world_rotations(frame)
    out: list[Bone] = []
    placed: set[str] = set()
    for bone, (segment, parent) in BONES.items():
        if bone not in world or (parent is not None and parent not in placed):
            continue
        p = unity_vector(frame.segments[segment][0])
        if parent is None:
            out.append(Bone(bone, p, world[bone]))
        else:
            pw = world[parent]
            pp = unity_vector(frame.segments[BONES[parent][0]][0])
            offset = qrotate(qconj(pw), np.subtract(p, pp))
            out.append(Bone(bone, offset, qmul(qconj(pw), world[bone])))
        placed.add(bone)
    return out


@functools.cache
def bone_angles() -> Mapping[str, tuple[str, ...]]:
    """The angles each bone's local rotation rests on: those on its segment's
    chain from the pelvis and not on its parent bone's (Chest and Head: none)."""
    chains = default_chains()
    out: dict[str, tuple[str, ...]] = {}
    for bone, (segment, parent) in BONES.items():
        above = set(chains[BONES[parent][0]]) if parent is not None else set()
        out[bone] = tuple(a for a in chains[segment] if a not in above)
    return out


def unmeasured_bones(frame: pose.PoseFrame) -> frozenset[str]:
    """The bones whose local rotation rests on an angle ``frame`` does not measure."""
    if not frame.flags:
        return frozenset()
    return frozenset(bone for bone, angles in bone_angles().items()
                     if not all(pose.is_measured(frame, a) for a in angles))  # fmt: skip


class HeldBones:
    """Each bone's last measured local rotation, sent instead of one that rests
    on an unmeasured angle (VMC has no per-bone mark); ``held`` counts those."""

    def __init__(self) -> None:
        self.last: dict[str, Quat] = {}
        self.held = 0

    def apply(self, frame: pose.PoseFrame, sent: list[Bone]) -> list[Bone]:
        """``sent`` (the bones of ``frame``) with the unmeasured ones held."""
        unmeasured = unmeasured_bones(frame)
        out: list[Bone] = []
        for bone in sent:
            if bone.name in unmeasured:
                self.held += 1
                out.append(replace(bone, rotation=self.last.get(bone.name, bone.rotation)))
            else:
                self.last[bone.name] = bone.rotation
                out.append(bone)
        return out


def ok_args(frame: pose.PoseFrame | None, fresh: bool) -> tuple[int, int, int, int]:
    """``/VMC/Ext/OK``: loaded, calibration state, calibration mode, tracking."""
    if frame is None:
        return (0, UNCALIBRATED, MODE_NORMAL, 0)
    state = UNCALIBRATED if pose.UNCALIBRATED in frame.flags.values() else CALIBRATED
    return (1, state, MODE_NORMAL, int(fresh and not frame.stale))


def messages(frame: pose.PoseFrame | None, fresh: bool, t_s: float,
             held: HeldBones | None = None) -> list[tuple[str, list[object]]]:  # fmt: skip
    """The OSC messages of one bundle: address and arguments; with ``held``, a
    bone resting on an unmeasured angle keeps its last measured rotation."""
    out: list[tuple[str, list[object]]] = [("/VMC/Ext/OK", list(ok_args(frame, fresh))),
                                           ("/VMC/Ext/T", [float(t_s)])]  # fmt: skip
    if frame is not None:
        out.append(("/VMC/Ext/Root/Pos", ["root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
        sent = bones(frame)
        for b in sent if held is None else held.apply(frame, sent):
            w, x, y, z = b.rotation
            out.append(("/VMC/Ext/Bone/Pos", [b.name, *map(float, b.position), x, y, z, w]))
    return out


def bundle(msgs: Sequence[tuple[str, Sequence[object]]]) -> bytes:
    """One OSC bundle (time tag "immediately") holding ``msgs``."""
    builder = OscBundleBuilder(IMMEDIATELY)
    for address, args in msgs:
        m = OscMessageBuilder(address)
        for a in args:
            m.add_arg(a, "s" if isinstance(a, str) else "i" if isinstance(a, int) else "f")
        builder.add_content(m.build())  # type: ignore[arg-type]
    return bytes(builder.build().dgram)


# --- the output -----------------------------------------------------------------------------


class VmcOutput(LiveOutput):
    """The newest pose of the subject, one bundle every ``1 / rate_hz`` s, to
    ``host:port`` over UDP."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 rate_hz: float = DEFAULT_RATE_HZ) -> None:  # fmt: skip
        self.address = (host, port)
        self.tick_s = 1.0 / rate_hz
        self.rate_hz = rate_hz
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise OSError(f"cannot resolve the receiver's host {host!r}: {exc.strerror}") from None
        self._sock = socket.socket(infos[0][0], socket.SOCK_DGRAM)
        self._start = time.monotonic()
        self._frame: pose.PoseFrame | None = None
        self._subject: str | None = None
        self._received = -math.inf
        self.sent = 0
        self.send_errors = 0
        #: the bones sent with their last measured rotation (``held.held`` of them)
        self.held = HeldBones()

    def describe(self) -> str:
        return f"VMC bundles at {self.rate_hz:g} Hz to {self.address[0]}:{self.address[1]}"

    def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
        if self._subject is None:
            self._subject = subject
        if subject == self._subject:  # one performer per VMC stream
            self._frame = frame
            self._received = time.monotonic()

    def tick(self, now: float) -> None:
        fresh = now - self._received < STALE_S
        data = bundle(messages(self._frame, fresh, now - self._start, self.held))
        try:
            self._sock.sendto(data, self.address)
            self.sent += 1
        except OSError:  # no route, port unreachable (ICMP from an earlier send)...
            self.send_errors += 1

    def close(self) -> None:
        self._sock.close()
