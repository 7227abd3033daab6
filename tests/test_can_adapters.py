"""The CAN bridge against what real adapters and shared buses do, through real
parts: python-can's slcan interface on a pseudo-terminal we write the adapter's
bytes into, python-can's virtual bus, and loopback Zenoh.

A line python-can cannot parse, a byte that is not text, other devices' frames
on the bus, an adapter's own clock and a frame that comes late are each what
hardware gives; none may stop the bridge, lose a good frame or read as bad input
or as a lost sample when it is not one.
"""

from __future__ import annotations

import itertools
import random
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
import zenoh
from zenoh_helpers import Running, health_collector, raw_collector

from bodynet.core.codecs import smartsuit_can
from bodynet.core.errors import Reason
from bodynet.core.messages import OleAccel
from bodynet.nodes.can_bridge import CanBridge
from bodynet.nodes.hardware import PtyPort
from bodynet.nodes.sources import live
from bodynet.nodes.sources.can_transport import BusClock


def slcan_line(node: int, encoder: int) -> bytes:
    """The slcan line an adapter sends for node ``node``'s frame."""
    reading = OleAccel(node, encoder, (node, 0, 0))
    return smartsuit_can.encode_slcan(smartsuit_can.encode_reading(reading))


@pytest.fixture
def slcan_bridge(
    zsession: zenoh.Session, tmp_path: Path, run_thread: Callable[..., Running]
) -> Iterator[tuple[PtyPort, CanBridge]]:
    """A pseudo-terminal playing a slcan adapter, and a CAN bridge on it through
    python-can's slcan interface, connected."""
    port = PtyPort(tmp_path / "slcan0", 115200)
    port.plug()
    health = health_collector(zsession)
    bridge = CanBridge(zsession, "slcan-adapter")
    running = run_thread(
        bridge.run_bus, interface="slcan", channel=str(port.link), sleep_after_open=0
    )
    health.wait_for(lambda h: any(m["device"] == "connected" for _, m in h))
    yield port, bridge
    running.stop()
    bridge.close()
    if port.master is not None:
        port.unplug()


@pytest.mark.parametrize(
    "bad",
    [b"T0006FFZZ8" + b"00" * 8 + b"\r", b"T0006FF\r"],
    ids=["not-hex", "cut-before-dlc"],
)
def test_a_slcan_line_python_can_cannot_parse_is_garbage_and_the_next_frames_flow(
    bad: bytes, zsession: zenoh.Session, slcan_bridge: tuple[PtyPort, CanBridge]
) -> None:
    """python-can's slcan raises ValueError / IndexError out of ``recv`` on these
    lines: the bridge counts one garbage line and publishes the frames after it."""
    port, bridge = slcan_bridge
    raw = raw_collector(zsession)
    port.write(slcan_line(1, 10) + bad + slcan_line(2, 20) + slcan_line(1, 11))
    seen = raw.wait_for(lambda s: len(s) >= 3)
    assert [(s.reading.node, s.reading.encoder) for _, s in seen] == [(1, 10), (2, 20), (1, 11)]
    assert {str(r): n for r, n in bridge.publisher.rejected.items()} == {"garbage": 1}
    assert bridge.publisher.device == "connected"


def test_a_byte_that_is_not_text_on_slcan_is_garbage_not_a_lost_device(
    zsession: zenoh.Session, slcan_bridge: tuple[PtyPort, CanBridge]
) -> None:
    """python-can's slcan cannot decode the line (CanOperationError from a
    UnicodeDecodeError): that line is counted and dropped; the adapter is not
    closed and opened again, and the lines after it are read."""
    port, bridge = slcan_bridge
    raw, health = raw_collector(zsession), health_collector(zsession)
    port.write(slcan_line(1, 10) + bytes([0xFF, 0xFE, 0x80, 0x00, 0x91]) + b"\r")
    port.write(slcan_line(2, 20) + slcan_line(1, 11))
    seen = raw.wait_for(lambda s: len(s) >= 3)
    assert [(s.reading.node, s.reading.encoder) for _, s in seen] == [(1, 10), (2, 20), (1, 11)]
    assert {str(r): n for r, n in bridge.publisher.rejected.items()} == {"garbage": 1}
    # health since the bad line: it counts it, and never said the device was gone
    bridge.publisher.publish_health()
    states = health.wait_for(lambda h: any(m["rejected"].get("garbage") for _, m in h))
    assert {m["device"] for _, m in states} == {"connected"}
    # and a device that does vanish still is
    port.unplug()
    health.wait_for(lambda h: h[-1][1]["device"] == "disconnected")


