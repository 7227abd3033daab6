"""Clinical metrics: the pure module against references, then live on
``body/@metrics`` from poses on Zenoh, and kept by the recorder."""

from __future__ import annotations

import json
import math
import time
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh
from scipy.integrate import quad
from zenoh_helpers import Collector, Running, client, wait_matching

from bodynet.clients import live
from bodynet.clients.metrics import MetricsOutput
from bodynet.core import keys, metrics
from bodynet.core.codecs import pose

FS = 100.0


def gaussian_sparc(sigma: float, fc: float = 10.0, amp_th: float = 0.05) -> float:
    """SPARC of the speed profile exp(-t^2 / (2 sigma^2)) in closed form: its
    normalised Fourier magnitude is exp(-2 pi^2 sigma^2 f^2), cut at fc or where
    it falls to amp_th; minus the arc length with frequency over the band's width."""
    band = min(fc, math.sqrt(math.log(1 / amp_th) / (2 * math.pi**2 * sigma**2)))

    def slope(f: float) -> float:
        return -4 * math.pi**2 * sigma**2 * f * math.exp(-2 * math.pi**2 * sigma**2 * f**2)

    return -quad(lambda f: math.sqrt((1 / band) ** 2 + slope(f) ** 2), 0, band)[0]


@pytest.mark.parametrize("sigma", [0.03, 0.1, 0.2])
def test_sparc_of_a_gaussian_speed_profile_matches_the_closed_form(sigma: float) -> None:
    t = np.arange(-1.5, 1.5, 1 / FS)
    speed = np.exp(-(t**2) / (2 * sigma**2))
    assert metrics.sparc(speed, FS) == pytest.approx(gaussian_sparc(sigma), abs=5e-3)


def min_jerk_speed(t: np.ndarray, duration: float = 1.0) -> np.ndarray:
    tau = np.clip(t / duration, 0, 1)
    return (30 * tau**2 - 60 * tau**3 + 30 * tau**4) / duration


def test_sparc_orders_smooth_and_jerky_movements() -> None:
    t = np.arange(0, 2, 1 / FS)
    one = min_jerk_speed(t)
    two = min_jerk_speed(t) + min_jerk_speed(t - 0.6)  # two overlapping sub-movements
    assert metrics.sparc(one, FS) == pytest.approx(-1.41, abs=0.01)
    assert metrics.sparc(two, FS) < metrics.sparc(one, FS) - 0.2
    assert math.isnan(metrics.sparc(np.zeros(50), FS))
    assert math.isnan(metrics.sparc([1.0, math.nan, 2.0], FS))


def reach_angles(t: np.ndarray, start: float, amplitude: float, duration: float) -> np.ndarray:
    """A minimum-jerk reach from ``start`` by ``amplitude`` degrees."""
    tau = np.clip((t - start) / duration, 0, 1)
    return amplitude * (10 * tau**3 - 15 * tau**4 + 6 * tau**5)


def test_range_repetitions_and_the_current_movements_smoothness() -> None:
    t = np.arange(0, 9, 1 / FS)
    x = 45 - 45 * np.cos(2 * np.pi * t / 2.0)  # 0..90 deg, a cycle every 2 s
    x[t > 6] = 0.0  # then still
    dof = metrics.DofMetrics()
    for ti, xi in zip(t, x, strict=True):
        dof.add(float(ti), float(xi))
    assert dof.lo == pytest.approx(0.0)
    assert dof.hi == pytest.approx(90.0, abs=0.01)
    assert dof.repetitions == 3  # 0-2, 2-4, 4-6 s, then rest
    jitter = metrics.DofMetrics()
    for i, ti in enumerate(t):
        jitter.add(float(ti), 2.0 * (-1) ** i)  # 4 deg peak to peak: under MIN_SPAN_DEG
    assert jitter.repetitions == 0

    reach = metrics.DofMetrics()
    t = np.arange(0, 4, 1 / FS)
    angle = reach_angles(t, 1.0, 60.0, 1.0) + reach_angles(t, 2.5, -60.0, 1.0)
    for ti, xi in zip(t, angle, strict=True):
        reach.add(float(ti), float(xi))
    # the current movement is the second reach alone: SPARC of one minimum-jerk profile
    assert reach.smoothness() == pytest.approx(-1.41, abs=0.03)
    assert reach.repetitions == 1
    snap = reach.snapshot()
    assert snap["range_deg"] == pytest.approx(60.0)
    assert snap["sparc"] == pytest.approx(-1.41, abs=0.03)


