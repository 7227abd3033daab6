"""``bodynet game``: the arm-reaching rehabilitation game, served to a browser.

One process: an aiohttp server serves the player's page (``/``), the
therapist's view of past sessions (``/therapist``, data at ``/api/sessions``)
and a WebSocket at ``/ws`` (``clients/game_web/``, no CDN: everything comes
from the package). It serves at once, before the Zenoh session is open: while
it waits for its router the page says so. Then a Zenoh subscriber on the
arms' branch poses (``body/arm/<side>/pose``) feeds the game's rules
(``clients/rehab.py``).

WebSocket messages, JSON, one object per message, ``t`` says which:

- to the browser, 25 times a second: ``{"t": "state", "state": ..., "arm":
  {"pts": [shoulder, elbow, wrist, hand tip], "stale": bool, "age_s": ...,
  "deg": {...}, "unmeasured": [...]}, "ball": [x, y, z], "target": {...},
  "trial": {...}, "flash": {...}, "router": {...}, ...}``, points in metres
  from the live shoulder (world axes: +X forward, +Y left, +Z up);
  ``{"t": "results", ...}`` (the session summary, and ``file`` once it is
  saved) on connect and after every trial; ``{"t": "error", "message": ...,
  "cause": ...}`` when a request is refused.
- from the browser: ``{"t": "start"}`` (begin the next trial), ``{"t":
  "stop"}`` (the therapist stops the running trial; it is saved as incomplete,
  "stopped by the therapist") and ``{"t": "new_session", "patient": ...,
  "arm": ...}`` (end this session, its running trial saved as incomplete, and
  begin another, in a new file, for this patient and arm).

When the last browser disconnects during a trial, that trial is saved as
incomplete ("player disconnected") and the game waits for Start from a
browser that connects again. The results are rewritten after every trial,
atomically, owner-only (0600, health data): ``rehab-<side>-arm-<time>[-<patient>].json``
(the summary with every trial and target) and ``.csv`` (one row per trial).
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import io
import json
import logging
import os
import socket
import stat
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import zenoh
from aiohttp import WSMsgType, web

from bodynet.clients.rehab import GameError, RehabGame, arm_pose, check_patient
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError
from bodynet.core.skeleton import ARM_DOFS
from bodynet.session import SessionError, open_session

log = logging.getLogger(__name__)

WEB_DIR = Path(__file__).parent / "game_web"
FRAME_S = 0.04  # state to the browsers at 25 Hz


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all, readable by the owner
    only (a nameless file until it is whole: a failed or killed run leaves
    nothing beside it)."""
    from bodynet.session.outputs import atomic_file

    with atomic_file(path, newline="") as f:
        f.write(text)


def _mean_time(trial: dict[str, Any]) -> float | None:
    times = [x["time_to_target_s"] for x in trial["targets"] if x["time_to_target_s"] is not None]
    return round(sum(times) / len(times), 3) if times else None


def results_csv(summary: dict[str, Any]) -> str:
    """One row per trial: outcome, score, times-to-target and range of motion."""
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(["patient", "arm", "trial", "practice", "attempt", "complete", "reason",
                "success", "targets_reached", "targets_not_measured", "targets", "score",
                "duration_s", "mean_time_to_target_s", "stale_s",
                *(f"{d}_range_deg" for d in ARM_DOFS)])  # fmt: skip
    for t in summary["trials"]:
        mean = _mean_time(t)
        rom = [t["rom_deg"].get(d, {}).get("range", "") for d in ARM_DOFS]
        w.writerow([summary.get("patient", ""), summary["arm"], t["number"], t["practice"],
                    t.get("attempt", 1), t["complete"], t["reason"], t["success"],
                    sum(x["reached"] for x in t["targets"]),
                    sum(x.get("outcome") == "not measured" for x in t["targets"]),
                    len(t["targets"]), t["score"], t["duration_s"],
                    "" if mean is None else mean, t["stale_s"], *rom])  # fmt: skip
    return out.getvalue()


def results_dir_problem(directory: Path) -> str | None:
    """Why no results could be saved in ``directory``, or None: it is a writable
    folder, or the nearest of it and its parents that exists is. Nothing is
    made here: the folder is made when the first results are saved."""
    path = directory
    while True:
        try:
            is_dir = stat.S_ISDIR(path.stat().st_mode)
        except (FileNotFoundError, NotADirectoryError):  # not there, or under a file
            if path.parent == path:
                return f"{path} does not exist"
            path = path.parent
            continue
        except OSError as exc:
            return f"{path}: {exc.strerror or exc}"
        if not is_dir:
            return f"{path} is not a folder"
        if not os.access(path, os.W_OK | os.X_OK):
            return f"{path} is not writable"
        return None


