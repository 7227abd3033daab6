"""``bodynet lsl``: its conversions alone, then the live streams read by a real
LSL inlet in another process (liblsl from pylsl's wheel, on loopback)."""

from __future__ import annotations

import math
import os
import statistics
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import zenoh
from lsl_inlet import Recorder, loopback_lsl
from zenoh_helpers import Collector, Running, free_port

from bodynet.clients import live, lsl
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.keys import LEFT_ARM, TRUNK
from bodynet.core.messages import OleAccel, Quat, RawSample, Source
from bodynet.core.skeleton import build_skeleton
from bodynet.core.subject import Profile
from bodynet.gateway.frames import pose_frame
from bodynet.gateway.service import Gateway
from bodynet.gateway.solver import BodySolver
from bodynet.nodes.emulator import BodyEmulator, Realism, smartsuit_sensors
from bodynet.nodes.motion import Routine
from bodynet.nodes.services import EmulationOptions, NodePlan, run_node
from bodynet.session import open_session, session_config

SKELETON = build_skeleton()
BLOCK = zenoh.CongestionControl.BLOCK  # a test's burst of puts: none dropped on the way
SEGMENT_SUFFIXES = ("x", "y", "z", "qw", "qx", "qy", "qz")


def frame(seq: int, t_ns: int, base: float = 0.0, flags: dict[str, str] | None = None
          ) -> pose.PoseFrame:  # fmt: skip
    """A whole-body pose with every angle and segment, values from ``base``."""
    names = SKELETON.angle_names()
    angles = {n: round(base + i * 0.5 + seq * 0.01, 6) for i, n in enumerate(names)}
    segments = {}
    for i, s in enumerate(SKELETON.segments):
        a = 0.1 * i + 0.01 * seq
        segments[s] = ((0.01 * i, -0.02 * i, 1.0 + base), (math.cos(a), 0.0, math.sin(a), 0.0))
    return pose.PoseFrame(seq, t_ns, angles, {}, segments, {}, flags or {}, {}, [])


# --- conversions ---------------------------------------------------------------------------


def test_clock_map_keeps_the_narrowest_bracket_and_maps_without_rounding() -> None:
    local = iter([10.0, 10.5, 20.0, 20.001, 30.0, 30.2])  # brackets of 0.5, 0.001, 0.2 s
    unix = iter([1_700_000_000_000_000_000, 1_700_000_010_000_000_000, 1_700_000_020_000_000_000])
    m = lsl.estimate_clock_map(lambda: next(local), lambda: next(unix), tries=3)
    assert m.unix_ns == 1_700_000_010_000_000_000
    assert m.local_s == pytest.approx(20.0005, abs=1e-12)
    # 1 ns later is 1 ns later on LSL's clock: the integer difference first
    assert m.to_local(1_700_000_010_000_000_001) - m.local_s == pytest.approx(1e-9, abs=1e-12)
    assert m.to_local(1_700_000_009_000_000_000) == pytest.approx(19.0005, abs=1e-9)


def test_unmeasured_angles_and_the_segments_they_carry_are_nan() -> None:
    flags = {"left_elbow_flexion_deg": "unobserved", "left_knee_flexion_deg": "clamped",
             "neck_rotation_deg": "held"}  # fmt: skip
    f = frame(3, 0, flags=flags)
    names = lsl.angle_names(SKELETON)
    values = dict(zip(names, lsl.angle_values(f, names), strict=True))
    assert math.isnan(values["left_elbow_flexion_deg"])
    assert math.isnan(values["neck_rotation_deg"])
    assert values["left_knee_flexion_deg"] == f.angles_deg["left_knee_flexion_deg"]  # clamped
    assert values["right_elbow_flexion_deg"] == f.angles_deg["right_elbow_flexion_deg"]

    chains = SKELETON.segment_chains()
    assert chains["left_hand"] == (*SKELETON.joint("left_wrist").angle_names(),
                                   *SKELETON.joint("left_elbow").angle_names(),
                                   *SKELETON.joint("left_shoulder").angle_names(),
                                   *SKELETON.joint("lumbar").angle_names())  # fmt: skip
    seg = lsl.segment_values(f, chains)
    labels = [c.label for c in lsl.segment_channels(SKELETON)]
    got = dict(zip(labels, seg, strict=True))
    for s in ("left_forearm", "left_hand", "head"):  # below the elbow, below the neck
        assert all(math.isnan(got[f"{s}_{c}"]) for c in SEGMENT_SUFFIXES)
    for s in ("pelvis", "thorax", "left_upperarm", "left_shank", "right_hand"):
        p, q = f.segments[s]
        assert [got[f"{s}_{c}"] for c in SEGMENT_SUFFIXES] == [*p, *q]
    missing = pose.PoseFrame(1, 0, f.angles_deg, {}, {"pelvis": f.segments["pelvis"]}, {})
    assert np.isnan(lsl.segment_values(missing, chains)[7:]).all()


