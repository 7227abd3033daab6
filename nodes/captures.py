"""Reading captures of the source systems' wire formats from files.

A capture is what a logger saw on one of the seeds' links: a CAN log
(anything python-can's ``LogReader`` reads: candump ``.log``, ``.asc``,
``.blf``, ``.trc``...), a Data Concentrator serial exchange, or an IMU central
data matrix. :func:`read_capture` decodes one with the core codecs and gives
each sample the capture's own time: the logged timestamp where the format has
one, otherwise the index of the reply (concentrator) or tick (IMU central)
divided by the link's rate.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import can

from bodynet.core.codecs.concentrator import ConcentratorDecoder
from bodynet.core.codecs.imu_matrix import ImuMatrixDecoder
from bodynet.core.codecs.smartsuit_can import CanFrame, decode_frame
from bodynet.core.errors import DecodeError, Reason, RejectCounts, Rejected
from bodynet.core.keys import Site
from bodynet.core.messages import NoNewData, OleAccel, Quat, Reading, SensorAbsent, Tick
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES

log = logging.getLogger(__name__)

CHUNK = 1 << 16

#: The Data Concentrator answers one request every 22 ms (000 seed, ch. 3.4.2).
CONCENTRATOR_RATE_HZ = 1 / 0.022
#: One tick of the IMU central: about what 230400 baud carries for 15 sensors.
IMU_CENTRAL_RATE_HZ = 25.0


class Format(StrEnum):
    CAN_LOG = "can-log"
    CONCENTRATOR = "concentrator"
    IMU_CENTRAL = "imu-central"


@dataclass(frozen=True, slots=True)
class CapturedSample:
    """A decoded reading, where it sits, and the capture's time of it."""

    t_s: float
    reading: Reading
    site: Site


@dataclass(slots=True)
class CaptureStats:
    """What a capture held besides its samples."""

    decoded: int = 0
    rejected: RejectCounts = field(default_factory=RejectCounts)
    no_new_data: int = 0
    sensor_absent: int = 0

    def summary(self) -> str:
        """``decoded N, rejected M (reason: count, ...)`` plus idle lines if any."""
        total = sum(self.rejected.values())
        text = f"decoded {self.decoded}, rejected {total}"
        if total:
            text += f" ({self.rejected.summary()})"
        idle = [(n, what) for n, what in ((self.no_new_data, "no new data"),
                (self.sensor_absent, "sensor absent")) if n]  # fmt: skip
        if idle:
            text += "; not samples: " + ", ".join(f"{what} {n}" for n, what in idle)
        return text


def default_rate_hz(fmt: Format) -> float | None:
    return {Format.CONCENTRATOR: CONCENTRATOR_RATE_HZ, Format.IMU_CENTRAL: IMU_CENTRAL_RATE_HZ}.get(
        fmt
    )


def read_capture(
    path: str | Path,
    fmt: Format | str,
    stats: CaptureStats,
    rate_hz: float | None = None,
) -> Iterator[CapturedSample]:
    """Decode a capture file into samples, counting everything else in ``stats``."""
    fmt = Format(fmt)
    if fmt is Format.CAN_LOG:
        yield from _can_log(Path(path), stats)
        return
    rate = rate_hz or default_rate_hz(fmt)
    assert rate is not None
    if fmt is Format.CONCENTRATOR:
        yield from _concentrator(Path(path), stats, rate)
    else:
        yield from _imu_central(Path(path), stats, rate)


def _chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as f:
        while chunk := f.read(CHUNK):
            yield chunk
    yield b""  # the end: decoders' close() follows


def _count(stats: CaptureStats, rejected: Rejected) -> None:
    stats.rejected[rejected.reason] += 1
    log.debug("rejected %s: %s %r", rejected.reason, rejected.detail, rejected.data)


def _sample(stats: CaptureStats, t_s: float, reading: Reading, site: Site) -> CapturedSample:
    stats.decoded += 1
    return CapturedSample(round(t_s, 9), reading, site)


def _concentrator(path: Path, stats: CaptureStats, rate: float) -> Iterator[CapturedSample]:
    decoder = ConcentratorDecoder()
    index = 0
    for chunk in _chunks(path):
        for event in decoder.feed(chunk) if chunk else decoder.close():
            if isinstance(event, Rejected):
                _count(stats, event)
            else:
                yield _sample(stats, index / rate, event, SMARTSUIT_SITES[event.node])
                index += 1


def _imu_central(path: Path, stats: CaptureStats, rate: float) -> Iterator[CapturedSample]:
    decoder = ImuMatrixDecoder()
    tick = 0
    for chunk in _chunks(path):
        for event in decoder.feed(chunk) if chunk else decoder.close():
            if isinstance(event, Quat):
                yield _sample(stats, tick / rate, event, IMU_SITES[event.node])
            elif isinstance(event, Tick):
                tick = event.index
            elif isinstance(event, Rejected):
                _count(stats, event)
            elif isinstance(event, NoNewData):
                stats.no_new_data += 1
            elif isinstance(event, SensorAbsent):
                stats.sensor_absent += 1


def frame_of(msg: can.Message) -> CanFrame:
    """The core's frame for a python-can message."""
    return CanFrame(
        msg.arbitration_id,
        bytes(msg.data or b""),
        msg.is_extended_id,
        msg.is_remote_frame,
        msg.is_error_frame,
        msg.dlc,
    )


def can_log_messages(path: Path, stats: CaptureStats) -> Iterator[can.Message]:
    """python-can's messages of a log; a candump line it cannot parse is counted.

    python-can's readers stop at the first line they cannot parse, so candump
    logs (one frame per line) are read a line at a time to survive a garbled
    line; other formats are read whole and a failure ends them, counted.
    """
    if path.suffix.lower() == ".log":
        with path.open(encoding="ascii", errors="replace") as f:
            for line in f:
                if not line.strip():
                    continue
                try:
                    yield from can.CanutilsLogReader(io.StringIO(line))
                except (ValueError, IndexError) as exc:
                    _count(stats, Rejected(Reason.GARBAGE, f"log line: {exc}", line[:64].encode()))
        return
    try:
        with can.LogReader(path) as reader:
            yield from reader
    except (ValueError, IndexError, OSError, can.CanError) as exc:
        _count(stats, Rejected(Reason.TRUNCATED, f"log reader stopped: {exc}"))


def _can_log(path: Path, stats: CaptureStats) -> Iterator[CapturedSample]:
    for msg in can_log_messages(path, stats):
        try:
            reading = decode_frame(frame_of(msg))
        except DecodeError as exc:
            _count(stats, Rejected.of(exc, bytes(msg.data or b"")))
            continue
        yield _sample(stats, msg.timestamp, reading, SMARTSUIT_SITES[reading.node])


def sample_json(sample: CapturedSample) -> dict[str, object]:
    """The JSON object ``bodynet decode`` prints for a sample."""
    r = sample.reading
    out: dict[str, object] = {"node": r.node, "key": sample.site.raw_key, "t_s": sample.t_s}
    if isinstance(r, OleAccel):
        out["encoder"] = r.encoder
        out["accel"] = list(r.accel)
    else:
        out["quat_wxyz"] = list(r.wxyz)
    return out
