"""The rehabilitation game: its rules, its results file, and the whole chain in a real
browser (gateway and emulated arm as processes, ``bodynet game``, headless Chromium).

The browser tests need Chromium: ``make test`` installs Debian's ``chromium`` when none
is there; ``BODYNET_CHROMIUM`` names another binary. Without one they FAIL, on purpose:
the game's page is tested in a real browser or not at all.
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

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bodynet.clients.game import ResultsFile, results_csv
from bodynet.clients.rehab import (
    ROUTE,
    STALE_S,
    GameError,
    RehabGame,
    arm_pose,
    route_offsets,
)
from bodynet.core.codecs.pose import PoseFrame
from bodynet.core.skeleton import DEFAULT_LENGTHS, build_skeleton
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

    def frame(self, angles: dict[str, float], seq: int = 0, stale: bool = False) -> PoseFrame:
        rot, pos = self.model.frame_placements(self.model.q(angles), self.frames)
        hand_q = Rotation.from_matrix(rot[2]).as_quat(scalar_first=True)
        s = self.side
        joints = {
            f"{s}_{j}": tuple(p) for j, p in zip(("shoulder", "elbow", "wrist"), pos, strict=True)
        }
        return PoseFrame(
            seq, 0, {n: v for n, v in angles.items() if n.startswith(s)}, {},
            {f"{s}_hand": (tuple(pos[2]), tuple(hand_q))}, joints,  # type: ignore[dict-item]
            stale=[f"body/arm/{s}/elbow/raw"] if stale else [],
        )  # fmt: skip


def test_route_is_the_seed_procedure_in_front_of_the_shoulder() -> None:
    left = route_offsets("left", 0.293, 0.265)
    right = route_offsets("right", 0.293, 0.265)
    names = [t.name for t in ROUTE]
    np.testing.assert_allclose(left[names.index("lift")], [ARM, 0, 0], atol=1e-9)  # forward
    np.testing.assert_allclose(left[names.index("rest")], [0, 0, -ARM], atol=1e-9)  # down
    np.testing.assert_allclose(left[names.index("side")], [0, ARM, 0], atol=1e-9)  # out left
    np.testing.assert_allclose(right[names.index("side")], [0, -ARM, 0], atol=1e-9)  # out right
    up = left[names.index("bend-elbow")]  # forearm and hand straight up from the elbow
    np.testing.assert_allclose(up, [0.293, 0, ARM - 0.293], atol=1e-9)
    # a longer arm moves the balls out with it
    assert route_offsets("left", 0.35, 0.30)[0][0] > left[0][0]


@pytest.mark.parametrize("side", ["left", "right"])
def test_arm_doing_the_reach_routine_completes_every_trial(side: str) -> None:
    arm = FkArm(side)
    routine = reach(side)
    game = RehabGame(side, trials=1, practice=1)
    t, dt = 0.0, 0.02
    game.on_pose(arm_pose(arm.frame(routine(t)), side), t)
    game.start(t)
    while game.state != "finished" and t < 4 * REACH_PERIOD_S:
        t += dt
        game.on_pose(arm_pose(arm.frame(routine(t)), side), t)
        game.tick(t)
    assert game.state == "finished"
    summary = game.summary()
    assert [(x["practice"], x["complete"], x["success"]) for x in summary["trials"]] == [
        (True, True, True), (False, True, True)]  # fmt: skip
    for trial in summary["trials"]:
        assert [x["name"] for x in trial["targets"]] == [x.name for x in ROUTE]
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


def test_a_still_arm_misses_its_targets_and_the_trial_fails() -> None:
    arm = FkArm("left")
    game = RehabGame("left", trials=1, target_timeout_s=2.0)
    game.on_pose(arm_pose(arm.frame({}), "left"), 0.0)
    game.start(0.0)
    t = 0.0
    while game.state != "finished" and t < 60:
        t += 0.05
        game.on_pose(arm_pose(arm.frame({}), "left"), t)
        game.tick(t)
    trial = game.summary()["trials"][0]
    assert trial["complete"]
    assert not trial["success"]
    reached = [x["name"] for x in trial["targets"] if x["reached"]]
    assert reached == ["rest", "rest", "rest"]  # where the arm hangs
    assert all(x["time_to_target_s"] is None for x in trial["targets"] if not x["reached"])


def test_interruptions_and_a_stale_arm() -> None:
    arm = FkArm("left")
    game = RehabGame("left", trials=1)
    with pytest.raises(GameError, match="no live signal"):
        game.start(0.0)
    game.on_pose(arm_pose(arm.frame({}), "left"), 0.0)
    game.start(0.0)
    with pytest.raises(GameError, match="already running"):
        game.start(0.1)
    game.abort(1.0, "player disconnected")
    assert game.state == "paused"
    first = game.summary()["trials"][0]
    assert (first["complete"], first["reason"], first["success"]) == (
        False, "player disconnected", False)  # fmt: skip
    # the arm falls silent: stale, counted in the trial, and no new trial can start
    game.on_pose(arm_pose(arm.frame({}), "left"), 2.0)
    game.start(2.0)
    game.tick(2.0)
    game.tick(2.0 + STALE_S + 1.0)
    assert game.snapshot(2.0 + STALE_S + 1.0)["arm"]["stale"] is True
    game.abort(4.0, "game stopped")
    assert game.summary()["trials"][1]["stale_s"] == pytest.approx(STALE_S + 1.0 - STALE_S, abs=1)
    with pytest.raises(GameError, match="no live signal"):
        game.start(5.0)
    # the gateway flagging the arm's sensors stale counts too, and such poses never reach
    game.on_pose(arm_pose(arm.frame({}, stale=True), "left"), 6.0)
    assert not game.arm_live(6.0)
    with pytest.raises(GameError, match="the pose has no right arm"):
        arm_pose(arm.frame({}), "right")


def test_results_are_owner_only_json_and_csv(tmp_path: Path) -> None:
    arm = FkArm("left")
    game = RehabGame("left", trials=1)
    game.on_pose(arm_pose(arm.frame({"left_shoulder_flexion_deg": 30.0}), "left"), 0.0)
    game.start(0.0)
    game.on_pose(arm_pose(arm.frame({"left_shoulder_flexion_deg": 50.0}), "left"), 0.5)
    game.abort(1.0, "aborted by the player")
    results = ResultsFile(tmp_path / "res", "left")
    results.save(game)
    for path in (results.json_path, results.csv_path):
        assert path.stat().st_mode & 0o777 == 0o600
    assert (tmp_path / "res").stat().st_mode & 0o777 == 0o700
    saved = json.loads(results.json_path.read_text())
    assert saved["trials"][0]["rom_deg"]["shoulder_flexion"] == {
        "min": 30.0, "max": 50.0, "range": 20.0}  # fmt: skip
    rows = list(csv.DictReader(results.csv_path.open()))
    assert rows[0]["reason"] == "aborted by the player"
    assert float(rows[0]["shoulder_flexion_range_deg"]) == 20.0
    assert results_csv(saved) == results.csv_path.read_bytes().decode()
    assert not list((tmp_path / "res").glob("*.part"))


def test_bad_options_are_refused_cleanly() -> None:
    out = subprocess.run([*BODYNET, "game", "--trials", "0"], capture_output=True, text=True,
                         timeout=60, check=False)  # fmt: skip
    assert out.returncode == 2
    assert "argument --trials: '0' is outside 1..1000" in out.stderr
    assert "Traceback" not in out.stderr


def test_a_taken_port_or_unwritable_results_are_told_at_once(tmp_path: Path) -> None:
    no_router = "tcp/127.0.0.1:1"  # never reached: the mistakes are told before that
    (tmp_path / "file").write_text("")
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = str(taken.getsockname()[1])
        for args, told in (
            (["--http-port", port, "--results", str(tmp_path / "r")], "cannot serve on"),
            (["--http-port", "0", "--results", str(tmp_path / "file" / "r")],
             "argument --results: cannot write"),
        ):  # fmt: skip
            out = subprocess.run([*BODYNET, "game", "-e", no_router, *args], capture_output=True,
                                 text=True, timeout=60, check=False)  # fmt: skip
            assert out.returncode == 2
            assert told in out.stderr
            assert "Traceback" not in out.stderr
            assert out.stdout == ""


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


def start_stack(procs: list[Proc], tmp_path: Path, *game_args: str) -> tuple[str, Proc, Proc]:
    """Gateway (router on a free port), an emulated left arm doing the reach routine,
    and the game; returns the page's URL, the arm's process and the game's."""
    from zenoh_helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs.append(Proc("gateway", "-l", endpoint, "--branch", "left-arm"))
    arm = Proc("node", "smartsuit", "--branch", "left-arm", "--routine", "reach", "--ideal",
               "-e", endpoint)  # fmt: skip
    procs.append(arm)
    game = Proc("game", "--arm", "left", "--http-port", "0", "--results", str(tmp_path / "res"),
                "-e", endpoint, *game_args)  # fmt: skip
    procs.append(game)
    url = game.wait_line("bodynet game: http://").removeprefix("bodynet game: ")
    return url, arm, game


