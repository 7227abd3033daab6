"""The benchmark runs and reports; it measures, it asserts no timing."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest


def test_tiny_decode_benchmark_writes_its_table(tmp_path: Path) -> None:
    bodynet = Path(sys.executable).with_name("bodynet")
    result = subprocess.run(
        [str(bodynet), "bench", "--only", "decode", "--seconds", "0.02", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    rows = json.loads((tmp_path / "decode.json").read_text())["rows"]
    names = {r["name"] for r in rows}
    assert {"imu-central lines", "CAN frames (frame codec)", "concentrator replies"} <= names
    assert all(r["bodynet_per_s"] > 0 and r["baseline_per_s"] > 0 for r in rows)
    assert "| imu-central lines |" in (tmp_path / "decode.md").read_text()
    assert "## Decode rates" in (tmp_path / "summary.md").read_text()  # the summary of what ran


def test_tiny_solver_benchmark_compares_batched_with_alone(tmp_path: Path) -> None:
    from bodynet.bench import solver

    result = solver.run(seconds=0.01, out_dir=tmp_path, bodies=(1, 3))
    # three bodies twice: all due each tick, and a new set of one or two of them each tick
    assert [(r["bodies"], r["varying"]) for r in result["runs"]] == [(1, False), (3, False),
                                                                     (3, True)]  # fmt: skip
    assert result["runs"][2]["due"] == (1, 2)
    assert all(r["alone_us"] > 0 and r["batched_us"] > 0 for r in result["runs"])
    assert all(r["paced_us"] > 0 for r in result["runs"])  # once a period, as live
    assert "| 3 |" in (tmp_path / "solver.md").read_text()
    assert "| 1-2 of 3, a new set each tick |" in (tmp_path / "solver.md").read_text()
    assert "batched once a period" in (tmp_path / "solver.md").read_text()
    assert all(r["paced_compiled_us"] > 0 for r in result["runs"])


def test_demo_runs_the_live_body_network(tmp_path: Path) -> None:
    from zenoh_helpers import free_port

    from bodynet.clients.mcap_store import read_poses

    bodynet = Path(sys.executable).with_name("bodynet")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    record = tmp_path / "demo.mcap"
    result = subprocess.run(
        [
            str(bodynet),
            "demo",
            "--seconds",
            "9",
            "-l",
            endpoint,
            "--record",
            str(record),
            "--viewer",
            "none",
            "--rrd",
            str(tmp_path / "demo.rrd"),
        ],
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "T-pose calibration: 9 sensors" in result.stdout
    last = result.stdout.split("-- t")[-1]
    assert "sources 15" in last
    # the knee bend after the T-pose told the gateway where the subject faces: the
    # table shows numbers, no longer 'uncal'
    assert "uncal" not in last, last
    poses = [f for _, f in read_poses(record)]  # the recorder's file is complete and readable
    assert len(poses) > 10
    assert len(poses[-1].sources) == 15
    # every source delivered to the end, by the samples' times, and the gateway saw
    # each fresh in its last two seconds: one source stale in the very last pose is a
    # host too busy to hand its samples on for a few periods (the demo runs in one
    # process: on a loaded machine, often), which the pose rightly says
    end = poses[-1].t_ns
    assert all(end - t <= 2e9 for t in poses[-1].sources.values()), poses[-1].sources
    recent = [f for f in poses if end - f.t_ns <= 2e9]
    assert all(any(k not in f.stale for f in recent) for k in poses[-1].sources), [
        f.stale for f in recent
    ]
    # the live view, read back by Rerun's own tool: figure, angles, gauges and status
    rerun = Path(sys.executable).with_name("rerun")
    printed = subprocess.run(
        [str(rerun), "rrd", "print", str(tmp_path / "demo.rrd")],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    for entity in (
        "/body/figure",
        "/body/joints",
        "/angles/left_elbow_flexion",
        "/gauges/faces",
        "/gauges/needles",
        "/status",
    ):
        assert f"- {entity} -" in printed, entity


def test_tiny_gateway_benchmark_reports_both_paths(tmp_path: Path) -> None:
    from bodynet.bench import gateway

    result = gateway.run(seconds=1.0, out_dir=tmp_path, bodies=(1, 2), gateways=(1, 2))
    rows = result["runs"]
    assert [(r["bodies"], r["feed"], r["gateways"]) for r in rows] == [
        (1, "realistic", 1), (1, "batched", 1), (1, "locked", 1),
        (2, "realistic", 1), (2, "batched", 1), (2, "locked", 1),
        (1, "realistic", 2), (2, "realistic", 2)]  # fmt: skip
    for one, two in ((rows[0], rows[3]), (rows[1], rows[4]), (rows[2], rows[5]),
                     (rows[6], rows[7])):  # fmt: skip
        assert 0 < one["sent"] <= 1500  # at most 15 nodes x 100 Hz x 1 s
        assert 1500 < two["sent"] <= 3000
        for row in (one, two):
            assert row["relay"]["received"] > 0
            assert row["gateway"]["poses"] > 0
            # the worker thread's CPU, a part of its process's (both over the same span)
            gw = row["gateway"]
            assert 0 < gw["worker_cpu_ms_per_body_s"] <= gw["cpu_ms_per_body_s"]
        # two bodies: poses of both subjects came back
        assert two["gateway"]["samples_received"] > one["gateway"]["samples_received"]
    table = (tmp_path / "gateway.md").read_text()
    assert table.startswith("| bodies | feed |")
    assert "| 2 | realistic | gateway (raw -> pose) |" in table
    assert "| 2 | batched | gateway (raw -> pose) |" in table
    assert "| 2 | realistic | 2 gateways sharing (raw -> pose) |" in table
    assert set(result["sustained_by_gateways"]) == {1, 2}
    assert set(result["sustained_by_feed"]) == {"realistic", "batched", "locked"}
    assert "One gateway by feed: realistic " in table


def test_gateway_benchmark_apart_feeds_relay_and_gateway_one_after_the_other(
    tmp_path: Path,
) -> None:
    from bodynet.bench import gateway

    result = gateway.run(seconds=0.5, out_dir=tmp_path, bodies=(1,), feeds=("realistic",),
                         apart=True)  # fmt: skip
    together, apart = result["runs"]
    assert (together["apart"], apart["apart"]) == (False, True)
    for path in ("relay", "gateway"):  # each of its own feed, in its own phase
        assert apart[path]["n"] > 0
    assert apart["relay"]["sent"] > 0
    assert apart["sent"] > 0
    table = (tmp_path / "gateway.md").read_text()
    assert "| 1 | realistic, apart | bare relay (raw -> raw) |" in table
    assert "| 1 | realistic, apart | gateway (raw -> pose) |" in table
    # the floor: Zenoh receiving the same feed alone, with its CPU
    assert apart["floor"]["sent"] == apart["sent"]
    assert apart["floor"]["cpu_ms_per_body_s"] > 0
    assert together["floor"] is None
    assert "| 1 | realistic, apart | Zenoh subscriber alone (floor: receives, no Python) |" in table
    # the floor under a polling worker: as often as the gateway's woke, the same feed
    poller = apart["poller"]
    assert poller["sent"] == apart["sent"]
    assert poller["wakes_per_s"] == apart["gateway"]["wakes_per_s"] > 0
    assert poller["cpu_ms_per_body_s"] > 0
    assert together["poller"] is None
    assert f"Python worker alone (floor: polls as the gateway's did, {poller['wakes_per_s']:.0f}" \
        in table  # fmt: skip


def test_gateway_benchmark_runs_each_row_again_and_gives_the_ranges(
    tmp_path: Path,
) -> None:
    from bodynet.bench import gateway

    result = gateway.run(seconds=0.5, out_dir=tmp_path, bodies=(1,), feeds=("locked",),
                         repeat=2)  # fmt: skip
    rows = result["runs"]
    assert [(r["feed"], r["run"]) for r in rows] == [("locked", 1), ("locked", 2)]
    table = (tmp_path / "gateway.md").read_text()
    assert "| 1 | locked, run 1 of 2 | gateway (raw -> pose) |" in table
    assert "| 1 | locked, run 2 of 2 | gateway (raw -> pose) |" in table
    ranges = table.split("Ranges over the 2 runs of each row")[1].splitlines()
    lines = [line for line in ranges if line.startswith("- ")]
    assert [line.split(":")[0] for line in lines] == ["- 1 body, locked, gateway"]
    cpus = sorted(round(r["gateway"]["cpu_ms_per_body_s"]) for r in rows[:2])
    shown = f"{cpus[0]}" if cpus[0] == cpus[1] else f"{cpus[0]}-{cpus[1]}"
    assert f", {shown} ms (" in lines[0]  # the range of the two runs' figures
    # sustained only where every run is: one body on the locked feed, or none
    locked = all(gateway.sustained(r, "gateway") for r in rows[:2])
    assert result["sustained_by_feed"]["locked"] == (1 if locked else 0)


def test_realistic_feed_is_not_phase_locked() -> None:
    """The realistic feed sends as real suits do: each body at its own phase, CAN
    nodes on their own timers, a serial receiver's lines one after another; the
    locked feed sends every node of every body at once."""
    from bodynet.nodes.timing import DRIFT_PPM, LINE_S, feed_schedule

    period = 0.01
    locked = feed_schedule(range(4), 15, 100.0, "locked")
    assert locked == [(0.0, period)] * 60
    real = feed_schedule(range(4), 15, 100.0, "realistic")
    assert len(real) == 60
    bodies = [real[i * 15 : (i + 1) * 15] for i in range(4)]
    starts = [min(o for o, _ in b) for b in bodies]
    assert len({round(s, 9) for s in starts}) == 4  # no two bodies in phase
    can, serial = bodies[0], bodies[1]
    assert len({round(o, 9) for o, _ in can}) == 15  # each CAN node its own phase
    assert all(abs(p / period - 1) <= DRIFT_PPM * 1e-6 for _, p in can)
    assert len({p for _, p in can}) > 1  # and its own clock
    gaps = np.diff([o for o, _ in serial])
    assert np.allclose(gaps, min(LINE_S, period / 15))  # lines one after another
    assert all(0 <= o < 2 * period for o, _ in real)


def test_the_demo_script_moves_as_a_body_can() -> None:
    """The demo's emulated subject never jumps: T-pose, knee bend and the routine
    join smoothly (a jump in the script is a jump in the poses, unflagged)."""
    from bodynet.cli.demo import demo_motion
    from bodynet.nodes.motion import ROUTINES

    script = demo_motion(ROUTINES["reach"].angles)
    frames = [script(k * 0.01) for k in range(4000)]
    steps = [max(abs(b.get(n, 0.0) - a.get(n, 0.0)) for n in {*a, *b})
             for a, b in itertools.pairwise(frames)]  # fmt: skip
    assert max(steps) < 5.0  # degrees in 10 ms
    assert max(frames[450].values()) > 20  # and it does move: the knee bend


def test_tiny_drift_benchmark_writes_its_tables(tmp_path: Path) -> None:
    """`bench --only drift` runs (a few emulated seconds here, ten minutes for real):
    every facing around the circle, and the drift without correction, with the hinge
    and two-dof joints', and with the three-dof joints' too; the twisted walk with IMU
    tags and with the hybrid suit; tags of their own headings found by the protocol
    (every tag found by 40 s, its errors measured from then)."""
    from bodynet.bench import drift

    result = drift.run(tmp_path, minutes=0.1)
    assert len(result["headings"]) == 12  # every 30 deg
    assert [d["corrected"] for d in result["drift"]] == [False, "hinges", True]
    assert all(d["groups"] for d in result["drift"])
    assert [d["hybrid"] for d in result["twisted"]] == [False, True]
    assert [r["seed"] for r in result["independent"]] == [1, 2, 3]
    assert all(not r["unknown"] and 0.0 < r["worst"]["deg"] < 10.0 for r in result["independent"])
    table = (tmp_path / "drift.md").read_text()
    assert "| worst joint |" in table
    assert table.startswith("Subject facing every 30 deg")
    assert json.loads((tmp_path / "drift.json").read_text())["headings"] == result["headings"]


def test_demo_startup_errors_are_one_line_and_stop_what_started(tmp_path: Path) -> None:
    """An output that cannot be made (in /proc), a web port in use: one line, exit 2,
    nothing left running (the process ends) and no recording left."""
    import socket

    from zenoh_helpers import free_port

    bodynet = Path(sys.executable).with_name("bodynet")
    common = ["demo", "--seconds", "3", "-l", f"tcp/127.0.0.1:{free_port()}"]
    bad = subprocess.run([str(bodynet), *common, "--record", "/proc/x.mcap", "--viewer", "none"],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr == "bodynet demo: cannot write /proc/x.mcap: No such file or directory\n"
    record = tmp_path / "demo.mcap"
    with socket.create_server(("0.0.0.0", 0)) as taken:
        port = taken.getsockname()[1]
        bad = subprocess.run([str(bodynet), *common, "--record", str(record), "--viewer", "web",
                              "--web-port", str(port)],
                             capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr == (f"bodynet demo: cannot serve on port {port} (--web-port): "
                          "Address already in use\n")  # fmt: skip
    assert list(tmp_path.iterdir()) == []


def test_demo_with_rerun_data_port_in_use_names_no_option_it_lacks(tmp_path: Path) -> None:
    """Rerun's data port (9876) in use: the web view's message names the port as the
    demo's, not `--grpc-port` (an option of `view`, not of `demo`); nothing is left."""
    import contextlib
    import socket

    from zenoh_helpers import free_port

    from bodynet.clients.view import GRPC_PORT

    bodynet = Path(sys.executable).with_name("bodynet")
    with contextlib.ExitStack() as stack:
        with contextlib.suppress(OSError):  # taken already: taken all the same
            stack.enter_context(socket.create_server(("0.0.0.0", GRPC_PORT)))
        bad = subprocess.run([str(bodynet), "demo", "--seconds", "3", "-l",
                              f"tcp/127.0.0.1:{free_port()}", "--record", str(tmp_path / "d.mcap"),
                              "--viewer", "web", "--web-port", str(free_port())],
                             capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr == (f"bodynet demo: cannot serve on port {GRPC_PORT} (Rerun's data port, "
                          "fixed in the demo; free it, or --viewer none): Address already in "
                          "use\n")  # fmt: skip
    assert list(tmp_path.iterdir()) == []


def test_demo_whose_recorder_cannot_start_stops_what_started(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The disk fills between the output's check and the recorder's start (the
    recorder raises, injected here): one line, exit 2, and the router, client and
    viewer already started are stopped (the unwinding once raised NameError)."""
    import threading

    from zenoh_helpers import free_port

    from bodynet.cli import demo

    def full_disk(*_: object) -> None:
        raise OSError(28, "No space left on device", str(tmp_path / "demo.mcap"))

    monkeypatch.setattr(demo, "Recorder", full_disk)
    rc = demo.run_demo(f"tcp/127.0.0.1:{free_port()}", "reach", 1.0, tmp_path / "demo.mcap",
                       threading.Event(), "none", tmp_path / "demo.rrd")  # fmt: skip
    assert rc == 2
    assert capsys.readouterr().err == (
        f"bodynet demo: cannot write {tmp_path / 'demo.mcap'}: No space left on device\n"
    )
    assert list(tmp_path.iterdir()) == []  # the .rrd begun is not kept


def test_heading_stall_benchmark_reports_the_other_bodys_gaps() -> None:
    """`python -m bodynet.bench.heading_stall aside 3` runs (a live router, the real
    gateway, a feeder and a probe): a line with the calibrated body's pose gaps over
    the searching body's search, and the searching body's longest step."""
    result = subprocess.run([sys.executable, "-m", "bodynet.bench.heading_stall", "aside", "3"],
                            capture_output=True, text=True, timeout=180, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    line = result.stdout.strip().splitlines()[-1]
    assert line.startswith("aside, 1 other bodies: over "), line
    gaps = int(line.split("their gaps ")[1].split(",")[0])
    assert gaps > 20, line  # the calibrated body's poses kept coming
    assert "a's step max " in line


def test_tiny_truth_benchmark_compares_recorded_sessions_with_the_truth(tmp_path: Path) -> None:
    """Three short sessions written as recordings and solved by ``bodynet process``:
    the table has a row each and its measured dofs agree with the truth within
    twice their uncertainty, but for a few (the locked walk has none off now);
    6-axis tags whose headings are told (after the calibration) are measured
    from the start, every dof."""
    from bodynet.bench import truth

    names = ["locked-walk-s1", "hybrid-instead-reach-s1", "given-indep-walk-s1"]
    result = truth.run(tmp_path, only=names, seconds=7.0)
    rows = {r["name"]: r for r in result["scenarios"]}
    assert sorted(rows) == sorted(names)
    walk, arm = rows["locked-walk-s1"], rows["hybrid-instead-reach-s1"]
    assert walk["heading"] == "found"
    assert walk["other"]["n"] > 1000
    assert walk["other"]["share_gt_2unc"] < 0.05
    given = rows["given-indep-walk-s1"]
    assert given["counts"]["flagged"] == 0
    assert given["counts"]["measured"] > 1000
    assert given["other"]["share_gt_2unc"] < 0.05
    # the SmartSuit modules' elbow is measured where the tags' heading is not found
    assert any(w["dof"] == "left_elbow_flexion_deg" for w in arm["other"]["worst"])
    assert arm["other"]["rms_deg"] < 5
    table = (tmp_path / "truth.md").read_text()
    assert "| scenario | measured / flagged | beyond 2x unc |" in table
    assert "| locked-walk-s1 |" in table
    assert "| hybrid-instead-reach-s1 |" in table
    assert json.loads((tmp_path / "truth.json").read_text()) == result
    with pytest.raises(ValueError, match="no truth scenario named nothing"):
        truth.run(tmp_path, only=["nothing"])


def test_the_batched_feed_puts_each_batch_as_a_bridge_does(router_endpoint: str,
                                                           zsession: Any) -> None:  # fmt: skip
    """The benchmark's batched feed works its batches out ahead and wakes once a
    batch: every sample still comes once, stamped with its send's due time, in a
    batch of its body's nodes that went out when all fifteen were in or 5 ms
    after the first, never before its last sample was due."""
    import multiprocessing as mp
    import threading
    import time

    from zenoh_helpers import wait_until

    from bodynet.bench import gateway
    from bodynet.core.codecs import raw_batch, raw_sample

    got: list[tuple[int, str, list[tuple[str, bytes]]]] = []
    sub = zsession.declare_subscriber(
        "*/body/@batch/*",
        lambda s: got.append(
            (
                time.time_ns(),
                str(s.key_expr),
                raw_batch.split(str(s.key_expr), s.payload.to_bytes()),
            )
        ),
    )
    time.sleep(0.5)  # the subscription reaches the router
    sent, ready = mp.Value("q", 0), threading.Event()
    ready.set()
    gateway._feed(router_endpoint, 0.3, sent, ready, range(2), 2, feed="batched")
    wait_until(lambda: sum(len(e) for _, _, e in got) >= sent.value, 10, "every batch")
    sub.undeclare()
    seen = [(key, raw_sample.decode(m).seq) for _, _, entries in got for key, m in entries]
    assert len(seen) == len(set(seen)) == sent.value >= 2 * 15 * 25  # ~30 ticks of 30 nodes
    for received, _, entries in got:
        stamps = [raw_sample.source_time(m) for _, m in entries]
        assert 1 <= len(entries) <= 15
        assert stamps == sorted(stamps)
        assert stamps[-1] - stamps[0] <= gateway.BATCH_S * 1e9  # one bridge window
        # not out before its last sample, nor before its window's end if not whole (the
        # stamps are monotonic times put on the wall clock: 0.5 ms for the two to part)
        assert received >= stamps[-1] - 500_000
        if len(entries) < 15:
            assert received >= stamps[0] + gateway.BATCH_S * 1e9 - 500_000


def test_a_late_feeder_still_closes_each_batch_at_its_windows_end(zsession: Any) -> None:
    """Sends taken late, all at once (a feeder behind its schedule), still make
    the batches a bridge would have: a new one where a send comes after its
    body's window closed, each put out once its time has passed."""
    import time

    from zenoh_helpers import wait_until

    from bodynet.bench import gateway
    from bodynet.core.codecs import raw_batch, raw_sample
    from bodynet.core.messages import RawSample, Source
    from bodynet.nodes.emulator import BodyEmulator, imu_tags
    from bodynet.nodes.motion import ROUTINES

    tag = imu_tags()[0]
    reading = BodyEmulator(ROUTINES["walk"], [tag]).sample(0.0)[0][0]
    key = "s00/body/@batch/bench"
    got: list[list[tuple[str, bytes]]] = []
    sub = zsession.declare_subscriber(key, lambda s: got.append(
        raw_batch.split(key, s.payload.to_bytes())))  # fmt: skip
    pub = gateway._publishers(zsession, [key], bridges=False)[0]
    time.sleep(0.3)  # the subscription is known
    batches = gateway._Batches([pub], nodes=15)
    for ms in range(13):  # a send every millisecond, one body, the sample's seq its ms
        message = raw_sample.encode(RawSample(reading, ms, ms, Source.IMU_CENTRAL))
        batches.add(0, tag.site.raw_key, message, ms / 1000)
    assert batches.flush_due(1.0) == 13  # long after all of them: every batch out
    wait_until(lambda: len(got) == 3, 10, "three batches")
    sub.undeclare()
    assert [[raw_sample.decode(m).seq for _, m in batch] for batch in got] == [
        [0, 1, 2, 3, 4], [5, 6, 7, 8, 9], [10, 11, 12]]  # fmt: skip
