"""The default profile: which node or sensor number sits where on the body.

SmartSuit CAN nodes (000 seed, ch. 3): three modules per limb, numbered along
the distributed bus; the Data Concentrator polls the same node numbers. IMU
tags (003 seed, Table 5.2): fifteen sensors by their table number.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from .keys import LEFT_ARM, LEFT_LEG, RIGHT_ARM, RIGHT_LEG, TRUNK, Branch, Site

NODES_PER_BRANCH = 3

#: SmartSuit node number -> site. Nodes 13-15 are the trunk-head IMUs.
SMARTSUIT_SITES: Mapping[int, Site] = MappingProxyType(
    {
        n: Site(branch, name)
        for n, (branch, name) in enumerate(
            [
                (LEFT_ARM, "shoulder"), (LEFT_ARM, "elbow"), (LEFT_ARM, "wrist"),
                (RIGHT_ARM, "shoulder"), (RIGHT_ARM, "elbow"), (RIGHT_ARM, "wrist"),
                (LEFT_LEG, "hip"), (LEFT_LEG, "knee"), (LEFT_LEG, "ankle"),
                (RIGHT_LEG, "hip"), (RIGHT_LEG, "knee"), (RIGHT_LEG, "ankle"),
                (TRUNK, "head"), (TRUNK, "upper_trunk"), (TRUNK, "lower_trunk"),
            ],
            start=1,
        )
    }
)  # fmt: skip

#: SmartSuit nodes that carry a quaternion instead of encoder + accelerometer.
SMARTSUIT_QUAT_NODES = frozenset({13, 14, 15})

#: IMU sensor number (003 seed, Table 5.2) -> (seed's sensor name, site).
IMU_SENSORS: Mapping[int, tuple[str, Site]] = MappingProxyType(
    {
        1: ("Forehead", Site(TRUNK, "forehead")),
        2: ("Chest", Site(TRUNK, "chest")),
        3: ("Left Arm", Site(LEFT_ARM, "upperarm")),
        4: ("Right Arm", Site(RIGHT_ARM, "upperarm")),
        5: ("Left Wrist", Site(LEFT_ARM, "forearm")),
        6: ("Right Wrist", Site(RIGHT_ARM, "forearm")),
        7: ("Left Hand", Site(LEFT_ARM, "hand")),
        8: ("Right Hand", Site(RIGHT_ARM, "hand")),
        9: ("Sacral (Back)", Site(TRUNK, "sacrum")),
        10: ("Left Knee", Site(LEFT_LEG, "thigh")),
        11: ("Right Knee", Site(RIGHT_LEG, "thigh")),
        12: ("Left Ankle", Site(LEFT_LEG, "shank")),
        13: ("Right Ankle", Site(RIGHT_LEG, "shank")),
        14: ("Left Foot", Site(LEFT_LEG, "foot")),
        15: ("Right Foot", Site(RIGHT_LEG, "foot")),
    }
)
IMU_SITES: Mapping[int, Site] = MappingProxyType({n: s for n, (_, s) in IMU_SENSORS.items()})


def smartsuit_branch_index(node: int) -> int:
    """1-based index of the bus branch (in ``keys.BRANCHES`` order) of a node."""
    return (node - 1) // NODES_PER_BRANCH + 1


def branch_of(node: int) -> Branch:
    return SMARTSUIT_SITES[node].branch


@dataclass(frozen=True, slots=True)
class Mount:
    """Where a site's sensor sits: on ``segment``, ``fraction`` of its length along it.

    For a SmartSuit module, ``ole_angle`` names the joint angle its encoder
    spans; its accelerometer rides on ``segment``.
    """

    segment: str
    fraction: float = 0.5
    ole_angle: str | None = None


#: SmartSuit module -> the joint dof its encoder measures (000 seed, ch. 3.1.6
#: and 4.3.2: the encoder covers the dof the accelerometer is blind to).
OLE_DOF = {
    "shoulder": "rotation", "elbow": "flexion", "wrist": "flexion",
    "hip": "rotation", "knee": "flexion", "ankle": "flexion",
}  # fmt: skip

_MODULE_SEGMENT = {"shoulder": "upperarm", "elbow": "forearm", "wrist": "hand",
                   "hip": "thigh", "knee": "shank", "ankle": "foot"}  # fmt: skip
_TRUNK_SEGMENT = {
    "head": ("head", 0.5), "upper_trunk": ("thorax", 0.6), "lower_trunk": ("pelvis", 0.5),
    "forehead": ("head", 0.6), "chest": ("thorax", 0.7), "sacrum": ("pelvis", 0.3),
}  # fmt: skip
_IMU_FRACTION = {"upperarm": 0.5, "forearm": 0.7, "hand": 0.4, "thigh": 0.5, "shank": 0.5,
                 "foot": 0.5}  # fmt: skip


def mount(site: Site) -> Mount:
    """The default mount of a site's sensor."""
    side = site.branch.side
    if site.branch == TRUNK:
        segment, fraction = _TRUNK_SEGMENT[site.name]
        return Mount(segment, fraction)
    if site.name in OLE_DOF:
        return Mount(
            f"{side}_{_MODULE_SEGMENT[site.name]}",
            0.5,
            f"{side}_{site.name}_{OLE_DOF[site.name]}_deg",
        )
    return Mount(f"{side}_{site.name}", _IMU_FRACTION[site.name])
