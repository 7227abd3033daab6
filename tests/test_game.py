"""The rehabilitation game: its rules, its results files, its options, and the whole
chain in a real browser (headless Chromium driven by Playwright).

Two browser tests: one drives the game with pose messages published here, whose
flags the test controls (a still arm, a lost signal, an unmeasured dof: exact
cases), the other runs the real chain (gateway and emulated SmartSuit arm as
processes). The browser tests need Chromium: ``make test`` installs Debian's
``chromium`` when none is there; ``BODYNET_CHROMIUM`` names another binary.
Without one they FAIL, on purpose: the game's page is tested in a real browser or
not at all.
"""

from __future__ import annotations

import csv
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodynet.cli.main import main as bodynet_main
from bodynet.clients.game import (
    GameOptions,
    GameServer,
    ResultsFile,
    results_csv,
    session_history,
)
from bodynet.clients.rehab import (
    GAP_S,
    ROUTE,
    STALE_S,
    GameError,
    RehabGame,
    arm_pose,
    route_offsets,
)
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.codecs.pose import PoseFrame
from bodynet.core.skeleton import ARM_DOFS, DEFAULT_LENGTHS, build_skeleton
from bodynet.kinematics.model import BodyModel
from bodynet.nodes.motion import ROUTINES, reach

BODYNET = [sys.executable, "-m", "bodynet.cli.main"]
REACH_PERIOD_S = ROUTINES["reach"].period_s or 0.0
ARM = DEFAULT_LENGTHS["upperarm"] + DEFAULT_LENGTHS["forearm"] + DEFAULT_LENGTHS["hand"]


# --- the rules, fed by the body model (no network) ------------------------------------
class FkArm:
    """Pose messages of one arm from forward kinematics of the body model."""

    def __init__(self, side: str) -> None:
        self.side = side
        self.model = BodyModel(build_skeleton())
        self.frames = [self.model.segment_frames[f"{side}_{s}"]
                       for s in ("upperarm", "forearm", "hand")]  # fmt: skip

    def frame(self, angles: dict[str, float], seq: int = 0, stale: bool = False,
              flags: dict[str, str] | None = None) -> PoseFrame:  # fmt: skip
        """``angles`` by full name; every arm dof is in the message (0 when not given),
        ``flags`` by stem (``{"shoulder_abduction": "unobserved"}``)."""
        s = self.side
        full = {f"{s}_{d}_deg": 0.0 for d in ARM_DOFS}
        full.update({n: v for n, v in angles.items() if n.startswith(s)})
        rot, pos = self.model.frame_placements(self.model.q(full), self.frames)
        hand_q = Rotation.from_matrix(rot[2]).as_quat(scalar_first=True)
        joints = {
            f"{s}_{j}": tuple(p) for j, p in zip(("shoulder", "elbow", "wrist"), pos, strict=True)
        }
        return PoseFrame(
            seq, 0, full, {}, {f"{s}_hand": (tuple(pos[2]), tuple(hand_q))},  # type: ignore[dict-item]
            joints,  # type: ignore[arg-type]
            flags={f"{s}_{d}_deg": f for d, f in (flags or {}).items()},
            stale=[f"body/arm/{s}/elbow/raw"] if stale else [],
        )  # fmt: skip

    def pose(self, angles: dict[str, float], **kw: object) -> object:
        return arm_pose(self.frame(angles, **kw), self.side)  # type: ignore[arg-type]


def play(game: RehabGame, arm: FkArm, motion: object, t: float = 0.0, until: float = 120.0,
         dt: float = 0.02, **kw: object) -> float:  # fmt: skip
    """Feed ``motion(t)`` (angles by full name) to the game until its trial or
    session ends; returns the time."""
    trials = len(game.results)
    while len(game.results) == trials and t < until:
        t += dt
        game.on_pose(arm.pose(motion(t), **kw), t)  # type: ignore[operator, arg-type]
        game.tick(t)
    return t


def still(_: float) -> dict[str, float]:
    return {}


def test_route_is_the_seed_procedure_in_front_of_the_shoulder() -> None:
    left = route_offsets("left", 0.293, 0.265)
    right = route_offsets("right", 0.293, 0.265)
    names = [t.name for t in ROUTE]
    np.testing.assert_allclose(left[names.index("lift")], [ARM, 0, 0], atol=1e-9)  # forward
    np.testing.assert_allclose(left[names.index("lower")], [0, 0, -ARM], atol=1e-9)  # down
    np.testing.assert_allclose(left[names.index("side")], [0, ARM, 0], atol=1e-9)  # out left
    np.testing.assert_allclose(right[names.index("side")], [0, -ARM, 0], atol=1e-9)  # out right
    up = left[names.index("bend-elbow")]  # forearm and hand straight up from the elbow
    np.testing.assert_allclose(up, [0.293, 0, ARM - 0.293], atol=1e-9)
    # a longer arm moves the balls out with it
    assert route_offsets("left", 0.35, 0.30)[0][0] > left[0][0]
    # every label says what its instruction says
    assert [t.name for t in ROUTE][:4] == ["lift", "bend-elbow", "straighten-elbow", "lower"]


