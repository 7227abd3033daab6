"""`bodynet view`: recordings to Rerun files, the web viewer served, bad input refused."""

from __future__ import annotations

import contextlib
import json
import os
import stat
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.writer import Writer
from rerun.chunk import RrdReader
from service_procs import ended
from zenoh_helpers import client, free_port, wait_matching

from bodynet.clients.view import Viewer, view_live
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.messages import RawSample
from bodynet.core.skeleton import build_skeleton
from bodynet.kinematics.model import BodyModel

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
    rrd.write_bytes(b"an older file")
    rrd.chmod(0o644)
    result = run("view", mcap, "--headless", "--save", rrd)  # Rerun's flag
    assert result.returncode == 0, result.stderr
    assert "30 poses" in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.mcap", "s.rrd"]  # nothing aside
    assert stat.S_IMODE(rrd.stat().st_mode) == 0o600  # health data: the owner's only
    printed = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True,
                             timeout=60, check=True).stdout  # fmt: skip
    assert "- /body/figure -" in printed
    assert "- /angles/right_shoulder_abduction -" in printed
    assert subprocess.run([str(RERUN), "rrd", "verify", str(rrd)], capture_output=True,
                          timeout=60, check=False).returncode == 0  # fmt: skip


def foreign_mcap(path: Path) -> Path:
    """A complete MCAP with two poses on ``body/pose``, then a message that is not one."""
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel("body/pose", "json", writer.register_schema("", "", b""))
        frames = [full_pose(i, 1_700_000_000_000_000_000 + i * 10_000_000) for i in range(2)]
        for i, data in enumerate([*map(pose.encode, frames), b'{"not": "a pose"}']):
            writer.add_message(channel, log_time=i + 1, data=data, publish_time=i + 1)
        writer.finish()
    return path


def test_bad_recording_is_a_clear_error_and_leaves_no_rrd(tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(b"\x89MCAP0\r\n" + bytes(10))
    foreign = foreign_mcap(tmp_path / "foreign.mcap")
    inputs = sorted(p.name for p in tmp_path.iterdir())
    for bad, message in ((cut, "not a complete MCAP file"), (foreign, "is not a bodynet pose")):
        result = run("view", bad, "--save", tmp_path / "x.rrd")
        assert result.returncode == 2
        assert message in result.stderr
        assert "Traceback" not in result.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == inputs  # no x.rrd, nothing aside
    # an earlier file of that name is left as it was
    earlier = tmp_path / "x.rrd"
    earlier.write_bytes(b"an earlier recording")
    before = earlier.stat()
    for bad in (cut, foreign):
        assert run("view", bad, "--save", earlier).returncode == 2
        assert earlier.read_bytes() == b"an earlier recording"
        assert earlier.stat().st_mtime_ns == before.st_mtime_ns
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*inputs, "x.rrd"])


def test_no_viewer_and_nothing_saved_is_refused(tmp_path: Path) -> None:
    """``--viewer none`` (``--headless``) without ``--save``, of a recording or
    live: nothing shown and nothing written, which exited 0 as if it had."""
    for args in ([foreign_mcap(tmp_path / "f.mcap"), "--headless"], ["--viewer", "none"]):
        result = run("view", *args, timeout=30)
        assert result.returncode == 2, result.stderr
        assert "shows nothing and writes nothing without --save" in result.stderr
        assert "Traceback" not in result.stderr


def test_save_into_a_missing_folder_is_a_clear_error(tmp_path: Path) -> None:
    result = run("view", foreign_mcap(tmp_path / "f.mcap"), "--save", tmp_path / "no" / "x.rrd")
    assert result.returncode == 2
    assert "cannot write" in result.stderr
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


# --- the live viewer ----------------------------------------------------------------

SKELETON = build_skeleton()
MODEL = BodyModel(SKELETON)


def full_pose(seq: int, t_ns: int) -> pose.PoseFrame:
    """A whole body standing in neutral, every segment and angle there."""
    q = MODEL.q({})
    rows = MODEL.segment_poses(q).tolist()
    segments = {s: (tuple(r[:3]), (r[6], r[3], r[4], r[5]))
                for s, r in zip(SKELETON.segments, rows, strict=True)}  # fmt: skip
    return pose.PoseFrame(seq, t_ns, MODEL.angles_deg(q), {}, segments, {})


