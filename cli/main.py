"""bodynet: a distributed body-network gateway for wearable motion capture.

Argument parsing only. :data:`COMMANDS` names, for each command, the function
it runs and the hook that adds its arguments, as ``"module:function"``
strings: a command's module is imported only when that command is parsed or
runs, so ``bodynet --help`` loads no Zenoh, Pinocchio, Rerun or pandas, and
the command modules of ``cli/`` keep their own imports inside the functions
that run. Each command calls a ``main``-style function of its module with
explicit arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import json
import logging
import signal
import sys
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bodynet.session import (
    DEFAULT_ROUTER,
    SessionError,
    add_session_args,
    argtypes,
    config_from_args,
    open_session,
)

log = logging.getLogger("bodynet")


def cmd_decode(args: argparse.Namespace) -> int:
    """Decode a capture: one JSON object per sample on stdout, a summary on stderr."""
    from bodynet.nodes.captures import (
        CaptureError,
        CaptureStats,
        capture_options,
        looks_else,
        read_capture,
        sample_json,
    )

    stats = CaptureStats()
    out = sys.stdout
    if out is None:  # started with its stdout closed
        print("bodynet decode: stdout is closed: nowhere to write the samples", file=sys.stderr)
        return 2
    samples = read_capture(args.file, args.format, stats, args.rate_hz, capture_options(args))
    try:
        while True:
            try:
                sample = next(samples)
            except StopIteration:
                break
            except CaptureError as exc:
                print(f"bodynet decode: {exc}", file=sys.stderr)
                return 2
            except OSError as exc:
                print(f"bodynet decode: cannot read {args.file}: {exc.strerror or exc}",
                      file=sys.stderr)  # fmt: skip
                return 2
            out.write(json.dumps(sample_json(sample), separators=(",", ":")) + "\n")
        out.flush()
    except BrokenPipeError:  # e.g. piped into head
        _stdout_gone()
        return 0
    except OSError as exc:  # a full disk, a closed descriptor
        _stdout_gone()
        print(f"bodynet decode: cannot write the samples to stdout: {exc.strerror or exc}",
              file=sys.stderr)  # fmt: skip
        return 1
    print(stats.summary(), file=sys.stderr)
    if not stats.decoded:
        print(f"bodynet decode: no {args.format} samples in {args.file}"
              + looks_else(args.file, args.format), file=sys.stderr)  # fmt: skip
        return 2
    return 0


def _stdout_gone() -> None:
    """Point stdout at /dev/null: what is still buffered cannot be written, and
    Python's own flush at exit would complain about it."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    finally:
        os.close(devnull)


def cmd_demo(args: argparse.Namespace) -> int:
    from bodynet.cli.demo import run_demo
    from bodynet.cli.nodes import stop_on_signals

    return run_demo(args.listen, args.routine, args.seconds, args.record, stop_on_signals(),
                    args.viewer, args.rrd, args.web_port)  # fmt: skip


def cmd_router(args: argparse.Namespace) -> int:
    from bodynet.cli.nodes import stop_on_signals

    if not args.listen and not args.config:
        args.listen = [DEFAULT_ROUTER]
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    where = ", ".join(args.listen) if args.listen else f"the endpoints of {args.config}"
    print(f"bodynet router listening on {where}", flush=True)
    stop.wait()
    session.close()
    return 0


BENCHMARKS = ("decode", "solver", "gateway", "peer", "rate", "recorder", "faults", "soak", "drift",
              "truth")  # fmt: skip
#: run only when asked for (--only): long, or measuring no speed
ON_DEMAND = ("soak", "drift", "truth")


