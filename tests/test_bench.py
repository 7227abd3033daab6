"""The benchmark runs and reports; it measures, it asserts no timing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def test_tiny_decode_benchmark_writes_its_table(tmp_path: Path) -> None:
    bodynet = Path(sys.executable).with_name("bodynet")
    result = subprocess.run([str(bodynet), "bench", "--seconds", "0.02", "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=120, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    rows = json.loads((tmp_path / "decode.json").read_text())["rows"]
    names = {r["name"] for r in rows}
    assert {"imu-central lines", "CAN frames (frame codec)", "concentrator replies"} <= names
    assert all(r["bodynet_per_s"] > 0 and r["baseline_per_s"] > 0 for r in rows)
    assert "| imu-central lines |" in (tmp_path / "decode.md").read_text()


def test_demo_decodes_the_bundled_captures() -> None:
    bodynet = Path(sys.executable).with_name("bodynet")
    root = Path(__file__).parents[1]
    result = subprocess.run([str(bodynet), "demo"], cwd=root, capture_output=True, text=True,
                            timeout=120, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "body/arm/left/elbow/raw" in result.stdout
    assert "body/leg/right/foot/raw" not in result.stdout  # sensor 15 is never seen there
    assert "decoded 400, rejected 7" in result.stdout
