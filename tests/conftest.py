"""Shared test settings: hypothesis profiles and the path of golden captures."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from hypothesis import HealthCheck, settings

sys.path.insert(0, str(Path(__file__).parent))  # the helpers beside the tests

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
