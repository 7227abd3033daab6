"""A subject's profile: segment lengths and sensor calibrations, versioned.

The profile is what calibration produces and the gateway consumes. It is kept
as plain data here (no file I/O); ``bodynet.session.profile_file`` reads and
writes it as TOML a user can read and edit:

```toml
version = 1
subject = "subject-1"

[segments]             # metres
upperarm = 0.293
forearm = 0.265

[ole.left_elbow_flexion_deg]   # encoder of one joint dof (000 seed, eq. 14-15)
radius_mm = 26.93
sf_travel_mm = [0.0, 14.1, 28.0, 39.1, 48.6, 52.2]
sf = [1.0, 1.0, 1.007, 1.084, 1.161, 1.261]

pose = "tpose"         # the calibration pose: tpose or npose
heading = "auto"       # auto: found from motion; fixed: the subject faced +X of the tags' frame
drift = "auto"         # which joints hold drifting tags' headings: auto, joints, hinges, off

[imu_mounts]           # sensor orientation in its segment (w, x, y, z), from calibration
"body/arm/left/upperarm/raw" = [1.0, 0.0, 0.0, 0.0]

[imu_headings]         # each tag's heading reference against the body's forward (deg), once known
"body/arm/left/upperarm/raw" = 0.0

[heading_reference]    # optional, declared: this tag's axis pointed forward during calibration
key = "body/trunk/mid/sacrum/raw"
axis = "+z"

[trackers]             # a sensor that says who it is (SlimeVR: MAC-sensor) -> its site
"aabbccddeeff-0" = "left-arm/upperarm"
```
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from .calibration import OleCalibration, default_ole
from .codecs.slimevr import normalise_tracker_id
from .keys import KeySpaceError, site_name, site_named
from .profile import OLE_DOF, SMARTSUIT_SITES

VERSION = 1
QuatWxyz = tuple[float, float, float, float]

#: Calibration poses: ``tpose`` (arms horizontal, palms down) and ``npose``
#: (standing neutral: arms down, palms to the thighs).
POSES = ("tpose", "npose")
#: How the tags' heading references relate to the body. ``auto``: all tags share
#: one reference (magnetometer-based sensors) and the subject faced anywhere: the
#: heading is found from the motion after calibration, or declared. ``fixed``: the
#: subject faced +X of the shared reference during calibration (emulators, captures
#: turned by hand). ``independent``: 6-axis tags, each its own reference: each
#: thigh and shank tag's heading is found from the knee's motion, the others stay
#: unknown (flagged).
HEADING_MODES = ("auto", "fixed", "independent")
#: Which joints hold the tags' headings against drift (gateway/heading.py,
#: ``JointDrift``). ``hinges``: the knees', ankles', elbows' and wrists'
#: constraints (they hold at every instant). ``joints``: those and the three-dof
#: joints' (hips, shoulders, lumbar, neck: their twist held at rest, averaging to
#: the calibration pose's while moving, an assumption). ``auto``: ``joints`` for tags
#: with references of their own (``independent`` heading: 6-axis tags, which drift),
#: else ``hinges`` (tags sharing a reference do not drift apart: give ``joints`` for
#: 6-axis tags reset together). ``off``: none.
DRIFT_MODES = ("auto", "joints", "hinges", "off")
#: Sensor axes a declared heading reference may name.
AXES = ("+x", "-x", "+y", "-y", "+z", "-z")


def default_ole_table() -> dict[str, OleCalibration]:
    """Encoder calibration of every SmartSuit module's dof, by joint angle name."""
    out = {}
    for site in SMARTSUIT_SITES.values():
        if site.name in OLE_DOF:
            name = f"{site.branch.side}_{site.name}_{OLE_DOF[site.name]}_deg"
            out[name] = default_ole(site.name)
    return out


class ProfileError(ValueError):
    """A profile that cannot be used, with the reason."""


