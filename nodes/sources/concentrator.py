"""The Data Concentrator (000 seed, ch. 3.4.2, 4.1): SmartSuit nodes polled over serial.

The bridge polls one node at a time and feeds only what the device sends to
the sans-io decoder (``replies_only``), telling it which node it asked and when
the answer is overdue: a reply is published only for the node just asked. A
reply that misses its ``REPLY_TIMEOUT_S`` is still waited for up to
``LATE_WINDOW_S`` more and then counted as ``late_reply``, not published, so
that it cannot be taken for the next node's (the concentrator answers in
order); bytes left over from an earlier exchange are decoded (and counted)
before the next request, and letters from the device (a reset banner) are
garbage, not requests. A capture of the link, both directions interleaved,
keeps its requests as requests. A sample's sequence number is the poll cycle
(a missed reply is a gap); a capture, which has no clock, times the replies
by their order at one per 22 ms.
"""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

from bodynet.core.codecs import concentrator as codec
from bodynet.core.keys import Site
from bodynet.core.messages import Reading, Tick
from bodynet.core.messages import Source as SourceId
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.nodes.sources.base import BLIND_S, Adapter, Feed, NodeParts, Transport
from bodynet.nodes.sources.serial_port import SerialSource
from bodynet.session import argtypes

#: How long the bridge waits for a node's reply; and how much longer a reply
#: still counts as the late answer to that request before the next one is sent.
REPLY_TIMEOUT_S = 0.1
LATE_WINDOW_S = 0.1
#: A node unanswered this many cycles in a row is asked only every DEAD_EVERY th cycle.
DEAD_AFTER, DEAD_EVERY = 3, 10


class CycleAdapter(Adapter):
    """Numbered by poll cycle (the bridge's ticks); timed, without a clock, by
    reply order at ``rate_hz``."""

    def __init__(self, period_s: float, rate_hz: float | None = None) -> None:
        super().__init__(period_s, rate_hz or 1.0 / codec.CYCLE_S)
        self.replies = 0

    def stamp(self, reading: Reading, t_s: float | None) -> tuple[int, float]:
        if t_s is None:
            t_s = self.replies / self.rate_hz
        self.replies += 1
        return self.base + self.tick, t_s


class Concentrator(SerialSource):
    name = "concentrator"
    wire_id = SourceId.CONCENTRATOR
    transport = Transport.SERIAL
    help = "the concentrator on a serial port (115200 baud)"
    SERIAL_TIMEOUT_S = 0.01
    SITES = SMARTSUIT_SITES
    PERIOD_S = codec.CYCLE_S
    BAUD = codec.BAUD
    formats: ClassVar = {"concentrator": "a capture of the concentrator's serial exchange"}
    emulators: ClassVar = {"concentrator": "a Data Concentrator with SmartSuit nodes"}
    TIMING: ClassVar = frozenset({"drop", "late"})  # polled: it answers when asked

    def __init__(self, sites: Mapping[int, Site] | None = None, period_s: float | None = None,
                 nodes: Sequence[int] = (1, 2, 3)) -> None:  # fmt: skip
        self.nodes = list(nodes)
        super().__init__(sites, period_s or codec.CYCLE_S * len(self.nodes))

    def decoder(self) -> codec.ConcentratorDecoder:
        return codec.ConcentratorDecoder()

    def adapter(self, rate_hz: float | None = None) -> Adapter:
        return CycleAdapter(self.period_s, rate_hz)

    def serve(self, link: Any, stop: threading.Event, bridge: Feed) -> None:
        """Poll each node in turn, a cycle after another, until ``stop``. A node
        that has not answered ``DEAD_AFTER`` cycles in a row is asked only every
        ``DEAD_EVERY`` th cycle until it answers again: each unanswered request
        costs the timeout and the late window, which would slow every live node."""
        decoder = codec.ConcentratorDecoder(replies_only=True)
        silent = dict.fromkeys(self.nodes, 0)  # cycles in a row without a reply
        cycle = 0
        while not stop.is_set():
            bridge.feed([Tick(cycle)])
            for node in self.nodes:
                if stop.is_set():
                    break
                if silent[node] >= DEAD_AFTER and cycle % DEAD_EVERY:
                    continue
                silent[node] = 0 if _ask(link, decoder, node, stop, bridge) else silent[node] + 1
            cycle += 1

    @classmethod
    def add_bridge_args(cls, p: argparse.ArgumentParser) -> None:
        super().add_bridge_args(p)
        p.add_argument("--nodes", type=argtypes.number_list(1, codec.MAX_NODES), default="1-3",
                       help=f"nodes to poll, 1..{codec.MAX_NODES} (default 1-3)")  # fmt: skip

    def bridge(self, session: Any, stop: Any, name: str, args: argparse.Namespace) -> None:
        Concentrator(self.sites, None, args.nodes).run_bridge(
            session, stop, name, args.port, args.baud or self.BAUD, batch_s=args.batch_ms / 1e3
        )

    def emulated_sensors(self, sensors: Any = None, branches: Any = None) -> list[Any]:
        from bodynet.nodes.emulator import smartsuit_sensors

        return smartsuit_sensors(branches)

    def emulator(self, device: str, body: Any, truth: Any, opts: dict[str, Any]) -> Any:
        from bodynet.nodes.hardware import ConcentratorEmulator

        return ConcentratorEmulator(opts["link"], body, truth=truth,
                                    silent=opts.get("silent", ()),
                                    timing=opts.get("timing"))  # fmt: skip

    def node(self, device: str, body: Any, where: Path, clock: Any, truth: Any,
             sensors: list[Any], label: str, timing: Any = None) -> NodeParts:  # fmt: skip
        from bodynet.nodes.hardware import ConcentratorEmulator

        emulator = ConcentratorEmulator(where / label, body, clock, truth, timing=timing)
        nodes = tuple(s.node for s in sensors)
        source = Concentrator(self.sites, None, nodes)
        return emulator, source.run_bridge, {"port": str(where / label)}