def wait(done: Callable[[], bool], timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline
        time.sleep(0.02)


METRICS = {"v": 1, "t_ns": 1, "dofs": {"left_elbow_flexion_deg": {
    "min_deg": 10.0, "max_deg": 100.0, "range_deg": 90.0, "repetitions": 3, "sparc": -1.5624,
    "samples": 300}}}  # fmt: skip


def rrd_texts(rrd: Path, entity: str) -> list[str]:
    """Every text logged to ``entity`` in a Rerun file, read back with Rerun's reader."""
    texts = []
    for chunk in RrdReader(rrd).stream():
        if chunk.entity_path == entity:
            batch = chunk.to_record_batch()
            texts += [t for row in batch.column("TextDocument:text").to_pylist() for t in row]
    return texts


def test_live_viewer_draws_partial_poses_and_survives_hostile_ones(
    tmp_path: Path, router_endpoint: str
) -> None:
    """A branch view (no pelvis), a pose of a few segments, poses of absurd
    numbers: drawn as far as they go; what cannot be shown is counted; the
    viewer never stops."""
    t0 = 1_700_000_000_000_000_000
    whole = full_pose(1, t0)
    arm = whole.subset(["left_shoulder", "left_elbow", "left_wrist"],
                       ["left_upperarm", "left_forearm", "left_hand"],
                       "body/arm/left/")  # fmt: skip
    assert "pelvis" not in arm.segments
    assert len(arm.segments) == 3
    few = pose.PoseFrame(3, t0 + 2, {"neck_flexion_deg": 5.0}, {},
                         {"head": whole.segments["head"], "left_foot": whole.segments["left_foot"],
                          "nonsense": ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))}, {})  # fmt: skip
    nothing = pose.PoseFrame(4, t0 + 3, {}, {}, {}, {})
    absurd = json.dumps({
        "v": 1, "seq": 5, "t_ns": -(2**63) + 1, "rel_deg": {}, "joints_m": {},
        "angles_deg": {"left_knee_flexion_deg": "inf", "": 1.0, "a/b c_deg": "nan"},
        "segments": {"head": {"p": [1e308, "nan", "-inf"], "q": [1, 0, 0, 0]},
                     "thorax": {"p": [0, 0, 1.2], "q": ["nan", 0, 0, 0]},
                     "pelvis": {"p": [0, 0, 1], "q": [1e308, 1e308, 0, 0]},
                     "left_thigh": {"p": [0, 0.1, 1], "q": [0, 0, 0, 0]}},
    }).encode()  # fmt: skip
    good = [pose.encode(f) for f in (arm, few, nothing)] + [absurd, pose.encode(whole)]
    out_of_time = pose.encode(pose.PoseFrame(5, 2**64 - 1, {}, {}, {}, {}))  # past int64 ns
    bad_pose = [b"\x00garbage", out_of_time]
    bad_admin = [(keys.TOPOLOGY, b"[" * 100_000), (keys.health_key("imu"), b"{not json")]
    health = {"source": "imu", "device": "connected", "rejected": {},
              "nodes": {"7": {"key": "body/arm/left/elbow/raw", "alive": True,
                              "rate_hz": 97, "samples": 4321, "gaps": 13,
                              "rejected": {"bad_length": 2}}}}  # fmt: skip
    for p in good:
        assert pose.decode(p)  # each of them is a pose the gateway could have sent

    rrd = tmp_path / "live.rrd"
    viewer = Viewer.start("none", save=rrd)
    viewer_session, publisher = client(router_endpoint), client(router_endpoint)
    stop = threading.Event()
    shown: list[int] = []
    lives: list[int] = []  # on_live: once, when the first poses are shown
    thread = threading.Thread(
        target=lambda: shown.append(
            view_live(viewer_session, viewer, stop, on_live=lambda: lives.append(viewer.shown))
        )
    )
    thread.start()
    try:
        for key in (keys.TOPOLOGY, keys.health_key("imu"), keys.METRICS, keys.pose_key()):
            wait_matching(publisher, key)  # the viewer's subscriptions reach the router
        for key, payload in bad_admin:
            publisher.put(key, payload)
        publisher.put(keys.health_key("imu"), json.dumps(health).encode())
        publisher.put(keys.METRICS, json.dumps(METRICS).encode())  # before the poses, in order
        for payload in [*good[:2], *bad_pose, *good[2:]]:
            publisher.put(keys.pose_key(), payload)
        wait(lambda: viewer.shown == len(good) and viewer.bad == len(bad_pose) + len(bad_admin))
        assert thread.is_alive()  # no message stopped it
    finally:
        stop.set()
        thread.join(timeout=15)
        for s in (publisher, viewer_session):
            s.close()
        viewer.close()
    assert shown == [len(good)]
    assert len(lives) == 1
    assert lives[0] > 0
    printed = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True,
                             text=True, timeout=60, check=True).stdout  # fmt: skip
    for entity in ("/body/figure", "/body/joints", "/angles/left_elbow_flexion", "/status"):
        assert f"- {entity} -" in printed
    status = rrd_texts(rrd, "/status")[-1]
    # per node health in the status panel, and the messages the view could not show
    node = "- node 7 `body/arm/left/elbow/raw`: alive, 97 Hz, 4321 samples, 13 gaps"
    assert f"{node}, rejected bad_length 2" in status
    assert "- **viewer**: 4 bad messages" in status
    assert "| left_elbow_flexion | 10 | 100 | 90 | 3 | -1.562 |" in rrd_texts(rrd, "/metrics")[-1]


