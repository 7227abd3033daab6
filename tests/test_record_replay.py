"""`bodynet record` (with rotation) and `bodynet replay`, as processes (salvage: test_faults)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import zenoh
from zenoh_helpers import raw_collector

from bodynet.clients.mcap_store import read_raw
from bodynet.core.keys import LEFT_ARM
from bodynet.nodes.can_bridge import CanBridge
from bodynet.nodes.emulator import BodyEmulator, Realism, smartsuit_sensors
from bodynet.nodes.hardware import CanNodes
from bodynet.nodes.motion import ROUTINES

BODYNET = Path(sys.executable).with_name("bodynet")


@pytest.fixture
def live_arm(zsession: zenoh.Session) -> Iterator[None]:
    """A SmartSuit left arm on a virtual bus, bridged onto the test router."""
    channel = f"rec-{time.monotonic_ns()}"
    stop = threading.Event()
    bridge = CanBridge(zsession, "rec-test")
    bus_args = {"interface": "virtual", "channel": channel}
    thread = threading.Thread(target=bridge.run_bus, args=(stop,), kwargs=bus_args, daemon=True)
    thread.start()
    with can.Bus(interface="virtual", channel=channel) as bus:
        nodes = CanNodes(bus, BodyEmulator(ROUTINES["elbow-slow"], smartsuit_sensors([LEFT_ARM]),
                                           realism=Realism.ideal()))  # fmt: skip
        nodes.start()
        yield
        nodes.stop()
    stop.set()
    thread.join(timeout=10)
    bridge.close()


def start_recorder(endpoint: str, out: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([str(BODYNET), "record", "-o", str(out), *extra, "-e", endpoint],
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def wait_for_size(path: Path, size: int, timeout: float = 20) -> None:
    deadline = time.monotonic() + timeout
    while not (path.exists() and path.stat().st_size >= size):
        assert time.monotonic() < deadline, f"{path} never reached {size} bytes"
        threading.Event().wait(0.05)


def test_record_stops_cleanly_into_a_complete_private_file(
    live_arm: None, zsession: zenoh.Session, router_endpoint: str, tmp_path: Path
) -> None:
    out = tmp_path / "session.mcap"
    raw = raw_collector(zsession, "body/*/*/*/raw")
    rec = start_recorder(router_endpoint, out)
    raw.wait_for(lambda s: len(s) >= 300)  # about a second of the arm
    wait_for_size(out, 2000)
    rec.send_signal(signal.SIGINT)
    assert rec.wait(timeout=20) == 0
    assert out.stat().st_mode & 0o777 == 0o600
    samples = list(read_raw(out))
    assert len(samples) > 100
    assert {topic for topic, _, _ in samples} == {
        "body/arm/left/shoulder/raw",
        "body/arm/left/elbow/raw",
        "body/arm/left/wrist/raw",
    }


def test_rotation_by_time(live_arm: None, router_endpoint: str, tmp_path: Path) -> None:
    out = tmp_path / "rot.mcap"
    rec = start_recorder(router_endpoint, out, "--rotate-s", "0.5")
    wait_for_size(tmp_path / "rot-002.mcap", 1)
    rec.send_signal(signal.SIGINT)
    assert rec.wait(timeout=20) == 0
    assert len(list(read_raw(out))) > 0
    assert len(list(read_raw(tmp_path / "rot-001.mcap"))) > 0


def test_replay_republishes_a_recording(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path, data_dir: Path
) -> None:
    mcap = tmp_path / "arm.mcap"
    subprocess.run([str(BODYNET), "process", str(data_dir / "smartsuit_arm.log"), "-o", str(mcap)],
                   check=True, capture_output=True, timeout=60)  # fmt: skip
    raw = raw_collector(zsession, "body/*/*/*/raw")
    result = subprocess.run([str(BODYNET), "replay", str(mcap), "--speed", "4", "-q",
                             "-e", router_endpoint], capture_output=True, text=True, timeout=60,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "400 samples published" in result.stderr
    seen = raw.wait_for(lambda s: len(s) >= 400)
    assert len(seen) == 400
    assert seen[0][1].reading == next(read_raw(mcap))[2].reading