@pytest.mark.parametrize("side", ["left", "right"])
def test_arm_doing_the_reach_routine_completes_every_trial(side: str) -> None:
    arm = FkArm(side)
    routine = reach(side)
    game = RehabGame(side, trials=1, practice=1)
    game.on_pose(arm.pose(routine(0.0)), 0.0)  # type: ignore[arg-type]
    game.start(0.0)
    t = play(game, arm, routine)
    t = play(game, arm, routine, t)
    assert game.state == "finished"
    summary = game.summary()
    assert [(x["practice"], x["number"], x["complete"], x["success"])
            for x in summary["trials"]] == [(True, 1, True, True),
                                            (False, 1, True, True)]  # fmt: skip
    for trial in summary["trials"]:
        assert [x["name"] for x in trial["targets"]] == [x.name for x in ROUTE]
        assert {x["outcome"] for x in trial["targets"]} == {"reached"}
        times = [x["time_to_target_s"] for x in trial["targets"]]
        assert all(0.0 < x <= game.target_timeout_s + game.travel_s for x in times)
        assert trial["score"] == sum(10 + max(0, 10 - int(x)) for x in times)
        rom = trial["rom_deg"]
        assert rom["shoulder_flexion"]["max"] == pytest.approx(90.0, abs=1.0)
        assert rom["elbow_flexion"]["range"] == pytest.approx(90.0, abs=1.0)
        assert rom["wrist_flexion"]["max"] >= 45.0
    assert summary["complete_trials"] == 1  # practice left out
    assert summary["score"] == sum(x["score"] for x in summary["trials"][1:])
    assert summary["mean_time_to_target_s"] > 0


def test_a_still_arm_scores_nothing_not_even_the_rest_stops() -> None:
    arm = FkArm("left")
    game = RehabGame("left", trials=1, practice=0, target_timeout_s=2.0)
    game.on_pose(arm.pose({}), 0.0)  # type: ignore[arg-type]
    game.start(0.0)
    play(game, arm, still)
    trial = game.summary()["trials"][0]
    assert trial["complete"]
    assert not trial["success"]
    assert trial["score"] == 0
    assert [x["outcome"] for x in trial["targets"]] == ["missed"] * len(ROUTE)
    assert all(x["time_to_target_s"] is None and x["waited_for"] == [] for x in trial["targets"])
    assert trial["rom_deg"]["shoulder_flexion"]["range"] == 0.0


def test_unmeasured_dofs_never_reach_nor_miss_and_leave_the_range_of_motion() -> None:
    """The reach routine with shoulder abduction unobserved and wrist flexion held: the
    touch targets and the wrist end "not measured"; the roll (forearm pronation,
    ``clamped`` = measured) is reached; the range of motion leaves those dofs out."""
    arm = FkArm("left")
    routine = reach("left")
    game = RehabGame("left", trials=1, practice=0, target_timeout_s=3.0)
    flags = {"shoulder_abduction": "unobserved", "wrist_flexion": "held",
             "elbow_pronation": "clamped"}  # fmt: skip
    game.on_pose(arm.pose(routine(0.0), flags=flags), 0.0)  # type: ignore[arg-type]
    game.start(0.0)
    play(game, arm, routine, flags=flags)
    trial = game.summary()["trials"][0]
    outcomes = {x["name"]: x for x in trial["targets"]}
    for target in ROUTE:
        x = outcomes[target.name]
        if target.name == "roll":
            assert x["outcome"] == "reached", x
        else:
            assert x["outcome"] == "not measured", x
            assert not x["reached"]
            assert x["points"] == 0
            assert x["waited_for"] == (["wrist_flexion"] if target.gate else ["shoulder_abduction"])
            assert x["waited_s"] == pytest.approx(3.0, abs=0.05)
    assert set(trial["rom_deg"]) == {"shoulder_flexion", "shoulder_rotation", "elbow_flexion",
                                     "elbow_pronation", "wrist_deviation"}  # fmt: skip
    assert trial["score"] == sum(x["points"] for x in trial["targets"]) > 0


