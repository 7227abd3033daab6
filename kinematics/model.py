"""The body model in Pinocchio, built from a :class:`~bodynet.core.skeleton.Skeleton`.

Model (constant) and Data (working memory) are kept apart as Pinocchio does.
The root is a free-flyer at the pelvis; every dof of the skeleton is one
revolute joint about its (unaligned) axis, so ``q = [root position (3), root
quaternion x, y, z, w (4), joint angles in rad (skeleton order)]``. Each segment
gets a frame at its joint centre, and each sensor site a frame where it sits.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pinocchio as pin

from bodynet.core.skeleton import Skeleton, Vec3

ROOT_NQ = 7


@dataclass(frozen=True, slots=True)
class SiteMount:
    """A sensor site on a segment: ``fraction`` of the segment's length along it."""

    name: str
    segment: str
    fraction: float = 0.5


class BodyModel:
    """Forward kinematics of a skeleton, with frames for segments and sites."""

    def __init__(self, skeleton: Skeleton, sites: Sequence[SiteMount] = ()) -> None:
        self.skeleton = skeleton
        model = pin.Model()
        model.name = "bodynet"
        root = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "root")
        segment_joint = {"pelvis": root}
        for joint in skeleton.joints:
            parent = segment_joint[joint.parent]
            placement = pin.SE3(np.eye(3), np.array(joint.offset))
            for dof in joint.dofs:
                axis = np.array(dof.axis, dtype=float)
                parent = model.addJoint(
                    parent,
                    pin.JointModelRevoluteUnaligned(axis),
                    placement,
                    f"{joint.name}_{dof.name}",
                )
                placement = pin.SE3.Identity()
            segment_joint[joint.child] = parent
        self.segment_frames: dict[str, int] = {}
        for segment, jid in segment_joint.items():
            frame = pin.Frame(segment, jid, pin.SE3.Identity(), pin.FrameType.OP_FRAME)
            self.segment_frames[segment] = model.addFrame(frame)
        self._segment_joints = [segment_joint[s] for s in skeleton.segments]
        # what can touch the floor besides the joint centres (the segments' origins):
        # the far end of each end segment (top of the head, finger tips, toes) and each
        # toe and heel at the sole, an ankle height below the ankle's line (points in
        # their segment's frame)
        sole = np.array([0.0, 0.0, -skeleton.lengths["ankle_height"]])
        ends = ("head", "left_hand", "right_hand", "left_foot", "right_foot")
        points: list[tuple[int, np.ndarray]] = []  # (its segment's joint, point)
        for segment in ends:
            points.append((segment_joint[segment], np.array(skeleton.directions[segment])
                           * skeleton.segment_length(segment)))  # fmt: skip
        for side in ("left", "right"):
            foot = segment_joint[f"{side}_foot"]
            tip = np.array(skeleton.directions[f"{side}_foot"]) * skeleton.segment_length("foot")
            points += [(foot, sole), (foot, tip + sole)]
        self._floor_joints = np.array([j for j, _ in points], dtype=np.int64)
        self._floor_xyz = np.array([p for _, p in points])
        self.site_frames: dict[str, int] = {}
        for site in sites:
            direction = np.array(skeleton.directions[site.segment])
            offset = direction * skeleton.segment_length(site.segment) * site.fraction
            frame = pin.Frame(
                site.name,
                segment_joint[site.segment],
                pin.SE3(np.eye(3), offset),
                pin.FrameType.OP_FRAME,
            )
            self.site_frames[site.name] = model.addFrame(frame)
        self.model = model
        self.data = model.createData()
        self.angle_names = skeleton.angle_names()
        self._index = {name: ROOT_NQ + i for i, name in enumerate(self.angle_names)}

    @property
    def nq(self) -> int:
        return int(self.model.nq)

    def q(
        self,
        angles_deg: Mapping[str, float],
        root_position: Vec3 | None = None,
        root_quat_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    ) -> np.ndarray:
        """Configuration vector from named joint angles (others stay 0)."""
        q = np.zeros(self.nq)
        q[:3] = root_position if root_position is not None else (0, 0, self.skeleton.root_height())
        q[3:7] = root_quat_xyzw
        for name, value in angles_deg.items():
            q[self._index[name]] = math.radians(value)
        return q

    def angles_deg(self, q: np.ndarray) -> dict[str, float]:
        return {n: math.degrees(q[i]) for n, i in self._index.items()}

    def frame_placements(
        self, q: np.ndarray, frames: Sequence[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (n, 3, 3) and positions (n, 3) of ``frames`` at ``q``."""
        pin.framesForwardKinematics(self.model, self.data, q)
        placements = self.data.oMf.tolist()  # one call, as in segment_poses
        rotations = np.array([placements[f].rotation for f in frames])
        positions = np.array([placements[f].translation for f in frames])
        return rotations, positions

    def segment_poses(self, q: np.ndarray) -> np.ndarray:
        """World pose of every segment (skeleton order) at ``q``, as rows of position
        x, y, z and quaternion x, y, z, w (Pinocchio's XYZQUAT). A segment's frame
        sits on its last dof's joint, so plain forward kinematics gives it."""
        pin.forwardKinematics(self.model, self.data, q)
        placements = self.data.oMi.tolist()  # one call: indexing oMi costs 0.6 us each
        return np.array([pin.SE3ToXYZQUAT(placements[j]) for j in self._segment_joints])

    @cached_property
    def chain(self) -> Chain:
        """The model's revolute joints as arrays, for forward kinematics of many
        bodies in one compiled pass (``gateway.kernels.forward_poses``), read from
        the Pinocchio model: joint ``r`` is Pinocchio's joint ``r + 2`` (1 is the
        root, -1 here) and angle ``r`` of ``q``."""
        model = self.model
        revolute = range(2, model.njoints)
        return Chain(
            parents=np.array([model.parents[j] - 2 for j in revolute], dtype=np.int64),
            axes=np.array([model.joints[j].extract().axis for j in revolute]),
            offsets=np.array([model.jointPlacements[j].translation for j in revolute]),
            root_z=self.skeleton.root_height(),
            segment_joints=np.array(self._segment_joints, dtype=np.int64) - 2,
            floor_joints=self._floor_joints - 2,
            floor_points=self._floor_xyz,
        )


@dataclass(frozen=True, slots=True)
class Chain:
    """:attr:`BodyModel.chain`: a body model's kinematic chain as arrays."""

    parents: np.ndarray  # (joints,) each revolute joint's parent (-1: the root)
    axes: np.ndarray  # (joints, 3) unit axes, in the joint's frame
    offsets: np.ndarray  # (joints, 3) the joint's origin in its parent's frame
    root_z: float  # the root's height at zero pose
    segment_joints: np.ndarray  # (segments,) the joint each segment's frame sits on
    # the points that can touch the floor besides the segments' origins (top of the
    # head, finger tips, heels, toes): each one's joint, and its place in that frame
    floor_joints: np.ndarray  # (points,)
    floor_points: np.ndarray  # (points, 3)


def accel_axes(direction: np.ndarray, flexion_axis: np.ndarray) -> np.ndarray:
    """A SmartSuit accelerometer's axes in its segment frame, as columns: x along
    the segment away from the body, y along the joint's flexion axis, z = x cross y."""
    x = direction / np.linalg.norm(direction)
    y = flexion_axis - x * float(x @ flexion_axis)
    y /= np.linalg.norm(y)
    return np.column_stack([x, y, np.cross(x, y)])
