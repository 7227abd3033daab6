"""SlimeVR trackers over real UDP on loopback, into the bridge and a real gateway.

The emulated tracker speaks the protocol as a tracker does (handshake until
answered, rotations, battery, signal strength, sensor info, ping echoes); the
bridge is bodynet in the place of the SlimeVR server.
"""

from __future__ import annotations

import json
import math
import socket
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from zenoh_helpers import Collector, Liveliness, Running, client, raw_collector, wait_until

from bodynet.cli.main import main
from bodynet.core.codecs import slimevr as codec
from bodynet.core.errors import Reason, Rejected
from bodynet.core.keys import LEFT_ARM, RIGHT_ARM, Site
from bodynet.core.messages import Quat, Source
from bodynet.gateway.service import Gateway
from bodynet.nodes.slimevr_bridge import SlimeVRBridge
from bodynet.nodes.sources.slimevr import EmulatedTracker, emulated_mac, free_udp_port
from bodynet.session import profile_file

UPPER, FORE = Site(LEFT_ARM, "upperarm"), Site(RIGHT_ARM, "forearm")
HALF = math.sqrt(0.5)


def still(_sensor: int, _t: float) -> tuple[float, float, float, float]:
    return (HALF, 0.0, 0.0, HALF)  # w, x, y, z: a quarter turn about z


@pytest.fixture
def served(zsession: zenoh.Session) -> Iterator[tuple[SlimeVRBridge, tuple[str, int]]]:
    listen = ("127.0.0.1", free_udp_port())
    bridge = SlimeVRBridge(zsession, "slimevr-test", {codec.tracker_id(emulated_mac(1), 0): UPPER})
    running = Running(lambda stop: bridge.run(listen, stop))
    yield bridge, listen
    running.stop()
    bridge.close()


@pytest.fixture
def trackers() -> Iterator[Callable[..., EmulatedTracker]]:
    made: list[EmulatedTracker] = []

    def make(server: tuple[str, int], number: int, **kw: object) -> EmulatedTracker:
        tracker = EmulatedTracker(server, emulated_mac(number), [0], still, **kw)  # type: ignore[arg-type]
        tracker.start()
        made.append(tracker)
        return tracker

    yield make
    for tracker in made:
        tracker.stop()