def _ask(link: Any, decoder: codec.ConcentratorDecoder, node: int, stop: threading.Event,
         bridge: Feed) -> bool:  # fmt: skip
    """One exchange on the open port (pyserial's ``Serial``): request ``node``'s
    reading and wait for it, then, if it is overdue, for its late reply. Whether
    it answered (on time or late). Left unanswered while this thread was held up
    (:class:`_Watch`), the request claims nothing of the node (:meth:`Adapter.unwatched`)."""
    if link.in_waiting:  # left from before: later than its late window, or a banner
        bridge.feed(decoder.feed(link.read(link.in_waiting)))
    bridge.feed(decoder.poll(node))
    link.write(codec.request(node))
    watch = _Watch()
    if _listen(link, decoder, REPLY_TIMEOUT_S, stop, bridge, watch):
        return True
    decoder.overdue()
    if _listen(link, decoder, LATE_WINDOW_S, stop, bridge, watch):
        return True
    if not watch.on_time:
        bridge.adapter.unwatched(node)
    return False


class _Watch:
    """Whether the bridge looked at the link all along an exchange: no read came
    back later than its own timeout and ``BLIND_S`` after the last look. A host too
    busy to run the bridge stalls the emulated nodes beside it too, which then
    answer at once: a bridge that woke late cannot tell a silent node from its own
    stall (as a CAN bridge's late read: ``CanBusBridge._receive``)."""

    def __init__(self) -> None:
        self.last = time.monotonic()  # the request was just written
        self.on_time = True

    def looked(self) -> None:
        now = time.monotonic()
        if now - self.last > Concentrator.SERIAL_TIMEOUT_S + BLIND_S:
            self.on_time = False
        self.last = now


def _listen(link: Any, decoder: codec.ConcentratorDecoder, timeout_s: float,
            stop: threading.Event, bridge: Feed, watch: _Watch) -> bool:  # fmt: skip
    """Decode what comes until the request is answered (True) or ``timeout_s``
    passes; it reads at least once, so a reply already there when the bridge
    was held up past the deadline still counts."""
    deadline = time.monotonic() + timeout_s
    while True:
        data = link.read(max(1, link.in_waiting))
        watch.looked()
        bridge.feed(decoder.feed(data))
        if not decoder.waiting:
            return True
        if stop.is_set() or time.monotonic() >= deadline:
            return False
