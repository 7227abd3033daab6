"""The main job, until the gateway exists: decode the bundled captures of both
source systems and show what each site of the body network published."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

from bodynet.nodes.captures import CaptureStats, Format, read_capture, sample_json

CAPTURES = (
    (Format.CAN_LOG, "smartsuit_arm.log", "SmartSuit left arm + trunk IMU on CAN (candump)"),
    (Format.CONCENTRATOR, "concentrator.cap", "SmartSuit Data Concentrator serial exchange"),
    (Format.IMU_CENTRAL, "imu_central.txt", "IMU central data matrix (15 BLE tags)"),
)


def run_demo(folder: Path) -> int:
    """Decode each bundled capture in ``folder``; print keys, counts, first samples."""
    for fmt, name, title in CAPTURES:
        path = folder / name
        if not path.exists():
            print(
                f"bodynet demo: no capture {path} (run from the repository root)", file=sys.stderr
            )
            return 2
        stats = CaptureStats()
        per_key: Counter[str] = Counter()
        first: dict[str, dict[str, object]] = {}
        for sample in read_capture(path, fmt, stats):
            key = sample.site.raw_key
            per_key[key] += 1
            first.setdefault(key, sample_json(sample))
        print(f"\n== {title}: {path}\n   {stats.summary()}")
        for key in sorted(per_key):
            shown = {k: v for k, v in first[key].items() if k not in ("key", "node")}
            print(f"   {key:34} {per_key[key]:5d} samples, first {shown}")
    print("\nEach key above is where the live system publishes that site's raw samples.")
    return 0
