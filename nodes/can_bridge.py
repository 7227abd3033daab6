"""CAN bridge: SmartSuit frames from any python-can bus (or a log) onto Zenoh.

The source itself is ``nodes.sources.smartsuit_can``; this is its live bridge
under the name earlier code knows.
"""

from __future__ import annotations

from collections.abc import Mapping

import zenoh

from bodynet.core.codecs.smartsuit_can import PERIOD_S
from bodynet.core.keys import Site
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.sources.live import CanBusBridge
from bodynet.nodes.sources.smartsuit_can import SmartSuitCan


class CanBridge(CanBusBridge):
    """Reads a bus (or a log) and publishes every SmartSuit frame it decodes."""

    def __init__(self, session: zenoh.Session, name: str,
                 sites: Mapping[int, Site] = SMARTSUIT_SITES,
                 period_s: float = PERIOD_S) -> None:  # fmt: skip
        super().__init__(session, SmartSuitCan(sites, period_s), name)