def test_angles_resting_on_a_stale_sensor_are_nan() -> None:
    """The left elbow module (on the forearm) stale, as the gateway solves it: the
    elbow and the wrist's tilt lose their measurement, and so the forearm's and
    hand's poses; the wrist's encoder and the upper arm's sensor keep theirs."""
    body = BodyEmulator(Routine("still", "", lambda t: {"left_elbow_flexion_deg": 60.0,
                                                        "left_wrist_flexion_deg": 20.0}),
                        smartsuit_sensors([LEFT_ARM, TRUNK]), realism=Realism.ideal())  # fmt: skip
    solver = BodySolver(Profile(heading="fixed"))
    solver.assume_calibrated()  # the ideal trunk sensors sit square on their segments
    for tick in range(50):
        readings, _ = body.sample(tick / 100)
        samples = {s.site: RawSample(r, tick, tick * 10_000_000)
                   for s, r in zip(body.sensors, readings, strict=True)}  # fmt: skip
        output = solver.solve(samples)
    stale_key = keys.raw_key("arm", "left", "elbow")
    solver.set_stale([stale_key])
    f = pose_frame(solver.solve(samples), 1, [stale_key])
    names = lsl.angle_names(SKELETON)
    values = dict(zip(names, lsl.angle_values(f, names), strict=True))
    arm = {n for j in ("left_shoulder", "left_elbow", "left_wrist")
           for n in SKELETON.joint(j).angle_names()}  # fmt: skip
    nan = {n for n in arm if math.isnan(values[n])}
    assert nan == {*SKELETON.joint("left_elbow").angle_names(), "left_wrist_deviation_deg"}
    assert values["left_wrist_flexion_deg"] == pytest.approx(20.0, abs=0.3)
    assert output.angles_deg["left_elbow_flexion_deg"] == pytest.approx(60.0, abs=0.3)  # fresh
    labels = [c.label for c in lsl.segment_channels(SKELETON)]
    seg = lsl.segment_values(f, SKELETON.segment_chains())
    got = dict(zip(labels, seg, strict=True))
    assert math.isnan(got["left_forearm_qw"])
    assert math.isnan(got["left_hand_x"])
    assert got["left_upperarm_qw"] == f.segments["left_upperarm"][1][0]


def test_a_pose_from_before_the_stale_reason_is_nan_where_it_rests_on_a_stale_sensor() -> None:
    """A pose of an older gateway: the elbow module listed stale, no dof flagged
    for it. The elbow and wrist (either end of the forearm) are NaN, and so the
    forearm's and hand's poses; the knee and upper arm keep theirs."""
    f = frame(3, 0)
    old = pose.PoseFrame(f.seq, f.t_ns, f.angles_deg, {}, f.segments, {},
                         stale=[keys.raw_key("arm", "left", "elbow")])  # fmt: skip
    names = lsl.angle_names(SKELETON)
    values = dict(zip(names, lsl.angle_values(old, names), strict=True))
    nan = {n for n in names if math.isnan(values[n])}
    assert nan == {*SKELETON.joint("left_elbow").angle_names(),
                   *SKELETON.joint("left_wrist").angle_names()}  # fmt: skip
    labels = [c.label for c in lsl.segment_channels(SKELETON)]
    got = dict(zip(labels, lsl.segment_values(old, SKELETON.segment_chains()), strict=True))
    assert math.isnan(got["left_forearm_qw"])
    assert math.isnan(got["left_hand_x"])
    assert got["left_upperarm_qw"] == f.segments["left_upperarm"][1][0]


