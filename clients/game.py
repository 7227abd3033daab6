"""``bodynet game``: the arm-reaching rehabilitation game, served to a browser.

One process: a Zenoh subscriber on ONE key, the chosen arm's branch pose
(``body/arm/<side>/pose``), feeds the game's rules (``clients/rehab.py``); an
aiohttp server serves the page (``clients/game_web/``, no CDN: everything
comes from the package) and a WebSocket at ``/ws``.

WebSocket messages, JSON, one object per message, ``t`` says which:

- to the browser, 25 times a second: ``{"t": "state", "state": ..., "arm":
  {"pts": [shoulder, elbow, wrist, hand tip], "stale": bool, "age_s": ...,
  "deg": {...}}, "ball": [x, y, z], "target": {...}, "trial": {...}, ...}``,
  points in metres from the live shoulder (world axes: +X forward, +Y left,
  +Z up); ``{"t": "results", ...}`` (the session summary) on connect and
  after every trial; ``{"t": "error", "message": ...}`` when a request is
  refused.
- from the browser: ``{"t": "start"}`` (begin the next trial) and
  ``{"t": "abort"}`` (stop the running trial; it is saved as incomplete).

When the last browser disconnects during a trial, that trial is saved as
incomplete ("player disconnected") and the game waits for Start from a
browser that connects again. The results are rewritten after every trial,
atomically, owner-only (0600, health data): ``rehab-<side>-arm-<time>.json``
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
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh
from aiohttp import WSMsgType, web

from bodynet.clients.rehab import GameError, RehabGame, arm_pose
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError
from bodynet.core.skeleton import ARM_DOFS

log = logging.getLogger(__name__)

WEB_DIR = Path(__file__).parent / "game_web"
FRAME_S = 0.04  # state to the browsers at 25 Hz


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically, readable by the owner only."""
    tmp = path.with_name(path.name + ".part")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", newline="") as f:
        f.write(text)
    tmp.replace(path)


def results_csv(summary: dict[str, Any]) -> str:
    """One row per trial: outcome, score, times-to-target and range of motion."""
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(["trial", "practice", "complete", "reason", "success", "targets_reached",
                "targets", "score", "duration_s", "mean_time_to_target_s", "stale_s",
                *(f"{d}_range_deg" for d in ARM_DOFS)])  # fmt: skip
    for t in summary["trials"]:
        times = [x["time_to_target_s"] for x in t["targets"] if x["time_to_target_s"] is not None]
        mean = round(sum(times) / len(times), 3) if times else ""
        rom = [t["rom_deg"].get(d, {}).get("range", "") for d in ARM_DOFS]
        w.writerow([t["number"], t["practice"], t["complete"], t["reason"], t["success"],
                    sum(x["reached"] for x in t["targets"]), len(t["targets"]), t["score"],
                    t["duration_s"], mean, t["stale_s"], *rom])  # fmt: skip
    return out.getvalue()


class ResultsFile:
    """The session's results on disk, rewritten whole after every change."""

    def __init__(self, directory: Path, side: str) -> None:
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        stem = f"rehab-{side}-arm-{time.strftime('%Y%m%dT%H%M%S')}"
        self.json_path = directory / f"{stem}.json"
        self.csv_path = directory / f"{stem}.csv"
        self.written = 0  # the game's revision on disk; nothing before the first trial ends

    def save(self, game: RehabGame) -> None:
        summary = game.summary()
        write_private(self.json_path, json.dumps(summary, indent=1) + "\n")
        write_private(self.csv_path, results_csv(summary))
        self.written = game.revision


