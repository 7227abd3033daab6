"""Recording what the body network carries into MCAP (see ``mcap_store``).

Subscribes to the chosen key expressions (by default raw samples, poses,
topology and health) and writes each message with its source time (MCAP's
``publish_time``) and the time the recorder wrote it (``log_time``); the file
is complete once :meth:`close` runs. The topology is also asked for once at
the start (the gateway publishes it on change), so a recording begins with it.

A message that cannot be stored is refused and counted by reason
(:attr:`Recorder.rejected`), and the recording goes on: one that does not
decode (``raw_sample``; topology and health must be JSON objects; a pose is
stored as it came, with only its header and segments read, see
``McapSink.write_pose_message``), or whose time MCAP cannot hold (a negative
``t_ns``, or past ``2**64 - 1``: ``out_of_range``).

Samples that a bridge run with ``--batch-ms`` put together on its batch key
(``codecs.raw_batch``) are written as the others: each on its site's raw key,
when that key is one the recording asked for. Whenever raw samples are asked
for, the batches are subscribed to as well.

Nothing is lost to a router restart where it can be fetched again: the
subscriptions that can carry raw samples are Zenoh advanced subscribers with
recovery (those of poses, topology and health are plain), so raw samples
missed while the router was away come back from the node publishers' caches
(see ``bodynet.nodes.publisher``), in order. What cannot come back is written
down: every jump in a topic's sequence numbers (raw ``seq``, pose ``seq``) is a
gap record on the ``@gaps`` channel (see ``mcap_store.GAPS_TOPIC``), so a
recording says where it is incomplete; the recorder itself only counts them
(:attr:`Recorder.gaps`, :attr:`Recorder.missing`), so what it holds in memory
does not grow with a lossy network.

Nothing is dropped on the way in either: each subscription hands its samples
to a deep FIFO (:data:`FIFO_DEPTH`) that a thread of the recorder empties into
the file; when the recorder falls behind, the FIFO fills and then holds Zenoh
back (the raw publishers block rather than drop, see
``bodynet.nodes.publisher``), instead of losing samples as a plain callback's
small internal queue did under load. :meth:`Recorder.close` writes what the
FIFOs still hold before it finishes the file.

A recording runs for hours: the recorder fixes the C library's mmap threshold
(``mcap_store.keep_large_buffers_off_heap``), without which the writer's
per-chunk buffers made its resident memory grow steadily.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext

from bodynet.clients.mcap_store import Gap, McapSink, check_time, keep_large_buffers_off_heap
from bodynet.core import keys
from bodynet.core.codecs import raw_batch, raw_sample
from bodynet.core.errors import DecodeError, Reason, RejectCounts, Rejected

log = logging.getLogger(__name__)

#: Raw samples, poses, topology, health and metrics. ``@`` chunks are verbatim
#: (no wildcard matches them): the admin keys are named.
DEFAULT_KEYS = (keys.all_raw(), keys.all_poses(), keys.TOPOLOGY, keys.all_health(),
                keys.METRICS)  # fmt: skip
#: The admin keys a recording holds by default (also after a subject).
ADMIN_KEYS = (keys.TOPOLOGY, keys.all_health(), keys.METRICS)


def admin_left_out(key_exprs: Sequence[str]) -> bool:
    """Whether ``key_exprs`` match none of the admin keys (topology, health,
    metrics, :data:`ADMIN_KEYS`): a Zenoh wildcard never matches a ``@`` chunk,
    so ``body/**`` leaves them all out."""
    admin = [zenoh.KeyExpr(k) for a in ADMIN_KEYS for k in (a, f"{keys.ANY_SUBJECT}/{a}")]
    return not any(zenoh.KeyExpr(k).intersects(a) for k in key_exprs for a in admin)


#: Samples each subscription holds for the recorder before Zenoh is held back:
#: about a second of twenty bodies' raw samples.
FIFO_DEPTH = 1 << 15
#: How long :meth:`Recorder.close` goes on writing what the FIFOs hold, at most.
DRAIN_S = 10.0


class Recorder:
    """Writes what it receives to ``path``. With ``rotate_bytes`` / ``rotate_s``
    it goes on in ``<stem>-001.mcap``, ``-002``... once the current file is
    that large or that old (0: never). No file is emptied: a name that is
    taken (an earlier recording, a recorder started again) is passed over for
    the next of the series (``files`` says which were written)."""

    def __init__(
        self,
        session: zenoh.Session,
        path: Path,
        key_exprs: Sequence[str] = DEFAULT_KEYS,
        rotate_bytes: int = 0,
        rotate_s: float = 0.0,
    ) -> None:
        self.path = path
        self._index, first, self._sink = self._new_file(0)
        self.files = [first]
        self.rejected = RejectCounts()
        keep_large_buffers_off_heap()  # before the first chunk's buffers
        self.rotate_bytes, self.rotate_s = rotate_bytes, rotate_s
        self._opened = time.monotonic()
        self._done = 0  # messages in files already closed
        self._lock = threading.Lock()
        self._closed = False
        self._last_seq: dict[str, tuple[int, int]] = {}  # topic -> (seq, t_ns) last written
        #: the write error that stopped the recording (a full disk), if one did
        self.error: OSError | None = None
        self.gaps = 0  # gap records written (each is in the file, not kept here)
        self.missing = 0  # messages they say are missing
        # Raw samples come from the bridges' advanced publishers: an advanced subscriber
        # fetches what a router restart made it miss. Poses, topology and health come from
        # plain publishers, with nothing to recover: a plain subscriber.
        recovery = zenoh.ext.RecoveryConfig(heartbeat=True)
        # raw samples asked for: the bridges' batches too, their samples kept where
        # their keys are among those asked for (all of them if batches were asked for)
        self._raw_exprs = [zenoh.KeyExpr(k) for k in key_exprs if _kind(k) == _RAW]
        self._all_batched = any(_kind(k) == _BATCH for k in key_exprs)
        self._wanted: dict[str, bool] = {}
        if self._raw_exprs and not self._all_batched:
            key_exprs = [*key_exprs, keys.all_batches(),
                         f"{keys.ANY_SUBJECT}/{keys.all_batches()}"]  # fmt: skip
        self._subs: list[Any] = [
            session.declare_subscriber(k, zenoh.handlers.FifoChannel(FIFO_DEPTH))
            if _kind(k) in _PLAIN
            else zenoh.ext.declare_advanced_subscriber(
                session, k, zenoh.handlers.FifoChannel(FIFO_DEPTH), recovery=recovery)
            for k in key_exprs
        ]  # fmt: skip
        # a thread per subscription empties its FIFO into the file (the FIFO outlives
        # the subscription: close undeclares, then the threads write what is left)
        self._drains = [
            threading.Thread(target=self._drain, args=(sub.handler,), daemon=True,
                             name=f"recorder {k}")
            for k, sub in zip(key_exprs, self._subs, strict=True)
        ]  # fmt: skip
        for thread in self._drains:
            thread.start()
        # the topology as it is now: published on change only, answered as a query
        for k in key_exprs:
            if _kind(k) == _TOPOLOGY:
                session.get(k, self._on_reply)

    def _drain(self, fifo: Any) -> None:
        """Write what ``fifo`` receives until its subscription is undeclared and
        it is empty."""
        try:
            while True:
                self._on_sample(fifo.recv())
        except zenoh.ZError:  # closed and empty
            pass

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._on_sample(reply.ok)

    def _new_file(self, index: int) -> tuple[int, Path, McapSink]:
        """The first file of the series from ``index`` on (0: ``path`` itself,
        else ``<stem>-NNN``) whose name is free, created, with its index."""
        while True:
            name = self.path if index == 0 else self.path.with_name(
                f"{self.path.stem}-{index:03d}{self.path.suffix}")  # fmt: skip
            try:
                # log time: when the message is written (under the lock, so in order)
                return index, name, McapSink(name, exclusive=True, receive_time=True)
            except FileExistsError:
                index += 1

    @property
    def messages(self) -> int:
        return self._done + self._sink.messages

    def _rotate_if_due(self) -> None:
        too_big = self.rotate_bytes and self.files[-1].stat().st_size >= self.rotate_bytes
        too_old = self.rotate_s and time.monotonic() - self._opened >= self.rotate_s
        if too_big or too_old:
            self._sink.close()
            self._done += self._sink.messages
            self._index, nxt, self._sink = self._new_file(self._index + 1)
            self.files.append(nxt)
            self._opened = time.monotonic()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        try:
            with self._lock:
                if self._closed:
                    return
                self._rotate_if_due()
                kind = _kind(key)
                if kind == _POSE:  # stored as it came: only its header is read (and segments)
                    seq, t_ns = self._sink.write_pose_message(key, data)
                    self._note_seq(key, seq, t_ns)
                elif kind == _TRUTH:
                    self._sink.write_truth(key, data, _truth_time(data))
                elif kind == _TOPOLOGY:
                    self._sink.write_topology(key, data, _admin_time(data))
                elif kind == _HEALTH:
                    self._sink.write_health(key, data, _admin_time(data))
                elif kind == _METRICS:
                    self._sink.write_metrics(key, data, _admin_time(data))
                elif kind == _BATCH:
                    for entry in raw_batch.split(key, data):
                        if isinstance(entry, Rejected):
                            self.rejected[entry.reason] += 1
                        elif self._wants(entry[0]):
                            self._write_raw(*entry)
                else:
                    self._write_raw(key, data)
        except DecodeError as exc:
            self.rejected[exc.reason] += 1
            log.debug("recorder: refused a message on %s: %s", key, exc)
        except OSError as exc:  # a full disk: the file ends here (what is flushed is salvageable)
            with self._lock:
                if self.error is None:
                    self.error = exc
                self._closed = True

    def _write_raw(self, key: str, data: bytes) -> None:
        """One raw sample, on its site's key; ``DecodeError`` if it does not decode
        (a batch's others are still written)."""
        try:
            raw = raw_sample.decode(data)
            self._note_seq(key, raw.seq, check_time(raw.t_ns))
        except DecodeError as exc:
            self.rejected[exc.reason] += 1
            log.debug("recorder: refused a message on %s: %s", key, exc)
            return
        self._sink.write_raw(key, raw, raw.t_ns)

    def _wants(self, key: str) -> bool:
        """Whether a batched sample's raw key is one the recording asked for."""
        wanted = self._wanted.get(key)
        if wanted is None:
            wanted = self._all_batched or any(e.intersects(key) for e in self._raw_exprs)
            if len(self._wanted) < 4096:
                self._wanted[key] = wanted
        return wanted

    def _note_seq(self, topic: str, seq: int, t_ns: int) -> None:
        """Write a gap record if ``seq`` skips numbers after the topic's last one.
        A lower number (a restarted gateway, a wrapped counter) starts afresh."""
        last = self._last_seq.get(topic)
        self._last_seq[topic] = (seq, t_ns)
        if last is not None and seq > last[0] + 1:
            gap = Gap(topic, last[0], seq - last[0] - 1, last[1], t_ns)
            self._sink.write_gap(gap)
            self.gaps += 1
            self.missing += gap.missing
            log.info("recorder: %d missing on %s after seq %d", gap.missing, topic, last[0])

    def close(self) -> None:
        """Stop receiving, write what the subscriptions' FIFOs still hold (for
        :data:`DRAIN_S` at most) and finish the file."""
        for sub in self._subs:
            sub.undeclare()
        deadline = time.monotonic() + DRAIN_S
        for thread in self._drains:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
        with self._lock:
            self._closed = True
            try:
                self._sink.close()
            except OSError as exc:  # the footer cannot be written either
                self.error = self.error or exc


_POSE, _TRUTH, _TOPOLOGY, _HEALTH, _RAW = "pose", "truth", "topology", "health", "raw"
_METRICS, _BATCH = "metrics", "batch"
_PLAIN = (_POSE, _TOPOLOGY, _HEALTH, _METRICS)  # what only plain publishers send


@lru_cache(maxsize=4096)  # on every sample's path; the key space is small
def _kind(key: str) -> str:
    """What a key (or key expression) of the recording carries, with or
    without a subject before it (``alice/body/@topology``)."""
    try:
        _, rest = keys.split_subject(key)
    except keys.KeySpaceError:
        rest = key
    # admin keys first: a bridge may be called "pose" (body/@health/pose)
    if rest == keys.TOPOLOGY:
        return _TOPOLOGY
    if rest.startswith(f"{keys.HEALTH}/"):
        return _HEALTH
    if rest == keys.METRICS:
        return _METRICS
    if rest.startswith(f"{keys.BATCH}/"):
        return _BATCH
    if key.endswith(f"/{keys.POSE}"):
        return _POSE
    if key.endswith(f"/{keys.Stream.TRUTH}"):
        return _TRUTH
    return _RAW


def _admin_time(data: bytes) -> int:
    """The log time of a topology or health message: its ``t_ns``, or the
    time it came if it has none; ``DecodeError`` unless it is a JSON object."""
    try:
        d = json.loads(data, parse_constant=_no_constant)
    except (ValueError, RecursionError) as exc:
        raise DecodeError(Reason.GARBAGE, f"not JSON: {exc}") from None
    if not isinstance(d, dict):
        raise DecodeError(Reason.GARBAGE, f"not a JSON object but {type(d).__name__}")
    t_ns = d.get("t_ns")
    if t_ns is None:
        return time.time_ns()
    if type(t_ns) is not int:
        raise DecodeError(Reason.GARBAGE, f"t_ns {t_ns!r} is not an integer")
    return check_time(t_ns)


def _no_constant(name: str) -> None:
    raise ValueError(f"{name} is not JSON")


def _truth_time(data: bytes) -> int:
    """The source time of a ground-truth message (JSON with ``t_ns``)."""
    try:
        t_ns = int(json.loads(data)["t_ns"])
    except (ValueError, KeyError, TypeError, OverflowError, RecursionError) as exc:
        raise DecodeError(Reason.GARBAGE, f"not a ground-truth message: {exc}") from None
    return check_time(t_ns)
