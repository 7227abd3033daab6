"""Shared test settings: hypothesis profiles and the path of golden captures."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from hypothesis import HealthCheck, settings

sys.path.insert(0, str(Path(__file__).parent))  # the helpers beside the tests

from zenoh_helpers import Running

settings.register_profile(
    "default", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
# `HYPOTHESIS_PROFILE=long` for a longer fuzzing run of the codecs.
settings.register_profile(
    "long", max_examples=20_000, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

DATA = Path(__file__).parent / "data"


@pytest.fixture
def data_dir() -> Path:
    return DATA


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """A Zenoh router on a free loopback port, scouting off."""
    from zenoh_helpers import free_port

    from bodynet.session import open_session, session_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(session_config("router", listen=[endpoint]))
    yield endpoint
    router.close()


@pytest.fixture
def zsession(router_endpoint: str) -> Iterator[zenoh.Session]:
    from zenoh_helpers import client

    session = client(router_endpoint)
    yield session
    session.close()


def _bodynet(*args: object) -> None:
    """``bodynet ARGS`` in this process (no interpreter to start); it must succeed."""
    from bodynet.cli.main import main

    assert main([str(a) for a in args]) == 0


@pytest.fixture(scope="session")
def body_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real recording of the whole body moving every dof (the exports' tests):
    3 s of T-pose, then 4 s of smooth random motion, through the IMU central's
    data matrix at 25 Hz and `bodynet process`."""
    from bodynet.core.codecs import imu_matrix
    from bodynet.core.messages import Quat
    from bodynet.core.skeleton import TPOSE
    from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
    from bodynet.nodes.motion import ROUTINES, Routine

    tmp = tmp_path_factory.mktemp("body")
    wander = ROUTINES["random"].angles
    motion = Routine("capture", "", lambda t: dict(TPOSE) if t < 3.0 else wander(t - 3.0))
    realism = Realism(0.0, 0.0, 0.0, 0.0, 0.0, random_tag_mounts=True)
    body = BodyEmulator(motion, imu_tags(), realism=realism, seed=7)
    capture = tmp / "session.txt"
    with capture.open("wb") as f:
        for tick in range(25 * 7):
            readings, _ = body.sample(tick / 25)
            f.write(b"".join(imu_matrix.encode_line(r) for r in readings if isinstance(r, Quat)))
    out = tmp / "session.mcap"
    _bodynet("process", capture, "--format", "imu-central", "-o", out)
    return out


@pytest.fixture(scope="session")
def arm_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The golden SmartSuit CAN log (left elbow 0-90-0, 100 Hz) processed."""
    out = tmp_path_factory.mktemp("arm") / "arm.mcap"
    # its head IMU nods from the first sample (no still window to calibrate from) and
    # sits on the suit as the emulator put it: its orientation is the head's own
    _bodynet("process", DATA / "smartsuit_arm.log", "-o", out, "--tpose-s", "0")
    return out


@pytest.fixture(scope="session")
def flagged(body_mcap: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``body_mcap`` with some angles flagged not measured for a window of frames
    (``export_recordings``)."""
    from export_recordings import write_flagged

    out = tmp_path_factory.mktemp("flagged") / "flagged.mcap"
    write_flagged(body_mcap, out)
    return out


@pytest.fixture
def run_thread() -> Iterator[Callable[..., Running]]:
    """Start a bridge's ``run`` in a thread; every one is stopped at teardown."""
    started: list[Running] = []

    def start(target: Callable[..., None], *args: Any, **kwargs: Any) -> Running:
        started.append(Running(lambda stop: target(*args, stop, **kwargs), timeout=10))
        return started[-1]

    yield start
    for running in started:
        running.stop()


@pytest.fixture
def gateway(router_endpoint: str, tmp_path: Path) -> Iterator[Any]:
    """A gateway on a client session of ``router_endpoint``, running, its profile
    in ``tmp_path``; stopped and closed at teardown."""
    from zenoh_helpers import client

    from bodynet.gateway.service import Gateway

    session = client(router_endpoint)
    gw = Gateway(session, profile_path=tmp_path / "subject.toml")
    running = Running(gw.run)
    yield gw
    running.stop()
    gw.close()
    session.close()
