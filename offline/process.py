"""``bodynet process``: exactly the gateway's solver, run over a capture.

The input is any capture ``bodynet decode`` reads (any format of a registered
source, ``nodes.sources``), or a bodynet recording's raw samples (MCAP, with
their flags: solved again). Samples are taken in the
capture's time order and grouped into ticks of at most ``1 / tick_hz``, a tick
ending early where a sensor already in it samples again (a data-matrix
frame, or a concentrator reply, is always one tick); after each tick the body
is solved as the live gateway would and the pose written to MCAP at the
tick's time, together with the raw samples. Orientation sensors are first
calibrated from a still window (the first ``tpose_s`` seconds, or ``window``;
none with ``tpose_s`` 0: the orientations are then the segments' own, in the
body's frame, as bodynet exports them;
of this capture or of another recording, ``calibrate_from``), unless the
profile already holds their mounts and no window is asked for: a window in
which the subject moved, too short, or missing a tag is refused
(:class:`~bodynet.gateway.heading.CalibrationRefused`). Where the tags'
heading is unknown (``auto``), a first pass finds it from a hinge's motion
(gateway/heading.py), so that every tick is solved with it; if no hinge moves,
the dofs the tags drive stay flagged ``uncalibrated``. Once known, the tags'
headings are held against drift by the joints' constraints tick by tick, the
same step as the live gateway's (``BodyHeading.step``). A site whose latest
sample is older than a few of its usual intervals at a tick's time (a tag gone
missing, its cells empty; the gateway's rule, ``solver.Rhythm``, in the
capture's time) is stale there, as live: listed in the pose's ``stale``, the
dofs resting on it flagged (``BodySolver.set_stale``), and the headings' search
and hold do not take its frozen sample.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from bodynet.clients.mcap_store import McapSink
from bodynet.core import keys
from bodynet.core.codecs.pose import PoseFrame
from bodynet.core.errors import DecodeError, Reason
from bodynet.core.keys import BRANCHES, Site
from bodynet.core.messages import OleAccel, Quat, RawSample, Reading
from bodynet.core.profile import OLE_DOF
from bodynet.core.subject import Profile, QuatWxyz
from bodynet.gateway.encoders import EncoderZero
from bodynet.gateway.frames import branch_views, pose_frame
from bodynet.gateway.heading import (
    BodyHeading,
    CalibrationRefused,
    WindowCalibration,
    calibrate_window,
)
from bodynet.gateway.solver import BodySolver, Rhythm, fresh_samples
from bodynet.nodes import sources
from bodynet.nodes.captures import RECORDING
from bodynet.nodes.sources.base import CapturedSample, CaptureError, CaptureStats

#: the calibration window when none is asked for: the capture's first seconds
TPOSE_S = 3.0


@dataclass
class ProcessResult:
    ticks: int
    samples: int
    calibrated: list[str]
    stats: CaptureStats
    calibration: dict[str, Any] | None = None  # the calibration report, when it calibrated
    heading: dict[str, Any] | None = None  # where the tags' heading stands (BodyHeading.state)
    refused: str | None = None  # why the default window could not calibrate (then it did not)
    #: seconds from the capture's first sample to its last
    span_s: float = 0.0


def recorded_samples(path: Path, fmt: str | None, stats: CaptureStats,
                     rate_hz: float | None = None, options: Mapping[str, Any] | None = None,
                     ) -> Iterator[tuple[float, Site, Reading]]:  # fmt: skip
    """(time s, site, reading) of a recording: an MCAP file's raw samples (``fmt``
    ``mcap`` or the file's suffix), or a capture of any source's format (``fmt``,
    or the one its suffix implies: ``.sto``, ``.log``...)."""
    if fmt is None:
        from bodynet.nodes.captures import format_of, looks_like

        fmt = RECORDING if path.suffix.lower() == ".mcap" else format_of(path)
        if fmt is None:
            what = looks_like(path)
            suffix = f"its suffix {path.suffix!r} names none" if path.suffix else "no suffix"
            raise ValueError(f"{path}: say which --format the recording is in ({suffix}"
                             + (f"; it looks like {what})" if what else ")"))  # fmt: skip
    for s in _captured(path, fmt, stats, rate_hz, options):
        yield s.t_s, s.site, s.reading


def _captured(path: Path, fmt: str, stats: CaptureStats, rate_hz: float | None,
              options: Mapping[str, Any] | None, wires: dict[Site, int] | None = None,
              ) -> Iterator[CapturedSample]:  # fmt: skip
    """A capture's samples in time order, each site's source byte into ``wires``: a
    source's file, or a bodynet recording's raw samples with their flags (a raw
    sample on another subject's key, ``alice/body/...``, is counted and left out:
    one body is processed at a time)."""
    if fmt != RECORDING:
        source = sources.by_format(fmt).from_options(options or {})
        for s in source.read(path, fmt, stats, rate_hz):
            if wires is not None:
                wires[s.site] = source.wire_id
            yield s
        return
    from bodynet.clients.mcap_store import read_raw

    for topic, _, sample in read_raw(path):
        try:
            site, _stream = keys.parse(topic)
        except keys.KeySpaceError:
            stats.rejected[Reason.UNKNOWN_NODE] += 1  # another subject's
            continue
        stats.decoded += 1
        if wires is not None:
            wires[site] = sample.source
        yield CapturedSample(sample.t_ns / 1e9, sample.reading, site, sample.flags)


def calibrate_recording(samples: Iterator[tuple[float, Site, Reading]], profile: Profile,
                        window: tuple[float, float], pose: str | None = None,
                        strict: bool = True) -> WindowCalibration:  # fmt: skip
    """Calibrate the orientation sensors from ``window`` (seconds from the
    recording's first sample, the end excluded) of a recording: every tag the
    recording holds must be in it, still, and with ``strict`` for most of the
    window's length (see :func:`~bodynet.gateway.heading.calibrate_window`)."""
    start, end = window
    found: dict[Site, list[tuple[float, QuatWxyz]]] = {}
    first: float | None = None
    for t, site, reading in samples:
        first = t if first is None else first
        if isinstance(reading, Quat):
            seen = found.setdefault(site, [])
            if start <= t - first < end:
                seen.append((t, reading.wxyz))
    return calibrate_window(found, profile, pose, expected=found,
                            seconds=end - start if strict else None)  # fmt: skip


def _ticks(samples: Iterator[CapturedSample], period_s: float) -> Iterator[list[CapturedSample]]:
    """Samples grouped into ticks of at most ``period_s``; a tick ends early where
    a sensor already in it gives its next sample (a file sampled faster than the
    ticks, or whose times jitter across a tick's edge: none of its poses merged)."""
    tick: list[CapturedSample] = []
    seen: set[tuple[Site, type]] = set()
    for s in samples:
        kind = (s.site, type(s.reading))
        again = kind in seen and s.t_s > tick[-1].t_s  # not the same frame's
        if tick and (again or s.t_s >= tick[0].t_s + period_s - 1e-9):
            yield tick
            tick, seen = [], set()
        tick.append(s)
        seen.add(kind)
    if tick:
        yield tick


def _survey(path: Path, fmt: str, rate_hz: float | None, options: Mapping[str, Any] | None,
            profile: Profile) -> tuple[set[str], set[Site], float]:  # fmt: skip
    """Every site of a capture (the solver's expected sensors), its orientation
    sensors with no mount in the profile, and its span (s, first sample to last)."""
    topology: set[str] = set()
    uncalibrated: set[Site] = set()
    first, t = None, 0.0
    for t, site, reading in recorded_samples(path, fmt, CaptureStats(), rate_hz, options):
        first = t if first is None else first
        topology.add(site.raw_key)
        if isinstance(reading, Quat) and site.raw_key not in profile.imu_mounts:
            uncalibrated.add(site)
    return topology, uncalibrated, 0.0 if first is None else t - first


def _solver(profile: Profile, topology: set[str], as_given: bool) -> BodySolver:
    """The capture's solver: its whole topology known; ``as_given``: the orientations
    are calibrated as they are (no T-pose)."""
    solver = BodySolver(profile)
    solver.expect(topology, complete=True)
    if as_given:
        solver.assume_calibrated()
    return solver


class _Ages:
    """When each site's latest sample was taken, and its rhythm: which are stale at a
    tick's time (the live gateway's rule, in the capture's time)."""

    def __init__(self) -> None:
        self.times: dict[Site, float] = {}
        self.rhythms: dict[Site, Rhythm] = {}

    def seen(self, s: CapturedSample) -> None:
        self.times[s.site] = s.t_s
        rhythm = self.rhythms.get(s.site)
        if rhythm is None:
            rhythm = self.rhythms[s.site] = Rhythm()
        rhythm.seen(s.t_s)

    def stale(self, t_s: float) -> list[str]:
        """The raw keys of the sites stale at ``t_s``, sorted."""
        rhythms = self.rhythms
        return sorted(site.raw_key for site, t in self.times.items()
                      if t_s - t > rhythms[site].after_s)  # fmt: skip


def _find_heading(heading: BodyHeading, ticks: Iterator[list[CapturedSample]]) -> None:
    """The first pass: the tags' heading from a hinge's motion, if one moves (not
    from a stale site's frozen sample); an ``auto`` heading taken is watched to
    the capture's end (a joint that tilts later may break it: then each tag's is
    searched, and the ticks before are not solved with it)."""
    latest: dict[Site, RawSample] = {}
    ages = _Ages()
    for tick in ticks:
        for s in tick:
            latest[s.site] = RawSample(s.reading, 0, 0)
            ages.seen(s)
        fresh = fresh_samples(latest, ages.stale(tick[-1].t_s))
        if heading.searching:
            heading.update(tick[-1].t_s, fresh)
        elif heading.check is None or heading.check.verdict != "shared":
            break
        else:
            heading.watch(tick[-1].t_s, fresh, heading.profile)


def _hold_drift(heading: BodyHeading, t_s: float, latest: Mapping[Site, RawSample],
                solver: BodySolver) -> None:  # fmt: skip
    """The tags' headings held against drift after a solved tick, the live gateway's
    own step (the heading's search ended with the first pass)."""
    step = heading.step(t_s, latest, solver.profile, solver.encoder_zeros)
    if step is not None and step[0] in ("turned", "switched"):  # switched: none known
        heading.hold(solver, step[1])


def _solve_at(solver: BodySolver, latest: Mapping[Site, RawSample], stale: list[str],
              seq: int) -> PoseFrame:  # fmt: skip
    """The pose of tick ``seq``, the sites ``stale`` (``_Ages.stale``) flagged."""
    solver.set_stale(stale)
    return pose_frame(solver.solve(latest), seq, stale)


def _raw(s: CapturedSample, seq: int, wire_id: int, zeros: dict[str, EncoderZero]) -> RawSample:
    """A captured sample as the gateway takes it: a SmartSuit module's, flagged
    ``RESUMED`` by the capture's reader (which judges silences as a live bridge
    does), loses its encoder's zero in ``zeros`` (its node's power-on until then)."""
    sample = RawSample(s.reading, seq, round(s.t_s * 1e9), wire_id, s.flags)
    if type(s.reading) is OleAccel and s.site.name in OLE_DOF:
        zeros.setdefault(s.site.raw_key, EncoderZero()).take(sample)
    return sample


def _write_raw(sink: McapSink, site: Site, sample: RawSample, path: Path) -> None:
    """A raw sample into the recording; one MCAP cannot hold (a time before 1970)
    is a ``CaptureError`` naming the capture and the sample's time."""
    try:
        sink.write_raw(site.raw_key, sample, sample.t_ns)
    except DecodeError as exc:
        raise CaptureError(f"{path}: the sample of {site.raw_key} at {sample.t_ns / 1e9:g} s "
                           f"cannot be recorded: {exc}") from None  # fmt: skip


def _solver_of(heading: BodyHeading, topology: set[str], as_given: bool
               ) -> tuple[BodySolver, dict[str, EncoderZero]]:  # fmt: skip
    """The capture's solver once its heading is settled, told how well the headings
    found are known, and its encoders' zeros (by raw key, lost on a RESUMED sample)."""
    solver = _solver(heading.profile, topology, as_given)
    heading.hold(solver, heading.profile)
    solver.encoder_zeros = zeros = dict[str, EncoderZero]()
    return solver, zeros


def process(path: Path, fmt: str, out: Path, profile: Profile | None = None,
            rate_hz: float | None = None, tick_hz: float = 100.0,
            tpose_s: float | None = None, options: Mapping[str, Any] | None = None,
            calibration: tuple[Path, str | None] | None = None, *,
            window: tuple[float, float] | None = None,
            pose: str | None = None) -> ProcessResult:  # fmt: skip
    """Solve every tick of a capture and write poses and raw samples to ``out``
    (``options``: the source's capture options, e.g. an orientation file's ``map``).
    The calibration pose is the first ``tpose_s`` seconds (None: the first
    ``TPOSE_S``), or ``window``, of the capture or of ``calibration`` (another file
    of the session, and its format). Raises ``CalibrationRefused`` (nothing
    written) when an asked-for calibration window (``tpose_s``, ``window``,
    ``calibration``) cannot be used; when the default one cannot, the capture
    is solved without it (``ProcessResult.refused`` says why)."""
    profile = profile or Profile()
    topology, uncalibrated, span = _survey(path, fmt, rate_hz, options, profile)
    if topology and tpose_s is not None and window is None and calibration is None and (
            tpose_s > span):  # fmt: skip
        raise ValueError(f"--tpose-s {tpose_s:g} is longer than the capture ({span:.3g} s of "
                         "samples); nothing written")  # fmt: skip
    # no calibration window: the orientations are the segments' own, as given
    asked = tpose_s is not None or window is not None or calibration is not None
    as_given = bool(uncalibrated) and tpose_s == 0 and window is None and calibration is None
    calibrated, refused = None, None
    if as_given:
        # no calibration window: the orientations are the segments' own, in the body's
        # frame (as bodynet exports them), so their mounts are none and heading 0
        profile = replace(
            profile,
            imu_headings=MappingProxyType(
                {**profile.imu_headings, **{s.raw_key: 0.0 for s in uncalibrated}}
            ),
        )
    elif uncalibrated or window is not None or calibration is not None:
        where, where_fmt = calibration or (path, fmt)
        try:
            calibrated = calibrate_recording(
                recorded_samples(where, where_fmt, CaptureStats(), rate_hz, options),
                profile,
                window or (0.0, TPOSE_S if tpose_s is None else tpose_s),
                pose,
                strict=window is not None,
            )
        except CalibrationRefused as exc:
            if asked:
                raise
            # the default window (the capture's first seconds) is not a still pose: the
            # capture is solved uncalibrated, its tags' dofs flagged, and the user told
            refused = str(exc)
        else:
            profile = calibrated.apply(profile, pose)
    heading = BodyHeading(profile)
    if heading.unknown:  # a first pass: the heading from a hinge's motion, if one moves
        _find_heading(heading, _ticks(_captured(path, fmt, CaptureStats(), rate_hz, options),
                                      1.0 / tick_hz))  # fmt: skip
        heading.end_search()  # it had the whole capture
    solver, zeros = _solver_of(heading, topology, as_given)
    stats = CaptureStats()
    sink = McapSink(out)
    latest: dict[Site, RawSample] = {}
    ages = _Ages()
    seqs: dict[Site, int] = {}
    wires: dict[Site, int] = {}  # each site's source byte
    ticks = 0
    try:
        for tick in _ticks(_captured(path, fmt, stats, rate_hz, options, wires), 1.0 / tick_hz):
            for s in tick:
                seq = seqs[s.site] = seqs.get(s.site, -1) + 1
                sample = latest[s.site] = _raw(s, seq, wires[s.site], zeros)
                ages.seen(s)
                _write_raw(sink, s.site, sample, path)
            ticks += 1
            t_ns = round(tick[-1].t_s * 1e9)
            stale = ages.stale(tick[-1].t_s)
            frame = _solve_at(solver, latest, stale, ticks)
            _hold_drift(heading, tick[-1].t_s, fresh_samples(latest, stale), solver)
            sink.write_pose(keys.pose_key(), frame, t_ns)
            for branch, view in branch_views(frame, BRANCHES).items():
                sink.write_pose(keys.pose_key(branch), view, t_ns)
    finally:
        sink.close()
    return ProcessResult(
        ticks,
        stats.decoded,
        sorted(calibrated.mounts) if calibrated else [],
        stats,
        calibrated.report if calibrated else None,
        heading.state(),
        refused,
        span,
    )