def test_figure_skips_missing_bones() -> None:
    from bodynet.clients.view import figure

    whole = full_pose(1, 0)
    strips, joints = figure(whole, SKELETON)
    assert [len(s) for s in strips] == [4, 5, 5, 5, 5]
    assert joints.shape == (15, 3)
    # no pelvis: the spine starts at the thorax, the legs at the thighs
    no_pelvis = pose.PoseFrame(1, 0, {}, {}, {k: v for k, v in whole.segments.items()
                                              if k != "pelvis"}, {})  # fmt: skip
    strips, joints = figure(no_pelvis, SKELETON)
    assert [len(s) for s in strips] == [3, 5, 4, 5, 4]
    assert joints.shape == (14, 3)
    np.testing.assert_allclose(strips[0][0], whole.segments["thorax"][0])
    # a forearm missing: the upper arm and the hand stay, apart
    no_forearm = pose.PoseFrame(1, 0, {}, {}, {k: v for k, v in whole.segments.items()
                                               if k != "left_forearm"}, {})  # fmt: skip
    strips, _ = figure(no_forearm, SKELETON)
    assert [len(s) for s in strips] == [4, 2, 2, 5, 5, 5]


def test_gauge_panel_is_a_three_by_three_matrix_of_dials() -> None:
    """Nine dials in three rows; a needle points along its dof's range of motion:
    at the minimum to the dial's lower left, at the maximum to its lower right,
    held at the end outside the range, and never off its dial."""
    from bodynet.clients.view import GAUGE_PITCH, GAUGES, gauge_faces, gauge_needles
    from bodynet.core.skeleton import rom

    arcs, _, where, names = gauge_faces()
    assert len(arcs) == len(names) == 9
    centres = {(round(x / GAUGE_PITCH), round((y - 1.15) / GAUGE_PITCH)) for x, y in where}
    assert centres == {(c, r) for c in range(3) for r in range(3)}
    lows = [rom(g)[0] for g in GAUGES]
    highs = [rom(g)[1] for g in GAUGES]
    (at_low, _), (at_high, _) = gauge_needles(lows), gauge_needles(highs)
    for (c0, lo), (c1, hi) in zip(at_low, at_high, strict=True):
        assert (c0 == c1).all()  # one centre per dial
        assert lo[0] < c0[0]  # lower left (2D: y grows downwards)
        assert lo[1] > c0[1]
        assert hi[0] > c0[0]  # lower right
        assert hi[1] > c0[1]
    beyond, readings = gauge_needles([h + 500.0 for h in highs])
    assert all(np.allclose(b, a) for b, a in zip(beyond, at_high, strict=True))
    assert readings[0] == f"{highs[0] + 500.0:.0f}°"  # the reading tells the real value
    mid = gauge_needles([(lo + hi) / 2 for lo, hi in zip(lows, highs, strict=True)])[0]
    assert all(abs(n[1][0] - n[0][0]) < 1e-9 for n in mid)  # halfway: straight up
    assert all(n[1][1] < n[0][1] for n in mid)