def test_a_lost_signal_pauses_the_target_instead_of_missing_it() -> None:
    arm = FkArm("left")
    game = RehabGame("left", trials=1, practice=0, target_timeout_s=2.0, travel_s=0.5)
    game.on_pose(arm.pose({}), 0.0)  # type: ignore[arg-type]
    game.start(0.0)
    t = 0.0
    for _ in range(50):  # 1 s of a still arm: the countdown runs
        t += 0.02
        game.on_pose(arm.pose({}), t)  # type: ignore[arg-type]
        game.tick(t)
    left = game.snapshot(t)["target"]["left_s"]
    assert left == pytest.approx(1.5, abs=0.05)
    for _ in range(500):  # 10 s without a pose: paused, not missed
        t += 0.02
        game.tick(t)
    snap = game.snapshot(t)
    assert snap["target"]["paused"]
    assert snap["target"]["i"] == 1
    assert snap["target"]["left_s"] == pytest.approx(left - GAP_S, abs=0.05)
    assert snap["arm"]["stale"]
    # the arm comes back and lifts: reached, the lost time left out of its time
    lifted = {"left_shoulder_flexion_deg": 90.0}
    for _ in range(5):
        t += 0.02
        game.on_pose(arm.pose(lifted), t)  # type: ignore[arg-type]
        game.tick(t)
    game.abort(t, "stopped by the therapist")
    first = game.summary()["trials"][0]["targets"][0]
    assert first["outcome"] == "reached"
    assert first["time_to_target_s"] == pytest.approx(1.0 + GAP_S, abs=0.1)
    assert first["paused_s"] == pytest.approx(10.0 - GAP_S, abs=0.1)
    assert game.summary()["trials"][0]["stale_s"] == pytest.approx(10.0 - STALE_S, abs=0.1)


def test_interruptions_keep_trial_numbers_and_refuse_without_a_signal() -> None:
    arm = FkArm("left")
    game = RehabGame("left", trials=1, practice=1)
    with pytest.raises(GameError, match="no live signal") as refused:
        game.start(0.0)
    assert refused.value.cause == "signal"
    game.on_pose(arm.pose({}), 0.0)  # type: ignore[arg-type]
    game.start(0.0)
    with pytest.raises(GameError, match="already running"):
        game.start(0.1)
    game.abort(1.0, "stopped by the therapist")
    assert game.state == "paused"
    game.on_pose(arm.pose({}), 1.5)  # type: ignore[arg-type]
    game.start(1.5)
    assert game.snapshot(1.5)["trial"] == {"number": 1, "practice": True, "attempt": 2, "score": 0}
    game.abort(2.0, "player disconnected")
    trials = game.summary()["trials"]
    assert [(t["practice"], t["number"], t["attempt"], t["complete"], t["reason"])
            for t in trials] == [(True, 1, 1, False, "stopped by the therapist"),
                                 (True, 1, 2, False, "player disconnected")]  # fmt: skip
    # the gateway flagging the arm's sensors stale counts as a lost signal
    game.on_pose(arm.pose({}, stale=True), 6.0)  # type: ignore[arg-type]
    assert not game.arm_live(6.0)
    with pytest.raises(GameError, match="no live signal"):
        game.start(6.0)
    with pytest.raises(GameError, match="the pose has no right arm"):
        arm_pose(arm.frame({}), "right")
    for bad in (float("nan"), float("inf"), 0.0, -1.0):
        with pytest.raises(GameError, match="finite number above 0"):
            RehabGame("left", radius_m=bad)
        with pytest.raises(GameError, match="finite number above 0"):
            RehabGame("left", target_timeout_s=bad)


