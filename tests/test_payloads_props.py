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
import math
import threading
import time
from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import rerun as rr
import zenoh
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from zenoh_helpers import Running, client, free_port, wait_matching

from bodynet.clients.view import GAUGES, MAX_M, Viewer, drawing, status_text
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError, Reason
from bodynet.core.messages import OleAccel, Quat, RawSample, Source
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES
from bodynet.core.skeleton import build_skeleton
from bodynet.gateway.service import Gateway
from bodynet.nodes.publisher import NodeHealth
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


node_healths = st.fixed_dictionaries({
    "key": st.sampled_from(sorted(s.raw_key for s in IMU_SITES.values())),
    "alive": st.booleans(), "rate_hz": st.integers(0, 1000), "samples": st.integers(0, 2**40),
    "gaps": st.integers(0, 2**32), "rejected": st.dictionaries(st.sampled_from(list(Reason)),
                                                               st.integers(1, 99), max_size=2),
})  # fmt: skip
bridge_healths = st.fixed_dictionaries({
    "source": st.text(max_size=8), "kind": st.just("imu"),
    "device": st.sampled_from(["connected", "reconnecting"]), "t_ns": st.integers(0, 2**63 - 1),
    "rejected": st.dictionaries(st.sampled_from(list(Reason)), st.integers(1, 99), max_size=2),
    "nodes": st.dictionaries(st.integers(0, 20).map(str), node_healths, max_size=4),
})  # fmt: skip


@given(json_values, st.dictionaries(st.text(max_size=8), json_values, max_size=2),
       st.dictionaries(st.text(max_size=8), bridge_healths, min_size=1, max_size=3),
       st.integers(0, 10**6))  # fmt: skip
def test_status_panel_shows_each_nodes_health(
    topology: Any, junk: dict[str, Any], bridges: dict[str, Any], bad: int
) -> None:
    """Among health of any shape, every bridge's device and every node's
    liveliness, rate, samples, gaps and rejections are in the panel."""
    text = status_text(topology, {**junk, **bridges}, bad)
    for source, h in bridges.items():
        assert f"- **{source}**: device {h['device']}" in text
        for node, n in h["nodes"].items():
            rejected = ", ".join(f"{r} {c}" for r, c in sorted(n["rejected"].items())) or "0"
            assert (
                f"  - node {node} `{n['key']}`: {'alive' if n['alive'] else 'not alive'}, "
                f"{n['rate_hz']} Hz, {n['samples']} samples, {n['gaps']} gaps, "
                f"rejected {rejected}"
            ) in text.splitlines()
    assert (f"{bad} bad messages" in text) == (bad > 0)


def test_status_panel_shows_what_a_bridge_publishes() -> None:
    """The health JSON of ``nodes/publisher.py``, as it is built."""
    site = next(iter(IMU_SITES.values()))
    now = time.monotonic()
    node = NodeHealth(site, samples=4321, gaps=13, alive=True, window=deque([now] * 97))
    node.rejected[Reason.BAD_LENGTH] += 2
    health = {"imu-ttyUSB0": {"source": "imu-ttyUSB0", "kind": "imu", "device": "connected",
                              "t_ns": time.time_ns(), "rejected": {},
                              "nodes": {"5": node.as_json(now)}}}  # fmt: skip
    text = status_text(None, json.loads(json.dumps(health)))
    assert "- **imu-ttyUSB0**: device connected, rejected 0" in text
    assert (f"  - node 5 `{site.raw_key}`: alive, 97 Hz, 4321 samples, 13 gaps, "
            "rejected bad_length 2") in text.splitlines()  # fmt: skip


def test_status_panel_shows_other_devices_frames_apart_from_rejections() -> None:
    """A CAN bridge on a bus shared with other devices: their frames by kind."""
    health = {"can-can0": {"source": "can-can0", "device": "connected", "nodes": {},
                           "rejected": {"bad_dlc": 1},
                           "foreign": {"standard_id": 20, "remote_frame": 3}}}  # fmt: skip
    assert ("- **can-can0**: device connected, rejected bad_dlc 1, other devices' frames "
            "remote_frame 3, standard_id 20") in status_text(None, health)  # fmt: skip