def cmd_bench(args: argparse.Namespace) -> int:
    try:
        from bodynet.bench import decode, faults, gateway, peer, recorder, report, soak, solver
    except ModuleNotFoundError as exc:  # psutil: the `bench` extra
        print(f"bodynet bench: {exc.name} is missing: install the bench extra "
              "(pip install -e '.[bench]', as make bench does)", file=sys.stderr)  # fmt: skip
        return 2

    only = args.only or [b for b in BENCHMARKS if b not in ON_DEMAND]
    if "decode" in only:
        decode.run(seconds=args.seconds, out_dir=args.out)
    if "solver" in only:
        solver.run(seconds=args.seconds, out_dir=args.out, bodies=(1, 5, 20))
    if "gateway" in only:
        gateway.run(seconds=args.gateway_seconds, out_dir=args.out, bodies=tuple(args.bodies),
                    gateways=tuple(args.gateways), apart=args.apart,
                    repeat=args.gateway_runs)  # fmt: skip
    if "peer" in only:
        peer.run(seconds=args.gateway_seconds, out_dir=args.out)
    if "rate" in only:
        gateway.run(seconds=args.gateway_seconds, out_dir=args.out, bodies=(1,),
                    rate_hz=args.rate_hz, name="rate")  # fmt: skip
    if "recorder" in only:
        recorder.run(seconds=args.seconds, out_dir=args.out,
                     gateway_seconds=args.gateway_seconds)  # fmt: skip
    if "faults" in only:
        faults.run(out_dir=args.out, repeat=args.repeat)
    if "drift" in only:
        from bodynet.bench import drift

        drift.run(out_dir=args.out, minutes=args.drift_minutes)
    if "truth" in only:
        from bodynet.bench import truth

        truth.run(out_dir=args.out, seeds=args.truth_seeds)
    if "soak" in only:
        result = soak.run(minutes=args.minutes, out_dir=args.out)
        if not result["pass"]:
            print("bodynet bench: the soak failed (loss or memory growth)", file=sys.stderr)
            return 1
    report.write(args.out)
    return 0


def add_decode_args(p: argparse.ArgumentParser) -> None:
    from bodynet.nodes.captures import add_capture_args, formats

    p.add_argument("--format", required=True, choices=formats())
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=None,
                   help="samples' time base where the capture has none "
                        "(concentrator: 1/22 ms; imu-central: 25 Hz)")  # fmt: skip
    add_capture_args(p)
    p.add_argument("file", type=argtypes.input_file)


def add_demo_args(p: argparse.ArgumentParser) -> None:
    from bodynet.nodes.motion import ROUTINES

    p.add_argument("-l", "--listen", default=DEFAULT_ROUTER, type=argtypes.endpoint,
                   help="where the router listens")  # fmt: skip
    p.add_argument(
        "--routine",
        default="reach",
        choices=sorted(ROUTINES),
        help="motion of the emulated body (default reach)",
    )
    p.add_argument("--seconds", type=argtypes.DURATION_S, default=None,
                   help="stop after this long")  # fmt: skip
    p.add_argument(
        "--viewer",
        choices=("auto", "native", "web", "none"),
        default="auto",
        help="live view: a window if there is a display, else the web viewer",
    )
    p.add_argument(
        "--rrd",
        type=argtypes.output_file,
        help="where the live view is saved (default beside --record)",
    )
    p.add_argument("--web-port", type=argtypes.port, default=None,
                   help="web viewer port (default 9090)")  # fmt: skip
    p.add_argument("--record", type=argtypes.output_file, default=Path("bodynet-demo.mcap"),
                   help="where the recorder writes (default bodynet-demo.mcap)")  # fmt: skip


def add_router_args(p: argparse.ArgumentParser) -> None:
    add_session_args(p, default_mode="router")


def add_bench_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=argtypes.bounded_float(0.01, 3600, "seconds, an hour at most"),
                   default=1.0, help="time per decode measurement")  # fmt: skip
    p.add_argument("--gateway-seconds", default=10.0, help="time of the gateway run",
                   type=argtypes.bounded_float(0.1, 3600, "seconds, an hour at most"))  # fmt: skip
    p.add_argument("--bodies", type=argtypes.positive_int(1000, "bodies"), nargs="+",
                   default=[1, 5, 10, 15, 20, 50],
                   help="numbers of bodies fed to the gateway")  # fmt: skip
    p.add_argument("--gateways", type=argtypes.positive_int(64, "gateways"), nargs="+",
                   default=[1, 2, 4],
                   help="numbers of gateway processes sharing the bodies (--share)")  # fmt: skip
    p.add_argument("--apart", action="store_true",
                   help="gateway benchmark: also feed relay, gateway, a bare Zenoh "
                        "subscriber (the floor) and a Python thread polling as the gateway's "
                        "worker did one after the other, each on the machine alone")  # fmt: skip
    p.add_argument("--gateway-runs", type=argtypes.positive_int(20, "runs"), default=1,
                   help="gateway benchmark: run each row this many times, interleaved, "
                        "and give the ranges of its figures (default 1)")  # fmt: skip
    p.add_argument("--only", action="append", choices=BENCHMARKS,
                   help="run only this benchmark (repeatable; default all but "
                        f"{', '.join(ON_DEMAND)})")  # fmt: skip
    p.add_argument(
        "--drift-minutes",
        type=argtypes.bounded_float(0.5, 120.0, "minutes"),
        default=10.0,
        help="emulated minutes of the drift benchmark (default 10)",
    )
    p.add_argument("--truth-seeds", type=argtypes.positive_int(1000, "seed"), nargs="+",
                   default=[1, 2], help="seeds of the truth benchmark's scenarios "
                                        "(default 1 2)")  # fmt: skip
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=1000.0,
                   help="per-node rate of the `rate` benchmark (default 1000)")  # fmt: skip
    p.add_argument("--repeat", type=argtypes.positive_int(100, "runs"), default=3,
                   help="runs of each fault (worst reported)")  # fmt: skip
    p.add_argument("--minutes", type=argtypes.bounded_float(0.1, 1440, "minutes, a day at most"),
                   default=10.0, help="length of the soak")  # fmt: skip
    p.add_argument("--out", type=argtypes.output_dir, default=Path("bench-results"))


