"""Faults done for real, each bounded in time; the events are checked, never their timing.

The scenarios live in ``bodynet.bench.faults`` so that ``bodynet bench --only
faults`` times exactly what these tests check (detection times against the
targets are in the README). Elsewhere: a branch process killed or stopped
while others carry on is in ``test_node_cli.py``; a CAN adapter unplugged and
back in ``test_nodes_transports.py``; garbage at full speed in
``test_gateway_live.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bodynet.bench import faults

pytestmark = pytest.mark.timeout(180)


def test_killed_node_is_seen_gone_by_tokens_and_gateway_topology() -> None:
    result = faults.node_killed(timeout=60)  # raises FaultError if either never comes
    assert set(result) == {"liveliness_s", "topology_s"}


def test_frozen_node_is_flagged_stale_while_the_other_branch_flows_then_fresh() -> None:
    result = faults.node_frozen(timeout=60)
    assert result["other_branch_flowed"]


def test_killed_recorder_is_salvaged_whole_up_to_its_last_chunk() -> None:
    result = faults.recorder_killed(timeout=60)
    assert result["salvaged"] > 100
    # what the recorder got before its last flushed chunk is all there (what a probe saw
    # published in that time; a subscriber on a loaded machine may drop the odd one)
    assert result["missing_inside"] <= 0.01 * result["salvaged"]
    assert result["salvage_is_whole"]  # a salvaged file salvages to itself


def test_restarted_gateway_keeps_its_calibration_and_resumes() -> None:
    result = faults.gateway_restarted(timeout=90)
    assert result["calibrated_sensors"] == 15
    assert result["uncalibrated_vs_calibrated_deg"] > 20  # random tag mounts: calibration matters
    assert result["restart_vs_calibrated_deg"] < 5  # the restarted gateway read it back


def test_serial_device_unplugged_and_back_resumes_by_itself() -> None:
    result = faults.serial_replugged(timeout=30)
    assert result["seq_rising"]  # sequence numbers keep rising across the reconnect


def test_faults_benchmark_writes_its_table(tmp_path: Path) -> None:
    result = faults.run(out_dir=tmp_path, repeat=1, only=["serial_replugged"])
    [run] = result["runs"]["serial_replugged"]
    table = (tmp_path / "faults.md").read_text()
    assert "error" not in run, table
    assert "| serial device plugged back: samples again |" in table
    assert "node killed" not in table  # not run: not reported
