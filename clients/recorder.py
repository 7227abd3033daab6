"""Recording what the body network carries into MCAP (see ``mcap_store``).

Subscribes to the chosen key expressions (raw samples, poses) and writes each
message with its source time; the file is complete once :meth:`close` runs.

Nothing is lost to a router restart where it can be fetched again: the
subscriptions are Zenoh advanced subscribers with recovery, so raw samples
missed while the router was away come back from the node publishers' caches
(see ``bodynet.nodes.publisher``), in order. What cannot come back is written
down: every jump in a topic's sequence numbers (raw ``seq``, pose ``seq``) is a
gap record on the ``@gaps`` channel (see ``mcap_store.GAPS_TOPIC``), so a
recording says where it is incomplete.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh
import zenoh.ext

from bodynet.clients.mcap_store import Gap, McapSink
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError, Reason, RejectCounts

log = logging.getLogger(__name__)

DEFAULT_KEYS = (keys.all_raw(), keys.all_poses())


class Recorder:
    """Writes what it receives to ``path``. With ``rotate_bytes`` / ``rotate_s``
    it goes on in ``<stem>-001.mcap``, ``-002``... once the current file is
    that large or that old (0: never)."""

    def __init__(
        self,
        session: zenoh.Session,
        path: Path,
        key_exprs: Sequence[str] = DEFAULT_KEYS,
        rotate_bytes: int = 0,
        rotate_s: float = 0.0,
    ) -> None:
        self.path = path
        self.files = [path]
        self.rejected = RejectCounts()
        self.rotate_bytes, self.rotate_s = rotate_bytes, rotate_s
        self._sink = McapSink(path)
        self._opened = time.monotonic()
        self._done = 0  # messages in files already closed
        self._lock = threading.Lock()
        self._closed = False
        self._last_seq: dict[str, tuple[int, int]] = {}  # topic -> (seq, t_ns) last written
        self.gaps: list[Gap] = []
        recovery = zenoh.ext.RecoveryConfig(heartbeat=True)
        self._subs = [
            zenoh.ext.declare_advanced_subscriber(session, k, self._on_sample, recovery=recovery)
            for k in key_exprs
        ]

    @property
    def messages(self) -> int:
        return self._done + self._sink.messages

    def _rotate_if_due(self) -> None:
        too_big = self.rotate_bytes and self.files[-1].stat().st_size >= self.rotate_bytes
        too_old = self.rotate_s and time.monotonic() - self._opened >= self.rotate_s
        if too_big or too_old:
            self._sink.close()
            self._done += self._sink.messages
            nxt = self.path.with_name(f"{self.path.stem}-{len(self.files):03d}{self.path.suffix}")
            self.files.append(nxt)
            self._sink = McapSink(nxt)
            self._opened = time.monotonic()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        try:
            with self._lock:
                if self._closed:
                    return
                self._rotate_if_due()
                if key.endswith(f"/{keys.POSE}"):
                    frame = pose.decode(data)
                    t_ns = frame.t_ns or time.time_ns()
                    self._note_seq(key, frame.seq, t_ns)
                    self._sink.write_pose(key, frame, t_ns, data)
                elif key.endswith(f"/{keys.Stream.TRUTH}"):
                    self._sink.write_truth(key, data, _truth_time(data))
                else:
                    raw = raw_sample.decode(data)
                    self._note_seq(key, raw.seq, raw.t_ns)
                    self._sink.write_raw(key, raw, raw.t_ns)
        except DecodeError as exc:
            self.rejected[exc.reason] += 1

    def _note_seq(self, topic: str, seq: int, t_ns: int) -> None:
        """Write a gap record if ``seq`` skips numbers after the topic's last one.
        A lower number (a restarted gateway, a wrapped counter) starts afresh."""
        last = self._last_seq.get(topic)
        self._last_seq[topic] = (seq, t_ns)
        if last is not None and seq > last[0] + 1:
            gap = Gap(topic, last[0], seq - last[0] - 1, last[1], t_ns)
            self.gaps.append(gap)
            self._sink.write_gap(gap)
            log.info("recorder: %d missing on %s after seq %d", gap.missing, topic, last[0])

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            self._closed = True
            self._sink.close()


def _truth_time(data: bytes) -> int:
    """The source time of a ground-truth message (JSON with ``t_ns``)."""
    try:
        return int(json.loads(data)["t_ns"])
    except (ValueError, KeyError, TypeError) as exc:
        raise DecodeError(Reason.GARBAGE, f"not a ground-truth message: {exc}") from None
