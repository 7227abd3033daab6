"""IMU central bridge: the live bridge of ``nodes.sources.imu_central`` under the
name earlier code knows."""

from __future__ import annotations

from collections.abc import Mapping

import zenoh

from bodynet.core.codecs.imu_matrix import TICK_S
from bodynet.core.keys import Site
from bodynet.core.profile import IMU_SITES
from bodynet.nodes.sources.imu_central import ImuCentral
from bodynet.nodes.sources.live import SerialBridge


class ImuCentralBridge(SerialBridge):
    def __init__(self, session: zenoh.Session, name: str,
                 sites: Mapping[int, Site] = IMU_SITES,
                 tick_s: float = TICK_S) -> None:  # fmt: skip
        super().__init__(session, ImuCentral(sites, tick_s), name)
