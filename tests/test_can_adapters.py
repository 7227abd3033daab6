"""The CAN bridge against what real adapters and shared buses do, through real
parts: python-can's slcan interface on a pseudo-terminal we write the adapter's
bytes into, python-can's virtual bus, and loopback Zenoh.

A line python-can cannot parse, a byte that is not text, other devices' frames
on the bus, an adapter's own clock and a frame that comes late are each what
hardware gives; none may stop the bridge, lose a good frame or read as bad input
or as a lost sample when it is not one.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from zenoh_helpers import Running, health_collector, raw_collector

from bodynet.core.codecs import smartsuit_can
from bodynet.core.messages import OleAccel
from bodynet.nodes.can_bridge import CanBridge
from bodynet.nodes.hardware import PtyPort


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
    run_thread(bridge.run_bus, interface="slcan", channel=str(port.link), sleep_after_open=0)
    health.wait_for(lambda h: any(m["device"] == "connected" for _, m in h))
    yield port, bridge
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
