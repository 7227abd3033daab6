"""A model with the tree and coordinates of OpenSim's full-body models
(Rajagopal 2015 / its OpenSense variant: pelvis, torso, femur, tibia, calcn,
humerus, ulna, radius, hand), built through opensim's own API, for OpenSense's
IMU inverse kinematics in the tests. Each coordinate turns about the axis, and
with the sign, that those models give it (the left side mirrored); body masses
and joint positions are placeholders: orientation tracking needs neither. The
real model files are not shipped (their repository has no licence)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import opensim as osim

Axis = tuple[float, float, float]


def _transform(
    rotations: Sequence[tuple[str | None, Axis]],
    translations: Sequence[str | None] = (None, None, None),
) -> osim.SpatialTransform:
    """Three rotation axes (completed with independent ones without a
    coordinate) then X, Y, Z translations."""
    rots = list(rotations)
    for axis in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)):
        if len(rots) < 3 and np.linalg.matrix_rank([*(a for _, a in rots), axis]) == len(rots) + 1:
            rots.append((None, axis))
    st = osim.SpatialTransform()
    axes = [
        *rots,
        *zip(translations, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), strict=True),
    ]
    for i, (coordinate, axis) in enumerate(axes):
        ta = st.updTransformAxis(i)
        ta.setAxis(osim.Vec3(*axis))
        if coordinate:
            ta.setCoordinateNames(osim.ArrayStr(coordinate, 1))
            ta.set_function(osim.LinearFunction())
        else:
            ta.set_function(osim.Constant(0.0))
    return st


def build_model(defaults_deg: Mapping[str, float]) -> osim.Model:
    """The model, its coordinates' default values (the pose of the
    calibration frame) from ``defaults_deg``."""
    model = osim.Model()
    model.setName("rajagopal_tree")
    bodies: dict[str, osim.Body] = {}

    def joint(
        name: str, parent: str, child: str, at: Axis, rotations: Sequence[tuple[str | None, Axis]]
    ) -> None:
        body = osim.Body(child, 1.0, osim.Vec3(0.0), osim.Inertia(0.1, 0.1, 0.1))
        model.addBody(body)
        bodies[child] = body
        frame = model.getGround() if parent == "ground" else bodies[parent]
        model.addJoint(
            osim.CustomJoint(
                name,
                frame,
                osim.Vec3(*at),
                osim.Vec3(0.0),
                body,
                osim.Vec3(0.0),
                osim.Vec3(0.0),
                _transform(rotations),
            )
        )

    body = osim.Body("pelvis", 1.0, osim.Vec3(0.0), osim.Inertia(0.1, 0.1, 0.1))
    model.addBody(body)
    bodies["pelvis"] = body
    st = _transform(
        [("pelvis_tilt", (0, 0, 1)), ("pelvis_list", (1, 0, 0)), ("pelvis_rotation", (0, 1, 0))],
        ("pelvis_tx", "pelvis_ty", "pelvis_tz"),
    )
    model.addJoint(
        osim.CustomJoint(
            "ground_pelvis",
            model.getGround(),
            osim.Vec3(0.0, 0.9, 0.0),
            osim.Vec3(0.0),
            body,
            osim.Vec3(0.0),
            osim.Vec3(0.0),
            st,
        )
    )
    joint(
        "back",
        "pelvis",
        "torso",
        (0, 0.1, 0),
        [
            ("lumbar_extension", (0, 0, 1)),
            ("lumbar_bending", (1, 0, 0)),
            ("lumbar_rotation", (0, 1, 0)),
        ],
    )
    for s, k in (("r", 1.0), ("l", -1.0)):
        joint(
            f"hip_{s}",
            "pelvis",
            f"femur_{s}",
            (0, 0, 0.085 * k),
            [
                (f"hip_flexion_{s}", (0, 0, 1)),
                (f"hip_adduction_{s}", (k, 0, 0)),
                (f"hip_rotation_{s}", (0, k, 0)),
            ],
        )
        # Rajagopal's knee: + flexion (gait2392's counts it negative, about +Z)
        joint(
            f"walker_knee_{s}",
            f"femur_{s}",
            f"tibia_{s}",
            (0, -0.42, 0),
            [(f"knee_angle_{s}", (0, 0, -1))],
        )
        joint(
            f"ankle_{s}",
            f"tibia_{s}",
            f"talus_{s}",
            (0, -0.42, 0),
            [(f"ankle_angle_{s}", (0, 0, 1))],
        )
        # the models' subtalar axis is oblique; here about X (+ inversion), so that
        # the foot's orientation can be matched (no .mot column to compare with)
        joint(
            f"subtalar_{s}",
            f"talus_{s}",
            f"calcn_{s}",
            (0, 0, 0),
            [(f"subtalar_angle_{s}", (-k, 0, 0))],
        )
        joint(
            f"acromial_{s}",
            "torso",
            f"humerus_{s}",
            (0, 0.36, 0.22 * k),
            [
                (f"arm_flex_{s}", (0, 0, 1)),
                (f"arm_add_{s}", (k, 0, 0)),
                (f"arm_rot_{s}", (0, k, 0)),
            ],
        )
        joint(
            f"elbow_{s}",
            f"humerus_{s}",
            f"ulna_{s}",
            (0, -0.29, 0),
            [(f"elbow_flex_{s}", (0, 0, 1))],
        )
        # the forearm's long axis, + pronation; 0 in full supination (palm forward)
        joint(
            f"radioulnar_{s}", f"ulna_{s}", f"radius_{s}", (0, 0, 0), [(f"pro_sup_{s}", (0, k, 0))]
        )
        # + flexion towards the palm, + ulnar deviation (with the palm forward)
        joint(
            f"radiocarpal_{s}",
            f"radius_{s}",
            f"hand_{s}",
            (0, -0.265, 0),
            [(f"wrist_flex_{s}", (0, 0, 1)), (f"wrist_dev_{s}", (k, 0, 0))],
        )
    coordinates = model.updCoordinateSet()
    for i in range(coordinates.getSize()):
        c = coordinates.get(i)
        if not c.getName().startswith("pelvis_t"):
            c.setRangeMin(-2 * math.pi)
            c.setRangeMax(2 * math.pi)
            c.setDefaultValue(math.radians(defaults_deg.get(c.getName(), 0.0)))
    model.finalizeConnections()
    return model
