"""Command-line wiring of the node services: ``bridge``, ``emulate`` and ``node``."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from bodynet.core.keys import BRANCHES, branch_named
from bodynet.nodes.motion import ROUTINES
from bodynet.session import add_session_args, argtypes, config_from_args, open_session

if TYPE_CHECKING:
    from bodynet.nodes.services import NodePlan

log = logging.getLogger("bodynet")


def stop_on_signals() -> threading.Event:
    """An event set by Ctrl-C or SIGTERM, for a service's main loop to wait on."""
    from bodynet.session import is_opening

    stop = threading.Event()

    def handler(*_: object) -> None:
        # set by another thread: the signal may come while this (the main) thread is
        # inside ``stop.wait()`` holding the event's lock, which ``stop.set()`` here
        # would wait on for ever (a service that then never stopped on SIGTERM)
        threading.Thread(target=stop.set, name="stop", daemon=True).start()
        if is_opening():  # still waiting for the router: nothing to close yet, and
            sys.stdout.flush()  # unwinding while Zenoh's opener thread runs would abort
            sys.stderr.flush()
            os._exit(0)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)
    return stop


def _numbers(text: str | tuple[int, ...]) -> tuple[int, ...]:
    """``"1-3,7"`` -> (1, 2, 3, 7) (an argparse type; an already parsed list is kept)."""
    from bodynet.nodes.sources.base import numbers

    return text if isinstance(text, tuple) else numbers(text)


def _branches(args: argparse.Namespace) -> tuple | None:  # type: ignore[type-arg]
    return tuple(branch_named(b) for b in args.branch) if args.branch else None


