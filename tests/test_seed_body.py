"""The seed's 40-DOF hierarchical model (kinematics/seed_body.py) against our body model.

Both are real Pinocchio models, compared in the world frame for random poses
within our range of motion and random root orientations: segment orientations,
the hands and feet from their shoulder and hip centres, the angle mapping both
ways, the neutral pose, and the equal sharing of the lumbar and neck rotations.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bodynet.core.skeleton import build_skeleton, rom
from bodynet.core.subject import Profile
from bodynet.kinematics.model import BodyModel
from bodynet.kinematics.seed_body import (
    LOWER_TRUNK_FRACTION,
    NECK_FRACTION,
    SIDES,
    SeedBody,
    joint_rotation,
)

SKELETON = build_skeleton()
BODY = BodyModel(SKELETON)
SEED = SeedBody(SKELETON)
L = SKELETON.lengths
TOL = 1e-9

OUR_POSES = st.fixed_dictionaries(
    {n: st.floats(*rom(n), allow_nan=False) for n in SKELETON.angle_names()}
)
ROOTS = st.tuples(*[st.floats(-2.0, 2.0)] * 3).map(
    lambda v: tuple(Rotation.from_rotvec(v).as_quat())
)


def poses(names: tuple[str, ...], rows: np.ndarray) -> dict[str, pin.SE3]:
    return {n: pin.XYZQUATToSE3(r) for n, r in zip(names, rows, strict=True)}


def both(angles: dict[str, float], root: tuple[float, ...]) -> tuple[dict, dict]:
    """World poses of every segment by name: (ours, the seed's) for our ``angles``."""
    ours = poses(SKELETON.segments, BODY.segment_poses(BODY.q(angles, root_quat_xyzw=root)))
    seed = poses(SEED.segments, SEED.segment_poses(SEED.q_from_ours(angles, root)))
    return ours, seed


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(pin.log3(a.T @ b)))


def pronation_roll(side: str, angles: dict[str, float]) -> np.ndarray:
    """Our forearm's roll about its long axis by the pronation angle."""
    axis = np.array(SKELETON.joint(f"{side}_elbow").dofs[1].axis)
    return Rotation.from_rotvec(axis * np.radians(angles.get(f"{side}_elbow_pronation_deg", 0.0)))


# -- the count (eq. 24) -------------------------------------------------------


def test_forty_dofs_on_sixteen_moving_links() -> None:
    assert SEED.model.nv == 40 + 6
    assert SEED.nq == 40 + 7  # the free root's quaternion
    assert len(SEED.dof_names) == 40
    moving = [s for s in SEED.segments if s != "pelvis"]
    assert len(moving) == 16
    by_dofs = Counter(len(j.dofs) for j in SEED.joints)
    assert by_dofs == {3: 12, 1: 4}
    # Kutzbach, pelvis fixed: F = 6 N - sum(i j_i), class i = 6 - f
    f = 6 * len(moving) - sum((6 - len(j.dofs)) for j in SEED.joints)
    assert f == 40 == SEED.model.nv - 6
    three = {j.name.removeprefix("left_").removeprefix("right_")
             for j in SEED.joints if len(j.dofs) == 3}  # fmt: skip
    assert three == {"shoulder", "wrist", "hip", "ankle",
                     "lower_trunk", "upper_trunk", "neck", "head"}  # fmt: skip
    hinges = {j.name for j in SEED.joints if len(j.dofs) == 1}
    assert hinges == {f"{s}_{j}" for s in SIDES for j in ("elbow", "knee")}


def test_dof_names_and_the_pinocchio_joints() -> None:
    names = SEED.dof_names
    assert names[:3] == ("lower_trunk_flexion_deg", "lower_trunk_lateral_deg",
                         "lower_trunk_rotation_deg")  # fmt: skip
    for side in SIDES:
        wrist = [f"{side}_wrist_{d}_deg" for d in ("pronation", "flexion", "deviation")]
        i = names.index(wrist[0])
        assert list(names[i : i + 3]) == wrist  # pronation is the wrist's first dof
        assert f"{side}_ankle_abduction_deg" in names
        assert f"{side}_elbow_pronation_deg" not in names
    # one revolute joint per dof, in q order after the root
    assert list(SEED.model.names)[2:] == [n.removesuffix("_deg") for n in names]
    assert SEED.segments[:5] == ("pelvis", "abdomen", "thorax", "neck", "head")


