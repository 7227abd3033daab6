"""Tiny runs of the measuring benchmarks, only to prove they work: no timing is asserted."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from bodynet.bench import gateway, peer, recorder, report, soak


def test_lsl_peer_runs_beside_the_gateway(tmp_path: Path) -> None:
    result = peer.run(seconds=1.0, out_dir=tmp_path)
    lsl = result["lsl_one_hop"]
    assert lsl["sent"] > 0
    assert lsl["received"] > 0  # the stream really went through liblsl
    assert result["gateway_two_hops"]["poses"] > 0
    assert "| LSL outlet -> inlet (raw -> raw) | 1 |" in (tmp_path / "peer.md").read_text()


def test_rate_parameter_feeds_faster(tmp_path: Path) -> None:
    # one feed: the three feeds' rows are the tiny gateway benchmark's (tests/test_bench.py)
    result = gateway.run(seconds=0.5, out_dir=tmp_path, bodies=(1,), rate_hz=1000.0, name="rate",
                         feeds=("realistic",))  # fmt: skip
    assert result["rate_hz_per_node"] == 1000.0
    assert result["sent"] > 1500  # more than 100 Hz could send in 0.5 s x 15 nodes x 2
    assert result["gateway"]["poses"] > 0
    assert json.loads((tmp_path / "rate.json").read_text())["sent"] == result["sent"]


def test_recorder_benchmark_against_the_bare_writer(tmp_path: Path) -> None:
    # and the row of twenty bodies recorded beside the gateway, small: 2 bodies, 2 s
    result = recorder.run(seconds=0.05, out_dir=tmp_path, bodies=2, gateway_seconds=2.0)
    assert [r["bodynet_per_s"] > 0 and r["baseline_per_s"] > 0 for r in result["rows"]] == [
        True,
        True,
    ]
    assert result["recorder_live"]["messages"] > 0
    row = result["with_gateway"]
    assert row["bodies"] == 2
    for counted in ("raw_sent", "poses_published", "raw_recorded", "poses_recorded", "admin_seen"):
        assert row[counted] > 0, counted
    assert row["lost"] == row["raw_lost"] + row["poses_lost"] + row["admin_lost"]
    assert "raw samples sent / in file" in (tmp_path / "recorder.md").read_text()
    report.write(tmp_path)  # the summary and the plot from what is there
    summary = (tmp_path / "summary.md").read_text()
    assert "## Recorder against the bare mcap writer" in summary
    assert "Machine: " in summary
    assert "zenoh " in summary
    assert (tmp_path / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_soak_feeds_as_the_bridges_do(router_endpoint: str) -> None:
    """The soak's feeder publishes through a bridge's SitePublisher: advanced
    publishers (their samples carry a source sequence number, which plain ones
    do not), the bridge's health, every sample it counts."""
    import multiprocessing as mp
    import queue
    import threading

    import zenoh.ext
    from zenoh_helpers import client

    from bodynet.core import keys

    session = client(router_endpoint)
    raw: queue.SimpleQueue[int | None] = queue.SimpleQueue()
    health: queue.SimpleQueue[str] = queue.SimpleQueue()
    subs = [
        zenoh.ext.declare_advanced_subscriber(
            session, keys.all_raw(), lambda s: raw.put(getattr(s.source_info, "source_sn", None)),
            recovery=zenoh.ext.RecoveryConfig(heartbeat=True)),
        session.declare_subscriber(keys.health_key("soak"), lambda s: health.put(str(s.key_expr))),
    ]  # fmt: skip
    sent, ready = mp.Value("q", 0), threading.Event()
    ready.set()
    try:
        soak._feed(router_endpoint, 0.2, sent, ready)
        assert sent.value > 0
        assert sent.value % 15 == 0  # whole ticks of the 15 tags
        received = [raw.get(timeout=10) for _ in range(sent.value)]
        assert None not in received  # each from an advanced publisher
        assert health.get(timeout=10) == keys.health_key("soak")
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()


@pytest.mark.soak
@pytest.mark.timeout(300)
def test_quarter_minute_soak_loses_nothing(tmp_path: Path) -> None:
    """The CI version of the hour's soak: one body through gateway and recorder
    (its memory is measured, not judged: a quarter of a minute says nothing of an
    hour; its growth here was 0.1-0.4%, 2026-12-07)."""
    result = soak.run(minutes=0.25, out_dir=tmp_path, warmup_s=5.0)
    assert result["sent"] > 0
    assert result["feeder_exitcode"] == 0
    assert len(result["rss_mb"]["gateway"]) >= 12  # sampled each second of the feed
    assert result["load_1min"]["max"] > 0.0  # sampled: this run loads the machine itself
    assert result["lost_gateway"] == 0
    assert result["lost_recorder"] == 0
    assert len(result["anon_mb"]["recorder"]) == len(result["rss_mb"]["recorder"])
    for name in ("gateway", "recorder"):
        assert 0 < result["anon_memory"][name]["end_mb"] < result["memory"][name]["end_mb"]
    for name, memory in result["memory"].items():
        assert not math.isnan(memory["growth"]), name
        assert memory["growth"] < soak.GROWTH_LIMIT, (name, memory)
        assert result["owned_growth"][name] < soak.GROWTH_LIMIT, (name, result["anon_memory"])