@dataclass(frozen=True)
class Command:
    """One ``bodynet`` command: what it runs and how its arguments are added.

    ``run`` and ``arguments`` are ``"module:function"``; neither module is
    imported unless this command is the one being parsed. ``run(args) -> int``
    gets the parsed arguments; ``arguments(parser)`` adds them to the
    command's own parser. A command with sub-commands (``bridge can``...)
    leaves ``run`` empty: its hook gives each sub-command a ``func`` default."""

    help: str
    arguments: str
    run: str | None = None


#: Every command, in the order ``bodynet --help`` lists them. A new command is
#: one line here; its module keeps heavy imports inside the functions that run.
COMMANDS: dict[str, Command] = {
    "decode": Command("decode a capture file to JSON lines",
                      "bodynet.cli.main:add_decode_args", "bodynet.cli.main:cmd_decode"),
    "demo": Command("the main job: show the system at work",
                    "bodynet.cli.main:add_demo_args", "bodynet.cli.main:cmd_demo"),
    "bridge": Command("bridge a device (CAN bus, serial port, UDP) onto Zenoh",
                      "bodynet.cli.nodes:add_bridge_args"),
    "emulate": Command("emulated hardware only, for a bridge to open",
                       "bodynet.cli.nodes:add_emulate_args"),
    "node": Command("emulated sensors with their bridge, live on Zenoh",
                    "bodynet.cli.nodes:add_node_args"),
    "gateway": Command("calibration and kinematics: raw samples in, poses out",
                       "bodynet.cli.gateway:add_gateway_args", "bodynet.cli.gateway:cmd_gateway"),
    "subjects": Command("list the subjects on the network and their branches",
                        "bodynet.cli.gateway:add_subjects_args",
                        "bodynet.cli.gateway:cmd_subjects"),
    "calibrate": Command("calibrate sensors of the subject",
                         "bodynet.cli.gateway:add_calibrate_args"),
    "process": Command("run the gateway over a capture into an MCAP file",
                       "bodynet.cli.gateway:add_process_args", "bodynet.cli.gateway:cmd_process"),
    "view": Command("the body in Rerun, live or from a recording",
                    "bodynet.cli.clients:add_view_args", "bodynet.cli.clients:cmd_view"),
    "export": Command("export a recording to a standard format",
                      "bodynet.cli.clients:add_export_args"),
    "record": Command("record raw samples, poses, topology and health to MCAP",
                      "bodynet.cli.clients:add_record_args", "bodynet.cli.clients:cmd_record"),
    "replay": Command("publish a recording's raw samples again",
                      "bodynet.cli.clients:add_replay_args", "bodynet.cli.clients:cmd_replay"),
    "report": Command("validation statistics of a recording (ROM, accuracy, repeatability, "
                      "ICC, Type A)",
                      "bodynet.cli.analysis:add_report_args", "bodynet.cli.analysis:cmd_report"),
    "game": Command("the arm-reaching rehabilitation game, in a browser",
                    "bodynet.cli.game:add_game_args", "bodynet.cli.game:cmd_game"),
    "lsl": Command("the live body as Lab Streaming Layer streams (LabRecorder)",
                   "bodynet.cli.live:add_lsl_args", "bodynet.cli.live:cmd_lsl"),
    "vmc": Command("the live body over the VMC protocol (Unity, VSeeFace, Blender add-ons)",
                   "bodynet.cli.live:add_vmc_args", "bodynet.cli.live:cmd_vmc"),
    "metrics": Command("clinical numbers live on body/@metrics: range of motion, repetitions, "
                       "smoothness", "bodynet.cli.live:add_metrics_args",
                       "bodynet.cli.live:cmd_metrics"),
    "certs": Command("a CA, certificates and Zenoh configs for a secure router and its clients",
                     "bodynet.cli.security:add_certs_args", "bodynet.cli.security:cmd_certs"),
    "router": Command("a Zenoh router for the body network (no zenohd needed)",
                      "bodynet.cli.main:add_router_args", "bodynet.cli.main:cmd_router"),
    "bench": Command("benchmarks, side by side with their baselines",
                     "bodynet.cli.main:add_bench_args", "bodynet.cli.main:cmd_bench"),
}  # fmt: skip


