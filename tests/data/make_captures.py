"""Writes the golden captures of tests/data (run from the repository root).

Each capture is a short, deterministic recording of one source system's wire
format with faults injected on purpose; ``<capture>.manifest.json`` records
what was injected (good samples, idle lines, rejections by reason), so tests
check the decoder against the writer's intent, not against itself.

    .venv/bin/python tests/data/make_captures.py
"""

from __future__ import annotations

import json
import math
import random
import struct
from collections import Counter
from pathlib import Path

from bodynet.core.codecs import concentrator, imu_matrix, smartsuit_can
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import NoNewData, OleAccel, Quat, SensorAbsent
from bodynet.nodes.emulator import BodyEmulator, Realism, smartsuit_sensors
from bodynet.nodes.motion import ROUTINES

HERE = Path(__file__).parent


def _axis_quat(angle: float, axis: tuple[float, float, float]) -> tuple[float, ...]:
    s = math.sin(angle / 2)
    return (math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s)


_ARM = BodyEmulator(ROUTINES["elbow-slow"], smartsuit_sensors([LEFT_ARM]), realism=Realism.ideal())


def _arm(node: int, t: float) -> OleAccel:
    """Module ``node`` of a left arm flexing its elbow 0-90-0 at 0.6 Hz, as the
    emulator's ideal sensors read it (so the captures are physically consistent)."""
    readings, _ = _ARM.sample(t)
    reading = next(r for r in readings if r.node == node)
    assert isinstance(reading, OleAccel)
    return reading


def can_log() -> dict[str, object]:
    counts: Counter[str] = Counter()
    foreign: Counter[str] = Counter()  # other devices' frames on the bus: not rejected
    lines = []

    def frame_line(t: float, frame: smartsuit_can.CanFrame) -> str:
        ident = (
            f"{frame.arbitration_id:08X}" if frame.is_extended_id else f"{frame.arbitration_id:03X}"
        )
        body = f"R{frame.dlc}" if frame.is_remote_frame else frame.data.hex().upper()
        return f"({t:.6f}) vcan0 {ident}#{body}"

    t0 = 1700000000.0
    for tick in range(100):  # 1 s at 100 Hz: nodes 1-3 and trunk IMU 13
        t = t0 + tick * 0.01
        for node in (1, 2, 3):
            lines.append(
                frame_line(t + node * 1e-4, smartsuit_can.encode_reading(_arm(node, t - t0)))
            )
            counts["decoded"] += 1
        q = Quat(13, _axis_quat(0.3 * math.sin(tick / 10), (0.0, 1.0, 0.0)))
        lines.append(frame_line(t + 5e-4, smartsuit_can.encode_reading(q)))
        counts["decoded"] += 1
        if tick == 10:
            lines.append(f"({t + 6e-4:.6f}) vcan0 123#0102030405060708")
            foreign["standard_id"] += 1
        if tick == 20:
            lines.append(f"({t + 6e-4:.6f}) vcan0 0006FFFF#R8")  # node 1 polled
            foreign["remote_frame"] += 1
        if tick == 30:
            lines.append(f"({t + 6e-4:.6f}) vcan0 0006FFFF#01020304")
            counts["bad_dlc"] += 1
        if tick == 40:
            lines.append(f"({t + 6e-4:.6f}) vcan0 0042FFFF#0102030405060708")  # node 16
            foreign["extended_id"] += 1
        if tick == 50:
            lines.append(f"({t + 6e-4:.6f}) vcan0 20000080#0000000000000000")  # bus error
            counts["error_frame"] += 1
        if tick == 60:
            lines.append(f"({t + 6e-4:.6f}) vcan0 0006FF~~#garbled")
            counts["garbage"] += 1
        if tick == 70:  # a trunk quaternion far from unit norm
            lines.append(f"({t + 6e-4:.6f}) vcan0 0036FFFF#0040004000400040")
            counts["bad_quat_norm"] += 1
    (HERE / "smartsuit_arm.log").write_text("\n".join(lines) + "\n")
    return {**counts, "foreign": dict(sorted(foreign.items()))}


