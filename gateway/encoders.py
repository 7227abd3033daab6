"""Where each SmartSuit encoder's count is zero, and when that is no longer known.

A node's firmware resets its quadrature counter (``POSCNT``) at start-up (000
seed, ch. 3.4.1): the count is travel since power-on, 0 wherever the joint then
was. bodynet takes a node's power-on as the joint's zero (the suit put on and
switched on with the joints at the calibration pose, as the seed's experiments
start), until a calibration pose sets the zero from where the joint is
(:func:`zero_from_window`).

A node that reboots mid-session (a brown-out, a loose connector) starts
counting again from where its joint is then, and nothing in its frames says
so: a SmartSuit frame (and a concentrator reply) carries no sequence number,
no status, no banner of the node's. What a reboot does leave is a silence of
the node on a link that is alive, and only the bridge reading that link sees
it as such (the gateway cannot tell a node's silence from its own link's: a
router restarted, Wi-Fi): the bridge flags the node's next sample ``RESUMED``
(``nodes/sources/base.py``, ``Adapter.resumed``). Such a sample loses the
encoder's zero: its dofs are flagged ``uncalibrated`` until the next
calibration pose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from bodynet.core.calibration import OleCalibration
from bodynet.core.messages import RESUMED, RawSample


@dataclass(slots=True)
class EncoderZero:
    """One encoder's zero: the count at its joint's zero (0: the node's power-on)
    and, when that is not known now, why (``lost``)."""

    counts: int = 0
    lost: str | None = None
    rezeroed: bool = False  # the zero was set by a calibration pose
    #: how many samples its bridge flagged ``RESUMED`` (the node may have rebooted,
    #: lost or not already): counts of one generation set no zero at another
    generation: int = 0

    def take(self, sample: RawSample) -> str | None:
        """A sample of the encoder's node: the reason the zero is lost now, when
        its bridge flagged it ``RESUMED`` and the zero was still known; else None."""
        if not sample.flags & RESUMED:
            return None
        self.generation += 1
        if self.lost is not None:
            return None
        self.lost = lost_reason(sample.t_ns)
        return self.lost

    def angle_counts(self, encoder: int) -> int | None:
        """The count from the joint's zero; None while the zero is lost."""
        return None if self.lost is not None else encoder - self.counts

    def state(self) -> dict[str, object]:
        """For health: the zero, whether the encoder measures, and why not."""
        return {"zero_counts": self.counts, "measured": self.lost is None,
                "zeroed_by": "calibration" if self.rezeroed else "power-on",
                "reason": self.lost}  # fmt: skip


def lost_reason(t_ns: int) -> str:
    """The reason health gives for an encoder whose node resumed at ``t_ns``."""
    return (f"node silent before {t_ns / 1e9:.3f} s on a live link (its bridge says): it may "
            "have rebooted, its encoder now counting from where the joint was then; hold the "
            "calibration pose and calibrate to measure it again")  # fmt: skip


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