class ResultsFile:
    """One session's results on disk, rewritten whole after every change; the
    folder (owner-only) is made when they are first saved."""

    def __init__(self, directory: Path, side: str, patient: str = "") -> None:
        stem = f"rehab-{side}-arm-{time.strftime('%Y%m%dT%H%M%S')}"
        if patient:
            stem += f"-{patient}"
        n = 1
        self.json_path = directory / f"{stem}.json"
        while self.json_path.exists():  # two sessions in one second
            n += 1
            self.json_path = directory / f"{stem}-{n}.json"
        self.csv_path = self.json_path.with_suffix(".csv")
        self.directory = directory
        self.written = 0  # the game's revision on disk; nothing before the first trial ends

    def save(self, game: RehabGame) -> None:
        from bodynet.session.outputs import OutputError

        summary = game.summary()
        try:
            self.directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        except OSError as exc:
            raise OutputError(f"cannot write results in {self.directory}: "
                              f"{exc.strerror or exc}") from None  # fmt: skip
        write_private(self.json_path, json.dumps(summary, indent=1) + "\n")
        write_private(self.csv_path, results_csv(summary))
        self.written = game.revision


def session_history(directory: Path) -> dict[str, Any]:
    """Every saved session in ``directory`` (``rehab-*.json``), newest first, with
    per-trial rows, and per patient, arm and day: trials, targets reached,
    time-to-target and the largest range of motion (deg) of each dof.
    Files that cannot be read are named in ``unreadable``."""
    sessions: list[dict[str, Any]] = []
    unreadable: list[str] = []
    for path in sorted(directory.glob("rehab-*.json")):
        try:
            data = json.loads(path.read_text())
            trials = [
                {
                    "number": t["number"],
                    "practice": bool(t["practice"]),
                    "attempt": t.get("attempt", 1),
                    "complete": bool(t["complete"]),
                    "reason": t["reason"],
                    "started_utc": t["started_utc"],
                    "reached": sum(bool(x["reached"]) for x in t["targets"]),
                    "not_measured": sum(x.get("outcome") == "not measured" for x in t["targets"]),
                    "targets": len(t["targets"]),
                    "score": t["score"],
                    "duration_s": t["duration_s"],
                    "mean_time_to_target_s": _mean_time(t),
                    "rom_deg": {d: v["range"] for d, v in t["rom_deg"].items()},
                }
                for t in data["trials"]
            ]
            sessions.append({
                "file": path.name,
                "patient": data.get("patient", ""),
                "arm": data["arm"],
                "started_utc": data.get("started_utc") or (
                    trials[0]["started_utc"] if trials else ""),
                "finished": bool(data["finished"]),
                "score": data["score"],
                "trials": trials,
            })  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            unreadable.append(f"{path.name}: {exc}")
    sessions.sort(key=lambda s: s["started_utc"], reverse=True)

    def new_day() -> dict[str, Any]:
        return {"sessions": 0, "trials": 0, "reached": 0, "targets": 0, "times": [], "rom_deg": {}}

    days: dict[tuple[str, str, str], dict[str, Any]] = defaultdict(new_day)
    for s in sessions:
        day = days[(s["patient"], s["arm"], s["started_utc"][:10])]
        day["sessions"] += 1
        for t in s["trials"]:
            if not t["complete"] or t["practice"]:
                continue
            day["trials"] += 1
            day["reached"] += t["reached"]
            day["targets"] += t["targets"]
            if t["mean_time_to_target_s"] is not None:
                day["times"].append(t["mean_time_to_target_s"])
            for d, r in t["rom_deg"].items():
                day["rom_deg"][d] = max(r, day["rom_deg"].get(d, r))
    by_day = []
    for (patient, arm, date), d in sorted(days.items(), key=lambda kv: kv[0][2], reverse=True):
        times = d.pop("times")
        by_day.append({"patient": patient, "arm": arm, "date": date, **d,
                       "mean_time_to_target_s":
                           round(sum(times) / len(times), 3) if times else None})  # fmt: skip
    return {"sessions": sessions, "days": by_day, "unreadable": unreadable,
            "units": {"rom_deg": "deg", "time": "s"}}  # fmt: skip


@dataclass(frozen=True)
class GameOptions:
    """What a new session is made with (``bodynet game``'s options)."""

    side: str = "left"
    trials: int = 10
    practice: int = 1
    radius_m: float = 0.12
    target_timeout_s: float = 20.0
    patient: str = ""

    def game(self) -> RehabGame:
        return RehabGame(self.side, self.trials, self.practice, self.radius_m,
                         self.target_timeout_s, patient=self.patient)  # fmt: skip


