"""``bodynet lsl``: the live body as Lab Streaming Layer streams (pylsl).

Per subject, created when its first pose (or raw sample) arrives and kept
for the life of the process, so a gateway or router restart only pauses
them (the Zenoh session reconnects by itself):

- ``bodynet <subject> joint angles``: one channel per ``<joint>_<dof>`` of the
  body model, degrees;
- ``bodynet <subject> segments``: per segment of the body model its position
  (``<segment>_x``, ``_y``, ``_z``, metres, world frame +X forward, +Y left,
  +Z up) and orientation quaternion (``<segment>_qw``, ``_qx``, ``_qy``, ``_qz``);
- with ``raw=True``, ``bodynet <subject> raw <limb>/<side>/<site>``: one stream
  per sensor site and kind, the sample's ``seq`` then its reading (encoder
  count and accelerometer counts, or the quaternion).

Every stream has type ``MoCap``, channel format double (the pose's numbers
exactly), an irregular nominal rate (the gateway ticks when a frame is
whole, not on a fixed grid), a ``source_id`` made of the subject and the
stream (``bodynet/<subject>/angles``...) so that LabRecorder and any inlet
opened with recovery reconnect to the same stream after ``bodynet lsl`` is
restarted, and channel metadata in its description as motion-capture LSL
apps give it (``channels/channel/{label, type, unit}``, plus the segment or
joint a channel belongs to).

Channels that no measurement stands behind carry NaN, never a held value:
an angle flagged anything but ``clamped`` (``pose.is_measured``: the gateway
flags what rests on a stale sensor, reason ``stale``); a segment whose chain
from the pelvis crosses such an angle (its world pose rests on a guess; the
upright model a body with no trunk sensor stands on is its reference, no guess);
anything the pose message lacks.

Timestamps: each sample carries its own source time (the pose's ``t_ns``,
the raw sample's ``t_ns``: Unix nanoseconds of the bridge that received it)
mapped onto LSL's clock. ``local_clock()`` is a monotonic clock with an
arbitrary epoch, the same for every process on the machine; the offset
between it and the Unix clock is estimated ONCE when the output starts (the
narrowest of 50 ``local_clock, time_ns, local_clock`` brackets, its middle:
a few microseconds) and then kept. A constant offset keeps the intervals
between samples exactly as the sources stamped them; re-estimating it for
every sample would add the estimate's jitter to every timestamp. The cost:
if the wall clock is stepped or slewed while it runs, the mapping drifts by
that much (restart the output after setting the clock). Bridges on other
machines must keep their clocks synchronised with this one (NTP, PTP): their
``t_ns`` are read on this machine's Unix clock.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from bodynet.clients.body_tree import unmeasured_segments
from bodynet.clients.live import LiveOutput
from bodynet.core.codecs import pose
from bodynet.core.keys import parse
from bodynet.core.messages import OleAccel, Quat, RawSample
from bodynet.core.metrics import measured_angles
from bodynet.core.skeleton import Skeleton, build_skeleton

STREAM_TYPE = "MoCap"
NAN = math.nan
#: How long closing leaves a consumed outlet up for liblsl to send what was pushed
#: (it writes a sample within milliseconds of its push; it has no flush to wait on).
LINGER_S = 0.5


# --- conversions (pure) -------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Channel:
    """One LSL channel's metadata, as it goes into the stream's description."""

    label: str
    type: str
    unit: str
    part: str  # the joint or segment (or sensor site) it belongs to


@dataclass(frozen=True, slots=True)
class ClockMap:
    """Unix time (ns) onto LSL's ``local_clock()`` (s): ``unix_ns`` and
    ``local_s`` were read at the same instant."""

    unix_ns: int
    local_s: float

    def to_local(self, t_ns: int) -> float:
        """``t_ns`` (Unix ns) on LSL's clock; the difference is taken in integers
        first, so no precision is lost to the size of a Unix time."""
        return self.local_s + (t_ns - self.unix_ns) * 1e-9


def estimate_clock_map(
    local_clock: Callable[[], float], unix_ns: Callable[[], int], tries: int = 50
) -> ClockMap:
    """The offset between the two clocks: of ``tries`` readings of the Unix clock
    bracketed by two of the local clock, the narrowest bracket's middle."""
    best: tuple[float, int, float] | None = None
    for _ in range(tries):
        a = local_clock()
        u = unix_ns()
        b = local_clock()
        if best is None or b - a < best[0]:
            best = (b - a, u, (a + b) / 2)
    assert best is not None, "tries must be at least 1"
    return ClockMap(best[1], best[2])