def test_a_pose_time_that_jumps_starts_the_movement_afresh() -> None:
    """One pose stamped at the end of 64-bit time between poses of a reach (a
    hostile publisher, or a broken clock): the movement measured after it is the
    reach's own, and no speed profile spans the jump (one asked numpy for 2.7
    TiB and ended ``bodynet metrics``); the poses' time back where it was
    starts afresh too, rather than being taken as out of order for ever."""
    body = metrics.BodyMetrics()
    t = np.arange(0, 4, 1 / FS)
    angle = reach_angles(t, 1.0, 60.0, 1.0) + reach_angles(t, 2.5, -60.0, 1.0)
    t0 = 1_700_000_000 * 10**9
    for k, (ti, xi) in enumerate(zip(t, angle, strict=True)):
        if k == 150:  # between the two reaches
            body.add(2**63 - 1, {"left_elbow_flexion_deg": float(xi)})
        body.add(t0 + round(ti * 1e9), {"left_elbow_flexion_deg": float(xi)})
    dof = body.dofs["left_elbow_flexion_deg"]
    assert dof.smoothness() == pytest.approx(-1.41, abs=0.03)
    assert dof.repetitions == 1


def test_body_metrics_snapshot_is_json_and_counts_only_what_it_is_given() -> None:
    body = metrics.BodyMetrics()
    assert body.snapshot() == {"v": 1, "t_ns": None, "dofs": {}}
    body.add(1_700_000_000_000_000_000, {"left_elbow_flexion_deg": 10.0})
    body.add(1_700_000_000_010_000_000, {"left_elbow_flexion_deg": 20.0, "x_deg": math.nan})
    snap = json.loads(json.dumps(body.snapshot(), allow_nan=False))
    assert set(snap["dofs"]) == {"left_elbow_flexion_deg"}  # NaN is no measurement
    assert snap["dofs"]["left_elbow_flexion_deg"]["min_deg"] == 10.0
    assert snap["dofs"]["left_elbow_flexion_deg"]["samples"] == 2
    assert snap["t_ns"] == 1_700_000_000_010_000_000


# --- live ------------------------------------------------------------------------------------


def elbow_poses(n: int, t0_ns: int) -> list[pose.PoseFrame]:
    """Elbow flexion cycling 10..100 deg at 100 Hz; every 7th pose flagged held at
    150 deg, every 11th at 160 deg while the elbow's module is stale, as the
    gateway flags it (no measurement either: neither may reach the range of motion)."""
    out = []
    for i in range(n):
        t = i / FS
        angle = round(55 - 45 * math.cos(2 * math.pi * t / 1.0), 6)
        flags, reasons = {}, {}
        stale = []
        if i % 7 == 3:
            angle, flags = 150.0, {"left_elbow_flexion_deg": "held"}
        elif i % 11 == 5:  # the elbow module stopped delivering: its last sample held
            angle, stale = 160.0, [keys.raw_key("arm", "left", "elbow")]
            flags = {"left_elbow_flexion_deg": "unobserved"}
            reasons = {"left_elbow_flexion_deg": ["unobserved", "stale"]}
        angles = {"left_elbow_flexion_deg": angle, "left_knee_flexion_deg": 5.0}
        out.append(pose.PoseFrame(i, t0_ns + i * 10_000_000, angles, {}, {}, {}, flags, {},
                                  stale, reasons))  # fmt: skip
    return out


