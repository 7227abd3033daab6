"""``bodynet export sto``: segment orientations as an OpenSense IMU orientation file.

The file OpenSim's ``IMUPlacer`` and ``IMUInverseKinematicsTool`` read (and
``TimeSeriesTableQuaternion``): a header (``DataRate=``,
``DataType=Quaternion``, ``version=3``, ``OpenSimVersion=``, ``endheader``),
then ``time`` (s, from the first frame; the recording's time of that frame is
``bodynet_start_ns`` in the header) and one column per segment, named after
the model body it rides (``pelvis_imu``, ``torso_imu``, ``head_imu``,
``femur_r_imu``, ``tibia_r_imu``, ``calcn_r_imu``, ``humerus_r_imu``,
``radius_r_imu``, ``hand_r_imu`` and the left side: ``core.opensim.IMU_BODIES``),
each cell a unit quaternion ``w,x,y,z`` on a regular frame grid.

Each column is a virtual IMU aligned with its segment's frame: at bodynet's
zero pose (anatomical neutral, palms to the thighs) every quaternion is the
identity. Orientations are given in OpenSim's ground frame (Y up), rotated
from bodynet's (Z up) by ``core.opensim.OPENSIM_FROM_BODYNET`` (-90 deg about
X: ``q = m * q_bodynet * m^-1``), so the header declares
``sensor_to_opensim_rotations=0 0 0``: give OpenSense the same (its default).

A segment's orientation is NaN (all four components) in a frame where an
angle of a joint between the pelvis and it has no measurement behind it
(``is_measured`` false): its orientation then rests on a value nothing measured;
every segment's, the pelvis's too, in a frame inside a gap in the poses
(``PoseTrack.chain_measured``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.clients.exports import Written
from bodynet.clients.exports.opensim import TO_OPENSIM, format_rows, header, number
from bodynet.clients.exports.track import PoseTrack, output_file
from bodynet.core.opensim import IMU_BODIES, OPENSIM_VERSION, SENSOR_TO_OPENSIM, imu_label


def orientations(track: PoseTrack) -> tuple[list[str], np.ndarray]:
    """The column labels after ``time`` and the (F, C, 4) quaternions w, x, y, z
    in OpenSim's ground frame, NaN where not measured."""
    segments = [s for s in IMU_BODIES if s in track.segments]
    m = Rotation.from_matrix(TO_OPENSIM)
    measured = track.chain_measured()
    out = np.empty((len(track), len(segments), 4))
    for c, segment in enumerate(segments):
        s = track.segments.index(segment)
        q = (m * Rotation.from_quat(track.segment_q[:, s], scalar_first=True) * m.inv()).as_quat(
            scalar_first=True
        )
        q *= np.where(q[:, :1] < 0, -1.0, 1.0)  # w >= 0: one of the two equal quaternions
        out[:, c] = np.where(measured[:, s, None], q, np.nan)
    return [imu_label(s) for s in segments], out


def write(track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
    """Write ``track`` (frames at ``track.rate_hz``) as OpenSense orientations. No options."""
    labels, quats = orientations(track)
    rate = track.rate_hz or track.measured_rate_hz()
    lines = [
        f"DataRate={rate:.6f}",
        "DataType=Quaternion",
        "version=3",
        f"OpenSimVersion={OPENSIM_VERSION}",
        f"{SENSOR_TO_OPENSIM}=0 0 0",
        f"bodynet_start_ns={int(track.t_ns[0])}",
    ]
    time_s = (track.t_ns - track.t_ns[0]) / 1e9
    cells = [[",".join(map(number, q)) for q in row] for row in quats.tolist()]
    with output_file(out) as tmp, tmp.open("w") as f:
        f.write(header(lines, ["time", *labels]))
        f.write(format_rows(time_s, cells))
    return Written(len(track))