SKELETON = build_skeleton()
# what pose.decode takes for a number: any JSON number, a boolean, or a string
# float() reads ("nan", "inf", "1e999")
numbers = (
    st.floats(width=64).map(lambda x: x if math.isfinite(x) else str(x))
    | st.integers(-(2**70), 2**70)
    | st.booleans()
    | st.sampled_from(["nan", "-inf", "1e999", " 1.5 ", "-0"])
)
segment_names = st.sampled_from(SKELETON.segments) | st.text(max_size=6)
angle_names = st.sampled_from([*SKELETON.angle_names(), *GAUGES]) | st.text(max_size=10)
decodable_poses = st.fixed_dictionaries({
    "v": st.just(pose.VERSION), "seq": st.integers(-(2**63), 2**64 - 1),
    "t_ns": st.integers(-(2**63), 2**64 - 1) | st.integers(0, 2 * 10**18),
    "angles_deg": st.dictionaries(angle_names, numbers, max_size=12),
    "rel_deg": st.dictionaries(st.text(max_size=6), numbers, max_size=3),
    "segments": st.dictionaries(segment_names, st.fixed_dictionaries({
        "p": st.lists(numbers, min_size=3, max_size=3)
             | st.lists(st.floats(-2, 2), min_size=3, max_size=3),  # a body's, mostly
        "q": st.lists(numbers, min_size=4, max_size=4)
             | st.just([1, 0, 0, 0]) | st.just([0.5, 0.5, 0.5, 0.5]),
    }), max_size=18),
    "joints_m": st.dictionaries(st.text(max_size=6), st.lists(numbers, min_size=3, max_size=3),
                                max_size=3),
}).map(lambda d: json.dumps(d).encode())  # fmt: skip


@given(decodable_poses)
def test_viewer_draws_any_decodable_pose(data: bytes) -> None:
    """Any pose pose.decode accepts (any subset of segments and angles, any
    numbers) becomes what the viewer logs, or ``None`` (not showable, counted):
    never an exception; and it logs to a real Rerun recording."""
    frame = pose.decode(data)
    drawn = drawing(frame, SKELETON)
    if drawn is None:
        assert not -(2**63) < frame.t_ns < 2**63
        return
    assert drawn.t_ns == frame.t_ns
    for strip in drawn.strips:
        assert strip.ndim == 2
        assert strip.shape[0] >= 2
        assert strip.shape[1] == 3
        assert np.all(np.abs(strip) <= MAX_M + 1)
    assert len(drawn.strips) <= 10
    present = [s for s in SKELETON.segments if s in frame.segments]
    assert drawn.joints.shape[1] == 3
    assert drawn.joints.shape[0] <= len(present)
    assert np.all(np.abs(drawn.joints) <= MAX_M)
    assert all(math.isfinite(g) for g in drawn.gauges)
    assert len(drawn.gauges) == len(GAUGES)
    for path, value in drawn.angles.items():
        assert path.startswith("angles/")
        assert path != "angles/"
        assert isinstance(value, float)
        assert math.isfinite(value) or math.isnan(value)
    rec = rr.RecordingStream("bodynet-test")
    rec.memory_recording()
    viewer = Viewer([rec], SKELETON)
    assert viewer.log_poses([frame, frame]) == 2
    assert viewer.bad == 0


# --- the live gateway --------------------------------------------------------------


@pytest.fixture(scope="module")
def live() -> Iterator[tuple[Gateway, zenoh.Session]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(session_config("router", listen=[endpoint]))
    gw_session, hostile = client(endpoint), client(endpoint)
    gateway = Gateway(gw_session)
    running = Running(gateway.run)
    wait_matching(hostile, SITE_KEYS[0])  # the gateway's subscription has reached the router
    yield gateway, hostile
    running.stop()
    gateway.close()
    for s in (hostile, gw_session, router):
        s.close()


def counted(gateway: Gateway) -> int:
    # every sample the worker takes from Zenoh's queue is counted: kept, rejected or refused
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
@example("inf")  # a window no history holds: answered at once, not waited for
@example("9")
@example("nan")
@example("-1")
@example("abc")  # refused: it was taken as the default window, a calibration not asked for
def test_tpose_query_answers_any_parameter(live: tuple[Gateway, zenoh.Session], value: str) -> None:
    _, session = live
    try:
        replies = list(session.get(f"{keys.CALIBRATE_TPOSE}?seconds={value}", timeout=10))
    except zenoh.ZError:
        return  # the client's own library refused the selector: nothing was sent
    answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    assert len(answers) == 1
    assert isinstance(answers[0]["ok"], bool)
    if value.isalpha() and value.lower() not in ("inf", "nan", "infinity"):
        assert answers[0] == {"ok": False, "error": f"seconds={value!r} is not a number of seconds"}