def resolve(spec: str) -> Callable[..., Any]:
    """The function a ``"module:function"`` string names (importing its module)."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)  # type: ignore[no-any-return]


class _Parser(argparse.ArgumentParser):
    """A parser that takes no abbreviation of an option: ``calibrate ole --from``
    is not ``--from-pairs``, ``process --out`` not ``--output``. Its sub-commands'
    parsers are of its class (``add_subparsers``), so none of them takes one either."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)


def build_parser(only: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The ``bodynet`` parser. Every command is listed with its help; the
    arguments are added for every command, or for those in ``only`` (the
    command about to run, so that no other command's module is imported)."""
    parser = _Parser(
        prog="bodynet",
        description="A distributed body-network gateway for wearable motion capture.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, command in COMMANDS.items():
        p = sub.add_parser(name, help=command.help)
        if only is None or name in only:
            resolve(command.arguments)(p)
            if command.run:
                p.set_defaults(command_run=command.run)
    return parser


def command_in(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names: its first word after the global options."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = command_in(argv)
    args = build_parser(only=(command,) if command else ()).parse_args(argv)
    logging.basicConfig(
        level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    func = getattr(args, "func", None) or resolve(args.command_run)
    try:
        with _offline_signals(args):
            code: int = func(args)
        if sys.stdout is not None:
            sys.stdout.flush()
    except (KeyboardInterrupt, SystemExit) as exc:  # SystemExit: outputs.Interrupted
        signum = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else getattr(exc, "signum", 0)
        if not signum or not _is_offline(args):
            raise
        print(f"bodynet {args.command}: interrupted by {signal.Signals(signum).name}: "
              "stopped; no output file is left half-written", file=sys.stderr)  # fmt: skip
        return 128 + signum
    except SessionError as exc:
        print(f"bodynet {args.command}: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        # stdout gone or full (a closed pipe, > /dev/full): the command's output is
        # lost; say so in one line instead of a traceback (other errors go on up)
        if exc.filename is not None or exc.errno not in _STREAM_ERRNOS:
            raise
        _stdout_gone()
        print(f"bodynet {args.command}: cannot write its output: {exc.strerror or exc}",
              file=sys.stderr)  # fmt: skip
        return 1
    return code


def _is_offline(args: argparse.Namespace) -> bool:
    """A command that works through files and stops when they are done (an
    interrupt is not its way to end, as it is a live service's)."""
    if args.command == "record":
        return getattr(args, "salvage", None) is not None
    if args.command == "view":
        return getattr(args, "recording", None) is not None
    return args.command in _OFFLINE


_OFFLINE = {"decode", "process", "export", "report"}


def _offline_signals(args: argparse.Namespace) -> contextlib.AbstractContextManager[None]:
    """An offline command ends on SIGTERM as on Ctrl-C: unwinding, told."""
    if not _is_offline(args):
        return contextlib.nullcontext()
    from bodynet.session.outputs import terminate_unwinds

    return terminate_unwinds()


#: Errors of writing to a stream (stdout): a closed pipe, a full device, a
#: closed descriptor.
_STREAM_ERRNOS = {errno.EPIPE, errno.ENOSPC, errno.EBADF, errno.EIO}


if __name__ == "__main__":
    sys.exit(main())