def angle_names(skeleton: Skeleton) -> tuple[str, ...]:
    """The pose's names (``<joint>_<dof>_deg``) of the angle channels, in order."""
    return skeleton.angle_names()


def angle_channels(skeleton: Skeleton) -> list[Channel]:
    """One channel per ``<joint>_<dof>``, degrees."""
    return [Channel(j.name + "_" + d.name, "JointAngle", "degrees", j.name)
            for j in skeleton.joints for d in j.dofs]  # fmt: skip


def angle_values(frame: pose.PoseFrame, names: Sequence[str]) -> list[float]:
    """The angles of ``frame`` in channel order; NaN where nothing was measured
    (flagged: ``core.metrics.measured_angles``)."""
    measured = measured_angles(frame)
    return [measured.get(n, NAN) for n in names]


_POSITION = (("x", "PositionX"), ("y", "PositionY"), ("z", "PositionZ"))
_ORIENTATION = (("qw", "OrientationA"), ("qx", "OrientationB"), ("qy", "OrientationC"),
                ("qz", "OrientationD"))  # fmt: skip


def segment_channels(skeleton: Skeleton) -> list[Channel]:
    """Seven channels per segment: position (m), then quaternion w, x, y, z
    (the XDF mocap convention's ``OrientationA..D``, A the scalar part)."""
    return [Channel(f"{seg}_{suffix}", kind, unit, seg)
            for seg in skeleton.segments
            for group, unit in ((_POSITION, "meters"), (_ORIENTATION, "normalized"))
            for suffix, kind in group]  # fmt: skip


def segment_values(frame: pose.PoseFrame, chains: Mapping[str, Sequence[str]]) -> list[float]:
    """Position and quaternion of every segment in channel order; NaN for a segment
    the pose lacks or whose chain holds an angle the pose lacks or does not measure
    (``body_tree.unmeasured_segments``: the upright model's is no guess)."""
    out: list[float] = []
    unmeasured = unmeasured_segments(frame, chains)
    for seg in chains:
        got = frame.segments.get(seg)
        if got is None or seg in unmeasured:
            out.extend((NAN,) * 7)
        else:
            out.extend(got[0])
            out.extend(got[1])
    return out


def raw_channels(sample: RawSample) -> list[Channel]:
    """The channels of one raw sample's kind: ``seq``, then its reading."""
    seq = Channel("seq", "SequenceNumber", "count", "")
    if isinstance(sample.reading, OleAccel):
        return [seq, Channel("encoder", "Encoder", "0.1 mm", ""),
                *(Channel(f"accel_{a}", f"Acceleration{a.upper()}", "counts (1024 per g)", "")
                  for a in "xyz")]  # fmt: skip
    return [seq, *(Channel(label, kind, "normalized", "") for label, kind in _ORIENTATION)]


def raw_values(sample: RawSample) -> list[float]:
    r = sample.reading
    if isinstance(r, OleAccel):
        return [float(sample.seq), float(r.encoder), *map(float, r.accel)]
    assert isinstance(r, Quat)
    return [float(sample.seq), *r.wxyz]


def source_id(subject: str, stream: str) -> str:
    """The stable identity of one stream: the same after a restart."""
    return f"bodynet/{subject}/{stream}"


# --- the output (pylsl) -------------------------------------------------------------------