def measured_here(f: pose.PoseFrame) -> dict[str, float]:
    """This test's own rule for its poses: flagged out (the stale elbow too); the
    knee (no sensor on the forearm takes part in it) stays."""
    return {n: v for n, v in f.angles_deg.items() if n not in f.flags}


def test_metrics_are_published_live_per_subject(router_endpoint: str,
                                                zsession: zenoh.Session) -> None:  # fmt: skip
    out_session = client(router_endpoint)
    output = MetricsOutput(out_session, all_subjects=True, rate_hz=10)
    running = Running(partial(live.run, out_session, output, all_subjects=True))
    got = Collector(zsession, f"*/{keys.METRICS}", json.loads)
    try:
        frames = elbow_poses(350, 1_700_000_000_000_000_000)
        # a burst: none dropped on the way, none sent before the output subscribed
        block = zenoh.CongestionControl.BLOCK
        pub = zsession.declare_publisher(f"alice/{keys.pose_key()}", congestion_control=block)
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching:
            assert time.monotonic() < deadline, "the output never subscribed"
            time.sleep(0.01)
        for f in frames:
            pub.put(pose.encode(f))
        zsession.put(f"bob/{keys.pose_key()}", pose.encode(frames[0]))
        last_t = frames[-1].t_ns

        def done(s: list[tuple[str, dict]]) -> bool:
            alice = any(k.startswith("alice/") and m["t_ns"] == last_t for k, m in s)
            return alice and any(k.startswith("bob/") for k, _ in s)

        seen = got.wait_for(done)
    finally:
        running.stop()
        out_session.close()
    alice = next(m for k, m in reversed(seen) if k == f"alice/{keys.METRICS}")
    elbow = alice["dofs"]["left_elbow_flexion_deg"]
    assert elbow["max_deg"] == pytest.approx(100.0, abs=0.01)  # never the held 150 or 160
    assert elbow["min_deg"] == pytest.approx(10.0, abs=0.01)
    assert elbow["repetitions"] == 3, alice  # 3.5 s of 1 s cycles
    assert elbow["samples"] == sum(1 for f in frames if not f.flags and not f.stale)
    # the same numbers as the module fed offline
    offline = metrics.BodyMetrics()
    for f in frames:
        offline.add(f.t_ns, measured_here(f))
    assert alice == json.loads(json.dumps(offline.snapshot()))
    assert alice["dofs"]["left_knee_flexion_deg"]["repetitions"] == 0


def test_the_recorder_keeps_metrics(router_endpoint: str, zsession: zenoh.Session,
                                    tmp_path: Path) -> None:  # fmt: skip
    from mcap.reader import make_reader

    from bodynet.clients.recorder import DEFAULT_KEYS, Recorder

    rec_session = client(router_endpoint)
    out = tmp_path / "m.mcap"
    recorder = Recorder(rec_session, out, DEFAULT_KEYS)
    wait_matching(zsession, keys.METRICS)  # a put before it subscribed would be lost
    message = {"v": 1, "t_ns": 1_700_000_000_000_000_000,
               "dofs": {"left_elbow_flexion_deg": {"min_deg": 1.0}}}  # fmt: skip
    zsession.put(keys.METRICS, json.dumps(message))
    zsession.put(keys.METRICS, b"[1, 2]")  # not an object: refused, counted
    deadline = time.monotonic() + 10
    while recorder.messages + sum(recorder.rejected.values()) < 2:
        assert time.monotonic() < deadline, "the recorder did not get both messages"
        time.sleep(0.01)
    recorder.close()
    rec_session.close()
    with out.open("rb") as f:
        found = [(c.topic, s.name, json.loads(m.data))
                 for s, c, m in make_reader(f).iter_messages(topics=[keys.METRICS])]  # fmt: skip
    assert found == [(keys.METRICS, "bodynet.Metrics", message)]
    assert sum(recorder.rejected.values()) == 1


