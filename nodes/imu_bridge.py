"""IMU central bridge: the data matrix from a serial port onto Zenoh.

A sample's sequence number is the central's tick, so a tick where a tag had
no new data (flag 00) shows downstream as a gap of one.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping

import serial
import zenoh

from bodynet.core.codecs.imu_matrix import ImuMatrixDecoder
from bodynet.core.errors import Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import NoNewData, Quat, SensorAbsent, Source, Tick
from bodynet.core.profile import IMU_SITES
from bodynet.nodes.device import keep_connected
from bodynet.nodes.hardware import IMU_TICK_S
from bodynet.nodes.publisher import SitePublisher

BAUD = 230400
DEVICE_ERRORS = (serial.SerialException, OSError)


class ImuCentralBridge:
    def __init__(
        self,
        session: zenoh.Session,
        name: str,
        sites: Mapping[int, Site] = IMU_SITES,
        tick_s: float = IMU_TICK_S,
    ) -> None:
        self.publisher = SitePublisher(session, sites, Source.IMU_CENTRAL, name, tick_s)
        self.absent: set[int] = set()
        self._tick_base = 0  # ticks of earlier connections, so seq keeps rising

    def run(self, port: str, stop: threading.Event, baud: int = BAUD) -> None:
        def serve(link: serial.Serial) -> None:
            decoder = ImuMatrixDecoder()
            tick = 0
            try:
                while not stop.is_set():
                    for event in decoder.feed(link.read(max(1, link.in_waiting))):
                        if isinstance(event, Quat):
                            self.absent.discard(event.node)
                            self.publisher.publish(event, self._tick_base + tick)
                        elif isinstance(event, Tick):
                            tick = event.index
                        elif isinstance(event, NoNewData):
                            pass  # shows as a gap: the tag's next sample skips this tick
                        elif isinstance(event, SensorAbsent):
                            self.absent.add(event.node)
                        elif isinstance(event, Rejected):
                            self.publisher.reject(event)
            finally:
                self._tick_base += tick + 1

        keep_connected(
            self.publisher,
            lambda: serial.Serial(port, baud, timeout=0.05),
            serve,
            lambda link: link.close(),
            DEVICE_ERRORS,
            stop,
        )

    def close(self) -> None:
        self.publisher.close()
