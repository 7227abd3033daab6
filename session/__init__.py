"""Zenoh sessions for every bodynet process: the standard flags and defaults.

Every service takes the same session flags as the zenoh-python examples:
``--mode``, ``-e/--connect``, ``-l/--listen``, ``-c/--config`` and
``--cfg KEY:VALUE``. Precedence: command line, then environment
(``BODYNET_ZENOH_CONFIG`` names a config file, ``BODYNET_ZENOH_CONNECT`` a
comma-separated list of endpoints), then the config file, then bodynet's
defaults: client mode towards the gateway's router on ``tcp/127.0.0.1:7447``,
multicast scouting off (endpoints are explicit), waiting for the router if it
is not up yet and reconnecting quickly when it comes back.

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
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bodynet.core.keys import KeySpaceError, subject_name

if TYPE_CHECKING:
    import zenoh

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
MODES = ("client", "peer", "router")


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
        metavar="ENDPOINT",
        help=f"endpoint to connect to (default for a client: {DEFAULT_ROUTER})",
    )
    group.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on")  # fmt: skip
    group.add_argument("-c", "--config", type=Path, default=None, help="Zenoh JSON5 config file")
    group.add_argument(
        "--cfg",
        action="append",
        default=[],
        metavar="KEY:VALUE",
        help="a config entry, VALUE in JSON5, e.g. --cfg 'scouting/multicast/enabled:true'",
    )
    group.add_argument(
        "--subject",
        default=None,
        type=_subject_arg,
        help="run in this subject's namespace (keys stay body/...; default: none, "
        "or $BODYNET_SUBJECT)",
    )
    parser.set_defaults(zenoh_default_mode=default_mode)


def _subject_arg(text: str) -> str:
    try:
        return subject_name(text)
    except KeySpaceError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def session_config(
    mode: str = "client",
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: Path | None = None,
    entries: Sequence[str] = (),
    subject: str | None = None,
) -> zenoh.Config:
    """A Zenoh config from explicit arguments (see the module docstring)."""
    import zenoh

    env_file = os.environ.get("BODYNET_ZENOH_CONFIG")
    path = config_file or (Path(env_file) if env_file else None)
    try:
        conf = zenoh.Config.from_file(str(path)) if path else zenoh.Config()
    except zenoh.ZError as exc:
        raise SessionError(f"cannot use Zenoh config {path}: {exc}") from None
    if not connect and (env_connect := os.environ.get("BODYNET_ZENOH_CONNECT")):
        connect = [e.strip() for e in env_connect.split(",") if e.strip()]
    if not connect and not path and mode == "client":
        connect = [DEFAULT_ROUTER]

    def put(key: str, value: Any) -> None:
        conf.insert_json5(key, json.dumps(value))

    if not path:
        put("scouting/multicast/enabled", False)
        put("connect/timeout_ms", -1 if mode == "client" else 0)
        put("connect/retry", {"period_init_ms": 100, "period_max_ms": 500})
    put("mode", mode)
    if connect:
        put("connect/endpoints", list(connect))
    if listen:
        put("listen/endpoints", list(listen))
    subject = subject or os.environ.get("BODYNET_SUBJECT") or None
    if subject:
        put("namespace", subject_name(subject))
    for entry in entries:
        key, sep, value = entry.partition(":")
        if not sep:
            raise SessionError(f"--cfg wants KEY:VALUE, not {entry!r}")
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as exc:
            raise SessionError(f"--cfg {entry!r}: {exc}") from None
    return conf


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    mode = args.mode or getattr(args, "zenoh_default_mode", "client")
    subject = getattr(args, "subject", None)
    return session_config(mode, args.connect, args.listen, args.config, args.cfg, subject)


class SessionError(RuntimeError):
    """A session that cannot be configured or opened (bad config file, port in use...)."""


_opening = threading.Event()


def is_opening() -> bool:
    """Is the main thread waiting for a session to open (a router to come up)?"""
    return _opening.is_set()


def open_session(conf: zenoh.Config) -> zenoh.Session:
    """Open a session; Zenoh's own logging follows ``RUST_LOG`` if set.

    A client waits for its router as long as it takes; the wait happens in a
    helper thread so that the main thread still runs signal handlers (see
    ``cli.nodes.stop_on_signals``: Ctrl-C or SIGTERM while waiting ends the process)."""
    import zenoh

    zenoh.try_init_log_from_env()
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["session"] = zenoh.open(conf)
        except zenoh.ZError as exc:
            box["error"] = exc

    thread = threading.Thread(target=target, name="zenoh-open", daemon=True)
    _opening.set()
    try:
        thread.start()
        while thread.is_alive():
            thread.join(0.1)
    finally:
        _opening.clear()
    if "error" in box:
        raise SessionError(f"cannot open the Zenoh session: {box['error']}")
    return box["session"]  # type: ignore[no-any-return]
