"""A subject's profile: segment lengths and sensor calibrations, versioned.

The profile is what calibration produces and the gateway consumes. It is kept
as plain data here (no file I/O); ``bodynet.session.profile_file`` reads and
writes it as TOML a user can read and edit:

```toml
version = 1
subject = "subject-1"
pose = "tpose"         # the calibration pose: tpose or npose
heading = "auto"       # auto: found from motion; fixed: the subject faced +X of the tags' frame
drift = "auto"         # which joints hold drifting tags' headings: auto, joints, hinges, off
accel_counts_per_g = 1024.0    # SmartSuit accelerometer counts in 1 g
accel_filter = 0.5     # weight of a new accelerometer sample in the tilt filter, (0, 1]

[segments]             # metres, each above 0 and at most 3 (DEFAULT_LENGTHS names them)
upperarm = 0.293
forearm = 0.265

[ole.left_elbow_flexion_deg]   # encoder of one joint dof (000 seed, eq. 14-15)
radius_mm = 26.93
sf_travel_mm = [0.0, 14.1, 28.0, 39.1, 48.6, 52.2]
sf = [1.0, 1.0, 1.007, 1.084, 1.161, 1.261]

[imu_mounts]           # sensor orientation in its segment (w, x, y, z), from calibration
"body/arm/left/upperarm/raw" = [1.0, 0.0, 0.0, 0.0]

[imu_headings]         # each tag's heading reference against the body's forward (deg), once known
"body/arm/left/upperarm/raw" = 0.0

[imu_scatter_deg]      # each tag's scatter (RMS, deg) in its calibration's still window
"body/arm/left/upperarm/raw" = 0.52

[heading_reference]    # optional, declared: this tag's axis pointed forward during calibration
key = "body/trunk/mid/sacrum/raw"
axis = "+z"

[trackers]             # a sensor that says who it is (SlimeVR: MAC-sensor) -> its site
"aabbccddeeff-0" = "left-arm/upperarm"
```

Every key is one of these (an unknown one, a typo, is refused by name) and every
number is finite and in its range (``from_dict``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from .calibration import OleCalibration, default_ole
from .codecs.slimevr import normalise_tracker_id
from .keys import KeySpaceError, site_name, site_named
from .profile import OLE_DOF, SMARTSUIT_SITES
from .skeleton import DEFAULT_LENGTHS

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

#: The keys of a profile that hold tables.
TABLES = ("ole", "imu_mounts", "segments", "trackers", "imu_headings", "heading_reference",
          "imu_scatter_deg")  # fmt: skip
#: The keys a profile may hold (what ``Profile.to_dict`` writes): any other is refused
#: by name, as a misspelt key would otherwise be dropped (a saved profile drops it too).
KEYS = (
    "version",
    "subject",
    "accel_counts_per_g",
    "accel_filter",
    "pose",
    "heading",
    "drift",
    *TABLES,
)
#: The longest a segment (``[segments]``, metres) may be: a human's are all under 1 m,
#: and a length far above that is a mistake (1e308 m overflows the solver to null).
MAX_SEGMENT_M = 3.0
#: ``accel_counts_per_g``'s range: 1 for a sensor that reports in g, 9.81 in m/s^2,
#: 16384 for +-2 g at 16 bits (0 divides by zero in the solver's tilt).
ACCEL_COUNTS_PER_G = (0.001, 1e6)
#: The norm an IMU mount (w, x, y, z) may have: it is normalised where it is used, so
#: one far from 1 is fine, but not one of about 0 (no rotation) or one that overflows.
MOUNT_NORM = (1e-3, 1e3)
#: The largest heading (deg, either way) in ``[imu_headings]``; the gateway writes
#: them within +-180.
MAX_HEADING_DEG = 360.0
#: The largest scatter (deg) in ``[imu_scatter_deg]``: a tag turning further at random
#: in a still window measures nothing (calibration refuses far less).
MAX_SCATTER_DEG = 90.0


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
    #: raw key -> the tag's scatter (RMS of its turns from its mean, deg) in the still
    #: window it was calibrated from: its noise, which the dofs it drives carry in
    #: their uncertainty (a tag without one: what good IMUs claim, ``UNC_TAG_DEG``)
    imu_scatter_deg: Mapping[str, float] = field(default_factory=dict)
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
            **({"imu_scatter_deg": dict(sorted(self.imu_scatter_deg.items()))}
               if self.imu_scatter_deg else {}),
            "trackers": dict(sorted(self.trackers.items())),
            **({"heading_reference": {"key": self.heading_reference[0],
                                      "axis": self.heading_reference[1]}}
               if self.heading_reference else {}),
        }  # fmt: skip

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Profile:
        """The profile ``data`` (a parsed TOML file) holds; ``ProfileError`` names the
        first key that is unknown, of the wrong type or out of its range (``KEYS``)."""
        version = data.get("version")
        if version is None:
            raise ProfileError(f"no version in the profile (version = {VERSION} for this bodynet)")
        if type(version) is not int:  # "1" is a string in TOML, not the number 1
            raise ProfileError(f"profile version must be a number (version = {VERSION}), "
                               f"not {type(version).__name__} {version!r:.40}")  # fmt: skip
        if version != VERSION:
            raise ProfileError(f"profile version {version!r}; this bodynet reads version {VERSION}")
        _known("", data, KEYS)
        for name in TABLES:  # a list or a number where a table belongs: say so, by name
            value = data.get(name, {})
            if not isinstance(value, Mapping):
                raise ProfileError(f"{name} must be a table ([{name}]), "
                                   f"not {type(value).__name__} {value!r:.40}")  # fmt: skip
        for name, c in data.get("ole", {}).items():
            if not isinstance(c, Mapping):
                raise ProfileError(f"ole.{name} must be a table (radius_mm, sf_travel_mm, sf), "
                                   f"not {type(c).__name__} {c!r:.40}")  # fmt: skip
        _known("ole.", data.get("ole", {}), tuple(default_ole_table()))
        _known("segments.", data.get("segments", {}), tuple(DEFAULT_LENGTHS))
        _known("heading_reference.", data.get("heading_reference", {}), ("key", "axis"))
        try:
            ole = dict(default_ole_table())
            for name, c in data.get("ole", {}).items():
                _known(f"ole.{name}.", c, ("radius_mm", "sf_travel_mm", "sf"))
                if "radius_mm" not in c:
                    raise ProfileError(f"ole.{name} needs radius_mm")
                ole[name] = OleCalibration(
                    float(c["radius_mm"]),
                    tuple(map(float, c.get("sf_travel_mm", [0.0]))),
                    tuple(map(float, c.get("sf", [1.0]))),
                )
            trackers = {}
            for tracker, site in data.get("trackers", {}).items():
                try:
                    trackers[normalise_tracker_id(str(tracker))] = site_name(site_named(str(site)))
                except (ValueError, KeySpaceError) as exc:
                    raise ProfileError(f"trackers[{tracker!r}]: {exc}") from None
            ref = data.get("heading_reference")
            if ref is not None and (missing := [k for k in ("key", "axis") if k not in ref]):
                raise ProfileError(f"heading_reference needs key and axis; "
                                   f"{' and '.join(missing)} missing")  # fmt: skip
            reference = (str(ref["key"]), str(ref["axis"])) if ref is not None else None
            return cls(
                pose=str(data.get("pose", "tpose")),
                heading=str(data.get("heading", "auto")),
                drift=str(data.get("drift", "auto")),
                imu_headings=MappingProxyType(_headings(data.get("imu_headings", {}))),
                imu_scatter_deg=MappingProxyType(_scatters(data.get("imu_scatter_deg", {}))),
                heading_reference=reference,
                subject=str(data.get("subject", "subject-1")),
                lengths=MappingProxyType(_lengths(data.get("segments", {}))),
                ole=MappingProxyType(ole),
                imu_mounts=MappingProxyType(_mounts(data.get("imu_mounts", {}))),
                trackers=MappingProxyType(trackers),
                accel_counts_per_g=_within(
                    "accel_counts_per_g", data.get("accel_counts_per_g", 1024.0),
                    ACCEL_COUNTS_PER_G, "counts of the accelerometer in 1 g",
                ),
                accel_filter=_within(
                    "accel_filter", data.get("accel_filter", 0.5), (0.0, 1.0),
                    "the weight of a new accelerometer sample", low_open=True,
                ),
            )  # fmt: skip
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            if isinstance(exc, ProfileError):
                raise
            raise ProfileError(f"bad profile: {exc}") from None


def _known(where: str, table: Mapping[str, Any], names: tuple[str, ...]) -> None:
    """Refuse a key of ``table`` (``where`` names it, "ole." say) not in ``names``:
    a misspelt key would otherwise be dropped without a word."""
    for key in table:
        if key not in names:
            raise ProfileError(f"unknown key {where}{key} (known here: {', '.join(names)})")


def _number(name: str, value: object) -> float:
    """``value`` as a finite float; ``ProfileError`` naming ``name`` if it is not one."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ProfileError(f"{name} must be a number, not {type(value).__name__} {value!r:.40}")
    try:
        number = float(value)
    except ValueError:
        raise ProfileError(f"{name} must be a number, not {value!r:.40}") from None
    if not math.isfinite(number):
        raise ProfileError(f"{name} must be a finite number, not {number}")
    return number