def test_limits_are_our_range_of_motion_where_a_dof_carries_over() -> None:
    lo, hi = SEED.model.lowerPositionLimit, SEED.model.upperPositionLimit
    i = {n: 7 + k for k, n in enumerate(SEED.dof_names)}
    for seed, ours in (("left_elbow_flexion_deg", "left_elbow_flexion_deg"),
                       ("right_wrist_pronation_deg", "right_elbow_pronation_deg"),
                       ("left_ankle_inversion_deg", "left_ankle_inversion_deg")):  # fmt: skip
        assert (lo[i[seed]], hi[i[seed]]) == pytest.approx(np.radians(rom(ours)))
    for free in ("lower_trunk_flexion_deg", "head_rotation_deg", "left_ankle_abduction_deg"):
        assert hi[i[free]] > 1e300  # a half, or not ours: no bound from our range


# -- against our body model ---------------------------------------------------


@given(OUR_POSES, ROOTS)
def test_segment_orientations_equal_ours(angles: dict[str, float], root: tuple) -> None:
    ours, seed = both(angles, root)
    for name in ours:
        if name.endswith("forearm"):
            continue
        assert angle_between(ours[name].rotation, seed[name].rotation) < TOL, name
    for side in SIDES:
        # the seed's forearm does not pronate (its wrist does): ours turned back
        back = ours[f"{side}_forearm"].rotation @ pronation_roll(side, angles).inv().as_matrix()
        assert angle_between(back, seed[f"{side}_forearm"].rotation) < TOL


@given(OUR_POSES, ROOTS)
def test_hands_and_feet_from_their_shoulders_and_hips_equal_ours(
    angles: dict[str, float], root: tuple
) -> None:
    ours, seed = both(angles, root)
    for side in SIDES:
        for end, base, tip in (("hand", "upperarm", (0, 0, -L["hand"])),
                               ("foot", "thigh", (L["foot"], 0, 0))):  # fmt: skip
            e, b = f"{side}_{end}", f"{side}_{base}"  # b's origin: the shoulder or hip centre
            for point in (np.zeros(3), np.array(tip, dtype=float)):
                mine = ours[e].act(point) - ours[b].translation
                theirs = seed[e].act(point) - seed[b].translation
                assert np.linalg.norm(mine - theirs) < TOL
            # the hips sit on the pelvis in both, so the feet agree in the world too
            if end == "foot":
                assert np.linalg.norm(ours[e].translation - seed[e].translation) < TOL


@given(OUR_POSES, ROOTS)
def test_our_angles_round_trip(angles: dict[str, float], root: tuple) -> None:
    q = SEED.q_from_ours(angles, root)
    assert q[3:7] == pytest.approx(root, abs=0)
    back = SEED.ours_from_q(q)
    assert list(back) == list(SKELETON.angle_names())
    for name, value in angles.items():
        assert back[name] == pytest.approx(value, abs=1e-9), name


@given(OUR_POSES)
def test_each_pair_shares_our_rotation_in_equal_halves(angles: dict[str, float]) -> None:
    seed = SEED.angles_deg(SEED.q_from_ours(angles))
    for ours, (first, second) in (("lumbar", ("lower_trunk", "upper_trunk")),
                                  ("neck", ("neck", "head"))):  # fmt: skip
        joint = SKELETON.joint(ours)
        whole = joint_rotation(joint.dofs, [angles[n] for n in joint.angle_names()])
        halves = []
        for j in (first, second):
            sj = next(x for x in SEED.joints if x.name == j)
            halves.append(joint_rotation(sj.dofs, [seed[n] for n in sj.angle_names()]))
        assert halves[0].approx_equal(halves[1], atol=TOL)
        assert np.allclose(halves[0].as_rotvec(), whole.as_rotvec() / 2, atol=TOL)
        assert (halves[0] * halves[1]).approx_equal(whole, atol=TOL)
        assert seed[f"{first}_flexion_deg"] == pytest.approx(seed[f"{second}_flexion_deg"])


def test_a_pure_lumbar_flexion_of_40_is_20_at_each_trunk_joint() -> None:
    seed = SEED.angles_deg(SEED.q_from_ours({"lumbar_flexion_deg": 40.0}))
    assert seed["lower_trunk_flexion_deg"] == pytest.approx(20.0, abs=1e-12)
    assert seed["upper_trunk_flexion_deg"] == pytest.approx(20.0, abs=1e-12)
    rest = {n: v for n, v in seed.items() if "trunk_flexion" not in n}
    assert all(abs(v) < 1e-12 for v in rest.values())
    seed = SEED.angles_deg(SEED.q_from_ours({"neck_rotation_deg": 60.0}))
    assert seed["neck_rotation_deg"] == pytest.approx(30.0)
    assert seed["head_rotation_deg"] == pytest.approx(30.0)