def test_a_flood_of_unreadable_lines_reopens_the_adapter_and_frames_flow_after(
    zsession: zenoh.Session, slcan_bridge: tuple[PtyPort, CanBridge]
) -> None:
    """Every line unreadable, a thousand in a row: each is counted, then the adapter
    is taken for broken and opened again (an error python-can raises over and over
    without reading anything would otherwise spin for ever); the frames after flow."""
    port, bridge = slcan_bridge
    raw, health = raw_collector(zsession), health_collector(zsession)
    port.write(b"T0006FF\r" * live.MAX_UNREADABLE)
    health.wait_for(lambda h: any(m["device"] == "disconnected" for _, m in h), timeout=60)
    health.wait_for(lambda h: h[-1][1]["device"] == "connected", timeout=60)
    port.write(slcan_line(1, 10) + slcan_line(2, 20))
    seen = raw.wait_for(lambda s: len(s) >= 2)
    assert [(s.reading.node, s.reading.encoder) for _, s in seen] == [(1, 10), (2, 20)]
    assert bridge.publisher.rejected[Reason.GARBAGE] == live.MAX_UNREADABLE


@pytest.fixture
def virtual_bridge(
    zsession: zenoh.Session, run_thread: Callable[..., Running]
) -> Iterator[Callable[[str], tuple[CanBridge, str]]]:
    """Starts a CAN bridge on a new python-can virtual bus, connected, and gives it
    and the channel's name; each is stopped, then closed, at teardown."""
    started: list[tuple[Running, CanBridge]] = []

    def start(name: str) -> tuple[CanBridge, str]:
        channel = f"{name}-{time.monotonic_ns()}"
        health = health_collector(zsession)
        bridge = CanBridge(zsession, name)
        started.append((run_thread(bridge.run_bus, interface="virtual", channel=channel), bridge))
        health.wait_for(lambda h: any(m["device"] == "connected" for _, m in h))
        health.close()
        return bridge, channel

    yield start
    for running, bridge in started:
        running.stop()
        bridge.close()


def node_message(node: int, encoder: int, timestamp: float = 0.0) -> can.Message:
    frame = smartsuit_can.encode_reading(OleAccel(node, encoder, (node, 0, 0)))
    return can.Message(arbitration_id=frame.arbitration_id, data=frame.data, timestamp=timestamp)


def test_an_adapters_own_clock_gives_wall_clock_times_that_never_go_back(
    zsession: zenoh.Session, virtual_bridge: Callable[[str], tuple[CanBridge, str]]
) -> None:
    """gs_usb, cantact, systec... stamp frames with the adapter's counter (seconds
    since it started; a 32-bit microsecond one wraps at 4294.967296 s): the samples
    carry wall-clock times, in order across the wrap. A wall-clock stamp (socketcan's
    kernel time) is kept as it is."""
    _, channel = virtual_bridge("adapter-clock")
    raw = raw_collector(zsession)
    stamps = [4294.93, 4294.94, 4294.95, 4294.96, 0.003, 0.013, 0.023]
    kernel = time.time() - 0.5
    with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
        for i, stamp in enumerate(stamps):
            bus.send(node_message(1, i, stamp))
        bus.send(node_message(2, 99, kernel))
    seen = raw.wait_for(lambda s: len(s) >= len(stamps) + 1)
    now = time.time()
    times = [s.t_ns / 1e9 for _, s in seen if s.reading.node == 1]
    assert [s.reading.encoder for _, s in seen if s.reading.node == 1] == list(range(len(stamps)))
    assert all(now - 60 < t <= now for t in times), times  # not 1970 + the adapter's uptime
    assert times == sorted(times)  # nor back at the wrap
    assert [s.t_ns for _, s in seen if s.reading.node == 2] == [round(kernel * 1e9)]


