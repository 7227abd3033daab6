"""Messages shared by every role: sensor readings and the stamped raw sample.

Readings are what a wire format says about one node at one instant, with no
time attached (codecs read no clock). A :class:`RawSample` is a reading stamped
by the process that received it: source time in integer nanoseconds and a
per-node sequence number. That is what travels on Zenoh.

The readings and the raw sample are values that nothing changes once made, but
they are not ``frozen`` dataclasses: a frozen dataclass is built through
``object.__setattr__`` field by field, three times the cost, and the gateway
makes a reading and a sample for every one of its 30,000 samples a second at
twenty bodies (frozen, building them took some 6% of its worker's time).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from .errors import Rejected


class Source(IntEnum):
    """Which kind of hardware (or emulator, or file) a sample came through.

    The raw-sample message carries this id in one byte. These are the ids this
    version knows by name; a message with any other id is accepted all the same
    (a source added elsewhere, see ``bodynet.nodes.sources``) and named by
    :func:`source_name` as ``source-<id>``.
    """

    UNKNOWN = 0
    CAN = 1
    CONCENTRATOR = 2
    IMU_CENTRAL = 3
    SLIMEVR = 4
    ORIENTATION_FILE = 5


#: How long before its stamp a source's sample may have been taken (s), where the
#: stamp says only when it arrived: the IMU central prints each tag's latest
#: notification on its own tick, and a tag notifies once a BLE connection interval
#: (003 seed, Table 7.6: 10 to 30 ms), so its reading is up to that old.
STAMP_SPREAD_S = {Source.IMU_CENTRAL: 0.03}


_SOURCE_PREFIX = "source-"


def source_name(source: int) -> str:
    """``"can"`` for :attr:`Source.CAN`, ``"source-231"`` for an id this version lacks."""
    try:
        return Source(source).name.lower()
    except ValueError:
        return f"{_SOURCE_PREFIX}{source}"


def source_of(name: str) -> int:
    """The id :func:`source_name` gave ``name``; ``ValueError`` if it gave none."""
    if name.startswith(_SOURCE_PREFIX) and name[len(_SOURCE_PREFIX) :].isdigit():
        value = int(name[len(_SOURCE_PREFIX) :])
        if 0 <= value <= 0xFF:
            return value
    try:
        return Source[name.upper()]
    except KeyError:
        raise ValueError(f"no source named {name!r}") from None


@dataclass(slots=True)
class OleAccel:
    """A SmartSuit sensing module: optical linear encoder plus accelerometer.

    ``encoder`` counts 0.1 mm of cable travel (signed); ``accel`` is x, y, z in
    accelerometer counts (1024 per g by default).
    """

    node: int
    encoder: int
    accel: tuple[int, int, int]


@dataclass(slots=True)
class Quat:
    """An orientation sensor: unit quaternion w, x, y, z.

    ``extra`` keeps payload bytes a format carries beside the quaternion
    (bytes 16-24 of an IMU data-matrix line), uninterpreted.
    """

    node: int
    wxyz: tuple[float, float, float, float]
    extra: bytes = b""


Reading = OleAccel | Quat


@dataclass(slots=True)
class RawSample:
    """A reading as published on ``body/<limb>/<side>/<site>/raw``.

    ``t_ns`` is the source timestamp (integer ns, the receiver's clock or the
    capture's), ``seq`` the per-node sequence number (uint32, wraps), ``source``
    the id of the source it came through (a :class:`Source` where this version
    knows it, any byte otherwise), ``flags`` what its bridge says of it (a
    SmartSuit sample's :data:`RESUMED`; 0 for an orientation sensor's).
    """

    reading: Reading
    seq: int
    t_ns: int
    source: int = Source.UNKNOWN
    flags: int = 0


#: A raw sample's flag: the first sample of its SmartSuit node after the node was
#: silent, on a link its bridge saw alive, long enough to have rebooted (its encoder
#: then counts from where its joint was); see docs/calibration.md.
RESUMED = 0x01


@dataclass(frozen=True, slots=True)
class NoNewData:
    """IMU central: the sensor sent nothing new since the last tick (flag 00)."""

    node: int


@dataclass(frozen=True, slots=True)
class SensorAbsent:
    """IMU central: the sensor has never been seen since power-up (flag ff)."""

    node: int


@dataclass(frozen=True, slots=True)
class Tick:
    """A stream decoder's marker: the events that follow belong to tick ``index``
    (of node ``node`` only, when it is given).

    The IMU central prints each sensor's line once per tick; a decoder emits a
    ``Tick`` when the sensor numbers start over. A SlimeVR tracker numbers its
    packets; its decoder gives each packet's number as the tracker's tick.
    """

    index: int
    node: int | None = None


@dataclass(frozen=True, slots=True)
class NodeStatus:
    """Something a node says about itself that is not a sample: battery, signal
    strength, which device it is (``key`` names it, e.g. ``battery_v``)."""

    node: int
    key: str
    value: float | int | str


#: Every event a source's stream decoder gives: readings, the markers and states
#: around them, and rejections. One adapter per source turns them into samples.
StreamEvent = OleAccel | Quat | NoNewData | SensorAbsent | Tick | NodeStatus | Rejected