def test_channel_metadata() -> None:
    angles = lsl.angle_channels(SKELETON)
    assert [c.label + "_deg" for c in angles] == list(SKELETON.angle_names())
    assert {(c.type, c.unit) for c in angles} == {("JointAngle", "degrees")}
    segs = lsl.segment_channels(SKELETON)
    assert len(segs) == 7 * len(SKELETON.segments)
    assert [(c.label, c.type, c.unit) for c in segs[:7]] == [
        ("pelvis_x", "PositionX", "meters"), ("pelvis_y", "PositionY", "meters"),
        ("pelvis_z", "PositionZ", "meters"), ("pelvis_qw", "OrientationA", "normalized"),
        ("pelvis_qx", "OrientationB", "normalized"), ("pelvis_qy", "OrientationC", "normalized"),
        ("pelvis_qz", "OrientationD", "normalized")]  # fmt: skip
    ole = RawSample(OleAccel(2, -35, (10, -1024, 3)), 7, 5)
    assert [c.label for c in lsl.raw_channels(ole)] == ["seq", "encoder", "accel_x", "accel_y",
                                                       "accel_z"]  # fmt: skip
    assert lsl.raw_values(ole) == [7.0, -35.0, 10.0, -1024.0, 3.0]
    quat = RawSample(Quat(9, (0.5, 0.5, -0.5, 0.5)), 8, 5)
    assert [c.label for c in lsl.raw_channels(quat)] == ["seq", "qw", "qx", "qy", "qz"]
    assert lsl.raw_values(quat) == [8.0, 0.5, 0.5, -0.5, 0.5]


# --- live, through a real inlet in another process -------------------------------------------


@pytest.fixture(autouse=True)
def _loopback_lsl(tmp_path_factory: pytest.TempPathFactory) -> None:
    loopback_lsl(tmp_path_factory.mktemp("lsl"))


def local_clock() -> float:
    """LSL's clock, the one the samples are stamped on (here, as in the recorder)."""
    import pylsl

    return float(pylsl.local_clock())


def unix_to_lsl_offset() -> float:
    """This test's own estimate of local_clock() - Unix time (s), as a median."""
    import pylsl

    offsets = []
    for _ in range(200):
        a = pylsl.local_clock()
        u = time.time_ns()
        b = pylsl.local_clock()
        offsets.append((a + b) / 2 - u * 1e-9)
    return statistics.median(offsets)


#: The joints a stale SmartSuit left-arm module takes part in: those at either end
#: of the segment it rides on (shoulder module: upper arm; elbow: forearm; wrist: hand).
def expected_angles(f: pose.PoseFrame, labels: list[str]) -> list[float]:
    """The pose's angle under each channel label; NaN where the pose says nothing
    measured it: flagged (not merely clamped), or resting on a sensor gone stale
    (the gateway flags that too; the solver's tests hold its flags to the truth)."""
    out = []
    for label in labels:
        name = label + "_deg"
        measured = f.flags.get(name) in (None, "clamped") and not (
            f.stale and pose.STALE in f.reasons.get(name, ())
        )
        out.append(f.angles_deg[name] if measured else math.nan)
    return out


def check_stream(rec: Recorder, sid: str, frames: list[pose.PoseFrame], offset: float) -> int:
    """Every pose of ``frames`` from the first the inlet got on is in the stream,
    in order, with equal values and a timestamp within 1 ms of its mapped source
    time; returns how many."""
    samples = rec.samples[sid]
    assert samples, f"{sid}: nothing received"
    labels = [c["label"] for c in rec.info[sid]["channels"]]
    mapped = np.array([f.t_ns * 1e-9 + offset for f in frames])
    first = int(np.argmin(np.abs(mapped - samples[0][1])))
    expected = frames[first:]
    assert len(samples) == len(expected), (
        f"{sid}: {len(samples)} samples for {len(expected)} poses from the first received"
    )
    for (values, stamp), f, m in zip(samples, expected, mapped[first:], strict=True):
        assert abs(stamp - m) < 1e-3, f"{sid}: seq {f.seq} stamped {(stamp - m) * 1e3:.3f} ms off"
        np.testing.assert_array_equal(values, expected_angles(f, labels))
    return len(samples)


def check_subject(rec: Recorder, subject: str, sent: list[pose.PoseFrame], offset: float) -> None:
    """One subject's two streams: the angles as :func:`check_stream`, the last
    segment sample's left hand as the last pose's."""
    sid = lsl.source_id(subject, "angles")
    assert rec.info[sid]["name"] == f"bodynet {subject} joint angles"
    check_stream(rec, sid, sent, offset)
    seg_sid = lsl.source_id(subject, "segments")
    labels = [c["label"] for c in rec.info[seg_sid]["channels"]]
    values = dict(zip(labels, rec.samples[seg_sid][-1][0], strict=True))
    p, q = sent[-1].segments["left_hand"]
    assert [values[f"left_hand_{c}"] for c in SEGMENT_SUFFIXES] == [*p, *q]