def test_results_are_owner_only_and_the_history_reads_them_back(tmp_path: Path) -> None:
    arm = FkArm("left")
    games = []
    for patient, lift in (("p1", 30.0), ("p2", 50.0)):
        game = RehabGame("left", trials=1, practice=0, patient=patient)
        game.on_pose(arm.pose({"left_shoulder_flexion_deg": 20.0}), 0.0)  # type: ignore[arg-type]
        game.start(0.0)
        game.on_pose(arm.pose({"left_shoulder_flexion_deg": lift}), 0.5)  # type: ignore[arg-type]
        # a sample flagged unobserved is left out of the range of motion
        game.on_pose(arm.pose({"left_shoulder_flexion_deg": 170.0},  # type: ignore[arg-type]
                              flags={"shoulder_flexion": "unobserved"}), 0.6)  # fmt: skip
        game.abort(1.0, "stopped by the therapist")
        results = ResultsFile(tmp_path / "res", "left", patient)
        results.save(game)
        games.append(results)
    twin = ResultsFile(tmp_path / "res", "left", "p1")  # same second, same patient
    assert twin.json_path != games[0].json_path
    assert not twin.json_path.exists()
    for results in games:
        for path in (results.json_path, results.csv_path):
            assert path.stat().st_mode & 0o777 == 0o600
    assert (tmp_path / "res").stat().st_mode & 0o777 == 0o700
    saved = json.loads(games[0].json_path.read_text())
    assert saved["patient"] == "p1"
    assert saved["trials"][0]["rom_deg"]["shoulder_flexion"] == {
        "min": 20.0, "max": 30.0, "range": 10.0, "samples": 2}  # fmt: skip
    rows = list(csv.DictReader(games[0].csv_path.open()))
    assert rows[0]["reason"] == "stopped by the therapist"
    assert float(rows[0]["shoulder_flexion_range_deg"]) == 10.0
    assert results_csv(saved) == games[0].csv_path.read_bytes().decode()
    assert not list((tmp_path / "res").glob("*.part"))
    (tmp_path / "res" / "rehab-left-arm-broken.json").write_text("{")
    history = session_history(tmp_path / "res")
    assert sorted(s["patient"] for s in history["sessions"]) == ["p1", "p2"]
    by_patient = sorted(history["sessions"], key=lambda s: s["patient"])
    assert [s["trials"][0]["rom_deg"]["shoulder_flexion"] for s in by_patient] == [10.0, 30.0]
    assert {(d["patient"], d["sessions"], d["trials"]) for d in history["days"]} == {
        ("p1", 1, 0),
        ("p2", 1, 0),
    }  # fmt: skip  (the stopped trials are not complete)
    assert len(history["unreadable"]) == 1
    assert "rehab-left-arm-broken.json" in history["unreadable"][0]


def test_a_new_session_saves_the_old_one_and_starts_a_file_of_its_own(tmp_path: Path) -> None:
    import time

    server = GameServer(GameOptions("left", 1, 0, 0.12, 5.0, "p1"), tmp_path)
    arm = FkArm("left")
    now = time.monotonic()
    server.game.on_pose(arm.pose({}), now)  # type: ignore[arg-type]
    server.game.start(now)
    old = server.results.json_path
    server.new_session("p1")  # the same patient within the same second
    assert server.results.json_path != old
    assert not server.results.json_path.exists()  # nothing saved before a trial ends
    (trial,) = json.loads(old.read_text())["trials"]
    assert (trial["complete"], trial["reason"]) == (False, "new session started")
    assert server.game.state == "ready"
    assert server.game.arm_live(time.monotonic())  # the arm's signal carries over
    with pytest.raises(GameError, match="a patient id is"):
        server.new_session("Jane Doe")
    server.new_session("p2", "right")
    assert (server.game.side, server.game.patient) == ("right", "p2")
    assert server.results.json_path.name.startswith("rehab-right-arm-")


