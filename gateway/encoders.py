"""Where each SmartSuit encoder's count is zero, and when that is no longer known.

A node's firmware resets its quadrature counter (``POSCNT``) at start-up (000
seed, ch. 3.4.1): the count is travel since power-on, 0 wherever the joint then
was. bodynet takes a node's power-on as the joint's zero (the suit put on and
switched on with the joints at the calibration pose, as the seed's experiments
start), until a calibration pose sets the zero from where the joint is
(:func:`zero_from_window`).

A node that reboots mid-session (a brown-out, a loose connector) starts
counting again from where its joint is then, and nothing on the wire says so:
a SmartSuit frame (and a concentrator reply) carries no sequence number, no
status, no banner of the node's. What a reboot does leave is a silence: the
node sends nothing while its power-up timer (128 ms in the dsPIC33F's default
configuration) and its start-up run. So a node silent for ``REBOOT_SILENCE_S``
or more and long enough for ``REBOOT_MISSED`` or more of its samples to be
missed in a row, by its usual interval between samples (a lost frame, or a
concentrator's lost reply, is no reboot; a node a concentrator polls among
fifteen sends every 330 ms) may have rebooted (so may the nodes behind a
restarted bridge: their power may have gone with the adapter's): its
encoder's zero is lost,
and its dofs are flagged ``uncalibrated`` until the next calibration pose. The
sequence numbers alone cannot tell: a CAN bridge counts a short silence's
missed periods only some frames later (``nodes/sources/base.py``,
``PeriodicSeq``).
"""

from __future__ import annotations

import statistics
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from bodynet.core.calibration import OleCalibration
from bodynet.core.messages import RawSample

#: The least silence taken for a possible reboot (s), and the least of the node's
#: usual intervals missed in a row: a lost frame or reply is no reboot.
REBOOT_SILENCE_S = 0.1
REBOOT_MISSED = 2
#: The node's usual interval is the median of up to this many of its last
#: intervals (a silence among them does not move it), once it has ``MIN_INTERVALS``
INTERVALS, MIN_INTERVALS = 15, 5


@dataclass(slots=True)
class EncoderZero:
    """One encoder's zero: the count at its joint's zero (0: the node's power-on)
    and, when that is not known now, why (``lost``)."""

    counts: int = 0
    lost: str | None = None
    rezeroed: bool = False  # the zero was set by a calibration pose
    #: the node's last intervals between samples (s)
    intervals: deque[float] = field(default_factory=lambda: deque(maxlen=INTERVALS))

    @property
    def interval_s(self) -> float | None:
        """The node's usual interval between samples; None before ``MIN_INTERVALS``."""
        known = len(self.intervals) >= MIN_INTERVALS
        return statistics.median(self.intervals) if known else None

    def observe(self, before: RawSample, after: RawSample) -> str | None:
        """Two samples of the node in a row: the reason the zero was lost now, if
        the silence between them may have held a reboot (see the module's
        docstring); None otherwise."""
        dt = (after.t_ns - before.t_ns) / 1e9
        # the median only where it matters: this runs for every module's sample
        silent = silence(before, after, self.interval_s) if dt >= REBOOT_SILENCE_S else None
        self.intervals.append(dt)
        if silent is None or self.lost is not None:
            return None
        self.lost = lost_reason(silent, after.t_ns)
        return self.lost

    def angle_counts(self, encoder: int) -> int | None:
        """The count from the joint's zero; None while the zero is lost."""
        return None if self.lost is not None else encoder - self.counts

    def state(self) -> dict[str, object]:
        """For health: the zero, whether the encoder measures, and why not."""
        return {"zero_counts": self.counts, "measured": self.lost is None,
                "zeroed_by": "calibration" if self.rezeroed else "power-on",
                "reason": self.lost}  # fmt: skip


def silence(before: RawSample, after: RawSample, interval_s: float | None) -> float | None:
    """How long (s) a node said nothing between two of its samples, when that is
    long enough to have held a reboot: ``REBOOT_SILENCE_S`` and ``REBOOT_MISSED``
    or more of its samples missed at its usual ``interval_s`` (half an interval
    more, for jitter; None: not known yet, so nothing is judged); else None."""
    if interval_s is None:
        return None
    silent = (after.t_ns - before.t_ns) / 1e9
    usual = (REBOOT_MISSED + 0.5) * interval_s
    return silent if silent >= REBOOT_SILENCE_S and silent > usual else None


def lost_reason(silent_s: float, t_ns: int) -> str:
    """The reason health gives for an encoder whose node went silent ``silent_s``."""
    return (f"node silent {silent_s:.2f} s before {t_ns / 1e9:.3f} s: it may have rebooted, "
            "its encoder now counting from where the joint was then; hold the calibration "
            "pose and calibrate to measure it again")  # fmt: skip


class ZeroRefused(ValueError):
    """A calibration pose in which an encoder's joint moved."""


#: An encoder's joint turning more than this (deg) in the calibration window moved;
#: and the fewest counts of it the window must hold.
STILL_DEG = 3.0
MIN_COUNTS = 5


def zero_from_window(counts: Sequence[int], calibration: OleCalibration | None,
                     pose_angle_deg: float, key: str) -> int:  # fmt: skip
    """The count at the joint's zero from its counts in a still window of the
    calibration pose (its joint at ``pose_angle_deg`` there). :class:`ZeroRefused`
    when the joint turned more than ``STILL_DEG`` in it, or it holds fewer than
    ``MIN_COUNTS`` counts."""
    if len(counts) < MIN_COUNTS:
        raise ZeroRefused(f"the window is too short: {len(counts)} counts of {key} in it; it "
                          f"needs at least {MIN_COUNTS}")  # fmt: skip
    lo, hi = min(counts), max(counts)
    mean = round(sum(counts) / len(counts))
    if calibration is None:
        return mean
    turned = abs(float(calibration.angle_deg(hi - lo)))
    if turned > STILL_DEG:
        raise ZeroRefused(f"the subject moved: {key}'s joint turned {turned:.1f} deg in the "
                          "window; stand still in the pose and try again")  # fmt: skip
    return mean - calibration.counts(pose_angle_deg)


def states(zeros: Mapping[str, EncoderZero]) -> dict[str, dict[str, object]]:
    """Health's view of the encoders whose zero is not their node's power-on."""
    return {k: z.state() for k, z in sorted(zeros.items()) if z.lost is not None or z.rezeroed}
