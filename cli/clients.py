"""Command-line wiring of the clients: ``view`` and ``export``."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from bodynet.session import add_session_args, argtypes, config_from_args, open_session

if TYPE_CHECKING:  # Rerun loads only when a view runs
    from bodynet.clients.view import Viewer

#: Frames per second of an export: a higher rate only repeats poses (and a
#: C3D at 1 MHz of a one-second recording takes gigabytes).
EXPORT_RATE_HZ = argtypes.bounded_float(0.1, 1000.0, "frames per second, 0.1 to 1000")
#: --rotate-s: 0 (never) or a file's age from half a second up.
ROTATE_S = argtypes.bounded_float(0.0, 7 * 86_400.0, "seconds, 0 for never, at most a week")


#: Frames an export may make of each recorded pose: resampling far above the
#: recording's own rate only repeats it (and costs memory: a C3D at 1 MHz of a
#: one-second recording took 10 GB).
MAX_EXPORT_FRAMES = 100


class _TooMany(Exception):
    """An export that would be mostly repeated frames."""


def cmd_export(args: argparse.Namespace) -> int:
    """``export <format>``: the recording's poses through the format's writer."""
    from bodynet.clients.exports import writer
    from bodynet.clients.exports.track import load_track, resample
    from bodynet.clients.mcap_store import StoreError
    from bodynet.core.subject import ProfileError

    entry = writer(args.kind)
    out = args.output or args.recording.with_suffix(entry.suffix)
    options = {o.dest: getattr(args, o.dest) for o in entry.options}
    try:
        entry.check(out, [args.recording, options.get("profile")])  # and the files beside it
        if options.get("profile"):
            from bodynet.core.skeleton import build_skeleton
            from bodynet.session import profile_file

            options["skeleton"] = build_skeleton(profile_file.load(options["profile"]).lengths)
        track = load_track(args.recording, progress=not args.quiet, every_tick=not entry.regular)
        if entry.regular:
            rate = args.rate_hz or track.measured_rate_hz()
            frames = (int(track.t_ns[-1] - track.t_ns[0]) / 1e9 * rate + 1) if len(track) else 0
            if frames > MAX_EXPORT_FRAMES * max(1, len(track)):
                raise _TooMany(f"--rate-hz {rate:g} makes {frames:.0f} frames of "
                               f"{len(track)} poses: no more than {MAX_EXPORT_FRAMES} a pose; "
                               "choose a lower rate")  # fmt: skip
            track = resample(track, rate)
        written = entry.write(track, out, options)
    except (StoreError, ProfileError, OSError, _TooMany) as exc:
        print(f"bodynet export: {exc}", file=sys.stderr)
        return 2
    for note in written.notes:
        print(f"bodynet export: {note}", file=sys.stderr)
    rate = f" at {track.rate_hz:g} Hz" if entry.regular else ""
    print(f"{written.count} {written.unit}{rate} -> {out}", file=sys.stderr)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    import os

    from bodynet.clients.mcap_store import StoreError
    from bodynet.clients.view import Viewer, view_live, view_recording

    if args.connect_viewer is not None:
        args.viewer, args.url = "connect", args.connect_viewer or args.url
    mode = args.viewer
    if mode == "none" and args.save is None:
        print("bodynet view: --viewer none (--headless) shows nothing and writes nothing "
              "without --save FILE.rrd", file=sys.stderr)  # fmt: skip
        return 2
    from bodynet.session.outputs import OutputError, check_output

    if args.save is not None:
        try:
            check_output(args.save, [args.recording])
        except OutputError as exc:
            print(f"bodynet view: {exc}", file=sys.stderr)
            return 2
    if mode == "auto":
        mode = (
            "none"
            if args.recording and args.save
            else ("native" if os.environ.get("DISPLAY") else "web")
        )
    stop = None
    if not args.recording:  # before anything is printed: a signal from then on ends it cleanly
        from bodynet.cli.nodes import stop_on_signals

        stop = stop_on_signals()
    try:
        viewer = Viewer.start(mode, args.save, args.url, args.web_port, args.grpc_port)
    except OSError as exc:  # e.g. --save in a folder that is not there
        why = f"cannot write {args.save} ({exc.strerror})" if exc.filename else str(exc)
        print(f"bodynet view: {why}", file=sys.stderr)
        return 2
    if viewer.address:
        print(f"bodynet view: web viewer at {viewer.address}", flush=True)
    complete = False  # the .rrd is kept only if complete; else nothing is left
    try:
        if args.recording:
            try:
                n = view_recording(args.recording, viewer)
            except StoreError as exc:
                print(f"bodynet view: {exc}", file=sys.stderr)
                return 2
            if viewer.address:  # the web viewer lives as long as this process
                _serve_until_stopped(viewer, n)
        else:
            assert stop is not None
            session = open_session(config_from_args(args))
            try:
                n = view_live(
                    session,
                    viewer,
                    stop,
                    on_live=lambda: print(
                        "bodynet view: live, poses arriving", file=sys.stderr, flush=True
                    ),
                )
            finally:
                session.close()
        complete = True
    finally:  # a live view ends on Ctrl-C or SIGTERM: promptly, a viewer gone or not
        if code := _close_viewer(viewer, complete, live=not args.recording):
            return code  # noqa: B012  the error said, the view is over
    bad = f", {viewer.bad} bad messages not shown" if viewer.bad else ""
    print(f"bodynet view: {n} poses{bad}" + (f", saved to {args.save}" if args.save else ""),
          file=sys.stderr)  # fmt: skip
    return 0


def _serve_until_stopped(viewer: Viewer, n: int) -> None:
    """Keep serving a recording's web viewer until Ctrl-C or SIGTERM."""
    from bodynet.cli.nodes import stop_on_signals

    stop = stop_on_signals()
    print(f"bodynet view: {n} poses in the web viewer at {viewer.address}; serving it "
          "until Ctrl-C", file=sys.stderr, flush=True)  # fmt: skip
    stop.wait()


