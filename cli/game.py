"""Command-line wiring of ``bodynet game`` (the rehabilitation game in a browser)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bodynet.session import add_session_args, argtypes, config_from_args, open_session

DEFAULT_HTTP_PORT = 8088


def cmd_game(args: argparse.Namespace) -> int:
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.clients.game import ResultsFile, listen_socket, run_game
    from bodynet.clients.rehab import GameError, RehabGame

    try:
        game = RehabGame(
            args.arm, args.trials, args.practice, args.radius_cm / 100.0, args.target_timeout
        )
    except GameError as exc:
        print(f"bodynet game: {exc}", file=sys.stderr)
        return 2

    def announce(url: str) -> None:
        print(f"bodynet game: {url}", flush=True)

    # the page's address and the results folder first: a mistake there is told at
    # once, not after waiting for the router
    try:
        sock = listen_socket(args.http_host, args.http_port)
    except OSError as exc:
        print(f"bodynet game: cannot serve on {args.http_host}:{args.http_port}: "
              f"{exc.strerror or exc}", file=sys.stderr)  # fmt: skip
        return 2
    try:
        results = ResultsFile(args.results, game.side)
    except OSError as exc:
        sock.close()
        print(f"bodynet game: cannot write results in {args.results}: {exc.strerror or exc}",
              file=sys.stderr)  # fmt: skip
        return 2
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    try:
        run_game(session, stop, game, results, sock, args.http_host, announce)
    except OSError as exc:  # the results folder went away mid-session
        print(f"bodynet game: {exc}", file=sys.stderr)
        return 2
    finally:
        sock.close()
        session.close()
    summary = game.summary()
    print(
        f"bodynet game: {summary['complete_trials']} complete trials, score {summary['score']}"
        + (f", results in {args.results}" if summary["trials"] else ""),
        file=sys.stderr,
    )
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("game", help="the arm-reaching rehabilitation game, in a browser")
    p.add_argument(
        "--arm",
        choices=("left", "right"),
        default="left",
        help="the player's arm (its pose key body/arm/<arm>/pose; default left)",
    )
    p.add_argument(
        "--http-host",
        default="127.0.0.1",
        type=argtypes.hostname,
        help="address the page is served on; 0.0.0.0 for a player on another "
        "machine (default 127.0.0.1)",
    )
    p.add_argument(
        "--http-port",
        type=argtypes.port_or_zero,
        default=DEFAULT_HTTP_PORT,
        help=f"port of the page and its WebSocket (default {DEFAULT_HTTP_PORT}; "
        "0 picks a free one)",
    )
    p.add_argument(
        "--results",
        type=argtypes.output_dir,
        default=Path("rehab-results"),
        help="folder of the session's results, JSON and CSV (default rehab-results)",
    )
    p.add_argument(
        "--trials",
        type=argtypes.positive_int(1000, "trials"),
        default=10,
        help="complete trials in the session, practice not counted (default 10)",
    )
    p.add_argument(
        "--practice",
        type=argtypes.bounded_int(0, 10, "practice trials"),
        default=1,
        metavar="N",
        help="practice trials first, left out of the summary (default 1)",
    )
    p.add_argument(
        "--radius-cm",
        type=argtypes.bounded_float(1.0, 100.0, "cm"),
        default=12.0,
        help="how close the hand tip must come to the ball (default 12)",
    )
    p.add_argument(
        "--target-timeout",
        type=argtypes.bounded_float(1.0, 3600.0, "seconds"),
        default=20.0,
        help="seconds a waiting ball gives the player before moving on (default 20)",
    )
    add_session_args(p)
    p.set_defaults(func=cmd_game)
