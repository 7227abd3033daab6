"""Command-line wiring of the analysis clients: ``bodynet report``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def still_range(text: str) -> tuple[float, float]:
    """``START:END`` in seconds from the recording's start."""
    try:
        start, end = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not START:END in seconds") from None
    if not 0 <= start < end:
        raise argparse.ArgumentTypeError(f"{text!r}: need 0 <= START < END")
    return start, end


def cmd_report(args: argparse.Namespace) -> int:
    from bodynet.clients.report import ReportError, make_report

    out = args.output or args.recordings[0].with_name(args.recordings[0].stem + "-report.md")
    try:
        files = make_report(args.recordings, out, args.reference, args.joint, args.still,
                            args.still_s, not args.no_trials)  # fmt: skip
    except ReportError as exc:
        print(f"bodynet report: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bodynet report: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"bodynet report: {files[0]} ({len(files) - 1} plots beside it)", file=sys.stderr)
    return 0


def add_report_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recordings", type=Path, nargs="+",
                   help="MCAP recording(s) with poses; several: each one is a trial")  # fmt: skip
    p.add_argument("-o", "--output", type=Path,
                   help="report.md or report.html, plots beside it "
                        "(default <recording>-report.md)")  # fmt: skip
    p.add_argument("--reference", type=Path,
                   help="reference angles: a recording (its ground truth, else its poses) or a "
                        "CSV with t_s and <joint>_<dof>_deg columns (default: the recording's "
                        "own ground truth, if it has any)")  # fmt: skip
    p.add_argument(
        "--joint",
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
    still.add_argument("--still-s", type=float, default=2.0,
                       help="length of the auto-detected still window (default 2 s)")  # fmt: skip
    p.add_argument("--no-trials", action="store_true",
                   help="leave out repeatability and ICC (e.g. a still recording)")  # fmt: skip
