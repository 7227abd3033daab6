"""The 000 seed's 7-DOF Denavit-Hartenberg arm (ch. 4.3, eq. 16-17, Table 4.2) in Pinocchio.

Strategy: the seed's arm and ours (:mod:`bodynet.core.skeleton`) turn about the
same seven axes in the same order (shoulder flexion, abduction, internal
rotation; elbow flexion; forearm pronation; wrist flexion, radial deviation),
so the D-H model is our arm written in D-H parameters, and each D-H angle is
one anatomical angle with a sign and a constant offset:
``theta_i = offset_i + sign_i * angle_i``. Only the lateralised dofs (abduction,
rotation, pronation, wrist flexion) change sign between the arms; the table
itself is the same for both.

Each link is eq. 16, ``T(i-1, i) = Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``:
joint ``i`` is a revolute joint about the local z of frame ``i-1`` (Pinocchio's
``JointModelRZ``), and the fixed ``Tz Tx Rx`` is the placement of the next joint
(and of the frame ``dh<i>``). The chain equation (eq. 17) is then Pinocchio's
forward kinematics.

Base frame. The seed puts its world frame on the pelvis with Xw forward and Yw
up, so Zw = Xw x Yw points to the body's right. Our world is +X forward, +Y
left, +Z up; the fixed rotation between them is a quarter turn about X::

    R_OURS_SEED = Rx(+90 deg): Xw = +X, Yw = +Z, Zw = -Y   (v_ours = R_OURS_SEED @ v_seed)

The base frame ``b`` has the seed's axes and sits at the shoulder centre, fixed
to the thorax. The seed's d0 and a0 (pelvis to shoulder) are replaced by that
fixed placement: a0 along x0 would swing the shoulder with theta0, and the
vertical part of the offset has no D-H parameter in link 0 at all. With the
torso neutral the thorax is the pelvis frame moved up, so the base is the
seed's pelvis frame carried to the shoulder. This model's own world (Pinocchio's
universe) is our thorax segment frame: compose with the thorax's world pose for
any other torso posture.

Reading of Table 4.2. The extracted table lists d3, a3 (both "upper arm
length"), d4, a4 (both "forearm length") and alpha3 = 0, and the text places
frames 0-2 at the shoulder, frame 3 at the elbow and frames 4-6 at the wrist.
These cannot all hold in standard D-H (eq. 16): joint i+1 turns about z_i
through frame i's origin, so

* d3 = a3 = L_upperarm would make the upper arm sqrt(2) L long and 45 degrees
  off its rotation axis;
* frame 3 at the elbow and frame 4 at the wrist means theta4 turns about a line
  through the elbow and must leave the wrist in place: z3 lies along the
  forearm (d4 = L_forearm, a4 = 0), theta4 is the forearm's roll, and z3 is
  perpendicular to the elbow axis z2, so |alpha3| = 90, not 0. With alpha3 = 0
  two consecutive joints hinge in one plane and nothing rolls the forearm;
* frame 2 lies on the elbow axis z2 (joint 3's axis), so it cannot be at the
  shoulder: it sits at the elbow centre, d2 = L_upperarm along the humeral axis z1.

We keep the text's frame 3 at the elbow and frames 4-6 at the wrist (so frames
0-1 sit at the shoulder, 2-3 at the elbow), the table's other twists (alpha0 =
alpha2 = alpha4 = 90, alpha1 = alpha5 = alpha6 = -90) and the seed's joint
meanings (ch. 4.3.2: theta2 from the shoulder encoder = humeral rotation,
theta3 = elbow angle, theta5 from the wrist encoder = wrist flexion, ch. 2.4.3),
and take alpha3 = -90 (with -90 the D-H zero
is a straight arm and theta3 is the elbow flexion itself; +90 would fold the
elbow at theta = 0). The upper arm goes in d2 and the forearm in d4; every a is 0.
The seed's alpha3 = 0 is kept only by a different reading (frame 3 at the wrist,
a3 = L_forearm, pronation folded into a 3-axis wrist with a non-linear Euler map),
which contradicts the text's frame 3 at the elbow.

Offsets: the anatomical neutral (arm hanging, palm to the thigh) is
theta = (90, 90, 90, 0, 90, 90, 90) degrees; the D-H zero theta = 0 is the arm
straight out along Zw (the right arm's side, horizontal). theta6's offset makes
frame 6 our hand segment frame, so no tool transform is needed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from bodynet.core.skeleton import ARM_DOFS, Skeleton, build_skeleton
from bodynet.core.subject import Profile

#: Our world axes from the seed's (columns: Xw, Yw, Zw in our frame).
R_OURS_SEED: np.ndarray = Rotation.from_euler("x", 90.0, degrees=True).as_matrix()

#: The dofs whose axis is mirrored between the arms (skeleton.py: ``lat``, ``rot``).
_LATERAL = frozenset({"shoulder_abduction", "shoulder_rotation", "elbow_pronation",
                      "wrist_flexion"})  # fmt: skip
#: theta_i offsets (deg) and twists alpha_i (deg), Table 4.2 as read above.
_OFFSETS_DEG = (90.0, 90.0, 90.0, 0.0, 90.0, 90.0, 90.0)
_ALPHAS_DEG = (90.0, -90.0, 90.0, -90.0, 90.0, -90.0, -90.0)
SIDES = ("left", "right")


@dataclass(frozen=True, slots=True)
class DhLink:
    """One row of Table 4.2: ``theta = theta_offset + sign * angle(dof)``."""

    dof: str  # the anatomical dof, e.g. "shoulder_flexion"
    sign: float  # +1 or -1
    theta_offset_deg: float
    d: float  # m, along z(i-1)
    a: float  # m, along x(i)
    alpha_deg: float

    def fixed(self) -> pin.SE3:
        """``Tz(d) Tx(a) Rx(alpha)``: frame i in the frame of joint i (after ``Rz(theta)``)."""
        rx = Rotation.from_euler("x", self.alpha_deg, degrees=True).as_matrix()
        return pin.SE3(rx, np.array([self.a, 0.0, self.d]))


def _check_side(side: str) -> None:
    if side not in SIDES:
        raise ValueError(f"side must be 'left' or 'right', not {side!r}")


def dh_table(side: str, upperarm: float = 0.293, forearm: float = 0.265) -> tuple[DhLink, ...]:
    """Table 4.2 for one arm: the upper arm in d2, the forearm in d4 (m)."""
    _check_side(side)
    lateral = 1.0 if side == "left" else -1.0
    d = (0.0, 0.0, upperarm, 0.0, forearm, 0.0, 0.0)
    return tuple(
        DhLink(dof, lateral if dof in _LATERAL else 1.0, off, di, 0.0, alpha)
        for dof, off, di, alpha in zip(ARM_DOFS, _OFFSETS_DEG, d, _ALPHAS_DEG, strict=True)
    )


def _wrap_deg(deg: float) -> float:
    """Into (-180, 180], so that 180 (full shoulder flexion) stays 180."""
    return 180.0 - (180.0 - deg) % 360.0


def dh_angles_from_anatomical(
    angles_deg: Mapping[str, float], side: str, table: Sequence[DhLink] | None = None
) -> np.ndarray:
    """theta0..theta6 (rad) from our joint angles (``left_elbow_flexion_deg`` ...;
    missing ones are 0, other names are ignored)."""
    table = table if table is not None else dh_table(side)
    return np.radians(
        [link.theta_offset_deg + link.sign * angles_deg.get(f"{side}_{link.dof}_deg", 0.0)
         for link in table]
    )  # fmt: skip


def anatomical_from_dh(
    theta_rad: Sequence[float] | np.ndarray, side: str, table: Sequence[DhLink] | None = None
) -> dict[str, float]:
    """Our joint angles (deg, each in (-180, 180]) from theta0..theta6 (rad)."""
    table = table if table is not None else dh_table(side)
    return {
        f"{side}_{link.dof}_deg": _wrap_deg(link.sign * (math.degrees(t) - link.theta_offset_deg))
        for link, t in zip(table, theta_rad, strict=True)
    }


class DhArm:
    """One arm as a Pinocchio chain of seven ``RZ`` joints built from D-H parameters.

    ``q`` is theta0..theta6 in rad. Frames: ``base`` (seed axes at the shoulder),
    ``dh0``..``dh6`` (the D-H frames), and ``shoulder`` = dh0, ``elbow`` = dh3,
    ``wrist`` = dh4, ``hand`` = dh6 (= our hand segment frame). Placements are in
    our thorax segment frame.
    """

    def __init__(
        self,
        side: str = "left",
        skeleton: Skeleton | None = None,
        table: Sequence[DhLink] | None = None,
    ) -> None:
        _check_side(side)
        skeleton = skeleton or build_skeleton()
        self.side = side
        self.dh_params: tuple[DhLink, ...] = tuple(
            table
            if table is not None
            else dh_table(side, skeleton.lengths["upperarm"], skeleton.lengths["forearm"])
        )
        if len(self.dh_params) != len(ARM_DOFS):
            raise ValueError(f"a D-H arm has {len(ARM_DOFS)} links, not {len(self.dh_params)}")
        shoulder = skeleton.joint(f"{side}_shoulder")
        #: The base frame b in the thorax frame: the seed's axes at the shoulder centre.
        self.thorax_M_base = pin.SE3(R_OURS_SEED, np.array(shoulder.offset, dtype=float))
        model = pin.Model()
        model.name = f"dh_{side}_arm"
        base = pin.Frame("base", 0, self.thorax_M_base, pin.FrameType.OP_FRAME)
        self.frames: dict[str, int] = {"base": model.addFrame(base)}
        parent, placement = 0, self.thorax_M_base
        for i, link in enumerate(self.dh_params):
            parent = model.addJoint(parent, pin.JointModelRZ(), placement, f"theta{i}")
            placement = link.fixed()
            frame = pin.Frame(f"dh{i}", parent, placement, pin.FrameType.OP_FRAME)
            self.frames[f"dh{i}"] = model.addFrame(frame)
        for name, dh in (("shoulder", 0), ("elbow", 3), ("wrist", 4), ("hand", 6)):
            self.frames[name] = self.frames[f"dh{dh}"]
        self.model = model
        self.data = model.createData()

    @classmethod
    def for_profile(cls, profile: Profile, side: str = "left") -> DhArm:
        """The arm with the subject's segment lengths."""
        return cls(side, build_skeleton(profile.lengths))

    def theta(self, angles_deg: Mapping[str, float]) -> np.ndarray:
        """theta0..theta6 (rad) for our joint angles of this arm."""
        return dh_angles_from_anatomical(angles_deg, self.side, self.dh_params)

    def anatomical(self, theta_rad: Sequence[float] | np.ndarray) -> dict[str, float]:
        return anatomical_from_dh(theta_rad, self.side, self.dh_params)

    def forward(self, theta_rad: Sequence[float] | np.ndarray) -> dict[str, pin.SE3]:
        """Placement (in the thorax frame) of every named frame at theta0..theta6 (rad)."""
        q = np.asarray(theta_rad, dtype=float)
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        return {name: pin.SE3(self.data.oMf[fid]) for name, fid in self.frames.items()}

    def forward_anatomical(self, angles_deg: Mapping[str, float]) -> dict[str, pin.SE3]:
        return self.forward(self.theta(angles_deg))
