"""The body as a tree of segments and joints: pure data, no maths library.

World and segment frames: +X forward, +Y left, +Z up, metres. The zero pose
is anatomical neutral: standing, arms at the sides with palms towards the
thighs (forearm neutral), legs straight, feet forward; every segment frame is
then aligned with the world. Each joint turns its child segment through a
sequence of degrees of freedom about fixed axes of the parent frame (an
intrinsic Euler sequence), signed so that a positive angle is the anatomical
positive direction:

| dof        | positive means                                         |
|------------|--------------------------------------------------------|
| flexion    | flexion (knee: bending; ankle: dorsiflexion)           |
| abduction  | away from the midline                                  |
| rotation   | internal rotation (lumbar, neck: turning to the left)  |
| pronation  | forearm pronation                                      |
| deviation  | radial deviation of the wrist                          |
| inversion  | ankle inversion                                        |
| lateral    | trunk or neck bending to the right                     |

Joint angles are named ``<joint>_<dof>_deg``, e.g. ``left_elbow_flexion_deg``.
The T-pose (for IMU calibration) is neutral with both shoulders abducted 90
degrees: arms horizontal, palms down.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache
from types import MappingProxyType

Vec3 = tuple[float, float, float]

X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def _neg(v: Vec3) -> Vec3:
    return (-v[0], -v[1], -v[2])


@dataclass(frozen=True, slots=True)
class Dof:
    name: str
    axis: Vec3  # unit axis in the parent segment's frame


@dataclass(frozen=True, slots=True)
class Joint:
    """A joint: where it sits on its parent segment, and its dofs in order."""

    name: str
    parent: str
    child: str
    offset: Vec3  # joint centre in the parent segment's frame at zero pose
    dofs: tuple[Dof, ...]

    def angle_names(self) -> tuple[str, ...]:
        return tuple(f"{self.name}_{d.name}_deg" for d in self.dofs)


#: Segment lengths (m). Upper arm and forearm from subject 1 of the 000 seed's
#: Table 5.1; the rest in proportion for a 1.70 m adult (Winter's ratios).
DEFAULT_LENGTHS: Mapping[str, float] = MappingProxyType(
    {
        "upperarm": 0.293,
        "forearm": 0.265,
        "hand": 0.184,
        "thigh": 0.417,
        "shank": 0.418,
        "foot": 0.258,
        "ankle_height": 0.066,
        "pelvis": 0.104,  # hip centres to the lumbar joint
        "thorax": 0.416,  # lumbar joint to the neck
        "head": 0.222,  # neck to the top of the head
        "shoulder_width": 0.44,  # between the shoulder joint centres
        "shoulder_drop": 0.06,  # shoulder joint centres below the neck
        "hip_width": 0.17,  # between the hip joint centres
    }
)


@dataclass(frozen=True, slots=True)
class Skeleton:
    """Segments rooted at the pelvis, and the joints between them."""

    lengths: Mapping[str, float]
    joints: tuple[Joint, ...]
    #: Direction of each segment's long axis, from its joint towards its end.
    directions: Mapping[str, Vec3] = field(default_factory=dict)

    @property
    def segments(self) -> tuple[str, ...]:
        return ("pelvis", *(j.child for j in self.joints))

    def joint(self, name: str) -> Joint:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(name)

    def angle_names(self) -> tuple[str, ...]:
        return tuple(n for j in self.joints for n in j.angle_names())

    def segment_chains(self) -> dict[str, tuple[str, ...]]:
        """Every angle name on the chain from the pelvis to each segment (the
        pelvis: none). The segment's world orientation rests on all of them, and
        the place of every joint centre on it (where its children hang) too: a
        number drawn from any of them while one is unmeasured is no measurement."""
        parent_joint = {j.child: j for j in self.joints}
        chains: dict[str, tuple[str, ...]] = {}
        for segment in self.segments:
            names: list[str] = []
            s = segment
            while s in parent_joint:
                names.extend(parent_joint[s].angle_names())
                s = parent_joint[s].parent
            chains[segment] = tuple(names)
        return chains

    def segment_length(self, segment: str) -> float:
        kind = segment.split("_", 1)[-1]
        return self.lengths.get(kind, 0.0)

    def root_height(self) -> float:
        """Height of the hip centres above the floor at zero pose."""
        return self.lengths["thigh"] + self.lengths["shank"] + self.lengths["ankle_height"]


def _limb_joints(side: str, lengths: Mapping[str, float]) -> list[Joint]:
    s = 1.0 if side == "left" else -1.0
    lat = (s, 0.0, 0.0)  # left abduction is about +X, right about -X
    down = _neg(Z)
    rot = down if side == "left" else Z  # internal rotation about the long axis
    L = lengths
    return [
        Joint(f"{side}_shoulder", "thorax", f"{side}_upperarm",
              (0.0, s * L["shoulder_width"] / 2, L["thorax"] - L["shoulder_drop"]),
              (Dof("flexion", _neg(Y)), Dof("abduction", lat), Dof("rotation", rot))),
        Joint(f"{side}_elbow", f"{side}_upperarm", f"{side}_forearm", (0.0, 0.0, -L["upperarm"]),
              (Dof("flexion", _neg(Y)), Dof("pronation", rot))),
        Joint(f"{side}_wrist", f"{side}_forearm", f"{side}_hand", (0.0, 0.0, -L["forearm"]),
              (Dof("flexion", _neg(lat)), Dof("deviation", _neg(Y)))),
        Joint(f"{side}_hip", "pelvis", f"{side}_thigh", (0.0, s * L["hip_width"] / 2, 0.0),
              (Dof("flexion", _neg(Y)), Dof("abduction", lat), Dof("rotation", rot))),
        Joint(f"{side}_knee", f"{side}_thigh", f"{side}_shank", (0.0, 0.0, -L["thigh"]),
              (Dof("flexion", Y),)),
        Joint(f"{side}_ankle", f"{side}_shank", f"{side}_foot", (0.0, 0.0, -L["shank"]),
              (Dof("flexion", _neg(Y)), Dof("inversion", _neg(lat)))),
    ]  # fmt: skip


def build_skeleton(lengths: Mapping[str, float] | None = None) -> Skeleton:
    """The full body for the given segment lengths (defaults fill the gaps)."""
    L = dict(DEFAULT_LENGTHS)
    L.update(lengths or {})
    spine = (Dof("flexion", Y), Dof("lateral", X), Dof("rotation", Z))
    joints = [
        Joint("lumbar", "pelvis", "thorax", (0.0, 0.0, L["pelvis"]), spine),
        Joint("neck", "thorax", "head", (0.0, 0.0, L["thorax"]), spine),
        *_limb_joints("left", L),
        *_limb_joints("right", L),
    ]
    directions: dict[str, Vec3] = {"pelvis": Z, "thorax": Z, "head": Z}
    for side in ("left", "right"):
        for seg in ("upperarm", "forearm", "hand", "thigh", "shank"):
            directions[f"{side}_{seg}"] = _neg(Z)
        directions[f"{side}_foot"] = X
    return Skeleton(MappingProxyType(L), tuple(joints), MappingProxyType(directions))


#: The joints of each part of the body, from the trunk outwards (a limb's
#: without its side: ``elbow`` is ``left_elbow`` on the left arm). The parts
#: are the branches of the body bus (``core/keys.py``): the trunk and each limb.
PART_JOINTS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {"trunk": ("lumbar", "neck"), "arm": ("shoulder", "elbow", "wrist"),
     "leg": ("hip", "knee", "ankle")}
)  # fmt: skip


@cache
def part(limb: str, side: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The joints and segments of one part of the body: ``part("arm", "left")``
    is the left shoulder, elbow and wrist and the segments they turn; the
    trunk (``part("trunk", "mid")``) also holds the root, the pelvis."""
    joints = tuple(j if limb == "trunk" else f"{side}_{j}" for j in PART_JOINTS[limb])
    child = {j.name: j.child for j in build_skeleton().joints}
    root = ("pelvis",) if limb == "trunk" else ()
    return joints, (*root, *(child[j] for j in joints))


