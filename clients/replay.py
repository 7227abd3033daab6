"""``bodynet replay``: a recording's raw samples back onto Zenoh, on their keys.

With the original timing (or ``speed`` times faster), optionally looping, so
a session can be run again through a newer calibration or gateway. Samples
are stamped with the time of replay (``t_ns``), keeping their sequence
numbers, so the gateway's staleness and latency work as they do live.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import zenoh
from tqdm import tqdm

from bodynet.clients.mcap_store import count_messages, read_raw
from bodynet.core.codecs import raw_sample
from bodynet.core.messages import RawSample


def replay(
    session: zenoh.Session,
    path: Path,
    stop: threading.Event,
    topics: list[str] | None = None,
    speed: float = 1.0,
    loop: bool = False,
    progress: bool = True,
) -> int:
    """Publish the raw samples of ``path``; returns how many were published."""
    publishers: dict[str, zenoh.Publisher] = {}
    sent = 0
    total = count_messages(path)
    with tqdm(total=total or None, unit="msg", disable=not progress, desc=path.name) as bar:
        while not stop.is_set():
            start, first = time.monotonic(), None
            for topic, log_time, sample in read_raw(path, topics):
                first = log_time if first is None else first
                due = start + (log_time - first) / 1e9 / speed
                if stop.wait(max(0.0, due - time.monotonic())):
                    return sent
                pub = publishers.get(topic) or publishers.setdefault(
                    topic, session.declare_publisher(topic)
                )
                pub.put(
                    raw_sample.encode(
                        RawSample(sample.reading, sample.seq, time.time_ns(), sample.source)
                    )
                )
                sent += 1
                bar.update()
            if not loop:
                break
            bar.reset()
    return sent