class GameServer:
    """The game, its Zenoh subscription and its web server, on one asyncio loop."""

    def __init__(self, session: zenoh.Session, game: RehabGame, results: ResultsFile) -> None:
        self.session = session
        self.game = game
        self.results = results
        self.clients: dict[web.WebSocketResponse, int] = {}  # -> results revision sent
        self.rejected = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sub: Any = None
        self.app = web.Application()
        self.app.add_routes([
            web.get("/", self._index),
            web.get("/ws", self._ws),
            web.static("/static", WEB_DIR),
        ])  # fmt: skip

    # --- Zenoh (its own thread) ---------------------------------------------------------
    def subscribe(self, loop: asyncio.AbstractEventLoop) -> str:
        self._loop = loop
        key = keys.pose_key(keys.Branch(keys.Limb.ARM, keys.Side(self.game.side)))
        self._sub = self.session.declare_subscriber(key, self._on_pose)
        return key

    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            arm = arm_pose(pose.decode(sample.payload.to_bytes()), self.game.side)
        except (DecodeError, GameError) as exc:
            self.rejected += 1
            if self.rejected <= 3:
                log.warning("game: not a pose of the %s arm: %s", self.game.side, exc)
            return
        loop = self._loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closing
                loop.call_soon_threadsafe(self.game.on_pose, arm, time.monotonic())

    # --- web ---------------------------------------------------------------------------
    async def _index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(WEB_DIR / "index.html")

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
            kind = json.loads(text).get("t")
        except (ValueError, AttributeError):
            kind = None
        try:
            if kind == "start":
                self.game.start(time.monotonic())
            elif kind == "abort":
                self.game.abort(time.monotonic(), "aborted by the player")
            else:
                raise GameError(f"unknown request {text[:80]!r}")
        except GameError as exc:
            await ws.send_json({"t": "error", "message": str(exc)})
        self._save_if_changed()

    def _results_message(self) -> dict[str, Any]:
        return {"t": "results", **self.game.summary(), "file": str(self.results.json_path)}

    def _save_if_changed(self) -> None:
        if self.results.written != self.game.revision:
            self.results.save(self.game)

    async def _broadcast(self) -> None:
        now = time.monotonic()
        self.game.tick(now)
        self._save_if_changed()
        if self.clients:
            text = json.dumps(self.game.snapshot(now), separators=(",", ":"))
            await asyncio.gather(*(self._send_to(ws, text) for ws in list(self.clients)))

    async def _send_to(self, ws: web.WebSocketResponse, state: str) -> None:
        with contextlib.suppress(ConnectionError, RuntimeError):  # closing under us
            if self.clients.get(ws) != self.game.revision:
                self.clients[ws] = self.game.revision
                await ws.send_str(json.dumps(self._results_message(), separators=(",", ":")))
            await ws.send_str(state)

    async def serve(self, sock: socket.socket, host: str, stop: threading.Event,
                    announce: Callable[[str], None]) -> None:  # fmt: skip
        """Serve on ``sock`` until ``stop`` is set; ``announce(url)`` once serving."""
        key = self.subscribe(asyncio.get_running_loop())
        runner = web.AppRunner(self.app, handle_signals=False, access_log=None)
        await runner.setup()
        try:
            await web.SockSite(runner, sock).start()
            log.info("game: subscribed to %s", key)
            announce(f"http://{_url_host(host)}:{sock.getsockname()[1]}/")
            while not stop.is_set():
                await self._broadcast()
                await asyncio.sleep(FRAME_S)
            self.game.abort(time.monotonic(), "game stopped")
            self._save_if_changed()
            for ws in list(self.clients):
                await ws.close()
        finally:
            if self._sub is not None:
                self._sub.undeclare()
            self._loop = None
            await runner.cleanup()


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def listen_socket(host: str, port: int) -> socket.socket:
    """The page's listening socket, bound before anything else starts (``OSError``
    if the address is taken or not this machine's); port 0 picks a free one."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    return socket.create_server((host, port), family=family)


def run_game(session: zenoh.Session, stop: threading.Event, game: RehabGame,
             results: ResultsFile, sock: socket.socket, host: str,
             announce: Callable[[str], None]) -> RehabGame:  # fmt: skip
    """Serve the game on ``sock`` until ``stop`` is set, saving to ``results``."""
    server = GameServer(session, game, results)
    asyncio.run(server.serve(sock, host, stop, announce))
    return game