def test_bus_clock_keeps_the_adapters_spacing_anchored_to_the_wall_clock() -> None:
    """The clock on explicit times: frames every 10 ms on an adapter counter near
    its wrap, received 0-3 ms late; then a counter 0.05 % slow for two hours; then
    one 1 % slow (more than the clock follows): anchored again."""
    clock, rng = BusClock(), random.Random(1)
    wall0, got, sent = 1.7e9, [], []
    for i in range(2000):
        stamp = (4290.0 + i * 0.01) % 4294.967296
        sent.append(wall0 + i * 0.01)
        got.append(clock.wall(stamp, sent[-1] + rng.uniform(0, 0.003)))
    assert got == sorted(got)
    assert all(0 <= g - s <= 0.003 for g, s in zip(got, sent, strict=True))  # as late as they came
    steps = [b - a for a, b in itertools.pairwise(got)]
    assert sum(abs(d - 0.01) < 2e-5 for d in steps) > 0.9 * len(steps)  # the adapter's spacing
    for slow in (0.0005, 0.01):
        clock = BusClock()
        for i in range(0, 720_000, 100):  # 2 h at 100 Hz, one frame in 100 looked at
            now = wall0 + i * 0.01
            t = clock.wall(5.0 + i * 0.01 * (1 - slow), now)
            assert now - BusClock.MAX_LAG_S - 0.01 <= t <= now
    assert clock.wall(wall0 - 3.0, wall0) == wall0 - 3.0  # on the wall clock: kept


def test_late_frames_are_not_gaps_dropped_ones_are(
    zsession: zenoh.Session, virtual_bridge: Callable[[str], tuple[CanBridge, str]]
) -> None:
    """Frames of a node at 100 Hz stamped as slcan's host stamps them: up to 4 ms
    late, and held back 2 to 6 periods then read at once (the host busy); two
    dropped. The node's health counts two gaps, not one per late frame, and its
    last sample is numbered as its period."""
    bridge, channel = virtual_bridge("late-frames")
    raw = raw_collector(zsession)
    rng, start = random.Random(4), time.time() - 8.0
    times = {i: start + i * 0.01 + rng.uniform(0, 0.004) for i in range(300)}
    for first, periods in ((40, 2), (90, 4), (150, 6)):
        end = times[first] + periods * 0.01
        for k, i in enumerate(range(first, first + periods + 1)):
            times[i] = max(times[i], end + k * 1e-4)
    dropped = {200, 201}
    with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
        for i, t in sorted(times.items()):
            if i not in dropped:
                bus.send(node_message(1, i, t))
    seen = raw.wait_for(lambda s: len(s) >= len(times) - len(dropped))
    seqs = [s.seq for _, s in seen]
    assert seqs == sorted(set(seqs))
    assert seqs[-1] - seqs[0] == 299
    assert bridge.publisher.nodes[1].gaps == len(dropped)


def test_other_devices_frames_on_a_shared_bus_are_foreign_not_rejected(
    zsession: zenoh.Session, virtual_bridge: Callable[[str], tuple[CanBridge, str]]
) -> None:
    """A bus shared with other devices (an 11-bit one, a J1939 one, the Data
    Concentrator polling node 1 with remote frames): their frames are counted as
    foreign in health, apart from rejections; a node's malformed frame and an
    error frame are still rejected, and every node frame is published."""
    bridge, channel = virtual_bridge("shared-bus")
    raw, health = raw_collector(zsession), health_collector(zsession)
    others = [
        can.Message(arbitration_id=0x123, data=bytes.fromhex("DEADBEEF00112233"),
                    is_extended_id=False),
        can.Message(arbitration_id=0x18FF0001, data=bytes(8)),
        can.Message(arbitration_id=0x0006FFFF, is_remote_frame=True, dlc=8),
    ]  # fmt: skip
    with can.Bus(interface="virtual", channel=channel) as bus:
        for i in range(20):
            bus.send(node_message(1 + i % 3, i))
            for msg in others:
                bus.send(msg)
        bus.send(can.Message(arbitration_id=0x000AFFFF, data=bytes(3)))  # node 2's, cut short
        bus.send(can.Message(is_error_frame=True))
        bus.send(node_message(3, 20))
    seen = raw.wait_for(lambda s: len(s) >= 21)
    assert [s.reading.encoder for _, s in seen] == list(range(21))
    assert {str(r): n for r, n in bridge.publisher.rejected.items()} == {
        "bad_dlc": 1, "error_frame": 1,
    }  # fmt: skip
    bridge.publisher.publish_health()
    report = health.wait_for(lambda h: any(sum(m["foreign"].values()) == 60 for _, m in h))
    assert report[-1][1]["foreign"] == {"standard_id": 20, "extended_id": 20, "remote_frame": 20}
    assert report[-1][1]["rejected"] == {"bad_dlc": 1, "error_frame": 1}