class GameServer:
    """The game, its Zenoh subscription and its web server, on one asyncio loop."""

    def __init__(self, options: GameOptions, results_dir: Path,
                 session: zenoh.Session | None = None) -> None:  # fmt: skip
        self.options = options
        self.game = options.game()
        self.results_dir = results_dir
        self.results = ResultsFile(results_dir, options.side, options.patient)
        self.session = session
        self.router: dict[str, Any] = {"connected": session is not None, "error": ""}
        self.clients: dict[web.WebSocketResponse, int] = {}  # -> results revision sent
        self.rejected = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._subs: list[Any] = []
        self.app = web.Application()
        self.app.add_routes([
            web.get("/", self._page("index.html")),
            web.get("/therapist", self._page("therapist.html")),
            web.get("/api/sessions", self._sessions),
            web.get("/ws", self._ws),
            web.static("/static", WEB_DIR),
        ])  # fmt: skip

    # --- Zenoh (its own thread) ---------------------------------------------------------
    def subscribe(self, session: zenoh.Session) -> list[str]:
        """Subscribe to both arms' poses (a new session may change arm)."""
        self.session = session
        out = []
        for side in ("left", "right"):
            key = keys.pose_key(keys.Branch(keys.Limb.ARM, keys.Side(side)))
            self._subs.append(session.declare_subscriber(key, self._on_pose(side)))
            out.append(key)
        return out

    def _on_pose(self, side: str) -> Callable[[zenoh.Sample], None]:
        def handler(sample: zenoh.Sample) -> None:
            game = self.game
            if game.side != side:
                return
            try:
                arm = arm_pose(pose.decode(sample.payload.to_bytes()), side)
            except (DecodeError, GameError) as exc:
                self.rejected += 1
                if self.rejected <= 3:
                    log.warning("game: not a pose of the %s arm: %s", side, exc)
                return
            loop = self._loop
            if loop is not None:
                with contextlib.suppress(RuntimeError):  # the loop is closing
                    loop.call_soon_threadsafe(self._pose_arrived, game, arm, time.monotonic())

        return handler

    def _pose_arrived(self, game: RehabGame, arm: Any, now: float) -> None:
        if game is self.game:  # not a pose that was on its way to the session before
            game.on_pose(arm, now)

    # --- web ---------------------------------------------------------------------------
    def _page(self, name: str) -> Callable[[web.Request], Any]:
        async def handler(request: web.Request) -> web.FileResponse:
            return web.FileResponse(WEB_DIR / name)

        return handler

    async def _sessions(self, request: web.Request) -> web.Response:
        history = await asyncio.get_running_loop().run_in_executor(
            None, session_history, self.results_dir
        )
        history["current"] = self.results.json_path.name if self.results.written else None
        return web.json_response(history)

    async def _ws(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=5.0)
        await ws.prepare(request)
        self.clients[ws] = -1  # the results go first, with the next state
        log.info("game: browser connected from %s", request.remote)
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._on_message(ws, msg.data)
        finally:
            self.clients.pop(ws, None)
            log.info("game: browser gone (%d left)", len(self.clients))
            if not self.clients and self.game.state in ("running", "rest"):
                self.game.abort(time.monotonic(), "player disconnected")
                self._save_if_changed()
        return ws

    async def _on_message(self, ws: web.WebSocketResponse, text: str) -> None:
        try:
            msg = json.loads(text)
            kind = msg.get("t")
        except (ValueError, AttributeError):
            msg, kind = {}, None
        try:
            if kind == "start":
                if not self.router["connected"]:
                    raise GameError("waiting for the Zenoh router: no arm signal yet", "signal")
                self.game.start(time.monotonic())
            elif kind == "stop":
                self.game.abort(time.monotonic(), "stopped by the therapist")
            elif kind == "new_session":
                self.new_session(str(msg.get("patient") or ""), msg.get("arm"))
            else:
                raise GameError(f"unknown request {text[:80]!r}")
        except GameError as exc:
            await ws.send_json({"t": "error", "message": str(exc), "cause": exc.cause})
        self._save_if_changed()

    def new_session(self, patient: str, arm: object = None) -> None:
        """End this session (its running trial saved as incomplete) and begin another,
        in a new file; ``GameError`` (and this session goes on) if it cannot be."""
        patient = check_patient(patient)
        side = str(arm) if arm in ("left", "right") else self.game.side
        if why := results_dir_problem(self.results_dir):
            raise GameError(f"cannot write results in {self.results_dir}: {why}", "results")
        results = ResultsFile(self.results_dir, side, patient)
        old = self.game
        old.abort(time.monotonic(), "new session started")
        self._save_if_changed()
        if results.json_path.exists():  # the old session's file, saved just now
            results = ResultsFile(self.results_dir, side, patient)
        self.options = replace(self.options, side=side, patient=patient)
        self.results = results
        self.game = self.options.game()
        if old.side == self.game.side:  # the arm's signal carries over
            self.game.arm, self.game.arm_at = old.arm, old.arm_at
        for ws in self.clients:
            self.clients[ws] = -1  # everyone gets the new (empty) results
        log.info("game: new session for %s's %s arm", patient or "(no id)", side)

    def _results_message(self) -> dict[str, Any]:
        saved = self.results.written > 0
        return {"t": "results", **self.game.summary(),
                "file": str(self.results.json_path) if saved else None}  # fmt: skip

    def _save_if_changed(self) -> None:
        if self.results.written != self.game.revision:
            self.results.save(self.game)

    async def _broadcast(self) -> None:
        now = time.monotonic()
        self.game.tick(now)
        self._save_if_changed()
        if self.clients:
            state = self.game.snapshot(now)
            state["router"] = self.router
            text = json.dumps(state, separators=(",", ":"))
            await asyncio.gather(*(self._send_to(ws, text) for ws in list(self.clients)))

    async def _send_to(self, ws: web.WebSocketResponse, state: str) -> None:
        with contextlib.suppress(ConnectionError, RuntimeError):  # closing under us
            if self.clients.get(ws) != self.game.revision:
                self.clients[ws] = self.game.revision
                await ws.send_str(json.dumps(self._results_message(), separators=(",", ":")))
            await ws.send_str(state)

    async def serve(self, sock: socket.socket, host: str, stop: threading.Event,
                    announce: Callable[[str], None],
                    connect: Callable[[], zenoh.Session] | None = None) -> None:  # fmt: skip
        """Serve on ``sock`` until ``stop`` is set; ``announce(url)`` once serving.
        With ``connect``, the Zenoh session is opened by it meanwhile (waiting for
        its router); a ``SessionError`` from it ends the serving and is raised."""
        self._loop = asyncio.get_running_loop()
        runner = web.AppRunner(self.app, handle_signals=False, access_log=None)
        await runner.setup()
        opened: asyncio.Future[zenoh.Session] | None = None
        try:
            await web.SockSite(runner, sock).start()
            announce(f"http://{_url_host(host)}:{sock.getsockname()[1]}/")
            if self.session is not None:
                self.subscribe(self.session)
            elif connect is not None:
                opened = self._open_in_thread(connect)
            while not stop.is_set():
                if opened is not None and opened.done():
                    self.subscribe(opened.result())  # a SessionError is raised here
                    self.router["connected"] = True
                    log.info("game: connected to the router")
                    opened = None
                await self._broadcast()
                await asyncio.sleep(FRAME_S)
            self.game.abort(time.monotonic(), "game stopped")
            self._save_if_changed()
            for ws in list(self.clients):
                await ws.close()
        finally:
            for sub in self._subs:
                sub.undeclare()
            self._loop = None
            await runner.cleanup()

    def _open_in_thread(self, connect: Callable[[], zenoh.Session]) -> asyncio.Future[Any]:
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()

        def done(result: Any, error: BaseException | None) -> None:
            if not future.done():
                (future.set_exception(error) if error else future.set_result(result))

        def target() -> None:
            try:
                session = connect()
            except SessionError as exc:
                loop.call_soon_threadsafe(done, None, exc)
            else:
                loop.call_soon_threadsafe(done, session, None)

        # a daemon: Ctrl-C while waiting for the router ends the process (see
        # session.open_session and cli.nodes.stop_on_signals)
        threading.Thread(target=target, name="game-connect", daemon=True).start()
        return future


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def listen_socket(host: str, port: int) -> socket.socket:
    """The page's listening socket, bound before anything else starts (``OSError``
    if the address is taken or not this machine's); port 0 picks a free one."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    return socket.create_server((host, port), family=family)


def run_game(conf: zenoh.Config, stop: threading.Event, options: GameOptions,
             results_dir: Path, sock: socket.socket, host: str,
             announce: Callable[[str], None]) -> GameServer:  # fmt: skip
    """Serve the game on ``sock`` until ``stop`` is set, saving under ``results_dir``;
    the Zenoh session (``conf``) opens meanwhile. ``SessionError`` if it cannot."""
    server = GameServer(options, results_dir)
    try:
        asyncio.run(server.serve(sock, host, stop, announce, lambda: open_session(conf)))
    finally:
        if server.session is not None:
            server.session.close()
    return server
