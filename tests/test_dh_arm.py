"""The seed's 7-DOF D-H arm (kinematics/dh_arm.py) against our anatomical body model.

Both are real Pinocchio models: the D-H chain of RZ joints and the full body of
kinematics/model.py, compared on the elbow and wrist centres and the hand's
orientation, in the world frame, after the D-H base's fixed placement.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bodynet.core.skeleton import ARM_DOFS, build_skeleton, rom
from bodynet.core.subject import Profile
from bodynet.kinematics.dh_arm import (
    R_OURS_SEED,
    SIDES,
    DhArm,
    anatomical_from_dh,
    dh_angles_from_anatomical,
    dh_table,
)
from bodynet.kinematics.model import BodyModel

SKELETON = build_skeleton()
BODY = BodyModel(SKELETON)
ARMS = {side: DhArm(side, SKELETON) for side in SIDES}
LU, LF = SKELETON.lengths["upperarm"], SKELETON.lengths["forearm"]
TOL = 1e-9


def arm_names(side: str) -> list[str]:
    return [f"{side}_{dof}_deg" for dof in ARM_DOFS]


def in_rom(side: str) -> st.SearchStrategy[dict[str, float]]:
    return st.fixed_dictionaries({n: st.floats(*rom(n), allow_nan=False) for n in arm_names(side)})


TORSO = [f"lumbar_{d}_deg" for d in ("flexion", "lateral", "rotation")]
ARM_POSES = st.sampled_from(SIDES).flatmap(lambda s: st.tuples(st.just(s), in_rom(s)))


def body_arm(
    side: str,
    angles: dict[str, float],
    root_quat_xyzw: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0),
) -> tuple[pin.SE3, np.ndarray, np.ndarray, np.ndarray]:
    """From the full-body FK: the thorax pose, elbow and wrist centres, hand rotation."""
    q = BODY.q(angles, root_quat_xyzw=root_quat_xyzw)
    frames = [BODY.segment_frames[s] for s in ("thorax", f"{side}_forearm", f"{side}_hand")]
    rot, pos = BODY.frame_placements(q, frames)
    return pin.SE3(rot[0], pos[0]), pos[1], pos[2], rot[2]


def mismatch(arm: DhArm, angles: dict[str, float], **root: tuple[float, ...]) -> float:
    """Largest difference (m or rad) between the D-H arm and the body model."""
    o_m_thorax, elbow, wrist, hand = body_arm(arm.side, angles, **root)
    dh = {k: o_m_thorax * m for k, m in arm.forward_anatomical(angles).items()}
    return max(
        float(np.linalg.norm(dh["elbow"].translation - elbow)),
        float(np.linalg.norm(dh["wrist"].translation - wrist)),
        float(np.linalg.norm(pin.log3(dh["hand"].rotation.T @ hand))),
    )


@given(ARM_POSES)
def test_equals_the_body_model_with_the_torso_neutral(pose: tuple[str, dict[str, float]]) -> None:
    side, angles = pose
    assert mismatch(ARMS[side], angles) < TOL


@given(
    ARM_POSES,
    st.fixed_dictionaries({n: st.floats(*rom(n)) for n in TORSO}),
    st.tuples(*[st.floats(-2.0, 2.0)] * 3),
)
def test_is_fixed_to_the_thorax_whatever_the_torso(
    pose: tuple[str, dict[str, float]], torso: dict[str, float], root_rotvec: tuple[float, ...]
) -> None:
    side, angles = pose
    root = tuple(Rotation.from_rotvec(root_rotvec).as_quat())
    assert mismatch(ARMS[side], {**angles, **torso}, root_quat_xyzw=root) < TOL


@given(ARM_POSES)
def test_anatomical_angles_round_trip(pose: tuple[str, dict[str, float]]) -> None:
    side, angles = pose
    back = anatomical_from_dh(dh_angles_from_anatomical(angles, side), side)
    assert back.keys() == angles.keys()
    for name, value in angles.items():
        assert back[name] == pytest.approx(value, abs=1e-9)


@given(st.sampled_from(SIDES), st.lists(st.floats(-10.0, 10.0), min_size=7, max_size=7))
def test_dh_angles_round_trip_modulo_a_turn(side: str, theta: list[float]) -> None:
    again = dh_angles_from_anatomical(anatomical_from_dh(theta, side), side)
    turns = (again - np.array(theta)) / (2 * np.pi)
    assert np.allclose(turns, np.round(turns), atol=1e-9)


@pytest.mark.parametrize("side", SIDES)
def test_neutral_hangs_the_arm_straight_down(side: str) -> None:
    arm = ARMS[side]
    theta = arm.theta({})
    assert np.degrees(theta) == pytest.approx([90, 90, 90, 0, 90, 90, 90])
    f = arm.forward(theta)
    base = f["base"]
    # in the seed's frame at the shoulder (Yw up): the elbow L_u, the wrist L_u + L_f below
    assert base.actInv(f["shoulder"].translation) == pytest.approx([0, 0, 0], abs=TOL)
    assert base.actInv(f["elbow"].translation) == pytest.approx([0, -LU, 0], abs=TOL)
    assert base.actInv(f["wrist"].translation) == pytest.approx([0, -(LU + LF), 0], abs=TOL)
    assert base.actInv(f["dh2"].translation) == pytest.approx([0, -LU, 0], abs=TOL)  # elbow too
    for k in ("dh5", "dh6"):
        assert f[k].translation == pytest.approx(f["wrist"].translation, abs=TOL)
    # and the hand frame is our neutral hand: aligned with the world
    assert f["hand"].rotation == pytest.approx(np.eye(3), abs=TOL)
    # the same as our model's zero pose
    assert mismatch(arm, {}) < TOL


@pytest.mark.parametrize("side", SIDES)
def test_dh_zero_is_the_straight_arm_along_zw(side: str) -> None:
    f = ARMS[side].forward(np.zeros(7))
    base = f["base"]
    assert base.actInv(f["elbow"].translation) == pytest.approx([0, 0, LU], abs=TOL)
    assert base.actInv(f["wrist"].translation) == pytest.approx([0, 0, LU + LF], abs=TOL)
    if side == "right":  # Zw points right: the right arm straight out at the side, level
        shoulder = f["shoulder"].translation
        assert f["wrist"].translation - shoulder == pytest.approx([0, -(LU + LF), 0], abs=TOL)


def test_base_rotation_is_the_seed_world_in_ours() -> None:
    # Xw forward, Yw up, Zw = Xw x Yw (to the right)
    seed_axes = np.column_stack([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    assert np.allclose(R_OURS_SEED, seed_axes, atol=TOL)
    for side in SIDES:
        assert ARMS[side].thorax_M_base.rotation == pytest.approx(R_OURS_SEED)
        assert ARMS[side].thorax_M_base.translation == pytest.approx(
            SKELETON.joint(f"{side}_shoulder").offset
        )


def eq16(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """The seed's eq. 16, written out."""
    ct, st_, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array([
        [ct, -ca * st_, sa * st_, a * ct],
        [st_, ca * ct, -sa * ct, a * st_],
        [0.0, sa, ca, d],
        [0.0, 0.0, 0.0, 1.0],
    ])  # fmt: skip


