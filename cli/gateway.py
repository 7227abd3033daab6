"""Command-line wiring of the gateway: ``gateway`` and ``calibrate``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bodynet.core import keys
from bodynet.core.keys import branch_named
from bodynet.core.subject import Profile, ProfileError
from bodynet.session import DEFAULT_ROUTER, add_session_args, config_from_args, open_session


def _profile(path: Path | None) -> Profile:
    from bodynet.gateway import profile_file

    if path is None or not path.exists():
        return Profile()
    return profile_file.load(path)


def cmd_gateway(args: argparse.Namespace) -> int:
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.gateway.service import Gateway

    try:
        profile = _profile(args.profile)
    except ProfileError as exc:
        print(f"bodynet gateway: {exc}", file=sys.stderr)
        return 2
    if (args.mode or "router") == "router" and not args.listen and not args.config:
        args.listen = [DEFAULT_ROUTER]
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    branches = [branch_named(b) for b in args.branch] or None
    gateway = Gateway(session, profile, args.profile, branches, args.rate_hz)
    where = ", ".join(args.listen) if args.listen else "its router"
    print(f"bodynet gateway: subject {profile.subject!r}, serving on {where}; "
          f"poses on {keys.pose_key()} and {keys.all_poses()}", flush=True)  # fmt: skip
    try:
        gateway.run(stop)
    finally:
        gateway.close()
        session.close()
    return 0


def cmd_calibrate_tpose(args: argparse.Namespace) -> int:
    session = open_session(config_from_args(args))
    try:
        replies = list(session.get(f"{keys.CALIBRATE_TPOSE}?seconds={args.seconds}", timeout=10.0))
    finally:
        session.close()
    for reply in replies:
        if reply.ok is not None:
            result = json.loads(reply.ok.payload.to_bytes())
            print(json.dumps(result, indent=2))
            return 0 if result.get("ok") else 1
    print("bodynet calibrate tpose: no gateway answered", file=sys.stderr)
    return 1


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("gateway", help="calibration and kinematics: raw samples in, poses out")
    p.add_argument("--profile", type=Path, help="subject profile (TOML); created by calibration")
    p.add_argument("--branch", action="append", default=[],
                   help="serve only these branches (repeatable; default all)")  # fmt: skip
    p.add_argument("--rate-hz", type=float, default=100.0, help="most poses per second")
    add_session_args(p, default_mode="router")
    p.set_defaults(func=cmd_gateway)

    cal = sub.add_parser("calibrate", help="calibrate sensors of the subject")
    csub = cal.add_subparsers(dest="what", required=True, metavar="WHAT")
    p = csub.add_parser("tpose", help="IMU mounts: the subject stands still in T-pose")
    p.add_argument("--seconds", type=float, default=1.0, help="still window to average")
    add_session_args(p)
    p.set_defaults(func=cmd_calibrate_tpose)