def concentrator_capture() -> Counter[str]:
    rng = random.Random(3)
    counts: Counter[str] = Counter()
    out = bytearray()
    for cycle in range(40):
        t = cycle * 3 * 0.022
        for node in (1, 2, 3):
            out += concentrator.request(node)
            newline = rng.choice([b"", b"\r", b"\n", b"\r\n"])
            out += concentrator.encode_reply(_arm(node, t), newline=newline, upper=cycle % 2 == 0)
            counts["decoded"] += 1
        if cycle == 5:
            out += b"\x00\xff\x13garbage!"
            counts["garbage"] += 1
        if cycle == 8:  # a reply that comes without a request
            out += concentrator.encode_reply(_arm(1, t))
            counts["unpaired_reply"] += 1
        if cycle == 12:  # node 2 never answers
            out += concentrator.request(2)
            counts["no_reply"] += 1
        if cycle == 15:  # a reply cut short, then the exchange goes on
            out += b"E0012X00"
            counts["garbage"] += 1
        if cycle == 20:  # the extended form of ch. 3.2
            for node in (1, 2, 3):
                out += concentrator.encode_extended_request(node)
                out += concentrator.encode_extended_reply(_arm(node, t))
                counts["decoded"] += 1
        if cycle == 25:
            out += b"1 1 99 5 5 5 5\r\n"
            counts["unknown_node"] += 1
    (HERE / "concentrator.cap").write_bytes(bytes(out))
    return counts


def imu_central() -> Counter[str]:
    rng = random.Random(5)
    counts: Counter[str] = Counter()
    out = bytearray()
    for tick in range(30):
        for sensor in range(1, 16):
            if sensor == 15:  # never seen since power-up
                out += imu_matrix.encode_line(SensorAbsent(sensor))
                counts["sensor_absent"] += 1
                continue
            if sensor == 14 and tick % 3:
                out += imu_matrix.encode_line(NoNewData(sensor))
                counts["no_new_data"] += 1
                continue
            angle = 0.5 * math.sin(tick / 5 + sensor)
            q = Quat(
                sensor,
                _axis_quat(angle, (0.0, 0.0, 1.0)),
                bytes(rng.randrange(256) for _ in range(9)),
            )
            line = imu_matrix.encode_line(q)
            out += line[:-1] + b"\r\n" if tick % 7 == 0 else line
            counts["decoded"] += 1
        if tick == 3:
            out += b"zz" + b"0" * 52 + b"\n"
            counts["not_hex"] += 1
        if tick == 6:
            out += b"0101abcdef\n"
            counts["bad_length"] += 1
        if tick == 9:  # a NaN quaternion
            nan = struct.pack("<4f", math.nan, 0, 0, 0) + bytes(9)
            out += b"0501" + nan.hex().encode() + b"\n"
            counts["not_finite"] += 1
        if tick == 12:  # a quaternion of norm 2
            q2 = struct.pack("<4f", 2.0, 0, 0, 0) + bytes(9)
            out += b"0601" + q2.hex().encode() + b"\n"
            counts["bad_quat_norm"] += 1
        if tick == 15:  # sensor 16 does not exist
            out += b"1001" + bytes(25).hex().encode() + b"\n"
            counts["unknown_node"] += 1
        if tick == 18:  # binary noise glued to the front of the next good line
            out += bytes([0, 0xFF, 0x10, 0x80]) * 5
            counts["garbage"] += 1
        if tick == 21:  # an unknown flag
            out += b"0707" + bytes(25).hex().encode() + b"\n"
            counts["bad_flag"] += 1
    (HERE / "imu_central.txt").write_bytes(bytes(out))
    return counts


def main() -> None:
    for name, make in (
        ("smartsuit_arm.log", can_log),
        ("concentrator.cap", concentrator_capture),
        ("imu_central.txt", imu_central),
    ):
        manifest = HERE / f"{name}.manifest.json"
        manifest.write_text(json.dumps(dict(sorted(make().items())), indent=2) + "\n")


if __name__ == "__main__":
    main()