def test_neutral_puts_every_segment_where_ours_is() -> None:
    ours, seed = both({}, (0.0, 0.0, 0.0, 1.0))
    for name, pose in seed.items():
        assert pose.rotation == pytest.approx(np.eye(3), abs=TOL), name
    for name in ours:
        if name not in ("thorax", "head"):
            assert seed[name].translation == pytest.approx(ours[name].translation, abs=TOL), name
    up = np.array([0.0, 0.0, 1.0])
    # the seed's abdomen and neck link start at our thorax and head, its thorax
    # and head a fraction of the way up them
    assert seed["abdomen"].translation == pytest.approx(ours["thorax"].translation, abs=TOL)
    assert seed["neck"].translation == pytest.approx(ours["head"].translation, abs=TOL)
    thorax = ours["thorax"].translation + up * LOWER_TRUNK_FRACTION * L["thorax"]
    head = ours["head"].translation + up * NECK_FRACTION * L["head"]
    assert seed["thorax"].translation == pytest.approx(thorax, abs=TOL)
    assert seed["head"].translation == pytest.approx(head, abs=TOL)
    assert SEED.q_from_ours({}) == pytest.approx(BODY.q({})[:7].tolist() + [0.0] * 40, abs=0)


SEED_ANGLES = st.fixed_dictionaries(
    {n: st.floats(-40.0, 40.0) for n in SEED.dof_names if "ankle_abduction" not in n}
)


@given(SEED_ANGLES, ROOTS)
def test_any_seed_posture_maps_to_ours_with_the_same_thorax_head_and_limbs(
    seed_angles: dict[str, float], root: tuple
) -> None:
    # unequal halves too: ours_from_q composes them, so the thorax and head agree
    q = SEED.q(seed_angles, root)
    seed = poses(SEED.segments, SEED.segment_poses(q))
    angles = SEED.ours_from_q(q)
    ours = poses(SKELETON.segments, BODY.segment_poses(BODY.q(angles, root_quat_xyzw=root)))
    for name in ours:
        if not name.endswith("forearm"):
            assert angle_between(ours[name].rotation, seed[name].rotation) < TOL, name


def test_unequal_halves_move_the_shoulders() -> None:
    # the same thorax orientation from (40, 0) as from (20, 20), shoulders elsewhere
    def shoulder(lower: float, upper: float) -> np.ndarray:
        q = SEED.q({"lower_trunk_flexion_deg": lower, "upper_trunk_flexion_deg": upper})
        p = poses(SEED.segments, SEED.segment_poses(q))
        assert angle_between(p["thorax"].rotation, Rotation.from_euler(
            "y", 40, degrees=True).as_matrix()) < TOL  # fmt: skip
        return p["left_upperarm"].translation

    assert np.linalg.norm(shoulder(40, 0) - shoulder(20, 20)) > 0.01
    assert SEED.ours_from_q(SEED.q({"lower_trunk_flexion_deg": 40.0}))[
        "lumbar_flexion_deg"
    ] == pytest.approx(40.0)


def test_ankle_abduction_is_zero_from_ours_and_dropped_back() -> None:
    q = SEED.q_from_ours({"left_ankle_flexion_deg": 10.0})
    seed = SEED.angles_deg(q)
    assert seed["left_ankle_abduction_deg"] == 0.0
    assert seed["left_ankle_flexion_deg"] == pytest.approx(10.0)
    q = SEED.q({"left_ankle_abduction_deg": 15.0})
    assert all(v == 0.0 for v in SEED.ours_from_q(q).values())


def test_unknown_names_are_refused() -> None:
    with pytest.raises(KeyError, match="left_wrist_pronation_deg"):
        SEED.q_from_ours({"left_wrist_pronation_deg": 10.0})  # a seed name, not ours


def test_subject_lengths_from_the_profile() -> None:
    lengths = {"thorax": 0.5, "head": 0.3, "upperarm": 0.31}
    seed = SeedBody.for_profile(Profile(lengths=lengths))
    p = poses(seed.segments, seed.segment_poses(seed.q_from_ours({})))
    assert p["thorax"].translation[2] - p["abdomen"].translation[2] == pytest.approx(
        LOWER_TRUNK_FRACTION * 0.5
    )
    assert p["head"].translation[2] - p["neck"].translation[2] == pytest.approx(NECK_FRACTION * 0.3)
    elbow = p["left_forearm"].translation - p["left_upperarm"].translation
    assert elbow == pytest.approx([0, 0, -0.31])
    body = BodyModel(build_skeleton(lengths))
    ours = poses(body.skeleton.segments, body.segment_poses(body.q({})))
    for name in ("left_upperarm", "left_hand", "right_foot"):
        assert p[name].translation == pytest.approx(ours[name].translation, abs=TOL)