def _options(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    from dataclasses import replace

    from bodynet.nodes.emulator import Headings, Realism
    from bodynet.nodes.services import EmulationOptions

    realism = (
        Realism.ideal()
        if args.ideal
        else Realism(ole_slack_mm=args.slack_mm, yaw_drift_deg_per_min=args.drift,
                     quat_noise_deg=args.noise_deg, random_tag_mounts=not args.aligned_mounts)
    )  # fmt: skip
    # where the subject faces and the tags' heading references hold even for --ideal
    realism = replace(realism, facing_deg=args.facing, headings=Headings(args.tag_headings))
    return EmulationOptions(args.routine, realism, args.seed, _timing(args))


def _timing(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    """The link's timing: healthy real hardware, or with ``--ideal`` an ideal link;
    the timing flags given say otherwise where they do."""
    from dataclasses import replace

    from bodynet.nodes.timing import LinkTiming, Timers

    base = LinkTiming.ideal() if args.ideal else LinkTiming.realistic()
    given = {
        "timers": Timers(args.timers) if args.timers else None,
        "clock_ppm": args.clock_ppm,
        "jitter_s": None if args.jitter_ms is None else args.jitter_ms / 1000,
        "drop": args.drop,
        "late": args.late,
        "reorder": args.reorder,
    }
    return replace(base, seed=args.seed, **{k: v for k, v in given.items() if v is not None})


#: each timing flag by the ``LinkTiming`` field it sets
_TIMING_FLAGS = {"timers": "--timers", "clock_ppm": "--clock-ppm", "jitter_s": "--jitter-ms",
                 "drop": "--drop", "late": "--late", "reorder": "--reorder"}  # fmt: skip


def _unused_timing(args: argparse.Namespace, devices: Sequence[str]) -> str | None:
    """Why a timing flag given does nothing on ``devices`` (None if each is used)."""
    from bodynet.nodes import sources

    used = set().union(*(sources.by_device(d).TIMING for d in devices))
    given = {"timers": args.timers, "clock_ppm": args.clock_ppm, "jitter_s": args.jitter_ms,
             "drop": args.drop, "late": args.late, "reorder": args.reorder}  # fmt: skip
    unused = [_TIMING_FLAGS[k] for k, v in given.items() if v is not None and k not in used]
    if not unused:
        return None
    takes = " ".join(_TIMING_FLAGS[k] for k in _TIMING_FLAGS if k in used) or "no timing flag"
    return f"{' '.join(unused)} does nothing here ({', '.join(devices)} takes {takes})"


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
    from bodynet.nodes import services, sources
    from bodynet.nodes.sources.base import CaptureError

    name = args.name or sources.get(args.device).bridge_name(args)
    try:
        return _with_session(args, services.bridge, args.device, name, args)
    except (OSError, CaptureError) as exc:  # a UDP port taken, a --replay of no frame...
        print(f"bodynet bridge {args.device}: {exc}", file=sys.stderr)
        return 2


def cmd_emulate(args: argparse.Namespace) -> int:
    from bodynet.nodes import services
    from bodynet.nodes.sources.base import EmulatorError

    if unused := _unused_timing(args, [args.device]):
        print(f"bodynet emulate {args.device}: {unused}", file=sys.stderr)
        return 2
    stop = stop_on_signals()
    session = open_session(config_from_args(args)) if args.truth else None
    # what the device's own options say (its source added them), for its emulator
    explicit = ("link", "sensors", "silent", "func")
    device_args = {k: v for k, v in vars(args).items() if k not in explicit}
    bus_args = {"interface": getattr(args, "interface", None),
                "channel": getattr(args, "channel", None)}  # fmt: skip
    try:
        services.emulate(
            args.device,
            stop,
            _options(args),
            link=getattr(args, "link", None),
            branches=_branches(args),
            sensors=_numbers(args.sensors) if args.sensors else None,
            silent=_numbers(args.silent) if args.silent else (),
            bus_args=bus_args,
            truth_session=session,
            **device_args,
        )
    except EmulatorError as exc:  # its link, bus or server: nothing was started
        print(f"bodynet emulate {args.device}: {exc}", file=sys.stderr)
        return 2
    finally:
        if session is not None:
            session.close()
    return 0


def cmd_node(args: argparse.Namespace) -> int:
    from bodynet.nodes.services import NodePlan, body_plan, run_node

    if args.sensors and args.system not in ("imu", "slimevr"):  # it was passed over
        print(f"bodynet node {args.system}: --sensors picks IMU tags (node imu, node "
              "slimevr); here it would be passed over", file=sys.stderr)  # fmt: skip
        return 2
    if args.system == "body":
        plans = body_plan()
    elif args.system in ("imu", "slimevr"):  # IMU tags on the central, or as SlimeVR trackers
        sensors = _numbers(args.sensors) if args.sensors else None
        via = "imu-central" if args.system == "imu" else "slimevr"
        plans = [NodePlan(args.system, via, _branches(args), sensors)]
    else:
        plans = [NodePlan("smartsuit", args.via, _branches(args))]
    if empty := _no_sensor(plans):
        print(f"bodynet node {args.system}: {_selection(args)} matches no {empty.system} "
              "sensor; nothing to emulate", file=sys.stderr)  # fmt: skip
        return 2
    if unused := _unused_timing(args, [p.via for p in plans]):
        print(f"bodynet node {args.system}: {unused}", file=sys.stderr)
        return 2
    return _with_session(args, run_node, plans, _options(args), args.name or f"node-{args.system}",
                         args.batch_ms / 1e3)  # fmt: skip


def _no_sensor(plans: Sequence[NodePlan]) -> NodePlan | None:
    """The first plan whose selection matches no sensor, or None."""
    from bodynet.nodes import sources

    for plan in plans:
        if not sources.by_device(plan.via)().emulated_sensors(plan.sensors, plan.branches):
            return plan
    return None


def _selection(args: argparse.Namespace) -> str:
    """The options that chose the sensors, as given."""
    chosen = [f"--branch {b}" for b in args.branch]
    if args.sensors:
        chosen.insert(0, "--sensors " + ",".join(map(str, _numbers(args.sensors))))
    return " with ".join(chosen) or "the selection"


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
        choices=[str(b) for b in BRANCHES],
        help="left-arm, right-arm, left-leg, right-leg or trunk (repeatable; default all)",
    )
    p.add_argument("--sensors", type=_numbers, help="IMU sensor numbers, e.g. 1-15 or 3,5,7")
    p.add_argument("--ideal", action="store_true",
                   help="noise-free, bias-free sensors on an ideal link (lock-step timers, "
                        "no jitter, nothing lost; timing flags given still apply)")  # fmt: skip
    p.add_argument("--slack-mm", type=argtypes.non_negative_float(50.0, "mm of slack"),
                   default=0.0, help="OLE cable slack (buckling)")  # fmt: skip
    p.add_argument("--drift", default=0.0, type=argtypes.bounded_float(-360.0, 360.0, "deg/min"),
                   help="IMU heading drift, deg per minute (independent tags: each its own "
                        "rate within +/- this)")  # fmt: skip
    p.add_argument("--facing", type=argtypes.bounded_float(-360.0, 360.0, "deg"), default=0.0,
                   metavar="DEG",
                   help="where the subject faces in the tags' shared frame (a magnetometer "
                        "suit: x to north), deg about the vertical (default 0: +X)")  # fmt: skip
    p.add_argument("--tag-headings", choices=("shared", "independent", "drifting"),
                   default="shared",
                   help="shared: one earth frame for all tags (magnetometer-based); "
                        "independent: 6-axis tags, each starting with a heading of its own; "
                        "drifting: 6-axis tags reset together, each drifting at its own "
                        "--drift rate")  # fmt: skip
    p.add_argument("--noise-deg", type=argtypes.non_negative_float(30.0, "deg"), default=0.3,
                   help="orientation noise, deg")  # fmt: skip
    p.add_argument("--aligned-mounts", action="store_true",
                   help="tags mounted with their axes along their segments' (default: "
                        "arbitrary mountings)")  # fmt: skip
    p.add_argument("--seed", type=argtypes.bounded_int(0, 2**32 - 1, "a 32-bit seed"), default=0)
    _timing_args(p)


def _timing_args(p: argparse.ArgumentParser) -> None:
    """The link's timing (``nodes.timing.LinkTiming``); None: the default's."""
    p.add_argument("--timers", choices=("independent", "locked"),
                   help="CAN nodes, IMU tags, SlimeVR trackers each on a timer of their own "
                        "(own phase in the period, own clock error) or all sending at once "
                        "(default independent; locked with --ideal)")  # fmt: skip
    p.add_argument("--clock-ppm", type=argtypes.non_negative_float(10_000.0, "ppm"),
                   metavar="PPM",
                   help="independent timers: each node's clock error drawn within +/- this "
                        "(default 100)")  # fmt: skip
    p.add_argument("--jitter-ms", type=argtypes.non_negative_float(100.0, "ms"), metavar="MS",
                   help="each send late by up to this (CAN frames, IMU tags' notifications "
                        "and the central's lines, SlimeVR rotations) (default 1; 0 with "
                        "--ideal)")  # fmt: skip
    p.add_argument("--drop", type=argtypes.bounded_float(0.0, 1.0, "a fraction"),
                   metavar="FRACTION",
                   help="share of frames lost: CAN frames (not sent), IMU tags' notifications "
                        "(the central prints no new data when none came), SlimeVR rotations "
                        "(numbered, not sent), concentrator replies (none) "
                        "(default 0)")  # fmt: skip
    p.add_argument("--late", type=argtypes.bounded_float(0.0, 1.0, "a fraction"),
                   metavar="FRACTION",
                   help="concentrator: share of replies given after the bridge's timeout "
                        "(default 0)")  # fmt: skip
    p.add_argument("--reorder", type=argtypes.bounded_float(0.0, 1.0, "a fraction"),
                   metavar="FRACTION",
                   help="SlimeVR: share of rotation datagrams overtaken by the next one "
                        "(default 0)")  # fmt: skip


def _batch_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch-ms", type=argtypes.bounded_float(0.0, 10.0, "ms"), default=0.0,
                   metavar="MS",
                   help="publish the samples together on body/@batch/<name>, once every "
                        "live node has one or MS after the first (default 0: each on its "
                        "site's key); far less CPU for the gateway, up to MS more "
                        "latency (docs/devices.md#batching)")  # fmt: skip


