"""The concentrator bridge attributes a reply only to the node it just polled.

A Data Concentrator on a pseudo-terminal (pyserial on the bridge's side) answers
its requests in order, like the real one; each reply carries the node it was
read from in accel x and its place in the exchange in the encoder, so a sample
published on the wrong node, or lost, shows. One reply comes late (past the
bridge's reply timeout), or the device prints a reset banner before a reply.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from zenoh_helpers import Running, health_collector, raw_collector

from bodynet.core.codecs import concentrator as codec
from bodynet.core.messages import OleAccel, RawSample
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.concentrator_bridge import ConcentratorBridge
from bodynet.nodes.hardware import PtyPort
from bodynet.nodes.sources.concentrator import REPLY_TIMEOUT_S

NODES = (1, 2, 3)
EVENT_AT = 8  # the eighth request: node 2's in the third cycle
AFTER = 30  # replies after the event that must all arrive


class PolledDevice:
    """A concentrator answering each request in turn with ``E****X****Y****Z****``:
    encoder = the request's number (1, 2, ...), accel x = the node polled. Before
    the answer to request ``EVENT_AT`` it does ``before``: waits (seconds) or
    prints (bytes)."""

    def __init__(self, link: Path, before: float | bytes) -> None:
        self.port = PtyPort(link, codec.BAUD)
        self.before = before
        self.answered: dict[int, int] = {}  # request number -> node

    def run(self, stop: threading.Event) -> None:
        count = 0
        while not stop.is_set():
            for b in self.port.read(0.05):
                node = codec.node_of_request(b)
                if node is None:
                    continue
                count += 1
                if count == EVENT_AT:
                    if isinstance(self.before, bytes):
                        self.port.write(self.before)
                    else:
                        time.sleep(self.before)
                time.sleep(0.002)
                self.port.write(codec.encode_reply(OleAccel(node, count, (node, 0, 0))))
                self.answered[count] = node


@pytest.fixture
def device(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[PolledDevice]:
    dev = PolledDevice(tmp_path / "dc", request.param)
    dev.port.plug()
    running = Running(dev.run)
    yield dev
    running.stop()
    dev.port.unplug()


def _run(zsession: zenoh.Session, device: PolledDevice) -> tuple[list[RawSample], dict]:
    """Bridge the device until the replies to ``AFTER`` requests after the event
    are published; the samples, and the bridge's last health once it counted a
    rejection."""
    raw, health = raw_collector(zsession), health_collector(zsession)
    bridge = ConcentratorBridge(zsession, "dc-pairing", nodes=NODES)
    running = Running(lambda stop: bridge.run(str(device.port.link), stop))
    try:
        seen = raw.wait_for(
            lambda s: any(x.reading.encoder >= EVENT_AT + AFTER for _, x in s), timeout=30
        )
        report = health.wait_for(lambda h: any(m["rejected"] for _, m in h), timeout=30)
    finally:
        running.stop()
        bridge.close()
    for key, sample in seen:
        reading = sample.reading
        assert isinstance(reading, OleAccel)
        # published on the node it was read from, and that node was polled for it
        assert reading.accel[0] == reading.node, f"node {reading.accel[0]}'s reading on {key}"
        assert device.answered[reading.encoder] == reading.node
        assert key == SMARTSUIT_SITES[reading.node].raw_key
    return [s for _, s in seen], report[-1][1]


@pytest.mark.parametrize("device", [REPLY_TIMEOUT_S * 1.5], indirect=True, ids=["late"])
def test_late_reply_is_counted_not_paired_with_the_next_request(
    zsession: zenoh.Session, device: PolledDevice
) -> None:
    samples, health = _run(zsession, device)
    published = {s.reading.encoder for s in samples}
    assert EVENT_AT not in published  # the late reply is not published...
    assert set(range(EVENT_AT + 1, EVENT_AT + AFTER + 1)) <= published  # ...all after it are
    assert health["rejected"].get("late_reply", 0) >= 1
    assert set(health["rejected"]) == {"late_reply"}  # not also a no_reply


@pytest.mark.parametrize("device", [b"RESET\r\n"], indirect=True, ids=["banner"])
def test_reset_banner_is_garbage_and_the_reply_after_it_kept(
    zsession: zenoh.Session, device: PolledDevice
) -> None:
    samples, health = _run(zsession, device)
    published = {s.reading.encoder for s in samples}
    assert {s.reading.node for s in samples} <= set(NODES)  # R, S, T polled nothing
    assert set(range(EVENT_AT, EVENT_AT + AFTER + 1)) <= published
    assert set(health["rejected"]) == {"garbage"}
    assert set(health["nodes"]) == {str(n) for n in NODES}