def test_the_results_folder_is_made_with_the_first_results_not_before(tmp_path: Path) -> None:
    """No router answers: the game ends (exit 2) and leaves no results folder, nor
    any of the missing folders above it; a folder under a file is refused at once."""
    results = tmp_path / "clinic" / "res"
    out = subprocess.run([*BODYNET, "game", "-e", "tcp/127.0.0.1:1", "--http-port", "0",
                          "--results", str(results), "--connect-timeout", "0.2"],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert out.returncode == 2, out.stderr
    assert "no router answered" in out.stderr.strip().splitlines()[-1]
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "file").write_text("")
    under_file = tmp_path / "file" / "a" / "res"
    assert bodynet_main(["game", "-e", "tcp/127.0.0.1:1", "--http-port", "0",
                         "--results", str(under_file)]) == 2  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.parametrize(
    ("args", "told"),
    [
        (["--http-port", "99999"], "--http-port: '99999' is outside 0..65535"),
        (["--http-port", "-1"], "--http-port: '-1' is outside 0..65535"),
        (["--http-port", "http"], "--http-port: 'http' is not a whole number"),
        (["--radius-cm", "nan"], "--radius-cm: 'nan' is not a finite number"),
        (["--radius-cm", "0"], "--radius-cm: '0' is outside [1, 100] (cm)"),
        (["--target-timeout", "inf"], "--target-timeout: 'inf' is not a finite number"),
        (["--target-timeout", "1e300"], "--target-timeout: '1e300' is outside [1, 3600]"),
        (["--trials", "0"], "--trials: '0' is outside 1..1000"),
        (["--practice", "-1"], "--practice: '-1' is outside 0..10"),
        (["--patient", "Jane Doe"], "--patient: a patient id is"),
        (["-e", "foo"], "-e/--connect: 'foo' is not a Zenoh endpoint"),
        (["--http-host", "bad..host"], "--http-host: 'bad..host' is neither a host name"),
    ],
)
def test_bad_options_are_refused_with_one_line(
    args: list[str], told: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exited:
        bodynet_main(["game", *args])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert told in err, err
    assert "Traceback" not in err


def test_a_bad_endpoint_a_taken_port_or_unwritable_results_are_told_at_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    no_router = "tcp/127.0.0.1:1"  # never reached: the mistakes are told before that
    (tmp_path / "file").write_text("")
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = str(taken.getsockname()[1])
        for args, told in (
            (["-e", no_router, "--http-port", port, "--results", str(tmp_path / "r")],
             "cannot serve on"),
            (["-e", no_router, "--http-port", "0", "--results", str(tmp_path / "file" / "r")],
             "cannot write results"),
        ):  # fmt: skip
            assert bodynet_main(["game", *args]) == 2
            out = capsys.readouterr()
            assert told in out.err
            assert len(out.err.strip().splitlines()) == 1, out.err
            assert ".rs:" not in out.err
            assert out.out == ""
    # an endpoint of the right shape that Zenoh still refuses: one line, no traceback
    assert bodynet_main(["game", "-e", "tcp/127.0.0.1:7447?", "--http-port", "0",
                         "--results", str(tmp_path / "r")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.startswith(
        "bodynet game: bad Zenoh session option connect/endpoints: Endpoints must be of the form"
    ), err
    assert len(err.strip().splitlines()) == 1, err
    assert ".rs:" not in err
    # the real executable, once: no router within --connect-timeout
    out = subprocess.run([*BODYNET, "game", "-e", no_router, "--http-port", "0", "--results",
                          str(tmp_path / "r"), "--connect-timeout", "0.2"],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert out.returncode == 2
    last = out.stderr.strip().splitlines()[-1]  # after the session's "waiting for ..."
    assert last.startswith("bodynet game: no router answered at tcp/127.0.0.1:1"), out
    assert "Traceback" not in out.stderr


# --- the whole chain in a real browser ---------------------------------------------------
def chromium() -> str:
    """The browser for the page tests; a missing one fails the test loudly."""
    for name in (os.environ.get("BODYNET_CHROMIUM"), "chromium", "chromium-browser",
                 "google-chrome", "google-chrome-stable"):  # fmt: skip
        if name and (path := shutil.which(name)):
            return path
    pytest.fail(
        "no Chromium for the browser tests of the game: run `make test` (it installs "
        "Debian's chromium with apt-get) or set BODYNET_CHROMIUM to a Chromium binary"
    )


class Proc:
    """A bodynet process whose stdout lines can be waited on."""

    def __init__(self, *args: str) -> None:
        self.popen = subprocess.Popen([*BODYNET, *args], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True)  # fmt: skip
        self.lines: queue.Queue[str] = queue.Queue()
        self.stderr = ""
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.put(line)

    def wait_line(self, prefix: str, timeout: float = 60.0) -> str:
        while True:
            try:
                line = self.lines.get(timeout=timeout)
            except queue.Empty:
                raise AssertionError(f"no line {prefix!r} from {self.popen.args}") from None
            if line.startswith(prefix):
                return line.strip()

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            _, self.stderr = self.popen.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            _, self.stderr = self.popen.communicate()
        return self.popen.returncode


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    yield started
    for p in started:
        p.stop(signal.SIGKILL)


def start_game(procs: list[Proc], tmp_path: Path, endpoint: str, *args: str) -> tuple[str, Proc]:
    """``bodynet game`` on a free port for the left arm; its page's URL once it serves."""
    game = Proc("game", "--arm", "left", "--http-port", "0", "--results", str(tmp_path / "res"),
                "-e", endpoint, *args)  # fmt: skip
    procs.append(game)
    url = game.wait_line("bodynet game: http://").removeprefix("bodynet game: ")
    return url, game


@pytest.fixture
def browser() -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    path = chromium()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=path, args=["--no-sandbox"])
        yield b
        b.close()


def open_page(browser: object, url: str, errors: list[str]) -> object:
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    return page


def text(page: object, selector: str) -> str:
    return str(page.text_content(selector))


def wait_js(page: Any, expression: str, timeout_s: float = 20.0) -> None:
    """Wait until ``expression`` holds in the page; on a timeout, say what the page shows."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_function(expression, timeout=timeout_s * 1000)
    except PlaywrightTimeout:
        shown = {s: page.text_content(s) for s in ("#state", "#arm-state", "#cue", "#target",
                                                   "#countdown", "#message", "#flash")}  # fmt: skip
        raise AssertionError(f"never true: {expression}; the page shows {shown}") from None


def wait_text(page: object, selector: str, test: str, timeout_s: float = 20.0) -> None:
    """Wait until ``document.querySelector(selector).textContent`` passes ``test`` (JS,
    of ``t``)."""
    wait_js(page, f"(() => {{ const e = document.querySelector({json.dumps(selector)}); "
                  f"if (!e) return false; const t = e.textContent; return {test}; }})()",
            timeout_s)  # fmt: skip


def saved(tmp_path: Path) -> list[dict[str, object]]:
    out = []
    for path in sorted((tmp_path / "res").glob("rehab-left-arm-*.json")):
        assert path.stat().st_mode & 0o777 == 0o600
        out.append({**json.loads(path.read_text()), "file": path.name})
    return out


class PosePublisher:
    """The left arm's branch poses, 50 a second, from the body model, published by a
    Zenoh router session of the test's own: ``angles``, ``flags`` and ``sending`` are
    changed on the fly."""

    def __init__(self, endpoint: str) -> None:
        from bodynet.session import open_session, session_config

        self.session = open_session(session_config("router", listen=[endpoint]))
        self.arm = FkArm("left")
        self.angles: dict[str, float] = {}
        self.flags: dict[str, str] = {}
        self.sending = threading.Event()
        self.sending.set()
        self._stop = threading.Event()
        key = keys.pose_key(keys.Branch(keys.Limb.ARM, keys.Side("left")))
        self._pub = self.session.declare_publisher(key)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        seq = 0
        while not self._stop.wait(0.02):  # the rate of the poses, not a wait for an event
            if self.sending.is_set():
                seq += 1
                self._pub.put(pose.encode(self.arm.frame(self.angles, seq, flags=self.flags)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._pub.undeclare()
        self.session.close()


def still_arm_trial(page: Any, publisher: PosePublisher, tmp_path: Path) -> None:
    """A still arm whose wrist flexion is held (not measured): countdowns, misses (the
    rest stop too), a lost signal, the wrist stop "not measured", the therapist's
    Stop; nothing reached, nothing saved before the trial ends."""
    assert text(page, "#file").startswith("not saved yet")
    assert saved(tmp_path) == []
    page.click("#start")
    # "1 / 9: Lift your arm forward" and the instruction: the label says what the cue says
    wait_text(
        page,
        "#target",
        "t.includes(' / 9: ') && t.endsWith(': ' + document.getElementById('cue').textContent)",
    )
    wait_text(page, "#countdown", "/^[0-9]+ s$/.test(t)")  # the countdown, in seconds
    wait_text(page, "#flash", "t === 'Missed'")
    page.screenshot(path=str(tmp_path / "missed.png"))
    # the signal is lost: the instruction gives way, the target waits
    publisher.sending.clear()
    page.wait_for_selector("#cue.lost")
    assert text(page, "#countdown") == "paused"
    lost_at = text(page, "#target")
    # lost for longer than a countdown: the target is still the same
    wait_text(page, "#arm-state", "t.startsWith('arm signal lost (2.')")
    assert text(page, "#target") == lost_at
    publisher.sending.set()
    page.wait_for_selector("#arm-state.ok")
    page.wait_for_selector("#cue:not(.lost)")
    # the still arm at a rest stop it is already at: not reached, missed
    wait_text(
        page, "#flash", "t === 'Missed' && document.getElementById('flash').dataset.i === '4'"
    )
    # the wrist's measurement is held: the game waits for one, then moves on
    wait_text(page, "#cue", "t === 'Waiting for a measurement of wrist flexion'")
    assert text(page, "#unmeasured") == "not measured now: wrist flexion"
    wait_text(page, "#flash", "t === 'Not measured (wrist flexion)'")
    assert text(page, "#file").startswith("not saved yet")
    page.click("#stop")
    row = page.wait_for_selector("#trials tr[data-complete='false']")
    assert "incomplete: stopped by the therapist" in row.text_content()
    wait_text(page, "#file", "t.startsWith('saved to ')")
    page.wait_for_selector("#flash", state="hidden")
    (first,) = saved(tmp_path)
    trial = first["trials"][0]  # type: ignore[index]
    assert (trial["complete"], trial["reason"], trial["score"]) == (
        False, "stopped by the therapist", 0)  # fmt: skip
    assert not any(x["reached"] for x in trial["targets"])
    assert [(x["outcome"], x["waited_for"]) for x in trial["targets"][:5]] == [
        *[("missed", [])] * 4, ("not measured", ["wrist_flexion"])]  # fmt: skip
    lost = int(lost_at.split(" / ")[0]) - 1  # the target whose signal was lost
    assert trial["targets"][lost]["paused_s"] > 1.5  # 2 s without a pose, less GAP_S
    assert trial["stale_s"] > 0.8  # the same, less STALE_S (and a tick)
    assert trial["rom_deg"]["shoulder_flexion"]["range"] == 0.0
    assert "wrist_flexion" not in trial["rom_deg"]  # never measured


def second_session(page: Any, publisher: PosePublisher, tmp_path: Path) -> None:
    """A new session for patient p2 without a restart: Start refused without a signal
    (the message clears when the signal is back), then a player who moves the arm to
    each stop when it is cued: every target reached, and the range of motion is the
    route's, exactly."""
    page.fill("#patient", "p2")
    page.click("#new-session")
    wait_text(page, "#state", "t === 'ready'")
    wait_text(page, "#file", "t.startsWith('not saved yet')")
    assert text(page, "#side") == "(p2, left arm)"
    assert page.query_selector_all("#trials tr") == []
    # Start without a signal is refused; the message goes when the signal is back
    publisher.sending.clear()
    page.wait_for_selector("#arm-state.bad")
    page.click("#start")
    wait_text(page, "#message", "t.includes('no live signal')")
    publisher.sending.set()
    wait_text(page, "#message", "t === ''")
    publisher.flags = {}
    page.click("#start")
    for i, target in enumerate(ROUTE, 1):
        wait_text(page, "#target", f"t.startsWith('{i} / 9: ')")
        publisher.angles = {f"left_{d}_deg": v for d, v in target.pose.items()}
    wait_text(page, "#state", "t === 'finished'")
    wait_text(page, "#cue", "t === 'Session complete. Thank you!'")
    wait_text(page, "#summary", "t.startsWith('1 complete trial (practice not counted), 1 "
                                "successful, 9 of 9 targets reached')")  # fmt: skip
    (result,) = [s for s in saved(tmp_path) if s["patient"] == "p2"]
    trial = result["trials"][0]  # type: ignore[index]
    assert [x["outcome"] for x in trial["targets"]] == ["reached"] * len(ROUTE)
    truth = {"shoulder_flexion": (0, 90), "shoulder_abduction": (0, 90),
             "shoulder_rotation": (0, 0), "elbow_flexion": (0, 90), "wrist_flexion": (0, 60),
             "elbow_pronation": (0, 60), "wrist_deviation": (0, 0)}  # fmt: skip
    rom = trial["rom_deg"]
    assert set(rom) == set(truth)
    for dof, (lo, hi) in truth.items():
        assert (rom[dof]["min"], rom[dof]["max"]) == pytest.approx((lo, hi), abs=0.01), dof
    # large print, for a player across the room
    size = "parseFloat(getComputedStyle(document.getElementById('cue')).fontSize)"
    normal = page.evaluate(size)
    page.click("#large")
    wait_js(page, "document.body.classList.contains('large')")
    assert page.evaluate(size) >= 2 * normal
    assert text(page, "#large") == "Normal print"
    page.screenshot(path=str(tmp_path / "large.png"))


def therapist_view(browser: Any, url: str, tmp_path: Path, errors: list[str]) -> None:
    """The therapist's view reads both sessions back from their files."""
    files = {s["patient"]: s["file"] for s in saved(tmp_path)}
    assert len(files) == 2
    view = open_page(browser, url + "therapist", errors)
    wait_text(view, "#status", "t === '2 sessions saved'")
    shown = [e.get_attribute("data-file") for e in view.query_selector_all("section.session")]
    assert sorted(shown) == sorted(files.values())
    assert "incomplete: stopped by the therapist" in text(
        view, f"section[data-file='{files['']}']")  # fmt: skip
    p2 = view.query_selector(f"section[data-file='{files['p2']}'] tbody tr")
    cells = [c.text_content() for c in p2.query_selector_all("td")]
    assert cells[:3] == ["1", "success", "9 / 9"]
    assert cells[-5:] == ["90.0", "90.0", "90.0", "60.0", "60.0"]  # the ranges, degrees
    days = {e.query_selector("td:nth-child(2)").text_content(): e.text_content()
            for e in view.query_selector_all("#days tr")}  # fmt: skip
    assert set(days) == {"–", "p2"}  # the session without a patient id, and p2's
    assert "9 / 9 (100 %)" in days["p2"]
    view.screenshot(path=str(tmp_path / "therapist.png"), full_page=True)


@pytest.mark.slow
@pytest.mark.timeout(150)
def test_browser_still_arm_countdown_miss_signal_loss_and_a_second_session(
    procs: list[Proc], browser: object, tmp_path: Path
) -> None:
    """Poses published here: the game waits for its router (and says so), a still arm
    sees every countdown run out (missed, score 0), a lost signal pauses the target and
    replaces the instruction, a held dof ends its target "not measured", the therapist
    stops the trial; then a second session without a restart, a moving arm whose
    ranges are the route's, and the therapist's view of both sessions."""
    from zenoh_helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    url, game = start_game(procs, tmp_path, endpoint, "--trials", "1", "--practice", "0",
                           "--target-timeout", "1.5")  # fmt: skip
    assert game.wait_line("bodynet game: waiting for the Zenoh router at ") == (
        f"bodynet game: waiting for the Zenoh router at {endpoint}")  # fmt: skip
    errors: list[str] = []
    page = open_page(browser, url, errors)
    wait_text(page, "#arm-state", "t.startsWith('waiting for the Zenoh router')")
    assert text(page, "#cue").startswith("Waiting for the Zenoh router")
    publisher = PosePublisher(endpoint)  # the router comes up, with a still arm
    publisher.flags = {"wrist_flexion": "held"}
    try:
        page.wait_for_selector("#arm-state.ok", timeout=30_000)
        still_arm_trial(page, publisher, tmp_path)
        second_session(page, publisher, tmp_path)
        therapist_view(browser, url, tmp_path, errors)
        assert errors == []
    finally:
        publisher.close()
    assert game.stop() == 0
    assert "Traceback" not in game.stderr
    assert "1 complete trial, score " in game.stderr


@pytest.mark.slow
@pytest.mark.timeout(150)
def test_browser_plays_the_real_chain_and_the_ranges_match_the_motion(
    procs: list[Proc], browser: object, tmp_path: Path
) -> None:
    """Gateway and an emulated SmartSuit arm doing the reach routine: a whole trial.
    A stop whose dofs the gateway flags unmeasured ends "not measured" (never reached
    or missed: the SmartSuit's tilt sensors may not see abduction with the arm lifted
    forward); the measured ranges stay within the routine's."""
    from zenoh_helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs.append(Proc("gateway", "-l", endpoint, "--branch", "left-arm"))
    procs.append(Proc("node", "smartsuit", "--branch", "left-arm", "--routine", "reach",
                      "--ideal", "-e", endpoint))  # fmt: skip
    url, game = start_game(procs, tmp_path, endpoint, "--trials", "1", "--practice", "0",
                           "--target-timeout", "3")  # fmt: skip
    errors: list[str] = []
    page = open_page(browser, url, errors)
    page.wait_for_selector("#arm-state.ok", timeout=60_000)
    page.click("#start")
    wait_text(page, "#state", "t === 'finished'", timeout_s=90)
    page.wait_for_selector("#trials tr")
    assert text(page, "#cue") == "Session complete. Thank you!"
    assert "1 complete trial (" in text(page, "#summary")
    page.screenshot(path=str(tmp_path / "finished.png"))
    assert errors == []
    assert game.stop() == 0
    assert "Traceback" not in game.stderr
    (result,) = saved(tmp_path)
    trial = result["trials"][0]  # type: ignore[index]
    outcomes = {x["outcome"] for x in trial["targets"]}
    assert outcomes <= {"reached", "missed", "not measured"}
    for x in trial["targets"]:  # only a measured target is reached or missed
        # a "not measured" stop waited for some dof; a reached one may have waited a
        # moment too (a tilt held near the vertical, measured again: issue 22)
        assert x["outcome"] != "not measured" or x["waited_for"], x
        assert x["reached"] == (x["outcome"] == "reached") == (x["time_to_target_s"] is not None)
    # which stops the arm meets in time depends on the routine's phase at Start (one
    # run of CI met a single one): at least one, and a score from it
    assert sum(x["reached"] for x in trial["targets"]) >= 1, trial["targets"]
    assert trial["score"] == sum(x["points"] for x in trial["targets"]) > 0
    # within the routine's truth (nodes/motion.py's reach); which of its peaks fall in
    # the trial depends on the phase at Start and on the load (a starved node skips
    # them), so only the envelope is checked here, the exact ranges with poses
    # published by the test. Wrist deviation is left out: this gateway's SmartSuit
    # arm shows up to 10 deg of it, measured, where the routine has none.
    truth = {"shoulder_flexion": (0, 90), "shoulder_abduction": (0, 90),
             "shoulder_rotation": (0, 0), "elbow_flexion": (0, 90),
             "wrist_flexion": (0, 60), "elbow_pronation": (-60, 60)}  # fmt: skip
    rom = trial["rom_deg"]
    for dof, (lo, hi) in truth.items():
        assert rom[dof]["samples"] > 100, rom[dof]
        assert lo - 3 <= rom[dof]["min"] <= rom[dof]["max"] <= hi + 3, (dof, rom[dof])
    assert max(r["range"] for r in rom.values()) >= 60  # the arm did move