@pytest.fixture
def browser() -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    path = chromium()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=path, args=["--no-sandbox"])
        yield b
        b.close()


def text(page: object, selector: str) -> str:
    return str(page.text_content(selector))  # type: ignore[attr-defined]


def _results(tmp_path: Path) -> dict[str, object]:
    (path,) = (tmp_path / "res").glob("rehab-left-arm-*.json")
    assert path.stat().st_mode & 0o777 == 0o600
    return json.loads(path.read_text())  # type: ignore[no-any-return]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_browser_plays_a_session_through_a_reconnect(
    procs: list[Proc], browser: object, tmp_path: Path
) -> None:
    url, _, game = start_stack(procs, tmp_path, "--trials", "1", "--practice", "1")
    page = browser.new_page()  # type: ignore[attr-defined]
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector("#arm-state.ok", timeout=30_000)  # the arm's poses arrive
    page.click("#start")
    page.wait_for_function("document.getElementById('state').textContent === 'running'")
    # the player reaches a first ball, then the browser goes away mid-trial
    page.wait_for_function("Number(document.getElementById('score').textContent) > 0",
                           timeout=2 * REACH_PERIOD_S * 1000)  # fmt: skip
    page.close()
    page = browser.new_page()  # type: ignore[attr-defined]
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    row = page.wait_for_selector("#trials tr[data-complete='false']", timeout=10_000)
    assert "incomplete: player disconnected" in row.text_content()
    assert text(page, "#state") == "paused"
    page.click("#start")
    page.wait_for_function("document.getElementById('state').textContent === 'finished'",
                           timeout=4 * REACH_PERIOD_S * 1000)  # fmt: skip
    page.wait_for_selector("#trials tr:nth-child(3)")
    assert "session finished" in text(page, "#summary")
    page.screenshot(path=str(tmp_path / "finished.png"))
    assert errors == []

    assert game.stop() == 0
    assert "Traceback" not in game.stderr
    saved = _results(tmp_path)
    trials = saved["trials"]
    assert isinstance(trials, list)
    assert [(t["practice"], t["complete"], t["reason"]) for t in trials] == [
        (True, False, "player disconnected"), (True, True, ""), (False, True, "")]  # fmt: skip
    assert sum(x["reached"] for x in trials[0]["targets"]) >= 1
    for trial in trials[1:]:
        assert trial["success"], trial
        assert all(x["time_to_target_s"] > 0 for x in trial["targets"])
        assert trial["score"] >= 10 * len(ROUTE)
        rom = trial["rom_deg"]
        assert rom["shoulder_flexion"]["range"] > 80  # the emulated arm lifts to 90
        assert rom["shoulder_abduction"]["range"] > 80
        assert rom["elbow_flexion"]["range"] > 80
        assert rom["wrist_flexion"]["max"] >= 45
        assert trial["poses"] > 500
    assert saved["finished"] is True
    assert (saved["complete_trials"], saved["successful_trials"]) == (1, 1)
    assert saved["score"] == trials[2]["score"]
    (csv_path,) = (tmp_path / "res").glob("rehab-left-arm-*.csv")
    rows = list(csv.DictReader(csv_path.open()))
    assert [r["complete"] for r in rows] == ["False", "True", "True"]
    assert csv_path.stat().st_mode & 0o777 == 0o600


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_browser_shows_a_stale_arm_when_the_node_dies(
    procs: list[Proc], browser: object, tmp_path: Path
) -> None:
    url, arm, game = start_stack(procs, tmp_path, "--trials", "1", "--practice", "0")
    page = browser.new_page()  # type: ignore[attr-defined]
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector("#arm-state.ok", timeout=30_000)
    page.click("#start")
    page.wait_for_function("document.getElementById('state').textContent === 'running'")
    arm.stop(signal.SIGKILL)  # the sensors' process dies: no more poses of the arm
    page.wait_for_function(
        "document.getElementById('arm-state').textContent.startsWith('arm signal lost')",
        timeout=15_000,
    )
    assert text(page, "#state") == "running"  # the game goes on
    page.screenshot(path=str(tmp_path / "stale.png"))
    page.click("#abort")
    row = page.wait_for_selector("#trials tr[data-complete='false']", timeout=10_000)
    assert "aborted by the player" in row.text_content()
    page.click("#start")  # refused while the arm is stale, with a message
    page.wait_for_function(
        "document.getElementById('message').textContent.includes('no live signal')"
    )
    assert game.popen.poll() is None  # still serving
    assert errors == []
    assert game.stop() == 0
    assert "Traceback" not in game.stderr
    trial = _results(tmp_path)["trials"][0]  # type: ignore[index]
    assert trial["complete"] is False
    assert trial["stale_s"] > 0
