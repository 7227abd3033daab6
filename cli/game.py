"""Command-line wiring of ``bodynet game`` (the rehabilitation game in a browser)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bodynet.session import SessionError, add_session_args, argtypes, config_from_args

DEFAULT_HTTP_PORT = 8088


def cmd_game(args: argparse.Namespace) -> int:
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.clients.game import GameOptions, listen_socket, results_dir_problem, run_game
    from bodynet.clients.rehab import GameError, check_patient, plural

    def fail(message: str) -> int:
        print(f"bodynet game: {message}", file=sys.stderr)
        return 2

    try:
        options = GameOptions(args.arm, args.trials, args.practice, args.radius_cm / 100.0,
                              args.target_timeout, check_patient(args.patient))  # fmt: skip
        options.game()  # the rules check them too
        conf = config_from_args(args)
    except (GameError, SessionError) as exc:  # SessionError: e.g. an endpoint Zenoh refuses
        return fail(str(exc))
    where = ", ".join(args.connect) or "the configured endpoints"

    def announce(url: str) -> None:
        print(f"bodynet game: {url}", flush=True)
        print(f"bodynet game: waiting for the Zenoh router at {where}", flush=True)

    # the results folder and the page's address first: a mistake there is told at
    # once, not after waiting for the router; the folder is made with the first results
    if why := results_dir_problem(args.results):
        return fail(f"cannot write results in {args.results}: {why}")
    try:
        sock = listen_socket(args.http_host, args.http_port)
    except OSError as exc:
        return fail(f"cannot serve on {args.http_host}:{args.http_port}: {exc.strerror or exc}")
    stop = stop_on_signals()
    try:
        server = run_game(conf, stop, options, args.results, sock, args.http_host, announce)
    except SessionError as exc:  # e.g. an endpoint Zenoh cannot use
        return fail(str(exc))
    except OSError as exc:  # the results folder went away mid-session
        return fail(str(exc))
    finally:
        sock.close()
    summary = server.game.summary()
    saved = f", results in {args.results}" if server.results.written else ", nothing saved"
    print(f"bodynet game: {plural(summary['complete_trials'], 'complete trial')}, "
          f"score {summary['score']}{saved}", file=sys.stderr)  # fmt: skip
    return 0


def _patient(text: str) -> str:
    from bodynet.clients.rehab import GameError, check_patient

    try:
        return check_patient(text)
    except GameError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_game_args(p: argparse.ArgumentParser) -> None:
    """``bodynet game``'s arguments (its entry in ``cli.main.COMMANDS``)."""
    p.add_argument(
        "--arm",
        choices=("left", "right"),
        default="left",
        help="the player's arm (its pose key body/arm/<arm>/pose; default left)",
    )
    p.add_argument(
        "--patient",
        type=_patient,
        default="",
        help="the patient's id (letters, digits, - and _), in the results' file names",
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
        help=f"port of the page and its WebSocket, 1-65535 (default {DEFAULT_HTTP_PORT}; "
        "0 picks a free one)",
    )
    p.add_argument(
        "--results",
        type=Path,
        default=Path("rehab-results"),
        help="folder of the sessions' results, JSON and CSV (default rehab-results)",
    )
    p.add_argument(
        "--trials",
        type=argtypes.positive_int(1000, "trials"),
        default=10,
        help="complete trials in a session, practice not counted, 1-1000 (default 10)",
    )
    p.add_argument(
        "--practice",
        type=argtypes.bounded_int(0, 10, "practice trials"),
        default=1,
        metavar="N",
        help="practice trials first (0-10), left out of the summary (default 1)",
    )
    p.add_argument(
        "--radius-cm",
        type=argtypes.bounded_float(1.0, 100.0, "cm"),
        default=12.0,
        help="how close the hand tip must come to the ball, 1-100 cm (default 12)",
    )
    p.add_argument(
        "--target-timeout",
        type=argtypes.bounded_float(1.0, 3600.0, "seconds, at most an hour"),
        default=20.0,
        help="seconds a waiting ball counts down before moving on, 1-3600 (default 20)",
    )
    add_session_args(p)