def test_a_tracker_connects_streams_and_reports_its_state(
    zsession: zenoh.Session, served: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    raw = raw_collector(zsession, UPPER.raw_key)
    health = Collector(zsession, "body/@health/slimevr-test", json.loads)
    tracker = trackers(listen, 1, compact=True)
    assert tracker.connected.wait(5)  # the handshake reply it waits for came
    seen = raw.wait_for(lambda s: len(s) >= 20)
    for _, sample in seen:
        assert sample.source is Source.SLIMEVR
        assert isinstance(sample.reading, Quat)
        w, x, y, z = sample.reading.wxyz
        assert (w, x, y, z) == pytest.approx((HALF, 0, 0, HALF), abs=1e-4)  # Q15
        accel = struct.unpack(">3h", sample.reading.extra)
        assert accel[2] / codec.Q7 == pytest.approx(9.81, abs=0.01)
    seqs = [s.seq for _, s in seen]
    assert seqs == sorted(seqs)
    wanted = {"battery_v", "rssi_dbm", "rtt_ms", "tracker"}
    report = health.wait_for(lambda h: any(
        wanted <= set(m["nodes"].get("1", {}).get("status", {})) for _, m in h))  # fmt: skip
    status = next(m for _, m in report if wanted <= set(m["nodes"].get("1", {}).get("status", {})))[
        "nodes"]["1"]["status"]  # fmt: skip
    assert status["tracker"] == "02b0d1000001-0"
    assert status["battery_v"] == pytest.approx(3.9)
    assert status["rssi_dbm"] == -52
    assert status["sensor_status"] == 1
    assert report[-1][1]["kind"] == "slimevr"
    assert tracker.heartbeats >= 1  # the server's heartbeats reach it
    assert tracker.pings_echoed >= 1
    assert 0 in tracker.acked  # its sensor info was acknowledged
    assert not bridge.publisher.rejected


def test_silence_and_back_and_a_packet_counter_jump(
    zsession: zenoh.Session, served: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    live = Liveliness(zsession)
    tracker = trackers(listen, 1)
    live.wait_for(lambda alive: UPPER.raw_key in alive)
    tracker.pause()  # unplugged: its token goes after a few periods
    live.wait_for(lambda alive: UPPER.raw_key not in alive)
    tracker.resume()
    live.wait_for(lambda alive: UPPER.raw_key in alive)
    node = bridge.publisher.nodes[1]
    gaps_before = node.gaps
    samples = node.samples
    tracker.skip(5)  # five packets the server never sees
    wait_until(lambda: node.samples > samples + 5, what="samples after the jump")
    assert node.gaps - gaps_before == 5
    conn = next(c for c in bridge.server.connections.values() if c.handshake.mac == tracker.mac)
    assert conn.lost >= 5


def test_a_second_tracker_appears_unassigned_and_is_assigned_live(
    router_endpoint: str, zsession: zenoh.Session, tmp_path: Path,
    served: tuple[SlimeVRBridge, tuple[str, int]], trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    gateway_session = client(router_endpoint)
    gateway = Gateway(gateway_session)
    topology = Collector(zsession, "body/@topology", json.loads)
    running = Running(gateway.run)
    try:
        trackers(listen, 1)
        second = trackers(listen, 2)
        ident = codec.tracker_id(emulated_mac(2), 0)
        topology.wait_for(lambda t: any(ident in m.get("unassigned", []) for _, m in t))
        assert bridge.unassigned_samples > 0
        raw = raw_collector(zsession, FORE.raw_key)
        profile = tmp_path / "subject.toml"
        typed = ident.upper().replace("-", "/")  # as a user may write it
        code = main(["calibrate", "assign", typed, "right-arm/forearm", "--profile", str(profile),
                     "-e", router_endpoint, "--timeout", "10"])  # fmt: skip
        assert code == 0
        assert profile_file.load(profile).trackers == {ident: "right-arm/forearm"}
        raw.wait_for(lambda s: len(s) >= 5)
        topology.wait_for(lambda t: not t[-1][1].get("unassigned")
                          and FORE.raw_key in json.dumps(t[-1][1]))  # fmt: skip
        assert second.connected.is_set()
    finally:
        running.stop()
        gateway.close()
        gateway_session.close()


def test_garbage_is_counted_by_reason_and_an_unknown_flood_costs_nothing(
    zsession: zenoh.Session, served: tuple[SlimeVRBridge, tuple[str, int]],
    trackers: Callable[..., EmulatedTracker],
) -> None:  # fmt: skip
    bridge, listen = served
    tracker = trackers(listen, 1)
    wait_until(lambda: 1 in bridge.publisher.nodes, what="the tracker's first sample")
    node = bridge.publisher.nodes[1]
    # from the tracker's own address, between its good packets
    bad = {
        Reason.TRUNCATED: b"\x00\x00",
        Reason.BAD_KIND: struct.pack(">iq", 99, 1 << 40),
        Reason.NOT_FINITE: codec.encode_rotation(1 << 41, 0, (math.nan, 0.0, 0.0, 1.0)),
        Reason.BAD_QUAT_NORM: codec.encode_rotation(1 << 42, 0, (0.0, 0.0, 0.0, 2.0)),
        Reason.OUT_OF_ORDER: codec.encode_rotation(3, 0, (0.0, 0.0, 0.0, 1.0)),
    }
    for data in bad.values():
        tracker.send(data)
    wait_until(lambda: all(bridge.publisher.rejected.get(r, 0) >= 1 for r in bad),
               what=f"rejections {dict(bridge.publisher.rejected)}")  # fmt: skip
    # a flood of well-formed rotations from an address that never shook hands
    flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent = 0
    try:
        for i in range(5000):
            flood.sendto(codec.encode_rotation(i + 1, 0, (0.0, 0.0, 0.0, 1.0)), listen)
            sent += 1
        wait_until(lambda: bridge.publisher.rejected.get(Reason.UNKNOWN_NODE, 0) > 0,
                   what="the flood counted")  # fmt: skip
    finally:
        flood.close()
    assert bridge.publisher.rejected[Reason.UNKNOWN_NODE] <= sent
    assert len(bridge.server.connections) == 1  # no state for the flood's address
    assert set(bridge.publisher.nodes) == {1}
    samples = node.samples
    wait_until(lambda: node.samples > samples + 10, what="the tracker still streaming")
    assert all(bridge.publisher.rejected[r] == 1 for r in bad)


def test_a_handshake_flood_fills_no_more_than_its_bound() -> None:
    """Handshakes from ever new addresses and MACs: at most ``max_trackers`` are
    kept, the rest refused and counted; a known tracker still reconnects, and a
    tracker's nodes keep their numbers when it comes back from a new address."""
    server = codec.SlimeVRServer(max_trackers=16)
    refused = 0
    for i in range(40):
        hs = codec.Handshake(bytes([2, 0, 0, 0, 0, i]), firmware="flood")
        events = server.receive(codec.encode_handshake(0, hs), ("10.0.0.1", 1000 + i))
        refused += sum(isinstance(e, Rejected) and e.reason is Reason.OUT_OF_RANGE for e in events)
        replies = server.take_replies()
        assert len(replies) == (1 if i < 16 else 0)  # no answer to a refused handshake
    assert (len(server.connections), refused) == (16, 24)
    first = codec.Handshake(bytes([2, 0, 0, 0, 0, 0]))
    server.forget(("10.0.0.1", 1000))
    server.receive(codec.encode_handshake(0, first), ("10.0.0.2", 5))  # back, elsewhere
    events = server.receive(codec.encode_rotation(1, 0, (0.0, 0.0, 0.0, 1.0)), ("10.0.0.2", 5))
    assert [e.node for e in events if isinstance(e, Quat)] == [1]  # its node as before