def test_the_samples_pushed_just_before_closing_reach_the_inlet() -> None:
    """Destroying an LSL outlet drops what liblsl has not sent yet: closing leaves its
    consumers time to take the last samples. Outputs of one raw stream each, closed
    right after a burst: without it, nearly each lost most of its burst (as the restart
    test once got 139 samples for 140 poses)."""
    key = keys.raw_key("arm", "left", "elbow")
    subjects = [f"close{os.getpid()}x{k}" for k in range(4)]
    sids = [lsl.source_id(s, "raw/arm/left/elbow/ole") for s in subjects]
    outputs = {s: lsl.LslOutput(raw=True) for s in subjects}
    pushed = dict.fromkeys(subjects, 0)

    def push(s: str) -> None:
        pushed[s] += 1
        sample = RawSample(OleAccel(2, pushed[s], (0, 0, 0)), pushed[s], time.time_ns(), Source.CAN)
        outputs[s].on_raw(s, key, sample)

    for s in subjects:
        push(s)  # the outlets are made by the first samples
    rec = Recorder(sids)
    try:
        rec.wait_ready()
        deadline = time.monotonic() + 30
        while not all(rec.samples[sid] for sid in sids):  # every inlet receiving
            assert time.monotonic() < deadline, {sid: len(rec.samples[sid]) for sid in sids}
            for s in subjects:
                push(s)
            rec.pump(0.05)
        for s in subjects:  # one after the other: a burst, then the stop
            for _ in range(10):
                push(s)
            outputs[s].close()
        rec.finish()
    finally:
        if not rec.done:
            rec.finish()
    for s, sid in zip(subjects, sids, strict=True):
        seqs = [int(values[0]) for values, _ in rec.samples[sid]]
        assert seqs == list(range(seqs[0], pushed[s] + 1)), f"{sid}: {seqs[-12:]}, {pushed[s]}"


def test_a_stopped_output_is_handed_what_came_in_before_the_stop(
    router_endpoint: str, zsession: zenoh.Session
) -> None:
    """Stopped while its output is busy with a pose, ``live.run`` hands it the poses
    that came in meanwhile before closing it (it dropped them: the restart test's LSL
    stream could lack the last poses the Zenoh subscriber beside it had)."""
    import threading

    busy, release = threading.Event(), threading.Event()

    class Busy(live.LiveOutput):
        def __init__(self) -> None:
            self.seen: list[int] = []
            self.closed_after: list[int] | None = None

        def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
            if not self.seen:  # busy with the first until released
                busy.set()
                assert release.wait(30)
            self.seen.append(frame.seq)

        def close(self) -> None:
            self.closed_after = list(self.seen)

    out_session = open_session(session_config("client", connect=[router_endpoint]))
    output = Busy()
    running = Running(partial(live.run, out_session, output))
    try:
        pub = zsession.declare_publisher(keys.pose_key(), congestion_control=BLOCK)
        deadline = time.monotonic() + 10
        while not pub.matching_status.matching:  # the output's subscription, alone yet
            assert time.monotonic() < deadline, "the output never subscribed"
            time.sleep(0.01)
        # beside it on its session: once this one has a pose, Zenoh has handed the
        # output's subscription every pose before it (one link, its samples handed out
        # in order), though its callback's thread may not have taken them yet
        arrived = Collector(out_session, keys.pose_key(), pose.decode)
        t0 = 1_700_000_000_000_000_000
        for seq in range(6):
            pub.put(pose.encode(frame(seq, t0 + seq * 10_000_000)))
        assert busy.wait(30)
        arrived.wait_for(lambda seen: len(seen) == 6, timeout=30)
        running.stop_event.set()  # stopped while the output is busy with pose 0
    finally:
        release.set()
        running.stop()
        out_session.close()
    assert output.closed_after is not None
    assert output.closed_after[:5] == [0, 1, 2, 3, 4]


def stop_gateway(gw: Gateway, running: Running) -> None:
    running.stop()
    gw.close()


