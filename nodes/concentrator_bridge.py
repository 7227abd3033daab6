"""Data Concentrator bridge: the live bridge of ``nodes.sources.concentrator``
under the name earlier code knows."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import zenoh

from bodynet.core.keys import Site
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.sources.concentrator import Concentrator
from bodynet.nodes.sources.live import SerialBridge


class ConcentratorBridge(SerialBridge):
    def __init__(self, session: zenoh.Session, name: str, nodes: Sequence[int] = (1, 2, 3),
                 sites: Mapping[int, Site] = SMARTSUIT_SITES) -> None:  # fmt: skip
        super().__init__(session, Concentrator(sites, None, nodes), name)
