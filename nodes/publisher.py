"""Putting a source's readings on Zenoh: raw samples, liveliness and health.

Every bridge (CAN, concentrator, IMU central) and every emulated node hands
its decoded readings to one :class:`SitePublisher`, which

- stamps each with its sequence number and source time and publishes it as a
  raw-sample message on the node's site key;
- holds one liveliness token per node, on that same key, while the node
  delivers: declared at its first sample, dropped once it has missed
  ``stale_periods`` periods (0.3 s at least), or at close, declared again when it returns;
- counts per node samples, sequence gaps and rejections, and publishes this
  health as JSON on ``body/@health/<source>`` every second and whenever a node
  comes or goes.

Sequence numbers come from the source's own structure where it has one (the
IMU central's tick, the concentrator's poll cycle); :class:`PeriodicSeq`
derives them from arrival times otherwise, so a gap means a missed period.

With :meth:`SitePublisher.batch`, the samples go out together instead: a
message on ``body/@batch/<source>`` (``codecs.raw_batch``) once every live node
(its token up) has a sample in it, or ``window_s`` after its first, whichever
comes first; the tokens and health stay per node.

Raw samples go out through Zenoh's advanced publisher (``zenoh.ext``): it
keeps the last :data:`CACHE_SAMPLES` samples of each node and sends a
heartbeat, so an advanced subscriber (the recorder) that missed samples, e.g.
while the router was restarting, fetches them from this cache once it is
back. Plain subscribers (the gateway) see ordinary samples.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import zenoh
import zenoh.ext

from bodynet.core import keys
from bodynet.core.codecs import raw_batch, raw_sample
from bodynet.core.errors import Reason, RejectCounts, Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import RESUMED, RawSample, Reading, source_name
from bodynet.nodes.sources.base import PeriodicSeq

__all__ = ["PeriodicSeq", "SitePublisher"]

log = logging.getLogger(__name__)

HEALTH_PERIOD_S = 1.0
MIN_STALE_S = 0.3
# samples kept per node for recovery: 10 s at 100 Hz, longer than a router restart
CACHE_SAMPLES = 1000
HEARTBEAT_S = 0.1


@dataclass
class NodeHealth:
    site: Site
    samples: int = 0
    gaps: int = 0
    resumed: int = 0  # samples flagged RESUMED: the node may have rebooted
    rejected: RejectCounts = field(default_factory=RejectCounts)
    last_seq: int | None = None
    last_seen: float = 0.0  # monotonic
    alive: bool = False
    window: deque[float] = field(default_factory=deque)  # arrival times of the last second
    status: dict[str, float | int | str] = field(default_factory=dict)  # battery, rssi...

    def as_json(self, now: float) -> dict[str, object]:
        recent = [t for t in self.window if now - t <= 1.0]
        out: dict[str, object] = {
            "key": self.site.raw_key,
            "alive": self.alive,
            "rate_hz": len(recent),
            "samples": self.samples,
            "gaps": self.gaps,
            "rejected": dict(self.rejected),
        }
        if self.resumed:
            out["resumed"] = self.resumed
        if self.status:
            out["status"] = dict(self.status)
        return out


def _raw_publisher(session: zenoh.Session, key: str) -> zenoh.ext.AdvancedPublisher:
    """A publisher whose recent samples a recovering subscriber can fetch again."""
    return zenoh.ext.declare_advanced_publisher(
        session,
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        cache=zenoh.ext.CacheConfig(CACHE_SAMPLES),
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=HEARTBEAT_S),
    )


class SitePublisher:
    """One source's readings onto Zenoh; see the module docstring."""

    def __init__(
        self,
        session: zenoh.Session,
        sites: Mapping[int, Site],
        source: int,
        name: str,
        period_s: float,
        stale_periods: float = 5.0,
    ) -> None:
        self.session = session
        self.sites = dict(sites)
        self.source = source
        self.name = name
        # never below 0.3 s: a busy machine can hold a 100 Hz node back for tens of ms
        self.stale_after_s = max(stale_periods * period_s, MIN_STALE_S)
        self.nodes: dict[int, NodeHealth] = {}
        self.rejected = RejectCounts()
        self.foreign: Counter[str] = Counter()  # other devices' messages, by kind
        self._early_status: dict[int, dict[str, float | int | str]] = {}
        self.device = "starting"
        self._publishers: dict[int, zenoh.ext.AdvancedPublisher] = {}
        self._tokens: dict[int, zenoh.LivelinessToken] = {}
        self._health_pub = session.declare_publisher(keys.health_key(name))
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._last_health = 0.0
        self._closed = False
        self._watch = threading.Thread(target=self._watchdog, name=f"{name}-watch", daemon=True)
        self._watch.start()
        # batching (:meth:`batch`): the samples waiting, their nodes, since when
        self.batch_s = 0.0
        self._batch_pub: zenoh.ext.AdvancedPublisher | None = None
        self._pending: list[raw_batch.Entry] = []
        self._pending_nodes: set[int] = set()
        self._pending_since = 0.0
        self._wake = threading.Condition(self._lock)
        self._batcher: threading.Thread | None = None

    def batch(self, window_s: float) -> None:
        """Publish the samples together from now on, in one message on
        ``body/@batch/<name>`` once every live node has a sample in it (a profile's
        sites with no node on the device are not waited for) or ``window_s`` after
        its first (a sample waits that long at most)."""
        if window_s <= 0 or self._batcher is not None:
            return
        self.batch_s = window_s
        self._batch_pub = _raw_publisher(self.session, keys.batch_key(self.name))
        self._batcher = threading.Thread(target=self._send_batches, name=f"{self.name}-batch",
                                         daemon=True)  # fmt: skip
        self._batcher.start()

    def _whole(self) -> bool:
        """Whether every live node has a sample in the batch (under the lock)."""
        return len(self._pending_nodes) >= len(self._tokens)

    def _send_batches(self) -> None:
        """The batcher's thread: each batch out when whole or due; what waits at
        :meth:`close` goes out before it ends."""
        assert self._batch_pub is not None
        while True:
            with self._wake:
                while not self._pending and not self._stop.is_set():
                    self._wake.wait()
                due = self._pending_since + self.batch_s
                while (not self._stop.is_set() and not self._whole()
                       and (left := due - time.monotonic()) > 0):  # fmt: skip
                    self._wake.wait(left)
                entries, self._pending = self._pending, []
                self._pending_nodes.clear()
            if entries:
                try:
                    self._batch_pub.put(raw_batch.encode(entries))
                except zenoh.ZError as exc:  # the session was closed under us
                    log.debug("%s: batch not published (%s); batcher ends", self.name, exc)
                    return
            elif self._stop.is_set():
                return

    def publish(self, reading: Reading, seq: int, t_ns: int | None = None,
                flags: int = 0) -> None:  # fmt: skip
        """Publish one reading of node ``reading.node`` (ignored if not in ``sites``),
        with its raw sample's ``flags`` (``RESUMED``)."""
        site = self.sites.get(reading.node)
        if self._closed:
            return
        if site is None:
            self.reject(Rejected(Reason.UNKNOWN_NODE, f"node {reading.node} not in this profile"))
            return
        now = time.monotonic()
        payload = raw_sample.encode(RawSample(reading, seq, t_ns or time.time_ns(), self.source,
                                                  flags))  # fmt: skip
        with self._lock:
            health = self.nodes.get(reading.node)
            if health is None:
                health = self.nodes[reading.node] = NodeHealth(site)
                health.status.update(self._early_status.pop(reading.node, {}))
            if health.last_seq is not None and seq > health.last_seq + 1:
                health.gaps += seq - health.last_seq - 1
            health.last_seq = seq
            health.samples += 1
            if flags & RESUMED:
                health.resumed += 1
            health.last_seen = now
            health.window.append(now)
            while now - health.window[0] > 1.0:
                health.window.popleft()
            came_back = not health.alive
            if came_back:
                health.alive = True
                self._tokens[reading.node] = self.session.liveliness().declare_token(site.raw_key)
            if self._batcher is not None:
                if not self._pending:
                    self._pending_since = now
                    self._wake.notify()
                self._pending.append((site.raw_key, payload))
                self._pending_nodes.add(reading.node)
                if self._whole():
                    self._wake.notify()
                publisher = None
            else:
                publisher = self._publishers.get(reading.node)
                if publisher is None:
                    publisher = self._publishers[reading.node] = _raw_publisher(
                        self.session, site.raw_key
                    )
        if publisher is not None:
            publisher.put(payload)
        if came_back:
            log.info("%s: node %d (%s) is live", self.name, reading.node, site.raw_key)
            self.publish_health()

    def reject(self, rejected: Rejected, node: int | None = None) -> None:
        """Count a rejection, against ``node`` too when it is known."""
        with self._lock:
            self.rejected[rejected.reason] += 1
            if node is not None and node in self.nodes:
                self.nodes[node].rejected[rejected.reason] += 1
        log.debug(
            "%s: rejected %s: %s %r", self.name, rejected.reason, rejected.detail, rejected.data
        )

    def count_foreign(self, kind: str) -> None:
        """Count a well-formed message of another device on the source's medium (a
        CAN bus shared with other devices): not this source's, and no rejection."""
        with self._lock:
            self.foreign[kind] += 1

    def move(self, node: int, site: Site) -> None:
        """Node ``node`` sits at ``site`` from now on (a tracker assigned live): what
        it published elsewhere is dropped (its samples waiting in a batch too), its
        health starts over."""
        with self._lock:
            old = self.sites.get(node)
            if old == site:
                return
            self.sites[node] = site
            if old is not None and node in self._pending_nodes:
                self._pending = [e for e in self._pending if e[0] != old.raw_key]
                self._pending_nodes.discard(node)
            token = self._tokens.pop(node, None)
            if token is not None:
                token.undeclare()
            publisher = self._publishers.pop(node, None)
            if publisher is not None:
                publisher.undeclare()
            health = self.nodes.pop(node, None)
            if health is not None:  # what the node said of itself still holds
                self._early_status[node] = dict(health.status)
        self.publish_health()

    def set_status(self, node: int, key: str, value: float | int | str) -> None:
        """Keep what node ``node`` says of itself (battery, signal strength...) for
        its health (what it says before its first sample is kept for then)."""
        with self._lock:
            health = self.nodes.get(node)
            if health is not None:
                health.status[key] = value
            else:
                self._early_status.setdefault(node, {})[key] = value

    def set_device(self, state: str) -> None:
        """Say how the device behind the source is doing (``connected``...)."""
        if state != self.device:
            self.device = state
            self.publish_health()

    def health(self) -> dict[str, object]:
        now = time.monotonic()
        with self._lock:
            return {
                "source": self.name,
                "kind": source_name(self.source),
                "device": self.device,
                "t_ns": time.time_ns(),
                "rejected": dict(self.rejected),
                "foreign": dict(self.foreign),
                "nodes": {str(n): h.as_json(now) for n, h in sorted(self.nodes.items())},
            }

    def publish_health(self) -> None:
        if self._closed:
            return
        self._last_health = time.monotonic()
        self._health_pub.put(json.dumps(self.health()).encode())

    def _watchdog(self) -> None:
        while not self._stop.wait(min(0.05, self.stale_after_s / 4)):
            now = time.monotonic()
            gone = []
            with self._lock:
                for node, health in self.nodes.items():
                    if health.alive and now - health.last_seen > self.stale_after_s:
                        health.alive = False
                        gone.append(node)
                        token = self._tokens.pop(node, None)
                        if token is not None:
                            token.undeclare()
            for node in gone:
                log.info("%s: node %d went quiet", self.name, node)
            if gone or now - self._last_health >= HEALTH_PERIOD_S:
                try:
                    self.publish_health()
                except zenoh.ZError as exc:  # the session was closed under us: nothing to tell
                    log.debug("%s: health not published (%s); watchdog ends", self.name, exc)
                    return

    def close(self) -> None:
        """Drop every token and publisher; the session stays open. Later calls
        of :meth:`publish` and :meth:`set_device` do nothing."""
        if self._closed:
            return
        with self._wake:
            self._stop.set()
            self._wake.notify()
        self._watch.join(timeout=2)
        if self._batcher is not None:  # what waits goes out first
            self._batcher.join(timeout=2)
        with self._lock:
            for token in self._tokens.values():
                token.undeclare()
            self._tokens.clear()
            for node in self.nodes.values():
                node.alive = False
            for publisher in self._publishers.values():
                publisher.undeclare()
            self._publishers.clear()
            if self._batch_pub is not None:
                self._batch_pub.undeclare()
                self._batch_pub = None
        self.publish_health()
        self._closed = True
        self._health_pub.undeclare()
