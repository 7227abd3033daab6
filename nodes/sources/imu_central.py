"""The IMU central (003 seed): its tags' quaternions as a data matrix over serial.

A sample's sequence number is the central's tick, so a tick where a tag had no
new data (flag 00) shows downstream as a gap of one; a capture, which has no
clock, times each tick at 25 Hz (``--rate-hz`` to say otherwise).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

from bodynet.core.codecs import imu_matrix as codec
from bodynet.core.messages import Source as SourceId
from bodynet.core.profile import IMU_SITES
from bodynet.nodes.sources.base import NodeParts, Transport
from bodynet.nodes.sources.serial_port import SerialSource


class ImuCentral(SerialSource):
    name = "imu-central"
    wire_id = SourceId.IMU_CENTRAL
    transport = Transport.SERIAL
    help = "the imu-central on a serial port (230400 baud)"
    SITES = IMU_SITES
    PERIOD_S = codec.TICK_S
    BAUD = codec.BAUD
    formats: ClassVar = {"imu-central": "the IMU central's data matrix (hex lines)"}
    emulators: ClassVar = {"imu-central": "the IMU central with its tags"}
    TIMING: ClassVar = frozenset({"timers", "clock_ppm", "jitter_s", "drop"})

    def decoder(self) -> codec.ImuMatrixDecoder:
        return codec.ImuMatrixDecoder()

    def emulated_sensors(self, sensors: Any = None, branches: Any = None) -> list[Any]:
        from bodynet.nodes.emulator import imu_tags

        return imu_tags(sensors, branches)

    def emulator(self, device: str, body: Any, truth: Any, opts: dict[str, Any]) -> Any:
        from bodynet.nodes.hardware import ImuCentralEmulator

        return ImuCentralEmulator(opts["link"], body, truth=truth, timing=opts.get("timing"))

    def node(self, device: str, body: Any, where: Path, clock: Any, truth: Any,
             sensors: list[Any], label: str, timing: Any = None) -> NodeParts:  # fmt: skip
        from bodynet.nodes.hardware import ImuCentralEmulator

        emulator = ImuCentralEmulator(where / label, body, clock, truth, timing=timing)
        return emulator, self.run_bridge, {"port": str(where / label)}
