"""Zenoh sessions for every bodynet process: the standard flags and defaults.

Every service takes the same session flags as the zenoh-python examples:
``--mode``, ``-e/--connect``, ``-l/--listen``, ``-c/--config`` and
``--cfg KEY:VALUE``. Precedence: command line, then environment
(``BODYNET_ZENOH_CONFIG`` names a config file, ``BODYNET_ZENOH_CONNECT`` a
comma-separated list of endpoints), then the config file, then bodynet's
defaults: client mode towards the gateway's router on ``tcp/127.0.0.1:7447``,
multicast scouting off (endpoints are explicit), waiting for the router if it
is not up yet (saying so, and giving up after ``--connect-timeout``, default
30 s) and reconnecting quickly when it comes back. A config file's mode
stands unless ``--mode`` is given.

``--subject NAME`` (or ``BODYNET_SUBJECT``) runs the session in the Zenoh
namespace ``NAME``: the process keeps using ``body/...`` keys while the
network carries ``NAME/body/...``, so several subjects share one router.

Zenoh itself is imported when a session is configured, not with this module,
so that parsing a command's flags (``bodynet --help``) stays quick.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bodynet.core.keys import KeySpaceError, subject_name
from bodynet.session import argtypes

if TYPE_CHECKING:  # zenoh loads only when a session is made, not for --help
    import zenoh

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
MODES = ("client", "peer", "router")
#: How long a client waits for its router by default before it gives up.
DEFAULT_CONNECT_TIMEOUT_S = 30.0
#: Zenoh's runtime unless ``ZENOH_RUNTIME`` says otherwise (Zenoh's own
#: example): receiving (``rx``) and accepting (``acc``) run on the two ``app``
#: threads instead of threads of their own, so a sample reaches its subscriber
#: without a hand-off between threads: about 40% less CPU to receive one body
#: (docs/benchmarks.md, "Zenoh's runtime"). Two, not one: with one, a flood
#: sent BLOCK lost samples (likely a subscriber's full queue blocking the only
#: thread, and with it every link of the process).
ZENOH_RUNTIME = "(rx: (handover: app), acc: (handover: app), app: (worker_threads: 2))"


def add_session_args(parser: argparse.ArgumentParser, default_mode: str = "client") -> None:
    """Add the standard Zenoh session flags to ``parser``."""
    group = parser.add_argument_group("Zenoh session")
    group.add_argument("--mode", choices=MODES, default=None,
                       help=f"session mode (default: {default_mode})")  # fmt: skip
    group.add_argument(
        "-e",
        "--connect",
        action="append",
        default=[],
        type=argtypes.endpoint,
        metavar="ENDPOINT",
        help=f"endpoint to connect to (default for a client: {DEFAULT_ROUTER})",
    )
    group.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                       type=argtypes.endpoint, help="endpoint to listen on")  # fmt: skip
    group.add_argument("-c", "--config", type=argtypes.input_file, default=None,
                       help="Zenoh JSON5 config file (its mode stands unless --mode)")  # fmt: skip
    group.add_argument(
        "--cfg",
        action="append",
        default=[],
        type=_cfg_arg,
        metavar="KEY:VALUE",
        help="a config entry, VALUE in JSON5, e.g. --cfg 'scouting/multicast/enabled:true'",
    )
    group.add_argument(
        "--connect-timeout",
        type=argtypes.bounded_float(0.1, 86_400.0, "seconds, at most a day"),
        default=None,
        metavar="SECONDS",
        help=f"a client gives up if its router does not answer within this time "
        f"(default {DEFAULT_CONNECT_TIMEOUT_S:g} s; it says it is waiting meanwhile)",
    )
    group.add_argument(
        "--subject",
        default=None,
        type=_subject_arg,
        help="run in this subject's namespace (keys stay body/...; default: none, "
        "or $BODYNET_SUBJECT)",
    )
    parser.set_defaults(zenoh_default_mode=default_mode)


def _cfg_arg(text: str) -> str:
    key, sep, value = text.partition(":")
    if not sep or not value.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not KEY:VALUE (VALUE in JSON5)")
    if not all(part and all(c.isalnum() or c in "_-" for c in part) for part in key.split("/")):
        raise argparse.ArgumentTypeError(f"{key!r} is not a config key like connect/endpoints")
    return text


def _subject_arg(text: str) -> str:
    try:
        return subject_name(text)
    except KeySpaceError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def session_config(
    mode: str | None = "client",
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: Path | None = None,
    entries: Sequence[str] = (),
    subject: str | None = None,
    *,
    default_mode: str = "client",
    connect_timeout_s: float | None = None,
) -> zenoh.Config:
    """A Zenoh config from explicit arguments (see the module docstring).

    ``mode`` None: the config file's mode if it names one, else ``default_mode``
    (a config's mode stands unless a flag says otherwise). A client waits for
    its router up to ``connect_timeout_s`` (default
    :data:`DEFAULT_CONNECT_TIMEOUT_S`), then :func:`open_session` gives up."""
    import zenoh

    env_file = os.environ.get("BODYNET_ZENOH_CONFIG")
    path = config_file or (Path(env_file) if env_file else None)
    try:
        conf = zenoh.Config.from_file(str(path)) if path else zenoh.Config()
    except zenoh.ZError as exc:
        said, where = _zenoh_error(exc)
        at = f", line {where[0]}, column {where[1]}" if where else ""
        raise SessionError(f"cannot use Zenoh config {path}{at}: {said}") from None
    if mode is None:
        mode = _file_mode(conf) or default_mode
    if not connect and (env_connect := os.environ.get("BODYNET_ZENOH_CONNECT")):
        connect = [_from_env("BODYNET_ZENOH_CONNECT", argtypes.endpoint, e.strip())
                   for e in env_connect.split(",") if e.strip()]  # fmt: skip
    if not connect and not path and mode == "client":
        connect = [DEFAULT_ROUTER]

    def put(key: str, value: Any) -> None:
        try:
            conf.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:  # e.g. an endpoint from BODYNET_ZENOH_CONNECT
            raise SessionError(f"bad Zenoh session option {key}: {_one_line(exc)}") from None

    if not path:
        put("scouting/multicast/enabled", False)
        put("connect/retry", {"period_init_ms": 100, "period_max_ms": 500})
    put("mode", mode)
    timeout_s = DEFAULT_CONNECT_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
    put("connect/timeout_ms", round(timeout_s * 1000) if mode == "client" else 0)
    if connect:
        put("connect/endpoints", list(connect))
    if listen:
        put("listen/endpoints", list(listen))
    if not subject and (env_subject := os.environ.get("BODYNET_SUBJECT")):
        subject = _from_env("BODYNET_SUBJECT", _subject_arg, env_subject)
    if subject:
        put("namespace", subject_name(subject))
    for entry in entries:
        key, sep, value = entry.partition(":")
        if not sep:
            raise SessionError(f"--cfg wants KEY:VALUE, not {entry!r}")
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as exc:  # a parser's column; serde's location is the value's start
            said, where = _zenoh_error(exc)
            at = f" (column {where[1]} of the value)" if where and where[1] > 1 else ""
            raise SessionError(f"--cfg {entry!r}{at}: {said}") from None
    return conf


def _from_env(name: str, check: Callable[[str], str], text: str) -> str:
    """``text``, from the environment variable ``name``, checked as its flag's value is."""
    try:
        return check(text)
    except argparse.ArgumentTypeError as exc:
        raise SessionError(f"environment variable {name}: {exc}") from None


def _one_line(exc: BaseException) -> str:
    """Zenoh's error on one line, without its Rust wrapping (``Json5Err(Message {
    msg: "..." })``) and source location."""
    return _zenoh_error(exc)[0]


def _zenoh_error(exc: BaseException) -> tuple[str, tuple[int, int] | None]:
    """Zenoh's error on one line, and the (line, column) of the JSON5 text it is
    about if it says (a parser's ``--> 3:26`` or serde's ``location``).

    The message is unwrapped from Rust's ``Debug`` string (``msg: "..."``, with
    its escapes: a literal ``\\n`` is a line break) and a parser's picture of the
    line is left out: ``= expected boolean or null`` is what it says."""
    text = str(exc)
    where: tuple[int, int] | None = None
    if quoted := re.search(r'(?:msg: |Error\(|Str\()"((?:[^"\\]|\\.)*)"', text):
        rest = text[: quoted.start()] + text[quoted.end() :]
        if found := re.search(r"line: (\d+), column: (\d+)", rest):
            where = (int(found.group(1)), int(found.group(2)))
        text = re.sub(r"\\(u\{[0-9a-fA-F]+\}|.)", _unescape, quoted.group(1))
    if found := re.match(r"\s*-->\s*(\d+):(\d+)", text):  # the JSON5 parser's own picture
        where = (int(found.group(1)), int(found.group(2)))
        said = re.findall(r"^\s*=\s*(.+)$", text, flags=re.MULTILINE)
        text = said[-1] if said else text[found.end() :]
    text = re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", " ".join(text.split()))
    return text.strip()[:300], where


def _unescape(match: re.Match[str]) -> str:
    """One escape of a Rust ``Debug`` string (``\\n``, ``\\"``, ``\\u{e9}``...)."""
    code = match.group(1)
    if code.startswith("u{"):
        value = int(code[2:-1], 16)
        return chr(value) if value <= sys.maxunicode else "\ufffd"
    return {"n": "\n", "t": "\t", "r": "\r", "0": "\0"}.get(code, code)


def _file_mode(conf: zenoh.Config) -> str | None:
    """The mode a config names, or None if it names none."""
    mode = json.loads(conf.get_json("mode"))
    return str(mode) if mode else None


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The session config of a command's standard session flags."""
    return session_config(
        args.mode,
        args.connect,
        args.listen,
        args.config,
        args.cfg,
        getattr(args, "subject", None),
        default_mode=getattr(args, "zenoh_default_mode", "client"),
        connect_timeout_s=getattr(args, "connect_timeout", None),
    )


class SessionError(RuntimeError):
    """A session that cannot be configured or opened (bad config file, port in use...)."""


_opening = threading.Event()


def is_opening() -> bool:
    """Is the main thread waiting for a session to open (a router to come up)?"""
    return _opening.is_set()


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """Open a session; Zenoh's own logging follows ``RUST_LOG`` if set.

    The process's first session sets Zenoh's runtime threads to
    :data:`ZENOH_RUNTIME` unless the environment's ``ZENOH_RUNTIME`` names
    others (Zenoh reads it once, when its runtime starts).

    A client whose router does not answer at once says so on stderr ("waiting
    for the router at ..."), again every few seconds, and gives up after the
    config's ``connect/timeout_ms`` (``--connect-timeout``) with
    ``SessionError``. The wait happens in a helper thread so that the main
    thread still runs signal handlers (see ``cli.nodes.stop_on_signals``:
    Ctrl-C or SIGTERM while waiting ends the process)."""
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME)
    import zenoh

    zenoh.try_init_log_from_env()
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["session"] = zenoh.open(conf)
        except zenoh.ZError as exc:
            box["error"] = exc
        except BaseException as exc:  # a Rust panic (pyo3's PanicException)
            box["panic"] = exc

    mode = json.loads(conf.get_json("mode"))
    where = ", ".join(json.loads(conf.get_json("connect/endpoints")) or ()) or "(none given)"
    timeout_ms = json.loads(conf.get_json("connect/timeout_ms"))
    limit = (f"{timeout_ms / 1000:g} s" if isinstance(timeout_ms, int) and timeout_ms > 0
             else "no limit")  # fmt: skip
    thread = threading.Thread(target=target, name="zenoh-open", daemon=True)
    _opening.set()
    start = time.monotonic()
    next_word = start + 0.5  # a router that is up answers well within this
    try:
        thread.start()
        while thread.is_alive():
            thread.join(0.1)
            now = time.monotonic()
            if mode == "client" and thread.is_alive() and now >= next_word:
                if now - start < 1:
                    said = f"waiting for the router at {where} ... (giving up after {limit})"
                else:
                    said = (f"still waiting for the router at {where} "
                            f"({now - start:.0f} s of {limit})")  # fmt: skip
                print(f"bodynet: {said}", file=sys.stderr, flush=True)
                next_word = now + 5.0
    finally:
        _opening.clear()
    if "session" not in box and "error" not in box:  # Zenoh panicked
        runtime = os.environ.get("ZENOH_RUNTIME")
        hint = (f"; is ZENOH_RUNTIME={runtime!r} valid?" if runtime != ZENOH_RUNTIME
                else "")  # fmt: skip
        raise SessionError(f"Zenoh failed to start: {_one_line(box.get('panic', ''))}{hint}")
    if "error" in box:
        # a client's listener that cannot bind fails too: only a failed connection is the router's
        if mode == "client" and "unable to connect" in str(box["error"]).lower():
            raise SessionError(
                f"no router answered at {where} within {time.monotonic() - start:.0f} s "
                f"(is it running? --connect-timeout sets the wait): {_one_line(box['error'])}"
            )
        raise SessionError(f"cannot open the Zenoh session: {_one_line(box['error'])}")
    return box["session"]  # type: ignore[no-any-return]
