"""``bodynet export mot``: joint angles as an OpenSim motion file (``.mot``).

The table OpenSim's Coordinates tool, its IK results and its GUI's
"Load Motion" read: a header ending at ``endheader`` (``inDegrees=yes``), then
``time`` (s, from the first frame; the recording's time of that frame is in
the header as ``bodynet_start_ns``) and one column per coordinate of OpenSim's
full-body models, in degrees, on a regular frame grid (``--rate-hz``).

Coordinates are written only where the mapping from bodynet's joint angles
is exact up to a sign and an offset: the same anatomical motion, about
corresponding axes, in the same Euler order (``core/skeleton.py`` gives
bodynet's dofs; OpenSim's are those of Rajagopal et al. 2015 and its OpenSense
variant, whose hip, knee, ankle, lumbar and pelvis coordinates are gait2392's
but for the knee, and whose arm is Holzbaur's / arm26's):

========================  ==================================  ==========================
OpenSim coordinate        from bodynet                        OpenSim's convention
========================  ==================================  ==========================
pelvis_tilt/list/rotation pelvis orientation, Euler Z-X-Y in  ground_pelvis: tilt about
                          OpenSim's ground frame              +Z, list +X, rotation +Y
hip_flexion_r             right_hip_flexion                   + flexion
hip_adduction_r           - right_hip_abduction               + adduction
hip_rotation_r            right_hip_rotation                  + internal rotation
knee_angle_r              right_knee_flexion                  + flexion (Rajagopal; NB
                                                              gait2392: - flexion)
ankle_angle_r             right_ankle_flexion                 + dorsiflexion, 0 at 90 deg
lumbar_extension          - lumbar_flexion                    + extension
lumbar_bending            lumbar_lateral                      + bending to the right
lumbar_rotation           lumbar_rotation                     + turning to the left
arm_flex_r                right_shoulder_flexion              + flexion
arm_add_r                 - right_shoulder_abduction          + adduction
arm_rot_r                 right_shoulder_rotation             + internal rotation
elbow_flex_r              right_elbow_flexion                 + flexion, 0 extended
pro_sup_r                 90 + right_elbow_pronation          + pronation, 0 = full
                                                              supination (palm forward);
                                                              bodynet's 0 is neutral
                                                              (palm to the thigh)
wrist_flex_r              right_wrist_flexion                 + flexion (palmar)
wrist_dev_r               - right_wrist_deviation             + ulnar deviation
========================  ==================================  ==========================

and the same for the left side (``_l``; OpenSim mirrors the left axes so that
the signs are the same). Not written, for want of a clear mapping: the
subtalar angle (OpenSim's axis is oblique, bodynet's inversion is not), the
neck (the models have none: the head is part of the torso), the pelvis
translations (OpenSim's pelvis origin is not bodynet's hip-centre midpoint).
OpenSim's elbow and forearm axes are oblique (the carrying angle): the values
agree for the flexion and the forearm's rotation, not for off-axis motion.

An angle with no measurement behind it (``is_measured`` false) is NaN, and
so is every coordinate, the pelvis's too, in a frame inside a gap in the
poses (``PoseTrack.posed``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.clients.exports import Written
from bodynet.clients.exports.opensim import TO_OPENSIM, format_rows, header, number
from bodynet.clients.exports.track import PoseTrack, euler_deg, output_file
from bodynet.core.opensim import OPENSIM_VERSION


class Coordinate(NamedTuple):
    """``value = sign * angle + offset`` (deg)."""

    name: str
    angle: str  # bodynet's joint angle
    sign: float = 1.0
    offset: float = 0.0


def _side(side: str) -> list[Coordinate]:
    s, b = side[0], side
    return [
        Coordinate(f"hip_flexion_{s}", f"{b}_hip_flexion_deg"),
        Coordinate(f"hip_adduction_{s}", f"{b}_hip_abduction_deg", -1.0),
        Coordinate(f"hip_rotation_{s}", f"{b}_hip_rotation_deg"),
        Coordinate(f"knee_angle_{s}", f"{b}_knee_flexion_deg"),
        Coordinate(f"ankle_angle_{s}", f"{b}_ankle_flexion_deg"),
        Coordinate(f"arm_flex_{s}", f"{b}_shoulder_flexion_deg"),
        Coordinate(f"arm_add_{s}", f"{b}_shoulder_abduction_deg", -1.0),
        Coordinate(f"arm_rot_{s}", f"{b}_shoulder_rotation_deg"),
        Coordinate(f"elbow_flex_{s}", f"{b}_elbow_flexion_deg"),
        Coordinate(f"pro_sup_{s}", f"{b}_elbow_pronation_deg", 1.0, 90.0),
        Coordinate(f"wrist_flex_{s}", f"{b}_wrist_flexion_deg"),
        Coordinate(f"wrist_dev_{s}", f"{b}_wrist_deviation_deg", -1.0),
    ]


#: Every coordinate written from a joint angle, in the file's order.
COORDINATES: tuple[Coordinate, ...] = (
    Coordinate("lumbar_extension", "lumbar_flexion_deg", -1.0),
    Coordinate("lumbar_bending", "lumbar_lateral_deg"),
    Coordinate("lumbar_rotation", "lumbar_rotation_deg"),
    *_side("right"),
    *_side("left"),
)
PELVIS = ("pelvis_tilt", "pelvis_list", "pelvis_rotation")


def coordinates_deg(track: PoseTrack) -> tuple[list[str], np.ndarray]:
    """The column labels after ``time`` and the (F, C) values in degrees, NaN
    where no measurement is behind the angle."""
    index = {a: i for i, a in enumerate(track.angles)}
    pelvis = Rotation.from_quat(track.segment_q[:, track.segments.index("pelvis")],
                                scalar_first=True)  # fmt: skip
    m = Rotation.from_matrix(TO_OPENSIM)
    tilt_list_rotation = euler_deg(m * pelvis * m.inv(), "ZXY")  # intrinsic
    columns = [np.where(track.frame_posed()[:, None], tilt_list_rotation, np.nan)]
    for c in COORDINATES:
        i = index[c.angle]
        value = c.sign * track.angle_deg[:, i] + c.offset
        columns.append(np.where(track.measured[:, i], value, np.nan)[:, None])
    return [*PELVIS, *(c.name for c in COORDINATES)], np.hstack(columns)


def write(track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
    """Write ``track`` (frames at ``track.rate_hz``) as a ``.mot``. No options."""
    labels, values = coordinates_deg(track)
    rate = track.rate_hz or track.measured_rate_hz()
    lines = [
        "Coordinates",
        "version=1",
        f"nRows={len(track)}",
        f"nColumns={len(labels) + 1}",
        "inDegrees=yes",
        f"DataRate={rate:.6f}",
        f"OpenSimVersion={OPENSIM_VERSION}",
        f"bodynet_start_ns={int(track.t_ns[0])}",
        "",
        "Units are S.I. units (second, meters, Newtons, ...)",
        "If the header above contains a line with 'inDegrees', this indicates whether "
        "rotational values are in degrees (yes) or radians (no).",
        "",
    ]
    time_s = (track.t_ns - track.t_ns[0]) / 1e9
    cells = [[number(v) for v in row] for row in values.tolist()]
    with output_file(out) as tmp, tmp.open("w") as f:
        f.write(header(lines, ["time", *labels]))
        f.write(format_rows(time_s, cells))
    return Written(len(track))
