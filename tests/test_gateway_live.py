"""The live gateway on loopback Zenoh, fed by emulated hardware on real transports."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from zenoh_helpers import Collector, client

from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.keys import LEFT_ARM
from bodynet.core.profile import IMU_SITES
from bodynet.core.skeleton import TPOSE
from bodynet.gateway import profile_file
from bodynet.gateway.service import Gateway
from bodynet.nodes.emulator import Realism
from bodynet.nodes.motion import Routine
from bodynet.nodes.services import EmulationOptions, NodePlan, run_node

IDEAL_RANDOM_MOUNTS = Realism(0.0, 0.0, 0.0, 0.0, 0.0, random_tag_mounts=True)
TARGET = {
    "lumbar_flexion_deg": 20.0,
    "left_shoulder_flexion_deg": 40.0,
    "left_elbow_flexion_deg": 60.0,
    "right_shoulder_abduction_deg": 30.0,
    "right_elbow_flexion_deg": 90.0,
    "left_knee_flexion_deg": 45.0,
}


class Running:
    """``target(*head, stop, *tail)`` in a thread: services take ``stop`` after the session."""

    def __init__(self, target: Any, *args: Any) -> None:
        self.stop_event = threading.Event()
        head, tail = args[:1], args[1:]
        self.thread = threading.Thread(
            target=target, args=(*head, self.stop_event, *tail), daemon=True
        )
        self.thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(timeout=15)


@pytest.fixture
def gateway(router_endpoint: str, tmp_path: Path) -> Iterator[Gateway]:
    session = client(router_endpoint)
    gw = Gateway(session, profile_path=tmp_path / "subject.toml")
    running = Running(gw.run)
    yield gw
    running.stop()
    gw.close()
    session.close()


def close_to(frame: pose.PoseFrame, target: dict[str, float], tol: float) -> bool:
    return all(abs(frame.angles_deg[n] - target.get(n, 0.0)) <= tol for n in target)


def test_gateway_calibrates_tracks_and_flags_stale(
    gateway: Gateway, router_endpoint: str, zsession: zenoh.Session
) -> None:
    current = {"pose": dict(TPOSE)}
    routine = Routine("scripted", "", lambda t: dict(current["pose"]))
    plans = [
        NodePlan("smartsuit", "can", (LEFT_ARM,)),  # the left arm by encoders and tilt
        NodePlan("imu", "imu-central", sensors=tuple(n for n, s in IMU_SITES.items()
                                                     if s.branch != LEFT_ARM)),
    ]  # fmt: skip
    node_session = client(router_endpoint)
    options = EmulationOptions(routine, IDEAL_RANDOM_MOUNTS, seed=3)
    nodes = Running(run_node, node_session, plans, options, "live")
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    left = Collector(zsession, keys.pose_key(LEFT_ARM), pose.decode)
    poses.wait_for(lambda s: bool(s) and len(s[-1][1].sources) == 15, timeout=20)  # all delivering

    replies = list(zsession.get(f"{keys.CALIBRATE_TPOSE}?seconds=0.5", timeout=10))
    result = json.loads(replies[0].ok.payload.to_bytes())
    assert result["ok"]
    assert "body/trunk/mid/chest/raw" in result["calibrated"]
    assert profile_file.load(Path(result["profile"])).imu_mounts  # written for next time

    current["pose"] = dict(TARGET)
    seen = poses.wait_for(lambda s: close_to(s[-1][1], TARGET, 0.3), timeout=20)
    frame = seen[-1][1]
    assert frame.flags.get("left_elbow_flexion_deg") is None
    assert frame.stale == []
    assert frame.segments["left_hand"][0][0] > 0.1  # the bent left arm reaches forward
    view = left.wait_for(bool)[-1][1]
    assert {n.rsplit("_", 2)[0] for n in view.angles_deg} == {
        "left_shoulder",
        "left_elbow",
        "left_wrist",
    }
    assert all(k.startswith("body/arm/left/") for k in view.sources)

    topology = json.loads(next(iter(zsession.get(keys.TOPOLOGY, timeout=5))).ok.payload.to_bytes())
    assert set(topology["branches"]) == {"left-arm", "right-arm", "left-leg", "right-leg", "trunk"}

    nodes.stop()  # every sensor goes: the last pose holds, flagged stale
    node_session.close()
    seen = poses.wait_for(lambda s: bool(s[-1][1].stale), timeout=10) if gateway.samples else []
    assert close_to(seen[-1][1], TARGET, 0.3)


def test_garbage_on_raw_keys_is_counted_and_never_stops_the_body(
    gateway: Gateway, router_endpoint: str, zsession: zenoh.Session
) -> None:
    held = {"left_elbow_flexion_deg": 60.0}
    plans = [NodePlan("smartsuit", "can", (LEFT_ARM,))]
    node_session = client(router_endpoint)
    options = EmulationOptions(Routine("held", "", lambda t: dict(held)), Realism.ideal())
    nodes = Running(run_node, node_session, plans, options, "victim")
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    poses.wait_for(
        lambda s: bool(s) and abs(s[-1][1].angles_deg["left_elbow_flexion_deg"] - 60) < 0.3
    )
    hostile = client(router_endpoint)
    bad = [
        b"",
        b"\x00" * 28,
        b"BN\x01\x01" + bytes(100),
        b"BN\x09" + bytes(30),
        b"{}",
        bytes(range(256)),
    ]
    flooding = threading.Event()
    stop_flood = threading.Event()

    def flood() -> None:  # as fast as it goes, on a live key and on keys outside the key space
        i = 0
        while not stop_flood.is_set():
            hostile.put("body/arm/left/elbow/raw", bad[i % len(bad)])
            hostile.put("body/arm/left/bogus/raw", b"BN")
            i += 1
            if i == 1000:
                flooding.set()

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    assert flooding.wait(timeout=30)
    held["left_elbow_flexion_deg"] = 100.0  # the body moves while the flood goes on
    n = len(poses.seen)
    poses.wait_for(
        lambda s: len(s) > n and abs(s[-1][1].angles_deg["left_elbow_flexion_deg"] - 100) < 0.3
    )
    assert flooder.is_alive()  # the poses came through during the flood
    stop_flood.set()
    flooder.join(timeout=10)
    assert sum(gateway.rejected.values()) >= 2000
    assert gateway.solver_errors == 0
    health = json.loads(next(iter(zsession.get(keys.TOPOLOGY, timeout=5))).ok.payload.to_bytes())
    assert "left-arm" in health["branches"]
    hostile.close()
    nodes.stop()
    node_session.close()