def _close_viewer(viewer: Viewer, keep: bool, live: bool = False) -> int:
    """Close the view's sinks: 0, or 1 with one line if one could not be. A
    viewer that takes nothing would hold Rerun, and the process, for ever: the
    process then ends at once, on an interrupt too (the .rrd, nameless until it
    is whole, leaves nothing). ``live``: stopped by Ctrl-C or SIGTERM, the viewer
    is waited for only briefly."""
    import os
    import signal

    from bodynet.clients.view import STOPPED_FLUSH_S

    code = 0
    try:
        viewer.close(keep=keep, patience_s=STOPPED_FLUSH_S if live else None)
    except OSError as exc:  # the .rrd could not be put in place (a full disk), no viewer
        print(f"bodynet view: {exc}", file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, SystemExit) as exc:  # SystemExit: outputs.Interrupted
        signum = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else getattr(exc, "signum", 0)
        if not viewer.stuck or not signum:
            raise
        print(f"bodynet view: interrupted by {signal.Signals(signum).name} while the viewer "
              f"at {viewer.url} took nothing: stopped", file=sys.stderr)  # fmt: skip
        code = 128 + signum
    if viewer.stuck:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code or 1)
    return code


#: Rerun's schemes only: it refuses http:// and https:// (its web viewer's address
#: is not where a viewer takes a recording)
_VIEWER_URL = argtypes.url("rerun", "rerun+http", "rerun+https")


