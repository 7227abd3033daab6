"""bodynet: a distributed body-network gateway for wearable motion capture.

(Argument parsing only: each subcommand calls a ``main``-style function of
its module with explicit arguments.)"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from bodynet.cli import analysis as analysis_cli
from bodynet.cli import clients as clients_cli
from bodynet.cli import game as game_cli
from bodynet.cli import gateway as gateway_cli
from bodynet.cli import nodes as nodes_cli
from bodynet.cli import security as security_cli
from bodynet.nodes.captures import CaptureStats, Format, read_capture, sample_json
from bodynet.nodes.motion import ROUTINES
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
    from bodynet.nodes.captures import looks_like

    stats = CaptureStats()
    out = sys.stdout
    if out is None:  # started with its stdout closed
        print("bodynet decode: stdout is closed: nowhere to write the samples", file=sys.stderr)
        return 2
    samples = read_capture(args.file, args.format, stats, args.rate_hz)
    try:
        while True:
            try:
                sample = next(samples)
            except StopIteration:
                break
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
        what = looks_like(args.file)
        print(f"bodynet decode: no {args.format} samples in {args.file}"
              + (f"; it looks like {what}" if what else ""), file=sys.stderr)  # fmt: skip
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


BENCHMARKS = ("decode", "solver", "gateway", "peer", "rate", "recorder", "faults", "soak")


def cmd_bench(args: argparse.Namespace) -> int:
    from bodynet.bench import decode, faults, gateway, peer, recorder, report, soak, solver

    only = args.only or [b for b in BENCHMARKS if b != "soak"]  # the soak on demand
    if "decode" in only:
        decode.run(seconds=args.seconds, out_dir=args.out)
    if "solver" in only:
        solver.run(seconds=args.seconds, out_dir=args.out, bodies=(1, 5, 20))
    if "gateway" in only:
        gateway.run(seconds=args.gateway_seconds, out_dir=args.out, bodies=tuple(args.bodies))
    if "peer" in only:
        peer.run(seconds=args.gateway_seconds, out_dir=args.out)
    if "rate" in only:
        gateway.run(seconds=args.gateway_seconds, out_dir=args.out, bodies=(1,),
                    rate_hz=args.rate_hz, name="rate")  # fmt: skip
    if "recorder" in only:
        recorder.run(seconds=args.seconds, out_dir=args.out)
    if "faults" in only:
        faults.run(out_dir=args.out, repeat=args.repeat)
    if "soak" in only:
        result = soak.run(minutes=args.minutes, out_dir=args.out)
        if not result["pass"]:
            print("bodynet bench: the soak failed (loss or memory growth)", file=sys.stderr)
            return 1
    report.write(args.out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bodynet",
        description="A distributed body-network gateway for wearable motion capture.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("decode", help="decode a capture file to JSON lines")
    p.add_argument("--format", required=True, choices=[f.value for f in Format])
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=None,
                   help="samples' time base where the capture has none "
                        "(concentrator: 1/22 ms; imu-central: 25 Hz)")  # fmt: skip
    p.add_argument("file", type=argtypes.input_file)
    p.set_defaults(func=cmd_decode)

    p = sub.add_parser("demo", help="the main job: show the system at work")
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
    p.set_defaults(func=cmd_demo)

    nodes_cli.add_parsers(sub)
    gateway_cli.add_parsers(sub)
    gateway_cli.add_process_parser(sub)
    clients_cli.add_parsers(sub)
    clients_cli.add_record_parsers(sub)
    analysis_cli.add_parsers(sub)
    game_cli.add_parsers(sub)
    security_cli.add_parsers(sub)

    p = sub.add_parser("router", help="a Zenoh router for the body network (no zenohd needed)")
    add_session_args(p, default_mode="router")
    p.set_defaults(func=cmd_router)

    p = sub.add_parser("bench", help="benchmarks, side by side with their baselines")
    p.add_argument("--seconds", type=argtypes.bounded_float(0.01, 3600, "seconds, an hour at most"),
                   default=1.0, help="time per decode measurement")  # fmt: skip
    p.add_argument("--gateway-seconds", default=10.0, help="time of the gateway run",
                   type=argtypes.bounded_float(0.1, 3600, "seconds, an hour at most"))  # fmt: skip
    p.add_argument("--bodies", type=argtypes.positive_int(1000, "bodies"), nargs="+",
                   default=[1, 5, 10, 15, 20, 50],
                   help="numbers of bodies fed to the gateway")  # fmt: skip
    p.add_argument("--only", action="append", choices=BENCHMARKS,
                   help="run only this benchmark (repeatable; default all but soak)")  # fmt: skip
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=1000.0,
                   help="per-node rate of the `rate` benchmark (default 1000)")  # fmt: skip
    p.add_argument("--repeat", type=argtypes.positive_int(100, "runs"), default=3,
                   help="runs of each fault (worst reported)")  # fmt: skip
    p.add_argument("--minutes", type=argtypes.bounded_float(0.1, 1440, "minutes, a day at most"),
                   default=10.0, help="length of the soak")  # fmt: skip
    p.add_argument("--out", type=argtypes.output_dir, default=Path("bench-results"))
    p.set_defaults(func=cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    try:
        code: int = args.func(args)
    except SessionError as exc:
        print(f"bodynet {args.command}: {exc}", file=sys.stderr)
        return 2
    return code


if __name__ == "__main__":
    sys.exit(main())
