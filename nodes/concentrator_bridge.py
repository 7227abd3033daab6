"""Data Concentrator bridge: poll the nodes over serial, publish their replies.

The bridge writes each request character and feeds both what it wrote and
what came back to the sans-io decoder, exactly as a capture of the link would
read, so pairing, missing replies and garbage are handled in one place.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping, Sequence

import serial
import zenoh

from bodynet.core.codecs import concentrator
from bodynet.core.errors import Reason, Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import OleAccel, Source
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.device import keep_connected
from bodynet.nodes.hardware import CONCENTRATOR_CYCLE_S
from bodynet.nodes.publisher import SitePublisher

BAUD = 115200
REPLY_TIMEOUT_S = 0.1
DEVICE_ERRORS = (serial.SerialException, OSError)


class ConcentratorBridge:
    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        nodes: Sequence[int] = (1, 2, 3),
        sites: Mapping[int, Site] = SMARTSUIT_SITES,
    ) -> None:
        self.nodes = list(nodes)
        period = CONCENTRATOR_CYCLE_S * len(self.nodes)
        self.publisher = SitePublisher(session, sites, Source.CONCENTRATOR, name, period)
        self._cycle = 0

    def run(self, port: str, stop: threading.Event, baud: int = BAUD) -> None:
        def serve(link: serial.Serial) -> None:
            decoder = concentrator.ConcentratorDecoder()
            while not stop.is_set():
                for node in self.nodes:
                    request = concentrator.request(node)
                    link.write(request)
                    self._events(decoder.feed(request))
                    deadline = time.monotonic() + REPLY_TIMEOUT_S
                    while time.monotonic() < deadline and not stop.is_set():
                        events = decoder.feed(link.read(max(1, link.in_waiting)))
                        self._events(events)
                        if any(isinstance(e, OleAccel) for e in events):
                            break
                self._cycle += 1

        keep_connected(
            self.publisher,
            lambda: serial.Serial(port, baud, timeout=0.01),
            serve,
            lambda link: link.close(),
            DEVICE_ERRORS,
            stop,
        )

    def _events(self, events: Sequence[OleAccel | Rejected]) -> None:
        for event in events:
            if isinstance(event, OleAccel):
                self.publisher.publish(event, self._cycle)
            else:  # a missed reply also shows as a gap: the node's next cycle is skipped
                node = int(event.detail.split()[-1]) if event.reason is Reason.NO_REPLY else None
                self.publisher.reject(event, node)

    def close(self) -> None:
        self.publisher.close()
