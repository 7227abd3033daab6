"""Command-line wiring of the node services: ``bridge``, ``emulate`` and ``node``."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from bodynet.core.keys import BRANCHES, branch_named
from bodynet.nodes.emulator import Realism
from bodynet.nodes.motion import ROUTINES
from bodynet.session import add_session_args, argtypes, config_from_args, open_session

log = logging.getLogger("bodynet")


def stop_on_signals() -> threading.Event:
    """An event set by Ctrl-C or SIGTERM, for a service's main loop to wait on."""
    from bodynet.session import is_opening

    stop = threading.Event()

    def handler(*_: object) -> None:
        stop.set()
        if is_opening():  # still waiting for the router: nothing to close yet, and
            sys.stdout.flush()  # unwinding while Zenoh's opener thread runs would abort
            sys.stderr.flush()
            os._exit(0)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return stop


#: Node and sensor numbers: SmartSuit nodes and IMU tags are numbered 1-15.
_NUMBERS = argtypes.number_list(1, 15)
_BRANCH_NAMES = [str(b) for b in BRANCHES]


def _numbers(numbers: tuple[int, ...] | str) -> tuple[int, ...]:
    """``"1-3,7"`` -> (1, 2, 3, 7) (already parsed by the option's type)."""
    return numbers if isinstance(numbers, tuple) else _NUMBERS(numbers)


def _interface(text: str) -> str:
    if not text.replace("_", "").replace("-", "").isalnum() or len(text) > 40:
        raise argparse.ArgumentTypeError(f"{text!r} is not a python-can interface name")
    return text


_INTERFACE = _interface


def _branches(args: argparse.Namespace) -> tuple | None:  # type: ignore[type-arg]
    return tuple(branch_named(b) for b in args.branch) if args.branch else None


def _options(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from bodynet.nodes.services import EmulationOptions

    realism = (
        Realism.ideal()
        if args.ideal
        else Realism(ole_slack_mm=args.slack_mm, yaw_drift_deg_per_min=args.drift)
    )
    return EmulationOptions(args.routine, realism, args.seed)


def _with_session(
    args: argparse.Namespace, run: Callable[..., None], *a: object, **kw: object
) -> int:
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    try:
        run(session, stop, *a, **kw)
    finally:
        session.close()
    return 0


def cmd_bridge(args: argparse.Namespace) -> int:
    from bodynet.nodes import services

    if args.device == "can":
        name = args.name or f"can-{args.channel or 'replay'}"
        bus_args = {"interface": args.interface, "channel": args.channel}
        if args.bitrate:
            bus_args["bitrate"] = args.bitrate
        return _with_session(args, services.bridge_can, name, args.replay, args.loop, **bus_args)
    name = args.name or f"{args.device}-{Path(args.port).name}"
    if args.device == "concentrator":
        return _with_session(
            args,
            services.bridge_concentrator,
            name,
            args.port,
            _numbers(args.nodes),
            args.baud or 115200,
        )
    return _with_session(args, services.bridge_imu_central, name, args.port, args.baud or 230400)


def cmd_emulate(args: argparse.Namespace) -> int:
    from bodynet.nodes import services

    stop = stop_on_signals()
    session = open_session(config_from_args(args)) if args.truth else None
    try:
        services.emulate(
            args.device,
            stop,
            _options(args),
            link=args.link,
            branches=_branches(args),
            sensors=_numbers(args.sensors) if args.sensors else None,
            silent=_numbers(args.silent) if args.silent else (),
            bus_args={"interface": args.interface, "channel": args.channel},
            truth_session=session,
        )
    finally:
        if session is not None:
            session.close()
    return 0


def cmd_node(args: argparse.Namespace) -> int:
    from bodynet.nodes.services import NodePlan, body_plan, run_node

    if args.system == "body":
        plans = body_plan()
    elif args.system == "imu":
        sensors = _numbers(args.sensors) if args.sensors else None
        plans = [NodePlan("imu", "imu-central", _branches(args), sensors)]
    else:
        plans = [NodePlan("smartsuit", args.via, _branches(args))]
    return _with_session(args, run_node, plans, _options(args), args.name or f"node-{args.system}")


def _emulation_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--routine",
        choices=sorted(ROUTINES),
        default="random",
        help="motion to perform (default: random)",
    )
    p.add_argument(
        "--branch",
        action="append",
        default=[],
        choices=_BRANCH_NAMES,
        help="left-arm, right-arm, left-leg, right-leg or trunk (repeatable; default all)",
    )
    p.add_argument("--sensors", type=_NUMBERS, help="IMU sensor numbers, e.g. 1-15 or 3,5,7")
    p.add_argument("--ideal", action="store_true", help="noise-free, bias-free sensors")
    p.add_argument("--slack-mm", type=argtypes.non_negative_float(50.0, "mm of slack"),
                   default=0.0, help="OLE cable slack (buckling)")  # fmt: skip
    p.add_argument("--drift", default=0.0, help="IMU yaw drift, deg per minute",
                   type=argtypes.bounded_float(-360.0, 360.0, "deg/min"))  # fmt: skip
    p.add_argument("--seed", type=argtypes.bounded_int(0, 2**32 - 1, "a 32-bit seed"), default=0)