#: The seven dofs of an arm, shoulder to hand (``<joint>_<dof>``, either side).
ARM_DOFS = (
    "shoulder_flexion",
    "shoulder_abduction",
    "shoulder_rotation",
    "elbow_flexion",
    "elbow_pronation",
    "wrist_flexion",
    "wrist_deviation",
)

#: Joint angles (deg) of the T-pose, the IMU calibration pose.
TPOSE: Mapping[str, float] = MappingProxyType(
    {"left_shoulder_abduction_deg": 90.0, "right_shoulder_abduction_deg": 90.0}
)


#: Joint angles (deg) of the N-pose (standing neutral: arms down, palms to the
#: thighs), the other calibration pose: the skeleton's zero pose.
NPOSE: Mapping[str, float] = MappingProxyType({})

#: The calibration poses by name.
CALIBRATION_POSES: Mapping[str, Mapping[str, float]] = MappingProxyType(
    {"tpose": TPOSE, "npose": NPOSE}
)


#: Range of motion (deg) of each dof kind: typical adult limits, used to keep
#: emulated motion plausible and to clamp and flag measured angles.
ROM_DEG: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        "shoulder_flexion": (-50, 180), "shoulder_abduction": (-30, 180),
        "shoulder_rotation": (-90, 90), "elbow_flexion": (-5, 150),
        "elbow_pronation": (-90, 90), "wrist_flexion": (-70, 80), "wrist_deviation": (-30, 20),
        "hip_flexion": (-30, 120), "hip_abduction": (-30, 45), "hip_rotation": (-45, 45),
        "knee_flexion": (-5, 140), "ankle_flexion": (-50, 20), "ankle_inversion": (-20, 35),
        "lumbar_flexion": (-30, 80), "lumbar_lateral": (-35, 35), "lumbar_rotation": (-45, 45),
        "neck_flexion": (-60, 50), "neck_lateral": (-45, 45), "neck_rotation": (-80, 80),
    }
)  # fmt: skip


def rom(angle_name: str) -> tuple[float, float]:
    """Range of motion of a joint angle such as ``left_elbow_flexion_deg``."""
    stem = angle_name.removesuffix("_deg").removeprefix("left_").removeprefix("right_")
    return ROM_DEG[stem]
