"""`bodynet view`: recordings to Rerun files, the web viewer served, bad input refused."""

from __future__ import annotations

import subprocess
import sys
import urllib.request
from pathlib import Path

from zenoh_helpers import free_port

BODYNET = Path(sys.executable).with_name("bodynet")
RERUN = Path(sys.executable).with_name("rerun")


def run(*args: object, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BODYNET), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, check=False)  # fmt: skip


def test_recording_to_rrd_without_a_window(tmp_path: Path, data_dir: Path) -> None:
    mcap = tmp_path / "s.mcap"
    assert (
        run(
            "process", data_dir / "imu_central.txt", "--format", "imu-central", "-o", mcap
        ).returncode
        == 0
    )
    rrd = tmp_path / "s.rrd"
    result = run("view", mcap, "--headless", "--save", rrd)  # Rerun's flag
    assert result.returncode == 0, result.stderr
    assert "30 poses" in result.stderr
    printed = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True,
                             timeout=60, check=True).stdout  # fmt: skip
    assert "- /body/figure -" in printed
    assert "- /angles/right_shoulder_abduction -" in printed
    assert subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True,
                          timeout=60, check=False).returncode == 0  # fmt: skip


def test_truncated_recording_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n" + bytes(10))
    result = run("view", bad, "--save", tmp_path / "x.rrd")
    assert result.returncode == 2
    assert "not a complete MCAP file" in result.stderr
    assert "Traceback" not in result.stderr


def test_web_viewer_is_served(router_endpoint: str) -> None:
    web, grpc = free_port(), free_port()
    proc = subprocess.Popen(
        [str(BODYNET), "view", "--serve-web", "--web-port", str(web), "--grpc-port", str(grpc),
         "-e", router_endpoint],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert f"web viewer at http://127.0.0.1:{web}/?url=" in line
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as page:
            assert page.status == 200
            assert "rerun" in page.read().decode(errors="replace").lower()
    finally:
        proc.send_signal(subprocess.signal.SIGINT)  # type: ignore[attr-defined]
        assert proc.wait(timeout=30) == 0
