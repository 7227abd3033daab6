"""Live outputs: the gateway's poses (and, if asked, raw samples) re-sent in
another tool's protocol, one subject or every subject at once.

Every live output is one module in ``clients/`` behind the same small
interface, :class:`LiveOutput`:

- **subscribe**: :func:`run` subscribes to the whole-body poses
  (``body/pose``) and, when the output wants them (``wants_raw``), the raw
  samples of one subject (the session's namespace) or of every subject
  (``*/body/...`` as well as the namespace-less ``body/...``, as the gateway's
  ``--all-subjects``), and hands each decoded message to the output with its
  subject's name, from one worker thread;
- **convert**: pure functions of the output's module turn a pose into that
  protocol's values (tested alone);
- **send**: the output's ``on_pose`` / ``on_raw`` / ``tick`` methods write them
  (an LSL outlet, a UDP socket, a Zenoh publisher).

A message that does not decode is counted (``Counts.bad``), one the output
fails on too (``Counts.failed``, logged): neither is fatal.
:data:`OUTPUTS` is the registry: name -> ``module:class``, imported lazily.
"""

from __future__ import annotations

import importlib
import logging
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose, raw_batch, raw_sample
from bodynet.core.errors import DecodeError, Rejected
from bodynet.core.messages import RawSample

log = logging.getLogger(__name__)

#: The live outputs: command name -> ``module:class`` (imported when used).
OUTPUTS: dict[str, str] = {
    "lsl": "bodynet.clients.lsl:LslOutput",
    "vmc": "bodynet.clients.vmc:VmcOutput",
    "metrics": "bodynet.clients.metrics:MetricsOutput",
}

#: The name a subject without namespace goes by in the outputs (stream names,
#: source ids): the same as its profile's in an all-subjects gateway.
DEFAULT_SUBJECT = "default"
#: how long a stopped output waits for what its subscriptions had taken in
STOP_FLUSH_S = 2.0


def output_class(name: str) -> type[LiveOutput]:
    """The class of the live output called ``name`` (see :data:`OUTPUTS`)."""
    module, _, cls = OUTPUTS[name].partition(":")
    found: type[LiveOutput] = getattr(importlib.import_module(module), cls)
    return found


class LiveOutput:
    """One live output. :func:`run` calls, from one thread:

    - ``on_pose(subject, frame)`` for every whole-body pose of a subject;
    - ``on_raw(subject, key, sample)`` for every raw sample when ``wants_raw``;
    - ``tick(now)`` at least every ``tick_s`` seconds (``time.monotonic()``), for
      outputs that send at a rate of their own;
    - ``close()`` once at the end.
    """

    wants_raw: bool = False
    tick_s: float = 0.1

    def describe(self) -> str:
        """What it sends where, in a few words (printed when it starts)."""
        return type(self).__name__

    def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
        """Convert and send one pose."""

    def on_raw(self, subject: str, key: str, sample: RawSample) -> None:
        """Convert and send one raw sample (``key`` without the subject's prefix)."""

    def tick(self, now: float) -> None:
        """Periodic work (rate-limited sending)."""

    def close(self) -> None:
        """Release what the output holds (outlets, sockets)."""


@dataclass
class Counts:
    """What :func:`run` handled: poses and raw samples per subject, bad messages."""

    poses: Counter[str] = field(default_factory=Counter)
    raw: Counter[str] = field(default_factory=Counter)
    bad: int = 0
    failed: int = 0
    refused_subjects: int = 0

    def summary(self) -> str:
        subjects = sorted(set(self.poses) | set(self.raw))
        parts = [f"{s}: {self.poses[s]} poses" + (f", {self.raw[s]} raw" if self.raw[s] else "")
                 for s in subjects]  # fmt: skip
        if self.bad:
            parts.append(f"{self.bad} messages that did not decode")
        if self.failed:
            parts.append(f"{self.failed} messages the output failed on (see the log)")
        if self.refused_subjects:
            parts.append(f"{self.refused_subjects} messages of subjects past the limit")
        return "; ".join(parts) or "nothing received"


