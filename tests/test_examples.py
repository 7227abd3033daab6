"""The examples in examples/ run as their own processes against a live gateway.

A real gateway and an emulated IMU body (its central on a pseudo-terminal and
its bridge) on a loopback router; each example is started with the standard
session flags pointing at that router, and what it prints is checked."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import pytest
from zenoh_helpers import Collector, Running, client

from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.profile import IMU_SITES
from bodynet.gateway.service import Gateway
from bodynet.nodes.emulator import Realism
from bodynet.nodes.motion import ROUTINES
from bodynet.nodes.services import EmulationOptions, NodePlan, run_node

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
IDEAL = Realism(0.0, 0.0, 0.0, 0.0, 0.0, random_tag_mounts=True)


@pytest.fixture(scope="module")
def live_body(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A router, a gateway and an emulated IMU body standing in T-pose; the router's endpoint."""
    from zenoh_helpers import free_port

    from bodynet.session import open_session, session_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(session_config("router", listen=[endpoint]))
    gw_session, node_session, watch = client(endpoint), client(endpoint), client(endpoint)
    gateway = Gateway(gw_session, profile_path=tmp_path_factory.mktemp("gw") / "subject.toml")
    serving = Running(gateway.run)
    plan = NodePlan("imu", "imu-central", sensors=tuple(IMU_SITES))
    options = EmulationOptions(ROUTINES["tpose"], IDEAL, seed=5)
    nodes = Running(partial(run_node, node_session, plans=[plan], options=options, name="ex"))
    poses = Collector(watch, keys.pose_key(), pose.decode)
    poses.wait_for(lambda s: bool(s) and len(s[-1][1].sources) == len(IMU_SITES), timeout=30)
    poses.close()
    yield endpoint
    nodes.stop()
    serving.stop()
    gateway.close()
    for session in (watch, node_session, gw_session, router):
        session.close()


def run_example(name: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_pose_subscriber_prints_whole_body_poses(live_body: str) -> None:
    done = run_example("pose_subscriber.py", "-e", live_body, "--count", "3")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert len(lines) == 3
    seqs = [int(line.split(" ", 1)[0]) for line in lines]
    assert seqs == sorted(seqs)
    assert "'left_elbow_flexion_deg'" in lines[-1]


def test_branch_subscriber_gets_only_its_branch(live_body: str) -> None:
    done = run_example("branch_subscriber.py", "-e", live_body, "--branch", "right-leg",
                       "--count", "2")  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert len(lines) == 2
    assert all(line.startswith("body/leg/right/pose ") for line in lines)
    assert "'right_shank'" in lines[-1]
    assert "left" not in lines[-1]  # no segment of another branch


def test_calibrate_tpose_gets_the_gateways_verdict(live_body: str) -> None:
    done = run_example("calibrate_tpose.py", "-e", live_body, "--seconds", "0.5")
    assert done.returncode == 0, done.stdout + done.stderr
    verdict = json.loads(done.stdout)
    assert verdict["ok"] is True
    assert "body/trunk/mid/chest/raw" in verdict["calibrated"]


def test_an_example_says_when_no_gateway_answers(tmp_path: Path) -> None:
    """Against a router with no gateway behind it, the calibration example fails plainly."""
    from zenoh_helpers import free_port

    from bodynet.session import open_session, session_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(session_config("router", listen=[endpoint]))
    try:
        done = run_example("calibrate_tpose.py", "-e", endpoint)
    finally:
        router.close()
    assert done.returncode == 1
    assert "no gateway answered" in done.stderr