def wait_after_restart(rec: Recorder, sid: str, since: float, gw: Gateway,
                       poses: Collector) -> None:  # fmt: skip
    """``rec.wait_since(sid, since, 20)`` after a gateway restart; if the stream stops there
    (seen once, 2026-12-06, not since), the failure says where the poses stopped."""
    try:
        rec.wait_since(sid, since, 20)
    except AssertionError as exc:
        listened = {s: dict(b.matching) for s, b in gw._bodies.items()}
        raise AssertionError(
            f"{exc}; the restarted gateway: {gw.health()}, listened to: "
            f"{listened}, poses on Zenoh: {len(poses.seen)} seen"
            f" + {poses.queue.qsize()} queued"
        ) from exc


def handed_without_gap(output: HandedLsl, poses: Collector) -> None:
    """The output was handed the poses on Zenoh (as a subscriber beside it on its
    session got them) without a gap, until it stopped: the gateway's last poses can
    reach that subscriber after the output's is gone."""
    while not poses.queue.empty():
        poses.seen.append(poses.queue.get_nowait())
    on_zenoh, handed = [f.t_ns for _, f in poses.seen], [f.t_ns for f in output.handed]
    start = on_zenoh.index(handed[0])
    assert handed == on_zenoh[start : start + len(handed)]


class HandedLsl(lsl.LslOutput):
    """The LSL output, keeping the poses it was handed: what its streams must hold."""

    def __init__(self) -> None:
        super().__init__()
        self.handed: list[pose.PoseFrame] = []

    def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
        self.handed.append(frame)
        super().on_pose(subject, frame)


def test_lsl_streams_every_pose_through_gateway_and_router_restarts(tmp_path: Path) -> None:
    subject = f"lsl{os.getpid()}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(session_config("router", listen=[endpoint]))
    sessions: list[zenoh.Session] = []

    def client() -> zenoh.Session:
        sessions.append(open_session(session_config("client", connect=[endpoint],
                                                    subject=subject)))  # fmt: skip
        return sessions[-1]

    def start_gateway() -> tuple[Gateway, Running]:
        gw = Gateway(client(), profile_path=tmp_path / "subject.toml")
        return gw, Running(gw.run)

    out_session = client()
    poses = Collector(out_session, keys.pose_key(), pose.decode)  # the poses on Zenoh
    output = HandedLsl()
    outlet = Running(partial(live.run, out_session, output, subject=subject))
    gw, gw_run = start_gateway()
    options = EmulationOptions("reach", seed=5)
    nodes = Running(partial(run_node, client(), plans=[NodePlan("smartsuit", "can", (LEFT_ARM,))],
                            options=options, name="lsl"))  # fmt: skip
    sid, rec = lsl.source_id(subject, "angles"), None
    try:
        poses.wait_for(lambda s: len(s) >= 3, timeout=30)
        rec = Recorder([sid])
        rec.wait_ready()
        assert rec.info[sid]["type"] == "MoCap"
        uid = rec.info[sid]["uid"]
        rec.wait_for(sid, 20)

        stop_gateway(gw, gw_run)  # a gateway restart: a new process would be the same to us
        restarted = local_clock()  # samples stamped later: the restarted gateway's poses
        gw, gw_run = start_gateway()
        wait_after_restart(rec, sid, restarted, gw, poses)

        router.close()  # a router restart; every client reconnects by itself
        restarted = local_clock()
        router = open_session(session_config("router", listen=[endpoint]))
        rec.wait_since(sid, restarted, 20)

        nodes.stop()
        stop_gateway(gw, gw_run)
        outlet.stop()  # the output is handed what Zenoh gave it, and sends it
        rec.finish()
    finally:
        if rec is not None and not rec.done:
            rec.finish()
        for s in sessions:
            s.close()
        router.close()
    handed_without_gap(output, poses)
    # and its stream has every pose it was handed from the first the inlet got
    assert check_stream(rec, sid, output.handed, unix_to_lsl_offset()) >= 60
    assert rec.info[sid]["uid"] == uid  # one outlet throughout: the inlet never re-resolved
    measured = ~np.isnan(np.array([v for v, _ in rec.samples[sid]]))
    labels = [c["label"] for c in rec.info[sid]["channels"]]
    # the CAN arm's encoder: measured but where its modules were stale (once the nodes stopped)
    assert measured[:, labels.index("left_elbow_flexion")].mean() > 0.9
    assert not measured.any(axis=0).all()  # and the rest of the body, without sensors, NaN


