"""``bodynet metrics``: clinical numbers live, on ``body/@metrics``.

A live output (``clients/live.py``) like the LSL and VMC ones, whose "send"
is a Zenoh put: it reads each subject's whole-body poses, feeds the measured
angles (no flag, or ``clamped``: the team's convention) to that subject's
:class:`bodynet.core.metrics.BodyMetrics`, and about twice a second
publishes its snapshot (JSON, see ``BodyMetrics.snapshot``) on the subject's
``body/@metrics``: per observed dof the range of motion so far, repetitions
and the SPARC smoothness of its current movement. Data still flows one way:
gateway -> Zenoh -> this client -> Zenoh -> viewers and recorders. The offline
report computes the same numbers with the same module.
"""

from __future__ import annotations

import json
from typing import Any

from bodynet.clients.live import DEFAULT_SUBJECT, LiveOutput
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.metrics import BodyMetrics, measured_angles

DEFAULT_RATE_HZ = 2.0


def metrics_key(subject: str, all_subjects: bool) -> str:
    """Where a subject's metrics go: its namespace's ``body/@metrics`` (a session
    in that namespace already adds the prefix)."""
    if not all_subjects or subject == DEFAULT_SUBJECT:
        return keys.METRICS
    return keys.subject_prefix(subject) + keys.METRICS


def encode(snapshot: dict[str, Any]) -> bytes:
    return json.dumps(snapshot, separators=(",", ":"), allow_nan=False).encode()


class MetricsOutput(LiveOutput):
    """Per subject, the running metrics of its poses, published every
    ``1 / rate_hz`` seconds when new poses came."""

    def __init__(self, session: Any, all_subjects: bool = False,
                 rate_hz: float = DEFAULT_RATE_HZ) -> None:  # fmt: skip
        self.session = session
        self.all_subjects = all_subjects
        self.tick_s = 1.0 / rate_hz
        self.rate_hz = rate_hz
        self.bodies: dict[str, BodyMetrics] = {}
        self._changed: set[str] = set()
        self.published = 0

    def describe(self) -> str:
        return f"{keys.METRICS} at {self.rate_hz:g} Hz"

    def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
        body = self.bodies.get(subject)
        if body is None:
            body = self.bodies[subject] = BodyMetrics()
        body.add(frame.t_ns, measured_angles(frame))
        self._changed.add(subject)

    def tick(self, now: float) -> None:
        for subject in sorted(self._changed):
            snapshot = self.bodies[subject].snapshot()
            self.session.put(metrics_key(subject, self.all_subjects), encode(snapshot))
            self.published += 1
        self._changed.clear()
