"""``bodynet export <format>``: the table of export writers.

Every format is one module of this package, named after the format, with one
function ``write(track, out, options) -> Written``: ``track`` is the
recording's poses as arrays (:class:`~bodynet.clients.exports.track.PoseTrack`,
on a regular frame grid when the entry says ``regular``), ``out`` the file to
write (atomically: complete or not at all), ``options`` the values of the
entry's own command-line options by their ``dest``. The table below is all
the CLI knows of a format: its name, its file suffix, its help line and its
options. Importing this module loads no numpy, scipy or mcap (``bodynet
export --help`` stays fast); a writer's module is imported when it runs.

To add a format: write ``<format>.py`` with ``write`` and add its entry here.

Unmeasured dofs (``core.codecs.pose.is_measured`` is false: flagged
``unobserved``, ``held``, ``uncalibrated``...) are written as the format allows
an absent value: an empty CSV cell, NaN in OpenSim's tables, an invalid C3D
point; BVH and ASF/AMC, which have no absent value, hold the last measured
value and say how many they held.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bodynet.session import argtypes

if TYPE_CHECKING:
    from bodynet.clients.exports.track import PoseTrack


@dataclass(frozen=True)
class Option:
    """One command-line option of a writer: argparse's flags and keywords."""

    flags: tuple[str, ...]
    kwargs: Mapping[str, Any] = field(default_factory=dict)

    @property
    def dest(self) -> str:
        if "dest" in self.kwargs:
            return str(self.kwargs["dest"])
        long = next((f for f in self.flags if f.startswith("--")), self.flags[0])
        return long.lstrip("-").replace("-", "_")


@dataclass(frozen=True)
class Written:
    """What a writer wrote: ``count`` rows or frames, and notes for the user
    (values held, files written beside ``out``)."""

    count: int
    unit: str = "frames"
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Writer:
    """One export format: ``bodynet export <name>`` writes ``<stem><suffix>``."""

    name: str
    suffix: str
    help: str
    module: str  # bodynet.clients.exports.<module> has write(track, out, options)
    regular: bool = True  # frames on a regular grid (--rate-hz), else one row per pose
    options: tuple[Option, ...] = ()
    #: files written beside ``out``: (suffix, what it holds); ``out`` with that suffix
    sidecars: tuple[tuple[str, str], ...] = ()

    def write(self, track: PoseTrack, out: Path, options: Mapping[str, Any]) -> Written:
        module = importlib.import_module(f"{__name__}.{self.module}")
        written: Written = module.write(track, out, options)
        return written

    def check(self, out: Path, inputs: Sequence[Path | None]) -> None:
        """``OutputError`` unless every file writing ``out`` makes, ``out`` and
        its sidecars, may be written (``check_output``), each a file of its own."""
        from bodynet.session.outputs import OutputError, check_output

        check_output(out, inputs)
        for suffix, what in self.sidecars:
            beside = out.with_suffix(suffix)
            if argtypes.same_file(beside, out):
                raise OutputError(f"refusing to write {out}: the {what} is written beside "
                                  f"it as {beside}, the same file; choose another output "
                                  f"(such as {out.with_suffix(self.suffix)})")  # fmt: skip
            check_output(beside, inputs)


#: ``--profile``: the subject's segment lengths (End Sites, ASF bone lengths);
#: the CLI reads the file and gives the writer ``options["skeleton"]``.
PROFILE = Option(("--profile",), {"type": argtypes.input_file,
                                  "help": "subject profile: segment lengths "
                                          "(hands, feet, head)"})  # fmt: skip
UP = Option(("--up",), {"choices": ("y", "z"), "default": "y",
                        "help": "y: Y up, facing +Z (the format's usual axes); "
                                "z: bodynet's axes (X forward, Z up)"})  # fmt: skip
UNITS = Option(("--units",), {"choices": ("m", "cm"), "default": "m"})

WRITERS: Mapping[str, Writer] = {
    w.name: w
    for w in (
        Writer(
            "csv",
            ".csv",
            "joint angles, rotations and joint centres, one row per tick",
            "csv",
            regular=False,
        ),
        Writer(
            "bvh",
            ".bvh",
            "BVH motion (Blender, MotionBuilder...): the body model's hierarchy, segment "
            "rotations per frame",
            "bvh",
            options=(UP, UNITS, PROFILE),
        ),
        Writer(
            "c3d",
            ".c3d",
            "C3D (biomechanics): joint centres in mm and joint angles as angle points",
            "c3d",
        ),
        Writer(
            "mot",
            ".mot",
            "OpenSim motion: joint angles as the coordinates of OpenSim's full-body models, "
            "degrees",
            "mot",
        ),
        Writer(
            "sto",
            ".sto",
            "OpenSense IMU orientations: one <body>_imu quaternion column per segment, for "
            "OpenSim's IMU inverse kinematics",
            "sto",
        ),
        Writer(
            "amc",
            ".amc",
            "Acclaim motion (.amc) and skeleton (.asf, written beside it), as the CMU database's",
            "amc",
            options=(UP, UNITS, PROFILE),
            sidecars=((".asf", "skeleton"),),
        ),
    )
}


def writer(name: str) -> Writer:
    """The entry of format ``name``; ``KeyError`` if there is none."""
    return WRITERS[name]