#: Subjects one output serves at most: a publisher inventing subject names must
#: not make it open outlets without end (the gateway's limit too).
MAX_SUBJECTS = 64


def subscriptions(all_subjects: bool, wants_raw: bool) -> list[str]:
    """The key expressions a live output subscribes to."""
    data = [keys.pose_key(), *([keys.all_raw(), keys.all_batches()] if wants_raw else [])]
    prefixes = ("", keys.ANY_SUBJECT + "/") if all_subjects else ("",)
    return [p + k for p in prefixes for k in data]


def run(
    session: zenoh.Session,
    output: LiveOutput,
    stop: threading.Event,
    *,
    subject: str | None = None,
    all_subjects: bool = False,
) -> Counts:
    """Feed ``output`` from ``session`` until ``stop`` is set; then hand it what had
    come in meanwhile, and close it.

    ``subject`` names the subject of a session in that subject's namespace (the
    keys it sees are plain ``body/...``); with ``all_subjects`` the session has
    no namespace and each key's first chunk names its subject."""
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()

    def put(sample: zenoh.Sample) -> None:
        inbox.put((str(sample.key_expr), sample.payload.to_bytes()))

    # Zenoh runs each subscription's callback on a thread of its own, behind a queue:
    # a subscription undeclared is done when its drop runs, after the samples queued
    done = threading.Semaphore(0)
    counts = Counts()
    subs = [session.declare_subscriber(k, zenoh.handlers.Callback(put, done.release))
            for k in subscriptions(all_subjects, output.wants_raw)]  # fmt: skip
    own = subject or DEFAULT_SUBJECT
    next_tick = time.monotonic()
    try:
        while not stop.is_set():
            now = time.monotonic()
            if now >= next_tick:
                output.tick(now)
                next_tick = now + output.tick_s
            try:
                key, data = inbox.get(timeout=max(0.0, min(0.1, next_tick - now)))
            except queue.Empty:
                continue
            _handle(output, counts, key, data, own, all_subjects)
        for sub in subs:  # stopped: nothing more comes in, and what came is sent
            sub.undeclare()
        deadline = time.monotonic() + STOP_FLUSH_S
        for _ in subs:
            done.acquire(timeout=max(0.0, deadline - time.monotonic()))
        subs = []
        while True:
            try:
                key, data = inbox.get_nowait()
            except queue.Empty:
                break
            _handle(output, counts, key, data, own, all_subjects)
    finally:
        for sub in subs:
            sub.undeclare()
        output.close()
    return counts


def _handle(output: LiveOutput, counts: Counts, key: str, data: bytes, own: str,
            all_subjects: bool) -> None:  # fmt: skip
    """Decode one message and hand it to ``output``, counting it; none raises."""
    try:
        name, body_key = keys.split_subject(key) if all_subjects else (own, key)
        name = name or DEFAULT_SUBJECT
        new = name not in counts.poses and name not in counts.raw
        if new and len(set(counts.poses) | set(counts.raw)) >= MAX_SUBJECTS:
            counts.refused_subjects += 1
            return
        if body_key == keys.pose_key():
            frame = pose.decode(data)
            counts.poses[name] += 1
            output.on_pose(name, frame)
        else:  # a bridge's batch, or a payload of samples back to back
            for entry in raw_batch.split(body_key, data):
                if isinstance(entry, Rejected):
                    counts.bad += 1
                    continue
                site_key, message = entry
                for event in raw_sample.decode_batch(message):
                    if isinstance(event, RawSample):
                        counts.raw[name] += 1
                        output.on_raw(name, site_key, event)
                    else:
                        counts.bad += 1
    except (DecodeError, keys.KeySpaceError):
        counts.bad += 1
    except Exception:  # one message the output could not send: counted, it goes on
        counts.failed += 1
        if counts.failed <= 3:
            log.exception("live output: a message on %s could not be sent", key)


def load_output(name: str, **options: Any) -> LiveOutput:
    """An instance of the live output ``name`` with its options."""
    return output_class(name)(**options)