def test_the_report_has_the_same_clinical_metrics(tmp_path: Path) -> None:
    from bodynet.clients import report
    from bodynet.clients.mcap_store import McapSink

    recording = tmp_path / "elbow.mcap"
    frames = elbow_poses(350, 1_700_000_000_000_000_000)
    sink = McapSink(recording)
    for f in frames:
        sink.write_pose(keys.pose_key(), f, f.t_ns)
    sink.close()
    table = report.clinical_table(recording)  # what analyse() puts in Analysis.clinical
    an = SimpleNamespace(recordings=[SimpleNamespace(source=str(recording))], clinical=[table])
    table = table.set_index("channel")
    elbow = table.loc["left_elbow_flexion_deg"]
    assert elbow["max (deg)"] == pytest.approx(100.0, abs=0.01)  # never the held 150 or 160
    assert elbow["repetitions"] == 3
    assert elbow["samples"] == sum(1 for f in frames if not f.flags and not f.stale)
    live = metrics.BodyMetrics()  # what body/@metrics said at the end (the live test: equal)
    for f in frames:
        live.add(f.t_ns, measured_here(f))
    want = live.snapshot()["dofs"]["left_elbow_flexion_deg"]
    assert elbow["SPARC (last movement)"] == want["sparc"]
    assert elbow["range (deg)"] == want["range_deg"]
    text = report._markdown(report._clinical_blocks(an))  # the section as written (no plots)
    section = text.split("## Clinical metrics", 1)[1]
    assert "left_elbow_flexion_deg" in section
    assert f"{want['sparc']:.4g}" in section


def test_the_views_metrics_panel_shows_what_it_can() -> None:
    from bodynet.clients.view import metrics_text

    text = metrics_text(
        {
            "dofs": {
                "left_knee_flexion_deg": {
                    "min_deg": 1.5,
                    "max_deg": 61.25,
                    "range_deg": 59.75,
                    "repetitions": 2,
                    "sparc": None,
                }
            }
        }
    )
    assert "| left_knee_flexion | 1.5 | 61.25 | 59.75 | 2 |  |" in text
    for hostile in (None, [], {"dofs": []}, {"dofs": {}}):
        assert metrics_text(hostile) == "No measured joint angle yet."
    odd = metrics_text({"dofs": {"x": {"min_deg": [1], "repetitions": "many" * 50}, "y": 3}})
    assert "| x | ? |" in odd
    assert "| y | ? | ? | ? | ? |" in odd


def test_bodynet_metrics_publishes_on_the_subjects_key(router_endpoint: str) -> None:
    import queue

    from service_procs import Services, bodynet

    from bodynet.session import open_session, session_config

    session = open_session(session_config("client", connect=[router_endpoint], subject="carol"))
    got = Collector(session, keys.METRICS, json.loads)  # carol/body/@metrics on the wire
    services = Services()
    argv = bodynet("metrics", "-e", router_endpoint, "--subject", "carol", "--rate-hz", "5")
    try:
        proc = services.start("metrics", argv)
        proc.wait_line("bodynet metrics: subject carol, body/@metrics at 5 Hz")
        frames = iter(elbow_poses(10_000, time.time_ns()))
        deadline = time.monotonic() + 30
        while True:  # poses until the command (subscribed by now or soon) answers
            assert time.monotonic() < deadline, proc.tail()
            session.put(keys.pose_key(), pose.encode(next(frames)))
            try:
                _, message = got.queue.get(timeout=0.05)
                break
            except queue.Empty:
                continue
        assert "left_elbow_flexion_deg" in message["dofs"]
        assert proc.stop() == 0
    finally:
        services.close()
        session.close()