def add_parsers(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    bridge = sub.add_parser("bridge", help="bridge a CAN bus or serial receiver onto Zenoh")
    bsub = bridge.add_subparsers(dest="device", required=True, metavar="DEVICE")
    p = bsub.add_parser("can", help="SmartSuit nodes on any python-can interface, or a log")
    p.add_argument("--interface", default="socketcan", type=_INTERFACE,
                   help="python-can interface (socketcan, slcan, pcan...)")  # fmt: skip
    p.add_argument("--channel", type=argtypes.free_text(200),
                   help="channel: can0, /dev/ttyACM0 (slcan)...")  # fmt: skip
    p.add_argument("--bitrate", default=None,
                   type=argtypes.bounded_int(1000, 8_000_000, "bit/s of a CAN bus"))  # fmt: skip
    p.add_argument("--replay", type=argtypes.input_file,
                   help="play a candump/asc/blf log at its recorded speed")  # fmt: skip
    p.add_argument("--loop", action="store_true", help="with --replay: play again and again")
    p.add_argument("--name", type=argtypes.free_text(100),
                   help="name on the health key (default from the channel)")  # fmt: skip
    add_session_args(p)
    p.set_defaults(func=cmd_bridge)
    for device, baud in (("concentrator", 115200), ("imu-central", 230400)):
        p = bsub.add_parser(device, help=f"the {device} on a serial port ({baud} baud)")
        p.add_argument("--port", required=True, type=argtypes.free_text(200),
                       help="serial device, e.g. /dev/ttyUSB0")  # fmt: skip
        p.add_argument("--baud", default=None, help=f"default {baud}",
                       type=argtypes.bounded_int(50, 4_000_000, "baud"))  # fmt: skip
        if device == "concentrator":
            p.add_argument("--nodes", default="1-3", type=_NUMBERS,
                           help="nodes to poll (default 1-3)")  # fmt: skip
        p.add_argument("--name", type=argtypes.free_text(100),
                       help="name on the health key (default from the port)")  # fmt: skip
        add_session_args(p)
        p.set_defaults(func=cmd_bridge)

    emulate = sub.add_parser("emulate", help="emulated hardware only, for a bridge to open")
    esub = emulate.add_subparsers(dest="device", required=True, metavar="DEVICE")
    for device, text in (
        ("slcan", "a slcan USB-CAN adapter with SmartSuit nodes"),
        ("concentrator", "a Data Concentrator with SmartSuit nodes"),
        ("imu-central", "the IMU central with its tags"),
        ("can", "SmartSuit nodes on a python-can bus"),
    ):
        p = esub.add_parser(device, help=text)
        _emulation_args(p)
        if device == "can":
            p.add_argument("--interface", default="socketcan", type=_INTERFACE)
            p.add_argument("--channel", default="vcan0", type=argtypes.free_text(200))
        else:
            p.add_argument(
                "--link",
                type=argtypes.link_path,
                required=True,
                help="path of the symlink to the pseudo-terminal",
            )
            p.set_defaults(interface=None, channel=None)
        p.add_argument("--silent", type=_NUMBERS,
                       help="concentrator: nodes that never answer, e.g. 3")  # fmt: skip
        p.add_argument(
            "--truth",
            action="store_true",
            help="publish the ground truth on Zenoh (session flags below)",
        )
        add_session_args(p)
        p.set_defaults(func=cmd_emulate)

    node = sub.add_parser("node", help="emulated sensors with their bridge, live on Zenoh")
    nsub = node.add_subparsers(dest="system", required=True, metavar="SYSTEM")
    for system, text in (
        ("smartsuit", "SmartSuit branches"),
        ("imu", "IMU tags"),
        ("body", "a full body: SmartSuit arms, IMU tags for the rest"),
    ):
        p = nsub.add_parser(system, help=text)
        _emulation_args(p)
        if system == "smartsuit":
            p.add_argument(
                "--via",
                choices=("can", "slcan", "concentrator"),
                default="can",
                help="transport of the emulated hardware (default can)",
            )
        p.add_argument("--name", type=argtypes.free_text(100),
                       help="name prefix on the health keys")  # fmt: skip
        add_session_args(p)
        p.set_defaults(func=cmd_node)