def test_the_calibration_state_is_drawn_per_segment(tmp_path: Path) -> None:
    """The gateway's health says per segment what holds its tag's heading; the view
    marks each segment in the 3D figure (green: a joint's geometry or a
    measurement; amber: a three-dof joint's mean twist; red: not held), read back
    from the saved .rrd with Rerun's own reader."""
    from bodynet.clients.view import CALIBRATION_COLOURS, calibration_marks
    from bodynet.core.subject import Profile
    from bodynet.gateway.frames import pose_frame
    from bodynet.gateway.heading import JointDrift, calibrate_window
    from bodynet.gateway.solver import BodySolver
    from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
    from bodynet.nodes.motion import ROUTINES

    body = BodyEmulator(ROUTINES["tpose"], imu_tags(), realism=Realism(), seed=3)
    window: dict[object, list[tuple[float, tuple[float, float, float, float]]]] = {}
    samples = {}
    for t in np.arange(0.0, 1.0, 0.02):
        readings, _ = body.sample(float(t))
        for s, r in zip(body.sensors, readings, strict=True):
            window.setdefault(s.site, []).append((float(t), r.wxyz))  # type: ignore[union-attr]
            samples[s.site] = RawSample(r, 0, round(t * 1e9))
    profile = Profile(heading="fixed", drift="joints")
    profile = calibrate_window(window, profile, "tpose").apply(profile)  # type: ignore[arg-type]
    segments = JointDrift(profile).segments(profile)
    marks = calibration_marks({"gateway": {"body": {"heading": {"segments": segments}}}})
    assert marks["left_shank"][0] == CALIBRATION_COLOURS["held"]  # the knee's hinge
    assert marks["thorax"][0] == CALIBRATION_COLOURS["assumed"]  # the lumbar's mean twist
    assert marks["left_thigh"][1].startswith("left_thigh: three-dof joint's mean twist +/-")
    assert calibration_marks({"gateway": {"body": {"heading": {"segments": [1, 2]}}}}) == {}
    rrd = tmp_path / "c.rrd"
    viewer = Viewer.start("none", save=rrd)
    viewer.calibration = marks
    frame = pose_frame(BodySolver(profile).solve(samples), 1, [])
    assert viewer.log_poses([frame]) == 1
    viewer.close()
    printed = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True,
                             timeout=60, check=True).stdout  # fmt: skip
    assert "- /body/calibration -" in printed


# --- a viewer that cannot be served or reached ---------------------------------------


def test_a_viewer_url_rerun_refuses_is_refused_as_the_option(tmp_path: Path) -> None:
    recording = foreign_mcap(tmp_path / "f.mcap")
    result = run("view", recording, "--connect-viewer", "http://127.0.0.1:1")
    assert result.returncode == 2
    assert "argument --connect-viewer: 'http://127.0.0.1:1' is not a URL like rerun://" in (
        result.stderr
    )
    result = run("view", recording, "--connect-viewer", "rerun+http://256.1.1.1:1/proxy")
    assert result.returncode == 2
    assert result.stderr.startswith("bodynet view: cannot reach the viewer at rerun+http://256")
    assert "Traceback" not in result.stderr


def test_ports_in_use_are_one_line(tmp_path: Path) -> None:
    import socket

    recording = foreign_mcap(tmp_path / "f.mcap")
    with socket.create_server(("0.0.0.0", 0)) as taken:
        port = taken.getsockname()[1]
        for option, other in (("--web-port", "--grpc-port"), ("--grpc-port", "--web-port")):
            result = run("view", recording, "--viewer", "web", option, port, other, free_port())
            assert result.returncode == 2, result.stderr
            assert result.stderr.strip() == (f"bodynet view: cannot serve on port {port} "
                                             f"({option}): Address already in use")  # fmt: skip


def test_a_viewer_that_takes_nothing_is_said_and_sigterm_ends_the_view(tmp_path: Path) -> None:
    """Nothing listening: said at once. A listener that never answers (Rerun would wait
    for it for ever): SIGTERM still ends the view."""
    import signal
    import socket

    recording = foreign_mcap(tmp_path / "f.mcap")
    result = run("view", recording, "--viewer", "connect",
                 "--url", f"rerun+http://127.0.0.1:{free_port()}/proxy")  # fmt: skip
    assert result.returncode == 2
    assert "cannot reach the viewer at rerun+http://127.0.0.1:" in result.stderr
    with socket.create_server(("127.0.0.1", 0)) as silent:
        url = f"rerun+http://127.0.0.1:{silent.getsockname()[1]}/proxy"
        proc = subprocess.Popen([str(BODYNET), "-v", "view", recording, "--viewer", "connect",
                                 "--url", url], stderr=subprocess.PIPE, text=True)  # fmt: skip
        silent.settimeout(60)
        peer, _ = silent.accept()  # Rerun connected: the view is logging, then flushing
        try:
            assert proc.stderr is not None
            said = ""  # SIGTERM once the view waits for the viewer (-v says so), not before
            while "to take the poses" not in said and proc.poll() is None:
                said = proc.stderr.readline()
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=60)
        finally:
            proc.kill()
            peer.close()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert f"interrupted by SIGTERM while the viewer at {url} took nothing" in err
    assert "Traceback" not in err


