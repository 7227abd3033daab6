"""Command-line wiring of the analysis clients: ``bodynet report``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bodynet.session import argtypes

#: ``START:END`` in seconds from the recording's start.
still_range = argtypes.time_window

#: The report's formats, by the output's suffix.
REPORT_SUFFIXES = (".md", ".html", ".htm")


def report_output(text: str) -> Path:
    """``-o``: a Markdown (``.md``) or HTML (``.html``) file; any other name is
    refused (a report named ``rep`` would be Markdown no viewer recognises)."""
    path = argtypes.output_file_new_folder(text)
    if path.suffix.lower() not in REPORT_SUFFIXES:
        argtypes.fail(f"{text[:200]!r} is neither .md nor .html: the report is Markdown "
                      f"({path.name}.md) or HTML ({path.name}.html)")  # fmt: skip
    return path


def cmd_report(args: argparse.Namespace) -> int:
    from bodynet.clients.report import ReportError, make_report
    from bodynet.session.outputs import OutputError, check_output

    out = args.output or args.recordings[0].with_name(args.recordings[0].stem + "-report.md")
    try:
        if out.parent.is_dir():  # else a new folder, made by the report: no input is in it
            check_output(out, [*args.recordings, args.reference])
    except OutputError as exc:
        print(f"bodynet report: {exc}", file=sys.stderr)
        return 2
    try:
        files = make_report(args.recordings, out, args.reference, args.joint, args.still,
                            args.still_s, not args.no_trials)  # fmt: skip
    except ReportError as exc:
        print(f"bodynet report: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        why = (
            str(exc)
            if isinstance(exc, OutputError)
            else f"cannot write {out}: {exc.strerror or exc}"
        )
        print(f"bodynet report: {why}", file=sys.stderr)
        return 2
    plots = ", ".join(f.name for f in files[1:])
    print(f"bodynet report: {files[0]} ({len(files) - 1} plots beside it: {plots})",
          file=sys.stderr)  # fmt: skip
    return 0


def add_report_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recordings", type=argtypes.input_file, nargs="+",
                   help="MCAP recording(s) with poses; several: each one is a trial")  # fmt: skip
    p.add_argument("-o", "--output", type=report_output,
                   help="report.md or report.html, plots beside it "
                        "(default <recording>-report.md)")  # fmt: skip
    p.add_argument("--reference", type=argtypes.input_file,
                   help="reference angles: a recording (its ground truth, else its poses) or a "
                        "CSV with t_s and <joint>_<dof>_deg columns (default: the recording's "
                        "own ground truth, if it has any)")  # fmt: skip
    p.add_argument(
        "--joint",
        type=argtypes.free_text(100),
        help="the channel whose repetitions cut the trials, e.g. "
        "left_elbow_flexion_deg (default: the smoothest repeating one)",
    )
    still = p.add_mutually_exclusive_group()
    still.add_argument(
        "--still",
        type=still_range,
        metavar="START:END",
        help="still window for Type A, s from the start (default: auto)",
    )
    still.add_argument("--still-s", default=2.0,
                       type=argtypes.bounded_float(0.1, 3600.0, "seconds of a still window"),
                       help="length of the auto-detected still window (default 2 s)")  # fmt: skip
    p.add_argument("--no-trials", action="store_true",
                   help="leave out repeatability and ICC (e.g. a still recording)")  # fmt: skip
