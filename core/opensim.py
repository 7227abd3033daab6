"""OpenSim's names and frames, for files bodynet writes and reads (pure data).

OpenSim's ground frame is +X forward, +Y up, +Z to the subject's right;
bodynet's is +X forward, +Y left, +Z up. :data:`OPENSIM_FROM_BODYNET` is the
rotation between them (its rows are OpenSim's X, Y, Z axes in bodynet's
frame): x -> x, z -> y, y -> -z, -90 deg about X. A vector ``v`` in bodynet's
frame is ``M v`` in OpenSim's; a segment orientation ``R`` is ``M R M^T``.

OpenSense's IMU orientation files (``.sto``, ``DataType=Quaternion``) name a
column ``<body>_imu`` after the model body the sensor rides; :data:`IMU_BODIES`
says which bodynet segment each body of OpenSim's full-body models (Rajagopal
2015 and its OpenSense variant) is. OpenSense rotates a file's orientations
into OpenSim's frame by ``sensor_to_opensim_rotations`` (X, Y, Z body-fixed
Euler angles in radians): a file written in OpenSim's frame declares
``0 0 0`` in its header (:data:`SENSOR_TO_OPENSIM`).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]

#: Rows: OpenSim's X, Y, Z axes in bodynet's frame.
OPENSIM_FROM_BODYNET: Matrix3 = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))

#: The OpenSim version whose file layout bodynet follows (``OpenSimVersion=``).
OPENSIM_VERSION = "4.6"

#: Header key of the rotation OpenSense applies to a file's orientations.
SENSOR_TO_OPENSIM = "sensor_to_opensim_rotations"

#: bodynet segment -> OpenSim body (the column is ``<body>_imu``).
IMU_BODIES: Mapping[str, str] = MappingProxyType(
    {
        "pelvis": "pelvis",
        "thorax": "torso",
        "head": "head",
        **{
            f"{side}_{segment}": f"{body}_{side[0]}"
            for side in ("right", "left")
            for segment, body in (
                ("thigh", "femur"),
                ("shank", "tibia"),
                ("foot", "calcn"),
                ("upperarm", "humerus"),
                ("forearm", "radius"),
                ("hand", "hand"),
            )
        },
    }
)


def imu_label(segment: str) -> str:
    """The OpenSense column of a bodynet segment: ``radius_r_imu`` for ``right_forearm``."""
    return f"{IMU_BODIES[segment]}_imu"


def segment_of_imu(label: str) -> str | None:
    """The bodynet segment of an OpenSense column, None if it is not one of them."""
    for segment, body in IMU_BODIES.items():
        if label == f"{body}_imu":
            return segment
    return None