def add_bridge_args(bridge: argparse.ArgumentParser) -> None:
    from bodynet.nodes import sources

    bsub = bridge.add_subparsers(dest="device", required=True, metavar="DEVICE")
    for cls in sources.all_sources():
        if not cls.has_bridge():
            continue
        p = bsub.add_parser(cls.name, help=cls.help)
        cls.add_bridge_args(p)
        p.add_argument("--name", type=argtypes.free_text(100),
                       help="name on the health key (default from the device)")  # fmt: skip
        _batch_arg(p)
        add_session_args(p)
        p.set_defaults(func=cmd_bridge)


def add_emulate_args(emulate: argparse.ArgumentParser) -> None:
    from bodynet.nodes import sources

    esub = emulate.add_subparsers(dest="device", required=True, metavar="DEVICE")
    for device, cls in sources.emulated_devices().items():
        p = esub.add_parser(device, help=cls.emulators[device])
        _emulation_args(p)
        cls.add_emulate_args(device, p)
        p.add_argument("--silent", type=_numbers,
                       help="concentrator: nodes that never answer, e.g. 3")  # fmt: skip
        p.add_argument(
            "--truth",
            action="store_true",
            help="publish the ground truth on Zenoh (session flags below)",
        )
        add_session_args(p)
        p.set_defaults(func=cmd_emulate)


def add_node_args(node: argparse.ArgumentParser) -> None:
    nsub = node.add_subparsers(dest="system", required=True, metavar="SYSTEM")
    for system, text in (
        ("smartsuit", "SmartSuit branches"),
        ("imu", "IMU tags"),
        ("slimevr", "IMU tags as SlimeVR trackers over UDP, with a SlimeVR bridge"),
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
        _batch_arg(p)
        add_session_args(p)
        p.set_defaults(func=cmd_node)