def _within(
    name: str,
    value: object,
    bounds: tuple[float, float],
    what: str,
    *,
    unit: str = "",
    low_open: bool = False,
) -> float:
    """``value`` as a number in ``bounds`` (above the low one if ``low_open``)."""
    number = _number(name, value)
    low, high = bounds
    if not (low < number if low_open else low <= number) or number > high:
        raise ProfileError(f"{name} must be {'above' if low_open else 'at least'} {low:g}{unit} "
                           f"and at most {high:g}{unit} ({what}), not {number:g}")  # fmt: skip
    return number


def _lengths(segments: Mapping[str, Any]) -> dict[str, float]:
    return {
        str(k): _within(
            f"segments.{k}", v, (0.0, MAX_SEGMENT_M), "a segment's length", unit=" m", low_open=True
        )
        for k, v in segments.items()
    }


def _headings(headings: Mapping[str, Any]) -> dict[str, float]:
    return {
        str(k): _within(
            f"imu_headings[{k!r}]",
            v,
            (-MAX_HEADING_DEG, MAX_HEADING_DEG),
            "a tag's heading",
            unit=" deg",
        )
        for k, v in headings.items()
    }


def _scatters(scatters: Mapping[str, Any]) -> dict[str, float]:
    return {
        str(k): _within(f"imu_scatter_deg[{k!r}]", v, (0.0, MAX_SCATTER_DEG),
                        "a tag's scatter in its calibration window", unit=" deg")
        for k, v in scatters.items()
    }  # fmt: skip


def _mounts(mounts: Mapping[str, Any]) -> dict[str, QuatWxyz]:
    out = {}
    for key, q in mounts.items():
        name = f"imu_mounts[{key!r}]"
        if isinstance(q, str | bytes) or not isinstance(q, Sequence) or len(q) != 4:
            raise ProfileError(f"{name} needs 4 numbers (w, x, y, z), not {q!r:.40}")
        w, x, y, z = (_number(name, v) for v in q)
        low, high = MOUNT_NORM
        if not low <= math.hypot(w, x, y, z) <= high:
            raise ProfileError(f"{name} must be a rotation (w, x, y, z) of norm at least {low:g} "
                               f"and at most {high:g} (normalised where used), "
                               f"not {[w, x, y, z]}")  # fmt: skip
        out[str(key)] = (w, x, y, z)
    return out
