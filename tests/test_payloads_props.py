"""Every Zenoh payload the gateway and the clients accept, fuzzed.

Decoders answer garbage with a ``DecodeError`` (a declared, counted reason)
and nothing else; the live gateway counts every hostile message (as a sample
or a rejection: none vanishes in a swallowed exception) and goes on serving
the body; the T-pose query answers any parameter with a JSON verdict; the
viewer's status panel shows whatever topology and health JSON it is given.
A longer run: ``HYPOTHESIS_PROFILE=long .venv/bin/python -m pytest
tests/test_payloads_props.py tests/test_codecs_props.py --timeout=0``.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from zenoh_helpers import client, free_port

from bodynet.clients.view import status_text
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError
from bodynet.core.messages import OleAccel, Quat, RawSample, Source
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES
from bodynet.gateway.service import Gateway
from bodynet.session import open_session, session_config

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=20,
)

GOOD_POSE = pose.encode(
    pose.PoseFrame(3, 10, {"left_elbow_flexion_deg": 1.0}, {"left_elbow": 1.0},
                   {"left_forearm": ((0.0, 0.1, 1.0), (1.0, 0.0, 0.0, 0.0))},
                   {"left_elbow": (0.0, 0.2, 1.1)}, {}, {"body/arm/left/elbow/raw": 9}, [])
)  # fmt: skip


@st.composite
def mutated_poses(draw: st.DrawFn) -> bytes:
    """A real pose message with some fields (at any depth) replaced by random JSON."""
    d: Any = json.loads(GOOD_POSE)
    for _ in range(draw(st.integers(1, 3))):
        node, path = d, []
        while isinstance(node, dict) and node and draw(st.booleans()):
            key = draw(st.sampled_from(sorted(node)))
            path.append(key)
            node = node[key]
        target = d
        for key in path[:-1]:
            target = target[key]
        if path:
            target[path[-1]] = draw(json_values)
    return json.dumps(d).encode()


def pose_or_declared_error(data: bytes) -> None:
    try:
        frame = pose.decode(data)
    except DecodeError:
        return
    pose.encode(frame)  # what decodes, encodes again
    assert all(len(p) == 3 and len(q) == 4 for p, q in frame.segments.values())
    assert all(len(p) == 3 for p in frame.joints_m.values())


@given(st.binary(max_size=300))
def test_pose_decode_of_random_bytes(data: bytes) -> None:
    pose_or_declared_error(data)


@given(json_values)
def test_pose_decode_of_random_json(value: Any) -> None:
    pose_or_declared_error(json.dumps(value).encode())


@given(mutated_poses())
def test_pose_decode_of_pose_shaped_json(data: bytes) -> None:
    pose_or_declared_error(data)


def test_pose_decode_of_deep_nesting_and_huge_numbers() -> None:
    for data in (
        b"[" * 100_000,
        b'{"v":1,"seq":1e999}',
        GOOD_POSE.replace(b'"seq":3', b'"seq":1e400'),
        GOOD_POSE.replace(b'"seq":3', b'"seq":1.8446744073709552e+19'),  # 2**64: no 64-bit field
    ):
        with pytest.raises(DecodeError):
            pose.decode(data)


@given(json_values, st.dictionaries(st.text(max_size=8), json_values, max_size=3))
def test_status_panel_shows_any_topology_and_health(topology: Any, health: Any) -> None:
    text = status_text(topology, health)
    assert text.startswith("## Topology")


# --- the live gateway --------------------------------------------------------------


@pytest.fixture(scope="module")
def live() -> Iterator[tuple[Gateway, zenoh.Session]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(session_config("router", listen=[endpoint]))
    gw_session, hostile = client(endpoint), client(endpoint)
    gateway = Gateway(gw_session)
    stop = threading.Event()
    thread = threading.Thread(target=gateway.run, args=(stop,), daemon=True)
    thread.start()
    yield gateway, hostile
    stop.set()
    thread.join(timeout=15)
    gateway.close()
    for s in (hostile, gw_session, router):
        s.close()


def counted(gateway: Gateway) -> int:
    # samples are taken (or rejected) on Zenoh's callback thread, before any queueing
    return gateway.samples + sum(gateway.rejected.values()) + gateway.refused_subjects


def wait_counted(gateway: Gateway, n: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while counted(gateway) < n:
        assert time.monotonic() < deadline, f"counted {counted(gateway)} of {n}"
        threading.Event().wait(0.001)


SITE_KEYS = sorted(s.raw_key for s in (*SMARTSUIT_SITES.values(), *IMU_SITES.values()))
raw_keys = st.sampled_from(SITE_KEYS) | st.builds(
    lambda limb, side, site: f"body/{limb}/{side}/{site}/raw",
    st.sampled_from(["arm", "leg", "trunk", "x"]), st.sampled_from(["left", "mid", "up"]),
    st.from_regex(r"[a-z_]{1,10}", fullmatch=True),
)  # fmt: skip
readings = st.one_of(
    st.builds(OleAccel, st.integers(0, 0xFFFF), st.integers(-0x8000, 0x7FFF),
              st.tuples(*[st.integers(-0x8000, 0x7FFF)] * 3)),
    st.builds(Quat, st.integers(0, 0xFFFF),
              st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(
                  lambda q: 0.9 <= sum(c * c for c in q) ** 0.5 <= 1.1)),
)  # fmt: skip
valid_messages = st.builds(
    lambda r, seq, t, src: raw_sample.encode(RawSample(r, seq, t, src)),
    readings, st.integers(0, 2**32 - 1), st.integers(-(2**63), 2**63 - 1), st.sampled_from(Source),
)  # fmt: skip
payloads = (
    st.binary(max_size=120)
    | valid_messages
    | st.builds(lambda m, cut: m[:cut], valid_messages, st.integers(0, 60))
)


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], deadline=None)
@given(raw_keys, payloads)
def test_gateway_counts_every_payload_on_any_raw_key(
    live: tuple[Gateway, zenoh.Session], key: str, payload: bytes
) -> None:
    gateway, hostile = live
    before = counted(gateway)
    hostile.put(key, payload)
    wait_counted(gateway, before + 1)  # a swallowed exception would leave it uncounted
    assert gateway.solver_errors == 0


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], deadline=None)
@given(st.text(max_size=20))
def test_tpose_query_answers_any_parameter(live: tuple[Gateway, zenoh.Session], value: str) -> None:
    _, session = live
    try:
        replies = list(session.get(f"{keys.CALIBRATE_TPOSE}?seconds={value}", timeout=10))
    except zenoh.ZError:
        return  # the client's own library refused the selector: nothing was sent
    answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    assert len(answers) == 1
    assert isinstance(answers[0]["ok"], bool)