@dataclass(frozen=True)
class Profile:
    subject: str = "subject-1"
    lengths: Mapping[str, float] = field(default_factory=dict)  # over the skeleton's defaults
    ole: Mapping[str, OleCalibration] = field(default_factory=default_ole_table)
    imu_mounts: Mapping[str, QuatWxyz] = field(default_factory=dict)  # raw key -> mount
    trackers: Mapping[str, str] = field(default_factory=dict)  # tracker id -> site name
    accel_counts_per_g: float = 1024.0
    accel_filter: float = 0.5  # weight of a new accelerometer sample in the tilt filter
    pose: str = "tpose"  # the calibration pose (POSES)
    heading: str = "auto"  # HEADING_MODES
    #: raw key -> the heading (deg, about the vertical) of that tag's reference frame
    #: against the body's forward at calibration; a tag without one has an unknown
    #: heading (in ``auto`` mode), and the dofs it drives are flagged ``uncalibrated``
    imu_headings: Mapping[str, float] = field(default_factory=dict)
    #: declared: (raw key, sensor axis such as "+z") that pointed forward in calibration
    heading_reference: tuple[str, str] | None = None
    drift: str = "auto"  # DRIFT_MODES
    version: int = VERSION

    def __post_init__(self) -> None:
        if self.pose not in POSES:
            raise ProfileError(f"pose must be one of {', '.join(POSES)}, not {self.pose!r}")
        if self.heading not in HEADING_MODES:
            raise ProfileError(
                f"heading must be one of {', '.join(HEADING_MODES)}, not {self.heading!r}"
            )
        if self.drift not in DRIFT_MODES:
            raise ProfileError(f"drift must be one of {', '.join(DRIFT_MODES)}, not {self.drift!r}")
        if self.heading_reference is not None and self.heading_reference[1] not in AXES:
            raise ProfileError(
                f"heading_reference axis must be one of {', '.join(AXES)}, "
                f"not {self.heading_reference[1]!r}"
            )

    def with_mounts(self, mounts: Mapping[str, QuatWxyz]) -> Profile:
        return replace(self, imu_mounts=MappingProxyType({**self.imu_mounts, **mounts}))

    def heading_known(self, key: str) -> bool:
        """Whether the dofs a tag drives can be trusted about the vertical."""
        return self.heading == "fixed" or key in self.imu_headings

    @property
    def drift_joints(self) -> tuple[bool, bool]:
        """Whether the hinge (and two-dof) joints, and the three-dof joints, hold
        the tags' headings against drift (``drift``, see ``DRIFT_MODES``)."""
        if self.drift == "auto":
            return True, self.heading == "independent"
        return self.drift != "off", self.drift == "joints"

    def heading_of(self, key: str) -> float:
        """The tag's heading reference (deg; 0 when unknown, or ``fixed`` and not
        corrected since: a yaw reset, a drift correction)."""
        return self.imu_headings.get(key, 0.0)

    def with_tracker(self, tracker: str, site: str) -> Profile:
        """``tracker`` (its canonical id) sits at ``site`` (``left-arm/upperarm``);
        a site holds one tracker, so any other tracker there is unassigned."""
        kept = {t: s for t, s in self.trackers.items() if s != site and t != tracker}
        return replace(self, trackers=MappingProxyType({**kept, tracker: site}))

    def with_ole(self, angle: str, calibration: OleCalibration) -> Profile:
        return replace(self, ole=MappingProxyType({**self.ole, angle: calibration}))

    def to_dict(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "subject": self.subject,
            "accel_counts_per_g": self.accel_counts_per_g,
            "accel_filter": self.accel_filter,
            "segments": dict(self.lengths),
            "ole": {
                name: {"radius_mm": c.radius_mm, "sf_travel_mm": list(c.sf_d_mm), "sf": list(c.sf)}
                for name, c in sorted(self.ole.items())
            },
            "imu_mounts": {k: list(q) for k, q in sorted(self.imu_mounts.items())},
            "pose": self.pose,
            "heading": self.heading,
            **({"drift": self.drift} if self.drift != "auto" else {}),
            "imu_headings": dict(sorted(self.imu_headings.items())),
            "trackers": dict(sorted(self.trackers.items())),
            **({"heading_reference": {"key": self.heading_reference[0],
                                      "axis": self.heading_reference[1]}}
               if self.heading_reference else {}),
        }  # fmt: skip

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Profile:
        version = data.get("version")
        if version != VERSION:
            raise ProfileError(f"profile version {version!r}; this bodynet reads version {VERSION}")
        tables = ("ole", "imu_mounts", "segments", "trackers", "imu_headings", "heading_reference")
        for name in tables:  # a list or a number where a table belongs: say so, by name
            value = data.get(name, {})
            if not isinstance(value, Mapping):
                raise ProfileError(f"{name} must be a table ([{name}]), "
                                   f"not {type(value).__name__} {value!r:.40}")  # fmt: skip
        for name, c in data.get("ole", {}).items():
            if not isinstance(c, Mapping):
                raise ProfileError(f"ole.{name} must be a table (radius_mm, sf_travel_mm, sf), "
                                   f"not {type(c).__name__} {c!r:.40}")  # fmt: skip
        try:
            ole = dict(default_ole_table())
            for name, c in data.get("ole", {}).items():
                ole[name] = OleCalibration(
                    float(c["radius_mm"]),
                    tuple(map(float, c.get("sf_travel_mm", [0.0]))),
                    tuple(map(float, c.get("sf", [1.0]))),
                )
            mounts = {}
            for key, q in data.get("imu_mounts", {}).items():
                if len(q) != 4:
                    raise ProfileError(f"imu_mounts[{key!r}] needs 4 numbers (w, x, y, z)")
                w, x, y, z = map(float, q)
                mounts[key] = (w, x, y, z)
            numbers = [*(v for q in mounts.values() for v in q),
                       *map(float, data.get("segments", {}).values()),
                       float(data.get("accel_counts_per_g", 1024.0))]  # fmt: skip
            if not all(math.isfinite(v) for v in numbers):
                raise ProfileError("a number that is not finite (nan or inf)")
            trackers = {}
            for tracker, site in data.get("trackers", {}).items():
                try:
                    trackers[normalise_tracker_id(str(tracker))] = site_name(site_named(str(site)))
                except (ValueError, KeySpaceError) as exc:
                    raise ProfileError(f"trackers[{tracker!r}]: {exc}") from None
            accel_filter = float(data.get("accel_filter", 0.5))
            if not 0.0 < accel_filter <= 1.0:
                raise ProfileError(f"accel_filter must be in (0, 1], not {accel_filter}")
            ref = data.get("heading_reference")
            reference = (str(ref["key"]), str(ref["axis"])) if ref is not None else None
            return cls(
                pose=str(data.get("pose", "tpose")),
                heading=str(data.get("heading", "auto")),
                drift=str(data.get("drift", "auto")),
                imu_headings=MappingProxyType(
                    {str(k): float(v) for k, v in data.get("imu_headings", {}).items()}
                ),
                heading_reference=reference,
                subject=str(data.get("subject", "subject-1")),
                lengths=MappingProxyType(
                    {k: float(v) for k, v in data.get("segments", {}).items()}
                ),
                ole=MappingProxyType(ole),
                imu_mounts=MappingProxyType(mounts),
                trackers=MappingProxyType(trackers),
                accel_counts_per_g=float(data.get("accel_counts_per_g", 1024.0)),
                accel_filter=accel_filter,
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            if isinstance(exc, ProfileError):
                raise
            raise ProfileError(f"bad profile: {exc}") from None