def make_outlet(name: str, sid: str, channels: Sequence[Channel], description: Mapping[str, str]
                ) -> Any:  # fmt: skip
    """An LSL outlet of type ``MoCap`` whose description lists ``channels``."""
    import pylsl

    info = pylsl.StreamInfo(name, STREAM_TYPE, len(channels), pylsl.IRREGULAR_RATE,
                            pylsl.cf_double64, sid)  # fmt: skip
    desc = info.desc()
    acq = desc.append_child("acquisition")
    acq.append_child_value("manufacturer", "bodynet")
    acq.append_child_value("model", "bodynet gateway")
    for k, v in description.items():
        desc.append_child_value(k, v)
    chans = desc.append_child("channels")
    for c in channels:
        ch = chans.append_child("channel")
        ch.append_child_value("label", c.label)
        ch.append_child_value("type", c.type)
        ch.append_child_value("unit", c.unit)
        if c.part:
            ch.append_child_value("object", c.part)
    return pylsl.StreamOutlet(info)


class LslOutput(LiveOutput):
    """Per subject, the joint-angle and segment streams (and with ``raw`` one
    stream per sensor site), each sample stamped with its mapped source time."""

    def __init__(self, raw: bool = False, skeleton: Skeleton | None = None,
                 clock: ClockMap | None = None) -> None:  # fmt: skip
        import pylsl

        self.wants_raw = raw
        self.skeleton = skeleton or build_skeleton()
        self.clock = clock or estimate_clock_map(pylsl.local_clock, time.time_ns)
        self._names = angle_names(self.skeleton)
        self._chains = self.skeleton.segment_chains()
        self._outlets: dict[tuple[str, str], Any] = {}
        self.pushed = 0

    def describe(self) -> str:
        raw = ", raw samples per site" if self.wants_raw else ""
        return f"LSL streams of type {STREAM_TYPE}: joint angles, segments{raw}"

    def _outlet(self, subject: str, stream: str, title: str, channels: Sequence[Channel],
                extra: Mapping[str, str] | None = None) -> Any:  # fmt: skip
        outlet = self._outlets.get((subject, stream))
        if outlet is None:
            description = {"subject": subject, "frame": "+X forward, +Y left, +Z up",
                           **(extra or {})}  # fmt: skip
            outlet = make_outlet(f"bodynet {subject} {title}", source_id(subject, stream),
                                 channels, description)  # fmt: skip
            self._outlets[(subject, stream)] = outlet
        return outlet

    def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
        stamp = self.clock.to_local(frame.t_ns)
        angles = self._outlet(subject, "angles", "joint angles", angle_channels(self.skeleton))
        angles.push_sample(angle_values(frame, self._names), stamp)
        segments = self._outlet(subject, "segments", "segments", segment_channels(self.skeleton))
        segments.push_sample(segment_values(frame, self._chains), stamp)
        self.pushed += 2

    def on_raw(self, subject: str, key: str, sample: RawSample) -> None:
        site, _ = parse(key)
        kind = "ole" if isinstance(sample.reading, OleAccel) else "quat"
        where = f"{site.branch.limb}/{site.branch.side}/{site.name}"
        extra = {"key": key, "node": str(sample.reading.node)}
        outlet = self._outlet(subject, f"raw/{where}/{kind}", f"raw {where}",
                              raw_channels(sample), extra)  # fmt: skip
        outlet.push_sample(raw_values(sample), self.clock.to_local(sample.t_ns))
        self.pushed += 1

    @property
    def streams(self) -> list[str]:
        """The source ids of the streams opened so far."""
        return [source_id(s, n) for s, n in self._outlets]

    def close(self) -> None:
        """Destroy the outlets, once their consumers had :data:`LINGER_S` to take the
        last samples: liblsl has no flush, and destroying an outlet closes its
        connections at once, dropping what its sender threads had not written yet
        (the last samples before a stop, as often as not)."""
        if any(o.have_consumers() for o in self._outlets.values()):
            time.sleep(LINGER_S)
        self._outlets.clear()  # pylsl destroys an outlet when it is collected
