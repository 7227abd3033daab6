"""``bodynet replay``: a recording's raw samples back onto Zenoh, on their keys.

With the original timing (or ``speed`` times faster), optionally looping, so
a session can be run again through a newer calibration or gateway. Samples
are stamped with the time of replay (``t_ns``), keeping their sequence
numbers, so the gateway's staleness and latency work as they do live.
``keys`` (key expressions, such as ``body/arm/left/**``) replays only the raw
samples of the topics they match. The progress bar counts what is replayed,
from the recording's summary (its per-channel message counts).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import zenoh
from tqdm import tqdm

from bodynet.clients.mcap_store import channel_counts, read_raw
from bodynet.core.codecs import raw_sample
from bodynet.core.messages import RawSample
from bodynet.session import _one_line

#: The schema of the channels replay republishes (see ``mcap_store``).
RAW_SCHEMA_NAME = "bodynet.RawSample"


def topic_filter(key_exprs: Sequence[str] | None) -> Callable[[str], bool]:
    """Whether a topic is one of those ``key_exprs`` match (every one if ``None``);
    ``ValueError`` for a key expression Zenoh does not take."""
    if key_exprs is None:
        return lambda topic: True
    selectors = []
    for k in key_exprs:
        try:
            selectors.append(zenoh.KeyExpr(k))
        except zenoh.ZError as exc:
            raise ValueError(f"{k!r} is not a key expression ({_one_line(exc)})") from None
    seen: dict[str, bool] = {}

    def wanted(topic: str) -> bool:
        hit = seen.get(topic)
        if hit is None:
            try:
                key = zenoh.KeyExpr(topic)
            except zenoh.ZError:
                hit = False
            else:
                hit = any(s.includes(key) for s in selectors)
            seen[topic] = hit
        return hit

    return wanted


def replay(
    session: zenoh.Session,
    path: Path,
    stop: threading.Event,
    topics: Sequence[str] | None = None,
    speed: float = 1.0,
    loop: bool = False,
    progress: bool = True,
) -> int:
    """Publish the raw samples of ``path`` (of the topics the key expressions
    ``topics`` match, else all); returns how many were published."""
    if not speed > 0:
        raise ValueError(f"speed must be positive, not {speed}")
    wanted = topic_filter(topics)
    counts = channel_counts(path)
    chosen: list[str] | None = None  # no summary: the messages are filtered as they come
    total = 0
    if counts is not None:
        raw = [c for c in counts if c.schema == RAW_SCHEMA_NAME and wanted(c.topic)]
        chosen = sorted({c.topic for c in raw})
        total = sum(c.messages for c in raw)
    publishers: dict[str, zenoh.Publisher] = {}
    sent = 0
    with tqdm(total=total or None, unit="msg", disable=not progress, desc=path.name) as bar:
        while not stop.is_set():
            start, first = time.monotonic(), None
            for topic, t_ns, sample in read_raw(path, chosen):
                if chosen is None and not wanted(topic):
                    continue
                first = t_ns if first is None else first
                due = start + (t_ns - first) / 1e9 / speed
                if stop.wait(max(0.0, due - time.monotonic())):
                    return sent
                pub = publishers.get(topic) or publishers.setdefault(
                    topic, session.declare_publisher(topic)
                )
                pub.put(
                    raw_sample.encode(
                        RawSample(
                            sample.reading, sample.seq, time.time_ns(), sample.source, sample.flags
                        )
                    )
                )
                sent += 1
                bar.update()
            if not loop or first is None:  # a loop over nothing would spin
                break
            bar.reset()
    return sent