def add_view_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=argtypes.input_file, nargs="?",
                   help="an MCAP recording (else: live)")  # fmt: skip
    p.add_argument("--viewer", choices=("auto", "native", "web", "connect", "none"), default="auto",
                   help="a window (if there is a display), the web viewer, or a running "
                        "viewer (--url); 'none' with --save writes the .rrd only")  # fmt: skip
    p.add_argument("--save", type=argtypes.output_file,
                   help="also write the recording to this .rrd")  # fmt: skip
    p.add_argument("--url", type=_VIEWER_URL, help="with --viewer connect: the viewer's gRPC url")
    # Rerun's usual script flags; its --connect is --connect-viewer here, because
    # -e/--connect is Zenoh's, as on every bodynet command
    p.add_argument("--serve-web", dest="viewer", action="store_const", const="web",
                   help="same as --viewer web")  # fmt: skip
    p.add_argument("--headless", dest="viewer", action="store_const", const="none",
                   help="same as --viewer none (with --save: the .rrd only)")  # fmt: skip
    p.add_argument(
        "--connect-viewer",
        metavar="URL",
        type=_VIEWER_URL,
        nargs="?",
        const="",
        help="same as --viewer connect --url URL (default: Rerun's local viewer)",
    )
    p.add_argument("--web-port", type=argtypes.port, default=None,
                   help="with --viewer web (default 9090)")  # fmt: skip
    p.add_argument("--grpc-port", type=argtypes.port, default=None,
                   help="with --viewer web (default 9876)")  # fmt: skip
    add_session_args(p)


def add_export_args(p: argparse.ArgumentParser) -> None:
    from bodynet.clients.exports import WRITERS

    esub = p.add_subparsers(dest="kind", required=True, metavar="FORMAT")
    for entry in WRITERS.values():
        e = esub.add_parser(entry.name, help=entry.help)
        e.add_argument("recording", type=argtypes.input_file, help="an MCAP file with poses")
        e.add_argument(
            "-o",
            "--output",
            type=argtypes.output_file,
            help=f"the file to write (default: the recording's name, {entry.suffix})",
        )
        if entry.regular:
            e.add_argument("--rate-hz", type=EXPORT_RATE_HZ, default=None,
                           help="frame rate (default: the recording's own tick rate)")  # fmt: skip
        for option in entry.options:
            e.add_argument(*option.flags, **option.kwargs)
        e.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
        e.set_defaults(func=cmd_export)