def test_a_recording_in_the_web_viewer_is_served_until_stopped(arm_mcap: Path) -> None:
    """No display: `--viewer auto` falls back to the web viewer, which lives as long as
    the process; it serves the recording until Ctrl-C instead of exiting at once."""
    import os
    import signal

    web, grpc = free_port(), free_port()
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    proc = subprocess.Popen([str(BODYNET), "view", str(arm_mcap),
                             "--web-port", str(web), "--grpc-port", str(grpc)],
                            stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert f"in the web viewer at http://127.0.0.1:{web}/" in line, line
        assert "serving it until Ctrl-C" in line
        with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10) as page:
            assert page.status == 200
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    finally:
        proc.kill()
        proc.wait(timeout=10)


def _rows(rrd: Path, entity: str, writing: bool = False) -> int:
    """How many rows an ``.rrd`` holds of ``entity``; ``writing``: one that Rerun is
    still writing (no footer yet, perhaps a chunk cut short: -1 until it reads)."""
    import warnings

    with warnings.catch_warnings():  # a stream still being written has no footer yet
        warnings.simplefilter("ignore")
        try:
            chunks = list(RrdReader(rrd).stream()) if rrd.exists() or not writing else []
        except Exception:
            if not writing:
                raise
            return -1
    return sum(c.to_record_batch().num_rows for c in chunks if c.entity_path == entity)


def test_sigterm_ends_a_live_view_promptly_flushing_what_it_has(
    tmp_path: Path, router_endpoint: str
) -> None:
    """A live view ends on SIGTERM within a second or two: a viewer that is there (a
    real Rerun, writing what it takes) has every pose the view showed, as has the
    --save'd .rrd; a viewer that takes nothing (a listener that never answers) is said
    in one line, exit 1, instead of holding the stop for a minute, and the .rrd is
    kept whole rather than lost with it."""
    import signal
    import socket

    angle = "/angles/left_elbow_flexion"
    port, got = free_port(), tmp_path / "viewer.rrd"
    procs: list[subprocess.Popen[str]] = []

    def view(url: str, rrd: str) -> subprocess.Popen[str]:
        procs.append(subprocess.Popen([str(BODYNET), "view", "--connect-viewer", url, "--save",
                                       tmp_path / rrd, "-e", router_endpoint],
                                      stderr=subprocess.PIPE, text=True,
                                      env={**os.environ, "PYTHONFAULTHANDLER": "1"}))  # fmt: skip
        return procs[-1]

    # in a session of its own: ``rerun`` is a wrapper whose child is the viewer, which
    # a kill of the wrapper alone left running after the tests
    viewer = subprocess.Popen([str(RERUN), "--port", str(port), "--save", str(got)],
                              stderr=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
    publisher = client(router_endpoint)
    try:
        wait(lambda: socket.socket().connect_ex(("127.0.0.1", port)) == 0, timeout=60)
        there = view(f"rerun+http://127.0.0.1:{port}/proxy", "there.rrd")
        wait_matching(publisher, keys.pose_key(), timeout=60)
        t0 = 1_700_000_000_000_000_000
        for i in range(20):
            publisher.put(keys.pose_key(), pose.encode(full_pose(i, t0 + i * 10_000_000)))
        wait(lambda: _rows(got, angle, writing=True) == 20, timeout=60)  # the viewer has them
        there.send_signal(signal.SIGTERM)
        code, err = ended(there, 30)
        assert (code, err) == (
            0,
            "bodynet view: live, poses arriving\n"
            f"bodynet view: 20 poses, saved to {tmp_path}/there.rrd\n",
        )
        assert _rows(tmp_path / "there.rrd", angle) == 20
        poses = publisher.declare_publisher(keys.pose_key())
        wait(lambda: not poses.matching_status.matching, timeout=60)  # that view is gone
        poses.undeclare()
        with socket.create_server(("127.0.0.1", 0)) as silent:
            url = f"rerun+http://127.0.0.1:{silent.getsockname()[1]}/proxy"
            gone = view(url, "silent.rrd")
            silent.settimeout(60)
            peer, _ = silent.accept()  # Rerun connected: the view is logging
            wait_matching(publisher, keys.pose_key(), timeout=60)
            gone.send_signal(signal.SIGTERM)
            with peer:
                code, err = ended(gone, 30)
                assert code == 1, err  # it waited 60 s (and lost the .rrd)
    finally:
        publisher.close()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=10)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(viewer.pid, signal.SIGKILL)
        viewer.wait(timeout=10)
    assert err.startswith(f"bodynet view: the viewer at {url} did not take the poses"), err
    assert err.count("\n") == 1, err
    assert _rows(tmp_path / "silent.rrd", "/gauges/faces") == 1
