"""The 000 seed's 40-DOF hierarchical body model (ch. 4.4, eq. 24) in Pinocchio.

Strategy: the seed's model and ours (:mod:`bodynet.core.skeleton`) are the same
tree except in three places, so the seed's joints are built from our
skeleton's, with our axes, offsets and sign conventions, and only those three
places differ:

* Trunk and head: four 3-dof joints where we have two. The seed renders "the
  pelvis[,] lower and upper trunk joints, thorax" (ch. 4.5.1) and tracks "head
  and body trunk (upper trunk and lower trunk)" with three IMUs (ch. 3.1); its
  count of 16 moving links needs a fourth, a neck link under the head (the
  figure that names it, 4-16/4-17, is lost). So: ``lower_trunk`` (pelvis to
  abdomen, at our lumbar joint), ``upper_trunk`` (abdomen to thorax, a
  :data:`LOWER_TRUNK_FRACTION` of our thorax length up), ``neck`` (thorax to
  neck link, at our neck joint) and ``head`` (neck link to head, a
  :data:`NECK_FRACTION` of our head length up). Each turns about our lumbar or
  neck axes in our order (flexion +Y, lateral +X, rotation +Z, intrinsic).
* Wrist and elbow: the seed's elbow is a one-dof hinge ("a ginglymus or hinge
  joint which is a one-DOF joint", ch. 2.4.2) and its wrist has three dofs
  (ch. 3.1: "three DOFs wrist motion (two DOFs from the accelerometer, and one
  DOF from the OLE)"), so forearm pronation, our elbow's second dof, is the
  seed wrist's first: ``<side>_wrist_pronation``, about the forearm's long
  axis, then our wrist flexion and deviation. That is also the seed's D-H arm
  (ch. 4.3, :mod:`bodynet.kinematics.dh_arm`): theta4, the forearm roll, before
  the wrist's theta5 and theta6. The axis runs through both the elbow and the
  wrist centres, so the hand is unchanged; the seed's forearm link is our
  forearm before its pronation (the ulna, which does not roll), so its
  orientation is ours turned back by the pronation angle about its long axis.
* Ankle: three dofs against our two. The seed names none; ours come first
  (flexion, inversion) and the third is ``<side>_ankle_abduction`` (toes away
  from the midline, about the foot's vertical axis). Neither suit observes it:
  :meth:`SeedBody.q_from_ours` sets it to 0 and :meth:`SeedBody.ours_from_q`
  drops it.

The count, eq. 24 with the pelvis as the fixed base: ``F = 6 N - sum(i j_i) =
6*16 - 3*12 - 5*4 = 40`` (twelve 3-dof joints: shoulders, wrists, hips, ankles,
lower and upper trunk, neck, head; four hinges: elbows, knees). The seed's root
node carries "a rotation and translation on the reference frame" and "other
nodes have only the relative rotation for their parent" (ch. 4.4), so the
pelvis is a free-flyer outside the 40, as in :class:`~bodynet.kinematics.model.BodyModel`:
``q = [root position (3), root quaternion x, y, z, w (4), 40 angles in rad]``.
Each dof is one ``JointModelRevoluteUnaligned``. The seed's "joint angle
limitation" per node becomes Pinocchio's position limits, from our
:data:`~bodynet.core.skeleton.ROM_DEG` for the dofs that carry over unchanged.

The mapping from our 32 angles. Limb dofs carry over (pronation moves to the
wrist). Our lumbar rotation ``R`` is shared equally by the lower and upper
trunk joints, and our neck rotation by the neck and head joints: each gets the
half rotation ``H = exp(log(R) / 2)`` (``from_rotvec(rotvec / 2)``), so
``H H = R`` and the thorax and the head turn exactly as ours; ``H`` is split
into the joint's three dofs by scipy's intrinsic Euler conversion in the joint's
axis order. The inverse composes the two joints' rotations back, so it is exact
for any seed posture; a seed posture whose two halves differ has the same
thorax and head but a different spine curve, which ours cannot show.

Frames: world and segment frames are ours (+X forward, +Y left, +Z up; the
seed's Xw forward, Yw up is ``R_OURS_SEED`` of :mod:`~bodynet.kinematics.dh_arm`
away), each segment's frame at its proximal joint centre. At the neutral pose
(all zero) every segment is aligned with the world, the pelvis and limb
segments sit where ours do, the seed's abdomen and neck link sit at our
thorax's and head's origins, and its thorax and head a fraction up those
segments' long axes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.skeleton import Dof, Joint, Skeleton, Vec3, build_skeleton, rom
from bodynet.core.subject import Profile
from bodynet.kinematics.model import ROOT_NQ, BodyModel

SIDES = ("left", "right")

#: Share of our thorax length (lumbar joint to neck) given to the seed's
#: abdomen, the lower trunk link: the lumbar spine (L1-L5, about 18 cm in an
#: adult) against the thoracic (T1-T12, about 28 cm), about two fifths. The
#: seed gives no trunk lengths; this only places the upper trunk joint.
LOWER_TRUNK_FRACTION = 0.4
#: Share of our head length (neck joint to the top of the head) given to the
#: seed's neck link, from the neck joint to the head joint at the skull's base
#: (atlanto-occipital, about ear height; vertex to ear canal is about 13 cm in
#: an adult, roughly half).
NECK_FRACTION = 0.5

#: The split joints: seed joint pairs that share one of our joints equally.
SPLITS: Mapping[str, tuple[str, str]] = MappingProxyType(
    {"lumbar": ("lower_trunk", "upper_trunk"), "neck": ("neck", "head")}
)


def _sequence(dofs: Sequence[Dof]) -> tuple[str, np.ndarray]:
    """scipy's intrinsic Euler sequence (e.g. ``"YXZ"``) and the sign of each dof,
    for dofs about signed coordinate axes: ``R = from_euler(seq, signs * angles)``."""
    letters, signs = "", []
    for dof in dofs:
        axis = np.array(dof.axis, dtype=float)
        k = int(np.argmax(np.abs(axis)))
        if abs(abs(axis[k]) - 1.0) > 1e-12 or np.count_nonzero(axis) != 1:
            raise ValueError(f"{dof.name}: axis {dof.axis} is not a coordinate axis")
        letters += "XYZ"[k]
        signs.append(float(np.sign(axis[k])))
    return letters, np.array(signs)


def joint_rotation(dofs: Sequence[Dof], angles_deg: Sequence[float]) -> Rotation:
    """The rotation of a joint whose dofs are ``dofs``, at ``angles_deg``."""
    seq, signs = _sequence(dofs)
    return Rotation.from_euler(seq, signs * np.asarray(angles_deg, dtype=float), degrees=True)


def joint_angles(dofs: Sequence[Dof], rotation: Rotation) -> np.ndarray:
    """The inverse of :func:`joint_rotation` (deg; the middle angle within 90)."""
    seq, signs = _sequence(dofs)
    return np.asarray(signs * rotation.as_euler(seq, degrees=True), dtype=float)


def half_rotation(rotation: Rotation) -> Rotation:
    """``H`` with ``H * H == rotation``, about the same axis (angle up to 180 degrees)."""
    return Rotation.from_rotvec(rotation.as_rotvec() / 2.0)


def _on(offset: Vec3, dz: float) -> Vec3:
    """``offset`` moved down a parent's long axis by ``dz`` (the parent's origin moved up)."""
    return (offset[0], offset[1], offset[2] - dz)


def seed_joints(
    skeleton: Skeleton,
    lower_trunk_fraction: float = LOWER_TRUNK_FRACTION,
    neck_fraction: float = NECK_FRACTION,
) -> tuple[Joint, ...]:
    """The seed's 16 joints in tree order, from our skeleton's (offsets in the
    seed parent's frame): lower and upper trunk, neck, head, then each side's
    shoulder, elbow, wrist, hip, knee, ankle."""
    L = skeleton.lengths
    lumbar, neck = skeleton.joint("lumbar"), skeleton.joint("neck")
    abdomen = lower_trunk_fraction * L["thorax"]
    neck_link = neck_fraction * L["head"]
    joints = [
        Joint("lower_trunk", "pelvis", "abdomen", lumbar.offset, lumbar.dofs),
        Joint("upper_trunk", "abdomen", "thorax", (0.0, 0.0, abdomen), lumbar.dofs),
        Joint("neck", "thorax", "neck", _on(neck.offset, abdomen), neck.dofs),
        Joint("head", "neck", "head", (0.0, 0.0, neck_link), neck.dofs),
    ]
    for side in SIDES:
        shoulder, elbow, wrist, hip, knee, ankle = (
            skeleton.joint(f"{side}_{j}")
            for j in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")
        )
        flexion, pronation = elbow.dofs
        toes_out = Dof("abduction", (0.0, 0.0, 1.0 if side == "left" else -1.0))
        joints += [
            Joint(shoulder.name, "thorax", shoulder.child, _on(shoulder.offset, abdomen),
                  shoulder.dofs),
            Joint(elbow.name, elbow.parent, elbow.child, elbow.offset, (flexion,)),
            Joint(wrist.name, wrist.parent, wrist.child, wrist.offset, (pronation, *wrist.dofs)),
            hip,
            knee,
            Joint(ankle.name, ankle.parent, ankle.child, ankle.offset, (*ankle.dofs, toes_out)),
        ]  # fmt: skip
    return tuple(joints)


def _our_name(seed_name: str) -> str | None:
    """Our angle carried over into the seed's ``seed_name`` unchanged, if any."""
    if seed_name.endswith("_wrist_pronation_deg"):
        return seed_name.replace("_wrist_", "_elbow_")
    if seed_name.endswith("_ankle_abduction_deg") or seed_name.startswith(
        ("lower_trunk_", "upper_trunk_", "neck_", "head_")
    ):
        return None
    return seed_name


class SeedBody:
    """The seed's 40-dof hierarchical model, with the map from and to our 32 angles.

    ``segments`` are the pelvis and the 16 moving links in tree order;
    ``dof_names`` the 40 angles (``<joint>_<dof>_deg``) in ``q`` order. The
    seed's ``neck_*`` and ``head_*`` angles are each half of our ``neck_*``
    rotation, not the same angles.
    """

    def __init__(
        self,
        skeleton: Skeleton | None = None,
        lower_trunk_fraction: float = LOWER_TRUNK_FRACTION,
        neck_fraction: float = NECK_FRACTION,
    ) -> None:
        self.skeleton = skeleton or build_skeleton()
        self.joints = seed_joints(self.skeleton, lower_trunk_fraction, neck_fraction)
        # the same Pinocchio chain as ours (free root, one revolute joint per dof, a
        # frame per segment), built from the seed's joints
        self.chain = BodyModel(Skeleton(self.skeleton.lengths, self.joints,
                                        self.skeleton.directions))  # fmt: skip
        self.model, self.data = self.chain.model, self.chain.data
        self.segments: tuple[str, ...] = self.chain.skeleton.segments
        self.segment_frames: dict[str, int] = self.chain.segment_frames
        self.dof_names: tuple[str, ...] = self.chain.angle_names
        for i, name in enumerate(self.dof_names, start=ROOT_NQ):
            ours = _our_name(name)
            if ours is not None:
                lo, hi = rom(ours)
                self.model.lowerPositionLimit[i] = math.radians(lo)
                self.model.upperPositionLimit[i] = math.radians(hi)
        self._ours = self.skeleton.angle_names()
        self._joint = {j.name: j for j in self.joints}

    @classmethod
    def for_profile(cls, profile: Profile) -> SeedBody:
        """The model with the subject's segment lengths."""
        return cls(build_skeleton(profile.lengths))

    @property
    def nq(self) -> int:
        return self.chain.nq

    def q(
        self,
        seed_angles_deg: Mapping[str, float],
        root_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        root_position: Vec3 | None = None,
    ) -> np.ndarray:
        """Configuration from the seed's own angles (by :attr:`dof_names`; others 0),
        the root at standing height unless ``root_position`` is given."""
        return self.chain.q(seed_angles_deg, root_position, root_xyzw)

    def angles_deg(self, q: np.ndarray) -> dict[str, float]:
        """The seed's 40 angles (deg) at ``q``."""
        return self.chain.angles_deg(q)

    def q_from_ours(
        self,
        angles_deg: Mapping[str, float],
        root_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
        root_position: Vec3 | None = None,
    ) -> np.ndarray:
        """The seed's configuration for our joint angles (names of
        :meth:`Skeleton.angle_names`, missing ones 0; an unknown name is a
        ``KeyError``) and root: limbs carried over, our elbow pronation as the
        wrist's first dof, ankle abduction 0, lumbar and neck halved."""
        unknown = set(angles_deg) - set(self._ours)
        if unknown:
            raise KeyError(f"not joint angles of our skeleton: {sorted(unknown)}")
        seed: dict[str, float] = {}
        for name in self.dof_names:
            ours = _our_name(name)
            if ours is not None:
                seed[name] = angles_deg.get(ours, 0.0)
        for our_joint, pair in SPLITS.items():
            joint = self.skeleton.joint(our_joint)
            whole = [angles_deg.get(n, 0.0) for n in joint.angle_names()]
            half = half_rotation(joint_rotation(joint.dofs, whole))
            for seed_joint in pair:
                sj = self._joint[seed_joint]
                angles = joint_angles(sj.dofs, half).tolist()
                seed.update(zip(sj.angle_names(), angles, strict=True))
        return self.q(seed, root_xyzw, root_position)

    def ours_from_q(self, q: np.ndarray) -> dict[str, float]:
        """Our 32 joint angles (deg, skeleton order) at the seed's ``q``: each split
        pair's rotations composed back into one joint; the ankle abduction, which
        ours has not, is dropped. The root is ``q[:7]`` in both models."""
        seed = self.angles_deg(q)
        ours = dict.fromkeys(self._ours, 0.0)
        for name, value in seed.items():
            our = _our_name(name)
            if our is not None:
                ours[our] = value
        for our_joint, (lower, upper) in SPLITS.items():
            parts = [self._joint[lower], self._joint[upper]]
            lo, up = (joint_rotation(j.dofs, [seed[n] for n in j.angle_names()]) for j in parts)
            joint = self.skeleton.joint(our_joint)
            angles = joint_angles(joint.dofs, lo * up).tolist()
            ours.update(zip(joint.angle_names(), angles, strict=True))
        return ours

    def segment_poses(self, q: np.ndarray) -> np.ndarray:
        """World pose of every segment (:attr:`segments` order) at ``q``, as rows of
        position x, y, z and quaternion x, y, z, w (Pinocchio's XYZQUAT)."""
        return self.chain.segment_poses(q)
