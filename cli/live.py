"""Command-line wiring of the live outputs: ``lsl``, ``vmc`` and ``metrics``."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from bodynet.session import add_session_args, argtypes, config_from_args, open_session


def _run_output(args: argparse.Namespace, name: str, options: dict[str, Any]) -> int:
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.clients import live

    command = f"bodynet {name}"
    args.all_subjects = getattr(args, "all_subjects", False)  # vmc: one performer
    if args.all_subjects and args.subject:
        print(f"{command}: --all-subjects or --subject, not both", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    output = None
    if name != "metrics":  # made first: a bad target is told before any wait for a router
        try:
            output = live.load_output(name, **options)
        except OSError as exc:  # e.g. vmc's --host that does not resolve
            print(f"{command}: {exc.strerror or exc}", file=sys.stderr)
            return 2
    session = open_session(config_from_args(args))
    if output is None:  # metrics: its "send" is a put on this session
        output = live.load_output(name, session=session, all_subjects=args.all_subjects,
                                  **options)  # fmt: skip
    subject = args.subject or live.DEFAULT_SUBJECT
    who = "every subject" if args.all_subjects else f"subject {subject}"
    print(f"{command}: {who}, {output.describe()}", flush=True)
    try:
        counts = live.run(session, output, stop, subject=args.subject,
                          all_subjects=args.all_subjects)  # fmt: skip
    finally:
        session.close()
    print(f"{command}: {counts.summary()}", file=sys.stderr)
    return 0


def cmd_lsl(args: argparse.Namespace) -> int:
    return _run_output(args, "lsl", {"raw": args.raw})


def cmd_vmc(args: argparse.Namespace) -> int:
    return _run_output(args, "vmc", {"host": args.host, "port": args.port,
                                     "rate_hz": args.rate_hz})  # fmt: skip


def cmd_metrics(args: argparse.Namespace) -> int:
    return _run_output(args, "metrics", {"rate_hz": args.rate_hz})


def add_lsl_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--raw", action="store_true",
                   help="also one stream per sensor site with its raw samples")  # fmt: skip
    p.add_argument("--all-subjects", action="store_true",
                   help="every subject on the network (<subject>/body/...), each its own "
                        "streams; else the session's --subject (or none)")  # fmt: skip
    add_session_args(p)


def add_vmc_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", type=argtypes.hostname, default="127.0.0.1",
                   help="where the VMC receiver (marionette) runs (default 127.0.0.1)")  # fmt: skip
    p.add_argument("--port", type=argtypes.port, default=39539,
                   help="its UDP port (default 39539)")  # fmt: skip
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=60.0,
                   help="bundles per second, each the newest pose (default 60)")  # fmt: skip
    add_session_args(p)


def add_metrics_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--all-subjects", action="store_true",
                   help="every subject on the network, each its own <subject>/body/@metrics; "
                        "else the session's --subject (or none)")  # fmt: skip
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=2.0,
                   help="metrics messages per second and subject (default 2)")  # fmt: skip
    add_session_args(p)
