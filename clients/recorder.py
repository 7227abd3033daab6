"""Recording what the body network carries into MCAP (see ``mcap_store``).

Subscribes to the chosen key expressions (raw samples, poses) and writes each
message with its source time; the file is complete once :meth:`close` runs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from bodynet.clients.mcap_store import McapSink
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError, RejectCounts

log = logging.getLogger(__name__)

DEFAULT_KEYS = (keys.all_raw(), keys.all_poses())


class Recorder:
    def __init__(
        self, session: zenoh.Session, path: Path, key_exprs: Sequence[str] = DEFAULT_KEYS
    ) -> None:
        self.path = path
        self.rejected = RejectCounts()
        self._sink = McapSink(path)
        self._lock = threading.Lock()
        self._closed = False
        self._subs = [session.declare_subscriber(k, self._on_sample) for k in key_exprs]

    @property
    def messages(self) -> int:
        return self._sink.messages

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        try:
            with self._lock:
                if self._closed:
                    return
                if key.endswith(f"/{keys.POSE}"):
                    frame = pose.decode(data)
                    self._sink.write_pose(key, frame, frame.t_ns or time.time_ns())
                else:
                    raw = raw_sample.decode(data)
                    self._sink.write_raw(key, raw, raw.t_ns)
        except DecodeError as exc:
            self.rejected[exc.reason] += 1

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            self._closed = True
            self._sink.close()