@given(st.sampled_from(SIDES), st.lists(st.floats(-np.pi, np.pi), min_size=7, max_size=7))
def test_pinocchio_chain_is_the_product_of_eq16(side: str, theta: list[float]) -> None:
    arm = ARMS[side]
    f = arm.forward(theta)
    t = arm.thorax_M_base.homogeneous
    for i, (link, th) in enumerate(zip(arm.dh_params, theta, strict=True)):
        t = t @ eq16(th, link.d, link.a, np.radians(link.alpha_deg))  # eq. 17
        assert f[f"dh{i}"].homogeneous == pytest.approx(t, abs=TOL)


def test_table() -> None:
    for side in SIDES:
        table = ARMS[side].dh_params
        assert [link.dof for link in table] == list(ARM_DOFS)
        assert [link.alpha_deg for link in table] == [90, -90, 90, -90, 90, -90, -90]
        assert [link.theta_offset_deg for link in table] == [90, 90, 90, 0, 90, 90, 90]
        assert [link.d for link in table] == [0, 0, LU, 0, LF, 0, 0]
        assert all(link.a == 0 for link in table)
    signs = {s: [link.sign for link in ARMS[s].dh_params] for s in SIDES}
    assert signs["left"] == [1, 1, 1, 1, 1, 1, 1]
    assert signs["right"] == [1, -1, -1, 1, -1, -1, 1]  # the lateralised dofs mirror


def test_subject_lengths_from_the_profile() -> None:
    arm = DhArm.for_profile(Profile(lengths={"upperarm": 0.31, "forearm": 0.25}), "left")
    assert [link.d for link in arm.dh_params] == [0, 0, 0.31, 0, 0.25, 0, 0]
    f = arm.forward(arm.theta({}))
    assert f["base"].actInv(f["wrist"].translation) == pytest.approx([0, -0.56, 0], abs=TOL)


SAMPLES = [
    {n: float(np.random.default_rng(i).uniform(*rom(n))) for n in arm_names("left")}
    for i in range(20)
]


@pytest.mark.parametrize("i", range(7))
def test_a_flipped_alpha_sign_breaks_the_match(i: int) -> None:
    table = list(dh_table("left", LU, LF))
    table[i] = replace(table[i], alpha_deg=-table[i].alpha_deg)
    arm = DhArm("left", SKELETON, table)
    assert max(mismatch(arm, a) for a in SAMPLES) > 0.05


def test_the_literal_alpha3_of_zero_cannot_be_our_arm() -> None:
    # Table 4.2 as extracted (alpha3 = 0) with frame 3 at the elbow: z3 is then
    # parallel to the elbow axis and the forearm (d4 along z3) sticks out sideways.
    table = list(dh_table("left", LU, LF))
    table[3] = replace(table[3], alpha_deg=0.0)
    arm = DhArm("left", SKELETON, table)
    f = arm.forward(arm.theta({}))
    forearm = f["base"].rotation.T @ (f["wrist"].translation - f["elbow"].translation)
    assert forearm == pytest.approx([0, 0, LF], abs=TOL)  # along Zw, not down
    assert max(mismatch(arm, a) for a in SAMPLES) > 0.05


def test_a_bad_side_is_refused() -> None:
    with pytest.raises(ValueError, match="side"):
        DhArm("middle")
    with pytest.raises(ValueError, match="links"):
        DhArm("left", SKELETON, dh_table("left")[:6])


def test_the_arm_dofs_are_the_skeletons_arm_in_chain_order() -> None:
    skeleton = build_skeleton()
    for side in SIDES:
        chain = [f"{j}_{d.name}" for j in ("shoulder", "elbow", "wrist")
                 for d in skeleton.joint(f"{side}_{j}").dofs]  # fmt: skip
        assert chain == list(ARM_DOFS)