def test_two_subjects_give_two_streams_each_and_raw_samples(router_endpoint: str) -> None:
    names = [f"a{os.getpid()}", f"b{os.getpid()}"]
    pub = open_session(session_config("client", connect=[router_endpoint]))
    sub = open_session(session_config("client", connect=[router_endpoint]))
    output = lsl.LslOutput(raw=True)
    outlet = Running(partial(live.run, sub, output, all_subjects=True))
    t0 = time.time_ns()
    raw_key = keys.raw_key("arm", "left", "elbow")
    sids = [lsl.source_id(s, k) for s in names for k in ("angles", "segments")]
    raw_sid = lsl.source_id(names[0], "raw/arm/left/elbow/ole")
    sent: dict[str, list[pose.PoseFrame]] = {s: [] for s in names}
    raws: list[RawSample] = []

    def publish(i: int) -> None:
        for k, s in enumerate(names):
            f = frame(i, t0 + i * 10_000_000 + k * 1_000_000, base=100.0 * k)
            sent[s].append(f)
            pub.put(f"{s}/{keys.pose_key()}", pose.encode(f), congestion_control=BLOCK)
        r = RawSample(OleAccel(2, 100 + i, (i, -1024, 3)), i, t0 + i * 10_000_000, Source.CAN)
        raws.append(r)
        pub.put(f"{names[0]}/{raw_key}", raw_sample.encode(r), congestion_control=BLOCK)

    rec = None
    try:
        deadline = time.monotonic() + 30
        while len(output.streams) < 5:  # the outlets are made by the first messages
            assert time.monotonic() < deadline, output.streams
            publish(len(raws))
            time.sleep(0.05)
        rec = Recorder([*sids, raw_sid])
        rec.wait_ready()
        start = len(raws)
        for i in range(start, start + 30):
            publish(i)
        for s in sids:
            rec.wait_for(s, 30)
        rec.wait_for(raw_sid, 30)
        outlet.stop()
        rec.finish()
    finally:
        if rec is not None and not rec.done:
            rec.finish()
        pub.close()
        sub.close()
    offset = unix_to_lsl_offset()
    for s in names:
        check_subject(rec, s, sent[s], offset)
    # the subjects' streams differ: bob's values are alice's plus 100
    a, b = rec.samples[sids[0]][-1][0], rec.samples[sids[2]][-1][0]
    assert b[0] - a[0] == pytest.approx(100.0)
    chans = rec.info[raw_sid]["channels"]
    assert [(c["label"], c["unit"]) for c in chans][:2] == [("seq", "count"), ("encoder", "0.1 mm")]
    got = rec.samples[raw_sid]
    by_seq = {int(v[0]): (v, t) for v, t in got}
    for r in raws[-30:]:
        v, t = by_seq[r.seq]
        assert v == [r.seq, r.reading.encoder, *r.reading.accel]  # type: ignore[union-attr]
        assert abs(t - (r.t_ns * 1e-9 + offset)) < 1e-3


def test_bodynet_lsl_restarted_is_picked_up_again_by_its_source_id(router_endpoint: str) -> None:
    """The command itself, stopped and started again: an inlet opened with
    recovery (as LabRecorder's) goes on receiving from the new process."""
    import threading

    from service_procs import Services, bodynet

    subject = f"cli{os.getpid()}"
    sid = lsl.source_id(subject, "angles")
    pub = open_session(session_config("client", connect=[router_endpoint], subject=subject))
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.wait(0.01):
            seq += 1
            pub.put(keys.pose_key(), pose.encode(frame(seq, time.time_ns())))

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    services = Services()
    argv = bodynet("lsl", "-e", router_endpoint, "--subject", subject)
    rec = None
    try:
        first = services.start("lsl", argv)
        first.wait_line(f"bodynet lsl: subject {subject}, LSL streams of type MoCap")
        rec = Recorder([sid])
        rec.wait_ready()
        rec.wait_for(sid, 10)
        assert first.stop() == 0
        assert any("poses" in line for line in first.output)  # its summary
        # samples stamped later were sent by the new process (not the first one's last,
        # still on their way to this process: a count of them let the test stop the new
        # one before it had even set its signal handler, exit -2)
        restarted = local_clock()
        second = services.start("lsl", argv)
        rec.wait_since(sid, restarted, 10, timeout=60)  # the inlet found the new outlet
        assert second.stop() == 0
        rec.finish()
    finally:
        stop.set()
        publisher.join(timeout=5)
        if rec is not None and not rec.done:
            rec.finish()
        services.close()
        pub.close()