def cmd_record(args: argparse.Namespace) -> int:
    import time

    from bodynet.session.memory import limit_malloc_arenas

    limit_malloc_arenas()  # before any thread (numpy's, Zenoh's) takes an arena of its own
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.clients.mcap_store import StoreError, salvage_report
    from bodynet.clients.recorder import ADMIN_KEYS, DEFAULT_KEYS, Recorder, admin_left_out

    if args.salvage:
        from bodynet.session.outputs import check_output

        try:
            check_output(args.output, [args.salvage])
            saved = salvage_report(args.salvage, args.output)
        except (StoreError, OSError) as exc:
            print(f"bodynet record: {exc}", file=sys.stderr)
            return 2
        print(f"bodynet record: {saved.messages} messages salvaged into {args.output}; "
              f"{saved.summary()}", file=sys.stderr)  # fmt: skip
        uncounted = saved.uncounted()
        if uncounted:
            print(f"bodynet record: {args.salvage}: {uncounted}", file=sys.stderr)
        return 0
    if args.keys and admin_left_out(args.keys):
        print("bodynet record: warning: these key expressions match no admin key, so the "
              "recording holds no topology, health or metrics (wildcards never match Zenoh's "
              f"'@' chunks); add {' '.join(ADMIN_KEYS)} to keep them", file=sys.stderr)  # fmt: skip
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    try:
        recorder = Recorder(session, args.output, args.keys or DEFAULT_KEYS,
                            int(args.rotate_mb * 1e6), args.rotate_s)  # fmt: skip
    except OSError as exc:
        session.close()
        print(f"bodynet record: cannot write {args.output}: {exc.strerror or exc}",
              file=sys.stderr)  # fmt: skip
        return 2
    if recorder.files[0] != args.output:  # an earlier recording is never emptied
        print(f"bodynet record: {args.output} exists (kept); recording to {recorder.files[0]}",
              file=sys.stderr)  # fmt: skip
    start = time.monotonic()
    try:
        while not stop.wait(1.0) and recorder.error is None:
            elapsed = time.monotonic() - start
            print(f"\rrecording {recorder.files[-1]}: {recorder.messages} messages, "
                  f"{elapsed:.0f} s, {recorder.messages / elapsed:.0f}/s", end="",
                  file=sys.stderr, flush=True)  # fmt: skip
    finally:
        recorder.close()
        session.close()
    print(f"\nbodynet record: {recorder.messages} messages in "
          f"{', '.join(map(str, recorder.files))}", file=sys.stderr)  # fmt: skip
    if recorder.rejected:
        print(f"bodynet record: {sum(recorder.rejected.values())} messages refused "
              f"({recorder.rejected.summary()})", file=sys.stderr)  # fmt: skip
    if recorder.error is not None:
        last = recorder.files[-1]
        print(f"bodynet record: cannot write {last}: "
              f"{recorder.error.strerror or recorder.error}; the recording stopped there "
              f"(`bodynet record --salvage {last} -o <new file>` keeps what reached the disk)",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.clients.mcap_store import StoreError, channel_counts
    from bodynet.clients.replay import RAW_SCHEMA_NAME, replay, topic_filter

    nothing = (f"bodynet replay: nothing to replay: {args.recording} holds no raw samples"
               + (" on these keys" if args.keys else ""))  # fmt: skip
    try:  # the file first: a mistake there is told before waiting for the router
        wanted = topic_filter(args.keys or None)
        counts = channel_counts(args.recording)
    except (ValueError, StoreError) as exc:
        print(f"bodynet replay: {exc}", file=sys.stderr)
        return 2
    if counts is not None and not any(c.schema == RAW_SCHEMA_NAME and c.messages
                                      and wanted(c.topic) for c in counts):  # fmt: skip
        print(nothing, file=sys.stderr)  # its summary says so: no router needed to tell
        return 2
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    try:
        n = replay(session, args.recording, stop, args.keys or None, args.speed, args.loop,
                   progress=not args.quiet)  # fmt: skip
    except StoreError as exc:
        print(f"bodynet replay: {exc}", file=sys.stderr)
        return 2
    finally:
        session.close()
    if not n:
        print(nothing, file=sys.stderr)
        return 2
    print(f"bodynet replay: {n} samples published", file=sys.stderr)
    return 0


def _rotate_mb(text: str) -> float:
    value = argtypes.non_negative_float(1e6, "MB, 0 for never, at most a terabyte")(text)
    if 0 < value < 1:
        argtypes.fail(f"{text!r}: a file of less than 1 MB (0 for never)")
    return value


def _rotate_s(text: str) -> float:
    value = ROTATE_S(text)
    if 0 < value < 0.5:
        argtypes.fail(f"{text!r}: files shorter than half a second (0 for never)")
    return value


def add_record_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("keys", nargs="*", type=argtypes.key_expr,
                   help="key expressions (default: every raw sample and pose, the topology, "
                        "every health and the metrics). Wildcards never match Zenoh's '@' "
                        "chunks: 'body/**' leaves out topology, health and metrics; name "
                        "them too (body/@topology 'body/@health/**' body/@metrics)")  # fmt: skip
    p.add_argument("-o", "--output", type=argtypes.output_file, required=True,
                   help="the MCAP file")  # fmt: skip
    p.add_argument("--rotate-mb", type=_rotate_mb, default=0.0,
                   help="start a new file past this size (0: never; at least 1 MB)")  # fmt: skip
    p.add_argument("--rotate-s", type=_rotate_s, default=0.0,
                   help="start a new file past this age (0: never; at least 0.5 s)")  # fmt: skip
    p.add_argument("--salvage", type=argtypes.input_file,
                   help="turn this unfinished file into -o, and stop")  # fmt: skip
    add_session_args(p)


def add_replay_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=argtypes.input_file)
    p.add_argument("--keys", nargs="*", type=argtypes.key_expr,
                   help="key expressions of the topics to replay, such as 'body/arm/left/**' "
                        "(default: every raw sample)")  # fmt: skip
    p.add_argument("--speed", default=1.0, help="2 plays twice as fast",
                   type=argtypes.bounded_float(0.01, 1000.0, "times real time"))  # fmt: skip
    p.add_argument("--loop", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_session_args(p)
