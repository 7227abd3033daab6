"""A serial bridge on real pseudo-terminals (pyserial), onto a loopback router:
what a wrong baud rate sends is said on the console, a port is held by one
bridge only, and a device unplugged and back is found again at once.

The device is a :class:`PtyPort` behind a symlink, as a USB serial device is
behind ``/dev/serial/by-id/...``; the bridge runs as ``bodynet bridge`` does
(a process) where what it prints is checked, in a thread where its parts are.
"""

from __future__ import annotations

import logging
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

import pytest
import zenoh
from zenoh_helpers import health_collector, raw_collector, wait_until

from bodynet.core.codecs import imu_matrix
from bodynet.core.messages import Quat
from bodynet.core.profile import IMU_SITES
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
from bodynet.nodes.hardware import ImuCentralEmulator, PtyPort
from bodynet.nodes.imu_bridge import ImuCentralBridge
from bodynet.nodes.motion import ROUTINES

BODYNET = Path(sys.executable).with_name("bodynet")
LINE = imu_matrix.encode_line(Quat(1, (1.0, 0.0, 0.0, 0.0), bytes(9)))  # one tick of tag 1
KEY_1 = IMU_SITES[1].raw_key


class Stderr:
    """A process's stderr lines, read as they come."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stderr is not None
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(proc.stderr,), daemon=True)
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.append(line)

    def said(self, text: str) -> list[str]:
        return [line for line in self.lines if text in line]


@pytest.fixture
def bridge_proc(router_endpoint: str) -> Iterator[Callable[[Path], subprocess.Popen[str]]]:
    """``bodynet bridge imu-central --port LINK`` processes, killed at teardown if
    still running."""
    procs: list[subprocess.Popen[str]] = []

    def start(link: Path) -> subprocess.Popen[str]:
        procs.append(subprocess.Popen(
            [str(BODYNET), "bridge", "imu-central", "--port", str(link), "-e", router_endpoint],
            text=True, stderr=subprocess.PIPE))  # fmt: skip
        return procs[-1]

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)


@pytest.fixture
def port(tmp_path: Path) -> Iterator[PtyPort]:
    plugged = PtyPort(tmp_path / "ttyACM0", imu_matrix.BAUD)
    plugged.plug()
    yield plugged
    plugged.unplug()


def _writing(port: PtyPort, data: Callable[[], bytes], done: Callable[[], bool],
             what: str, timeout: float = 30.0) -> None:  # fmt: skip
    """Write ``data()`` to the port every 20 ms until ``done()``."""
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        port.write(data())
        time.sleep(0.02)


def test_bytes_that_never_decode_are_said_and_good_lines_after_them_flow(
    zsession: zenoh.Session, port: PtyPort, bridge_proc: Callable[[Path], subprocess.Popen[str]]
) -> None:
    """A wrong baud rate gives bytes of every value: the bridge says so on its
    console (once for now: every 30 s while it lasts), naming the port and what it
    rejected; right bytes after it are published and the all-clear said."""
    health, raw = health_collector(zsession), raw_collector(zsession)
    bridge = bridge_proc(port.link)
    stderr = Stderr(bridge)
    health.wait_for(lambda h: any(m["device"] == "connected" for _, m in h), timeout=30)
    rng = random.Random(5)
    said = f"imu-central-ttyACM0: receiving bytes from {port.link} but nothing valid for 2 s ("
    _writing(port, lambda: rng.randbytes(220), lambda: bool(stderr.said(said)), "the warning")
    [warning] = stderr.said(said)
    assert "rejected bad_length: " in warning, warning
    assert warning.rstrip().endswith("): wrong --baud (it is 230400)?"), warning
    assert raw.queue.empty()  # nothing of it published

    _writing(port, lambda: LINE, lambda: raw.queue.qsize() >= 20, "samples")
    raw.wait_for(lambda s: len(s) >= 20)
    assert {key for key, _ in raw.seen} == {KEY_1}
    wait_until(lambda: bool(stderr.said(f"imu-central-ttyACM0: {port.link} sends valid data "
                                        "again")), 30, "the all-clear")  # fmt: skip
    assert len(stderr.said(said)) == 1  # not repeated within 30 s
    bridge.send_signal(signal.SIGINT)
    assert bridge.wait(timeout=30) == 0
    assert not stderr.said("Traceback")


def test_a_port_another_bridge_holds_is_refused_and_the_first_loses_nothing(
    zsession: zenoh.Session, port: PtyPort, bridge_proc: Callable[[Path], subprocess.Popen[str]]
) -> None:
    """A second bridge on the port (a second terminal's mistake) says so in one
    line and exits 2 instead of taking a share of its bytes: the first bridge
    publishes every line the device sent meanwhile."""
    health, raw = health_collector(zsession), raw_collector(zsession, KEY_1)
    first = bridge_proc(port.link)
    health.wait_for(lambda h: any(m["device"] == "connected" for _, m in h), timeout=30)
    sent = 0
    second = bridge_proc(port.link)
    while second.poll() is None or sent < 100:  # lines go on while the second tries
        port.write(LINE)
        sent += 1
        assert sent < 3000, "the second bridge did not end"  # a minute of lines
        time.sleep(0.02)
    assert second.returncode == 2
    assert second.communicate()[1] == (
        f"bodynet bridge imu-central: cannot open the device: {port.link} is in use by "
        "another program (another bridge? ModemManager?)\n")  # fmt: skip
    assert port.dropped == 0
    raw.wait_for(lambda s: len(s) >= sent, timeout=30)
    assert len(raw.seen) == sent  # every line, once
    assert raw.queue.empty()
    first.send_signal(signal.SIGINT)
    assert first.wait(timeout=30) == 0


def test_a_port_taken_while_the_device_was_away_is_said_and_waited_for(
    zsession: zenoh.Session, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two bridges waiting for one device (its link absent): the one that opens
    it first holds it; the other says the port is in use, retries, and takes
    over when the first lets go."""
    caplog.set_level(logging.INFO, logger="bodynet.nodes.device")
    port = PtyPort(tmp_path / "ttyACM0", imu_matrix.BAUD)  # not plugged yet
    raw = raw_collector(zsession, KEY_1)
    bridges = {name: ImuCentralBridge(zsession, name) for name in ("imu-a", "imu-b")}
    stops = {name: threading.Event() for name in bridges}
    threads = {name: threading.Thread(target=bridge.run, args=(str(port.link), stops[name]),
                                      daemon=True) for name, bridge in bridges.items()}  # fmt: skip
    try:
        for thread in threads.values():
            thread.start()
        wait_until(lambda: len(caplog.messages) >= 2, 30, "both bridges to wait for the device")
        port.plug()
        busy = f"{port.link} is in use by another program (another bridge? ModemManager?)"
        wait_until(lambda: any(busy in m for m in caplog.messages), 30, "the port said in use")
        [said] = [r for r in caplog.records if busy in r.getMessage()]
        loser = said.getMessage().partition(":")[0]
        [holder] = set(bridges) - {loser}
        assert said.getMessage() == f"{loser}: device unavailable ({busy}); retrying until it " \
                                    "is back"  # fmt: skip
        _writing(port, lambda: LINE, lambda: bridges[holder].publisher.nodes.get(1) is not None,
                 "the holder's samples")  # fmt: skip
        assert bridges[loser].publisher.device == "disconnected"
        assert not bridges[loser].publisher.nodes
        stops[holder].set()
        threads[holder].join(timeout=10)
        _writing(port, lambda: LINE, lambda: bridges[loser].publisher.nodes.get(1) is not None,
                 "the other's samples once the holder let go")  # fmt: skip
        assert f"{loser}: device is back" in caplog.messages
        assert len([m for m in caplog.messages if busy in m]) == 1  # said once, not each retry
    finally:
        for name, thread in threads.items():
            stops[name].set()
            thread.join(timeout=10)
        for bridge in bridges.values():
            bridge.close()
        port.unplug()
        raw.close()


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
    central = ImuCentralEmulator(tmp_path / "imu", body, tick_s=0.01, interval_s=0.005)
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