def test_a_recordings_view_shows_its_last_metrics(tmp_path: Path) -> None:
    from test_view import rrd_texts

    from bodynet.clients.mcap_store import McapSink, read_metrics
    from bodynet.clients.view import Viewer, view_recording

    recording = tmp_path / "m.mcap"
    frames = elbow_poses(120, 1_700_000_000_000_000_000)
    body = metrics.BodyMetrics()
    sink = McapSink(recording)
    for i, f in enumerate(frames):
        sink.write_pose(keys.pose_key(), f, f.t_ns)
        body.add(f.t_ns, metrics.measured_angles(f))
        if i % 50 == 49 or i == len(frames) - 1:
            sink.write_metrics(keys.METRICS, json.dumps(body.snapshot()).encode(), f.t_ns)
    sink.close()
    assert [m["t_ns"] for _, _, m in read_metrics(recording)][-1] == frames[-1].t_ns
    rrd = tmp_path / "m.rrd"
    viewer = Viewer.start("none", save=rrd)
    try:
        assert view_recording(recording, viewer) == len(frames)
    finally:
        viewer.close()
    last = body.snapshot()["dofs"]["left_elbow_flexion_deg"]
    assert (
        f"| left_elbow_flexion | 10 | 100 | 90 | {last['repetitions']} |"
        in rrd_texts(rrd, "/metrics")[-1]
    )


def test_a_publisher_inventing_dofs_cannot_grow_a_body_without_end() -> None:
    body = metrics.BodyMetrics()
    for i in range(10):
        body.add(i, {f"made_up_{i}_{k}_deg": 1.0 for k in range(50)})
    assert len(body.dofs) == metrics.MAX_DOFS


def test_a_message_an_output_fails_on_is_counted_and_the_output_goes_on(
    router_endpoint: str, zsession: zenoh.Session
) -> None:
    class Picky(live.LiveOutput):
        def __init__(self) -> None:
            self.seen: list[int] = []

        def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
            if frame.seq == 2:
                raise RuntimeError("a bug met by one message")
            self.seen.append(frame.seq)

    out_session = client(router_endpoint)
    output = Picky()
    result: list[live.Counts] = []
    running = Running(lambda stop: result.append(live.run(out_session, output, stop)))
    try:
        block = zenoh.CongestionControl.BLOCK
        pub = zsession.declare_publisher(keys.pose_key(), congestion_control=block)
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching:
            assert time.monotonic() < deadline, "the output never subscribed"
            time.sleep(0.01)
        for f in elbow_poses(4, 1_700_000_000_000_000_000):
            pub.put(pose.encode(f))
        deadline = time.monotonic() + 10
        while len(output.seen) < 3:
            assert time.monotonic() < deadline, output.seen
            time.sleep(0.01)
    finally:
        running.stop()
        out_session.close()
    assert output.seen == [0, 1, 3]
    assert result[0].failed == 1
    assert "1 messages the output failed on" in result[0].summary()


def test_a_pose_from_before_the_stale_reason_still_loses_what_rests_on_a_stale_sensor() -> None:
    """A gateway (or recording) before the ``stale`` reason lists the stale site
    and flags none of its dofs: the old rule holds (the joints at either end of
    the forearm: elbow and wrist). A pose that flags some dof ``stale`` is taken
    at its word (the wrist's encoder still measures)."""
    key = keys.raw_key("arm", "left", "elbow")
    angles = {"left_elbow_flexion_deg": 42.0, "left_wrist_flexion_deg": 3.0,
              "left_knee_flexion_deg": 5.0}  # fmt: skip
    old = pose.PoseFrame(1, 1, angles, {}, {}, {}, {}, {}, [key])
    assert metrics.measured_angles(old) == {"left_knee_flexion_deg": 5.0}
    flag, reasons = {"left_elbow_flexion_deg": "unobserved"}, ["unobserved", "stale"]
    flagged = pose.PoseFrame(1, 1, angles, {}, {}, {}, flag, {}, [key],
                             {"left_elbow_flexion_deg": reasons})  # fmt: skip
    assert metrics.measured_angles(flagged) == {"left_wrist_flexion_deg": 3.0,
                                                "left_knee_flexion_deg": 5.0}  # fmt: skip
    assert metrics.measured_angles(pose.PoseFrame(1, 1, angles, {}, {}, {})) == angles
