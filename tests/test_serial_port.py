"""A serial bridge on real pseudo-terminals (pyserial), onto a loopback router:
a device unplugged and back is found again at once.

The device is a :class:`PtyPort` behind a symlink, as a USB serial device is
behind ``/dev/serial/by-id/...``; the bridge runs in a thread.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import pytest
import zenoh
from zenoh_helpers import wait_until

from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
from bodynet.nodes.hardware import ImuCentralEmulator
from bodynet.nodes.imu_bridge import ImuCentralBridge
from bodynet.nodes.motion import ROUTINES


class RecordedStop(threading.Event):
    """A stop event that keeps what each wait on it was for: a bridge's retries."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[float | None] = []

    def wait(self, timeout: float | None = None) -> bool:
        self.waits.append(timeout)
        return super().wait(timeout)


def test_a_device_unplugged_and_back_is_retried_every_half_second_quietly(
    zsession: zenoh.Session, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """While the device is away the bridge tries it again at most 0.5 s apart
    (a replug is found within half a second), says so once, and resumes."""
    caplog.set_level(logging.DEBUG, logger="bodynet.nodes.device")
    body = BodyEmulator(ROUTINES["tpose"], imu_tags([1, 2]), realism=Realism.ideal())
    central = ImuCentralEmulator(tmp_path / "imu", body, tick_s=0.01)
    central.start()
    bridge = ImuCentralBridge(zsession, "replug")
    stop = RecordedStop()
    thread = threading.Thread(target=bridge.run, args=(str(central.link), stop), daemon=True)
    thread.start()
    try:
        wait_until(lambda: bridge.publisher.nodes.get(1, None) is not None, 30, "samples")
        node = bridge.publisher.nodes[1]
        central.port.unplug()
        wait_until(lambda: len(stop.waits) >= 8, 60, "the bridge to retry eight times")
        before, last_seq = node.samples, node.last_seq or 0
        central.port.plug()
        wait_until(lambda: node.samples >= before + 10, 30, "samples after the replug")
        assert (node.last_seq or 0) > last_seq  # sequence numbers go on rising
        assert max(w for w in stop.waits if w is not None) <= 0.5, stop.waits
        said = [r.getMessage().partition(": ")[2] for r in caplog.records
                if r.name == "bodynet.nodes.device" and r.levelno >= logging.INFO]  # fmt: skip
        assert [s.partition(" (")[0] for s in said] == [
            "device connected", "device lost", "device is back"]  # fmt: skip
    finally:
        stop.set()
        thread.join(timeout=10)
        central.stop()
        bridge.close()
