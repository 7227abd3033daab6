"""Poses against the truth (``bench --only truth``): no timing, only the numbers.

Each scenario is an emulated body (:class:`~bodynet.nodes.emulator.BodyEmulator`
with its :class:`~bodynet.nodes.emulator.Realism`: tag noise, tissue wobble,
shared, drifting or independent headings, a facing) holding its calibration
pose for ``HOLD_S`` and then moving; every sensor samples on its own timer (an
offset, a clock off by up to 100 ppm, jitter, drops; or all locked together),
a tag may die, SmartSuit arm modules may sit beside or instead of the arm's
tags. The samples are written as a bodynet recording (MCAP raw samples, as the
recorder writes them), solved by ``bodynet process`` (``offline.process``: the
gateway's calibration, heading search and hold, staleness and solver), and the
poses read back: every dof not flagged is compared with the truth. Per
scenario: the share of them off by more than twice their ``unc_deg`` (also
against the truth anywhere between the pose's oldest source sample and its
time: lag rather than error), the share off by more than 10 deg, the RMS, the
worst dofs. A shoulder's dofs while its abduction is past 60 deg (near its
gimbal lock) are counted apart.
"""

from __future__ import annotations

import itertools
import json
import math
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from bodynet.clients.mcap_store import McapSink, read_poses
from bodynet.core.codecs.pose import PoseFrame, is_measured
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import RawSample, Source
from bodynet.core.skeleton import CALIBRATION_POSES
from bodynet.core.subject import Profile
from bodynet.gateway.heading import with_headings
from bodynet.nodes.emulator import (
    BodyEmulator,
    EmulatedSensor,
    Headings,
    Kind,
    Realism,
    imu_tags,
    smartsuit_sensors,
)
from bodynet.nodes.motion import ROUTINES, Routine, bow, eased, heading_protocol
from bodynet.nodes.sources.base import CaptureStats
from bodynet.offline.process import ProcessResult, calibrate_recording, process, recorded_samples

Angles = Callable[[float], dict[str, float]]

#: the calibration pose is held this long (``bodynet process``'s default window)
HOLD_S = 3.0
#: then eased into the motion over this long
BLEND_S = 1.0
#: sample times fall on this grid (one emulator step per grid point serves every
#: sensor due there: the emulator costs per step, not per sensor)
GRID_S = 0.005
#: a shoulder's dofs are counted apart while its abduction is past this (gimbal lock)
GIMBAL_ABDUCTION_DEG = 60.0
#: the tag that dies in the ``die-`` scenarios
LEFT_THIGH = "body/leg/left/thigh/raw"
#: worst dofs listed per scenario (each dof once)
WORST = 6


@dataclass(frozen=True)
class Scenario:
    """One emulated session; ``seconds`` from the first sample, the pose held first."""

    name: str
    motion: str = "walk"  # a routine of nodes.motion, "bow", or "protocol" (the heading protocol)
    pose: str = "tpose"
    headings: Headings = Headings.SHARED
    heading_mode: str = "auto"  # the profile's mode, or "given": each tag's own, told calibrated
    noise: float = 0.3  # deg, each tag's orientation noise
    wobble: float = 0.0  # deg, tissue wobble
    drift: float = 0.0  # deg/min
    facing: float = 0.0  # deg
    rate_hz: float = 50.0
    timers: str = "independent"  # or "locked": every sensor sampled at once
    jitter_s: float = 0.002
    drop: float = 0.0  # share of samples lost after the pose
    die: tuple[str, float] | None = None  # (raw key, time s): that sensor sends nothing from then
    # "beside": SmartSuit left-arm modules and the tags; "instead": no arm tags; "hand":
    # shoulder and elbow modules instead of the upper arm's and forearm's tags, the hand's
    # tag kept (a tag below a module: its wrist from that tag alone)
    hybrid: str = ""
    seconds: float = 20.0
    seed: int = 1


def scenarios(seeds: Iterable[int] = (1, 2)) -> list[Scenario]:
    """Every scenario, for each seed."""
    S = Scenario
    out = []
    seeds = tuple(seeds)
    for seed in seeds:
        for m in ("walk", "reach", "upper-body", "lower-body", "full-body", "random",
                  "elbow-slow", "bow"):  # fmt: skip
            out.append(S(f"shared-auto-{m}-s{seed}", motion=m, seed=seed, facing=37.0 * seed))
    for seed in seeds:
        walk = S("walk", seed=seed)  # each named below
        protocol = replace(walk, motion="protocol", headings=Headings.INDEPENDENT,
                           heading_mode="independent", drift=3.0, seconds=30.0)  # fmt: skip
        # fmt: off
        out += [
            *(replace(walk, name=f"noise{n}-walk-s{seed}", noise=n, facing=200.0)
              for n in (0.3, 1.0, 2.0)),
            replace(walk, name=f"wobble3-walk-s{seed}", wobble=3.0, facing=110.0),
            replace(walk, name=f"wobble3-full-s{seed}", motion="full-body", wobble=3.0),
            replace(walk, name=f"fixed-walk-s{seed}", heading_mode="fixed"),
            replace(walk, name=f"drifting5-fixed-walk-s{seed}", headings=Headings.DRIFTING,
                    drift=5.0, heading_mode="fixed", seconds=30.0),
            replace(walk, name=f"shared-drift5-auto-walk-s{seed}", drift=5.0, facing=300.0),
            replace(protocol, name=f"indep-protocol-npose-s{seed}", pose="npose"),
            replace(protocol, name=f"indep-protocol-tpose-s{seed}"),
            replace(walk, name=f"given-indep-walk-s{seed}", headings=Headings.INDEPENDENT,
                    heading_mode="given"),
            replace(walk, name=f"locked-walk-s{seed}", timers="locked", jitter_s=0.0),
            replace(walk, name=f"jitter20-drop10-walk-s{seed}", jitter_s=0.02, drop=0.1),
            replace(walk, name=f"die-lthigh-walk-s{seed}", die=(LEFT_THIGH, 10.0)),
            replace(walk, name=f"hybrid-beside-reach-s{seed}", hybrid="beside", motion="reach"),
            replace(walk, name=f"hybrid-instead-reach-s{seed}", hybrid="instead",
                    motion="reach"),
            replace(walk, name=f"hybrid-instead-walk-s{seed}", hybrid="instead"),
            replace(walk, name=f"hybrid-hand-walk-s{seed}", hybrid="hand"),
            replace(walk, name=f"auto-indep-walk-s{seed}", headings=Headings.INDEPENDENT),
        ]
        # fmt: on
    return out


def motion(name: str, pose: str) -> Angles:
    """The truth's joint angles at t s: ``pose`` held for ``HOLD_S``, then eased into
    the motion ``name`` (the heading protocol follows the pose at once)."""
    still = dict(CALIBRATION_POSES[pose])
    if name == "protocol":  # its own first second is the pose
        protocol = heading_protocol(bow_at_s=16.0, pose=pose).angles
        return lambda t: dict(still) if t < HOLD_S else protocol(t - HOLD_S + 1.0)
    moving = _bows(still) if name == "bow" else ROUTINES[name].angles

    def angles(t: float) -> dict[str, float]:
        if t < HOLD_S:
            return dict(still)
        m = moving(t - HOLD_S)
        return m if t >= HOLD_S + BLEND_S else eased(still, m, (t - HOLD_S) / BLEND_S)

    return angles


def _bows(still: dict[str, float]) -> Angles:
    """A 50 deg bow from ``still`` every 4 s."""
    bowing = bow(depth_deg=50.0)
    return lambda t: {**still, **bowing(t % 4.0)}


def sensors_of(sc: Scenario) -> list[EmulatedSensor]:
    """The scenario's sensors: the fifteen tags, with or without the left arm's modules."""
    tags = imu_tags()
    if sc.hybrid == "beside":
        return [*tags, *smartsuit_sensors([LEFT_ARM])]
    if sc.hybrid == "instead":
        return [s for s in tags if s.site.branch != LEFT_ARM] + smartsuit_sensors([LEFT_ARM])
    if sc.hybrid == "hand":
        kept = [s for s in tags if s.site.branch != LEFT_ARM or s.site.name == "hand"]
        return kept + [s for s in smartsuit_sensors([LEFT_ARM]) if s.site.name != "wrist"]
    return tags


def schedule(sc: Scenario, sensors: Sequence[EmulatedSensor],
             rng: np.random.Generator) -> list[tuple[float, int]]:  # fmt: skip
    """(time s, sensor index) of every sample, in time order, on ``GRID_S``: each
    sensor on its own timer (or all locked), jittered, some dropped, one dying."""
    period = 1.0 / sc.rate_hz
    events = []
    for i, sensor in enumerate(sensors):
        offset, own = 0.0, period
        if sc.timers != "locked":
            offset, own = rng.uniform(0, period), period * (1 + rng.uniform(-100, 100) * 1e-6)
        end = sc.die[1] if sc.die and sc.die[0] == sensor.site.raw_key else sc.seconds
        for k in itertools.count():
            t = offset + k * own + (rng.uniform(0, sc.jitter_s) if sc.jitter_s else 0.0)
            if t >= min(end, sc.seconds):
                break
            if sc.drop and t > HOLD_S and rng.random() < sc.drop:
                continue
            events.append((round(t / GRID_S) * GRID_S, i))
    return sorted(set(events))  # a sensor twice on one grid point: once


def record(sc: Scenario, body: BodyEmulator, path: Path) -> None:
    """The scenario's samples as a bodynet recording: each sensor's raw samples on
    its key, at its own times, numbered per sensor (as the recorder writes them)."""
    events = schedule(sc, body.sensors, np.random.default_rng(sc.seed + 100))
    seq = [0] * len(body.sensors)
    sink = McapSink(path)
    try:
        at, readings = -1.0, []
        for t, i in events:
            if t != at:
                at, readings = t, body.sample(t)[0]
            sensor = body.sensors[i]
            # tags stamped when taken, each on its own timer, as SlimeVR trackers are
            # (an IMU central's stamp is its line's arrival: STAMP_SPREAD_S)
            source = Source.SLIMEVR if sensor.kind is Kind.TAG else Source.CAN
            t_ns = round(t * 1e9)
            sink.write_raw(sensor.site.raw_key, RawSample(readings[i], seq[i], t_ns, source), t_ns)
            seq[i] += 1
    finally:
        sink.close()


def profile_of(sc: Scenario, body: BodyEmulator, recording: Path) -> Profile:
    """The subject's profile: the heading mode, or (``given``) as a user tells each
    tag's heading: calibrated from the held pose of ``recording`` first (a calibration
    drops the headings it had, ``heading.dropped_note``), then each tag's heading told
    against where the subject faced in that pose (``R_s = Rz(psi) R_seg M``)."""
    if sc.heading_mode != "given":
        return Profile(pose=sc.pose, heading=sc.heading_mode)
    profile = Profile(pose=sc.pose, heading="auto")
    samples = recorded_samples(recording, "mcap", CaptureStats())
    calibrated = calibrate_recording(samples, profile, (0.0, HOLD_S), sc.pose, strict=False)
    # the emulator's tag frames: turned by their heading; with shared ones, the
    # subject faced ``facing`` among them (independent ones ignore it)
    facing = 0.0 if sc.headings is Headings.INDEPENDENT else sc.facing
    told = {s.site.raw_key: body.headings_deg[s.node] - facing
            for s in body.sensors if s.kind is Kind.TAG}  # fmt: skip
    return with_headings(calibrated.apply(profile, sc.pose), told)


def compare(poses: Path, truth: Angles) -> tuple[list[tuple[Any, ...]], dict[str, int]]:
    """Every measured dof of the poses after the held pose against the truth:
    rows (t, dof, error, error allowing the pose's lag, unc, near gimbal lock),
    and the counts of dofs measured and flagged."""
    return compare_frames(read_poses(poses), truth)


def compare_frames(frames: Iterable[tuple[int, PoseFrame]], truth: Angles, from_s: float = HOLD_S,
                   t0_ns: int = 0) -> tuple[list[tuple[Any, ...]], dict[str, int]]:  # fmt: skip
    """:func:`compare` of ``frames`` (time ns, pose), the truth's time 0 at ``t0_ns``
    (poses live: the wall-clock time the emulator's clock started), from ``from_s``."""
    rows = []
    counts = {"measured": 0, "flagged": 0}
    for t_ns, frame in frames:
        t = (t_ns - t0_ns) / 1e9
        if t < from_s:
            continue
        now = truth(t)
        oldest = (min(frame.sources.values()) - t0_ns) / 1e9 if frame.sources else t
        lagged = [truth(float(x)) for x in np.linspace(min(oldest, t), t, 6)]
        for dof, value in frame.angles_deg.items():
            if not is_measured(frame, dof):
                counts["flagged"] += 1
                continue
            counts["measured"] += 1
            error = value - now.get(dof, 0.0)
            lag_error = min(abs(value - then.get(dof, 0.0)) for then in lagged)
            side = dof.split("_")[0]
            gimbal = "shoulder" in dof and (
                now.get(f"{side}_shoulder_abduction_deg", 0.0) > GIMBAL_ABDUCTION_DEG
            )
            unc = frame.unc_deg.get(dof, math.nan)
            rows.append((round(t, 3), dof, round(error, 2), round(lag_error, 2), unc, gimbal))
    return rows, counts


def summarize(rows: Sequence[tuple[Any, ...]]) -> dict[str, Any] | None:
    """Shares off by more than twice the uncertainty (a dof with none: any error)
    and by more than 10 deg, RMS and the worst dofs of ``rows``."""
    if not rows:
        return None
    error = np.array([abs(r[2]) for r in rows])
    lag_error = np.array([r[3] for r in rows])
    unc = np.array([r[4] for r in rows], float)
    bound = 2 * np.where(np.isfinite(unc), unc, 0.0)
    worst, seen = [], set()
    for r in sorted(rows, key=lambda r: -abs(r[2])):
        if r[1] not in seen:
            seen.add(r[1])
            worst.append({"t": r[0], "dof": r[1], "err": r[2], "err_lag": r[3], "unc": r[4]})
            if len(worst) == WORST:
                break
    return {
        "n": len(rows),
        "share_gt_2unc": round(float(np.mean(error > bound)), 4),
        "share_lag_gt_2unc": round(float(np.mean(lag_error > bound)), 4),
        "share_gt_10": round(float(np.mean(error > 10)), 4),
        "unc_missing": int((~np.isfinite(unc)).sum()),
        "rms_deg": round(float(np.sqrt(np.mean(error**2))), 2),
        "worst": worst,
    }


def session(
    sc: Scenario, work: Path
) -> tuple[list[tuple[Any, ...]], dict[str, int], ProcessResult]:
    """Emulate, record, process and compare one scenario (files in ``work``, removed
    after): :func:`compare`'s rows and counts, and ``process``'s result."""
    truth = motion(sc.motion, sc.pose)
    realism = Realism(quat_noise_deg=sc.noise, tissue_wobble_deg=sc.wobble,
                      yaw_drift_deg_per_min=sc.drift, facing_deg=sc.facing,
                      headings=sc.headings)  # fmt: skip
    body = BodyEmulator(Routine(sc.name, "", truth), sensors_of(sc), realism=realism, seed=sc.seed)
    recording, poses = work / f"{sc.name}.mcap", work / f"{sc.name}.poses.mcap"
    record(sc, body, recording)
    # a profile holding every tag's mount (``given``) is not calibrated again
    profile = profile_of(sc, body, recording)
    result = process(recording, "mcap", poses, profile, tpose_s=HOLD_S, pose=sc.pose)
    rows, counts = compare(poses, truth)
    recording.unlink()
    poses.unlink()
    return rows, counts, result


def measure(sc: Scenario, work: Path) -> dict[str, Any]:
    """Emulate, record, process and compare one scenario (files in ``work``)."""
    cpu = time.process_time()
    rows, counts, result = session(sc, work)
    state = result.heading or {}
    return {
        "name": sc.name,
        "scenario": {k: (v.value if isinstance(v, Headings) else v) for k, v in asdict(sc).items()},
        "counts": counts,
        "heading": state.get("state"),
        "refused": result.refused,
        "other": summarize([r for r in rows if not r[5]]),
        "shoulder_near_90": summarize([r for r in rows if r[5]]),
        "cpu_s": round(time.process_time() - cpu, 1),
    }


def run(out_dir: Path, only: Iterable[str] | None = None, seeds: Iterable[int] = (1, 2),
        seconds: float | None = None) -> dict[str, Any]:  # fmt: skip
    """Every scenario (or those named in ``only``; each ``seconds`` long if given);
    ``truth.json`` and ``truth.md`` in ``out_dir``."""
    chosen = scenarios(seeds)
    if only is not None:
        wanted = set(only)
        unknown = wanted - {sc.name for sc in chosen}
        if unknown:
            raise ValueError(f"no truth scenario named {', '.join(sorted(unknown))}")
        chosen = [sc for sc in chosen if sc.name in wanted]
    if seconds is not None:
        chosen = [replace(sc, seconds=seconds) for sc in chosen]
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="bodynet-truth-") as work:
        results = [measure(sc, Path(work)) for sc in chosen]
    result = {"hold_s": HOLD_S, "grid_s": GRID_S, "scenarios": results}
    (out_dir / "truth.json").write_text(json.dumps(result, indent=1))
    (out_dir / "truth.md").write_text(table(results))
    return result


def _share(part: dict[str, Any] | None, key: str) -> str:
    return "-" if part is None else f"{100 * part[key]:.2f}%"


def table(results: Sequence[dict[str, Any]]) -> str:
    """The results as a markdown table, one row per scenario."""
    lines = [
        f"Every dof not flagged after the held pose ({HOLD_S:g} s) against the emulator's "
        "truth; a shoulder's dofs past "
        f"{GIMBAL_ABDUCTION_DEG:g} deg abduction counted apart (near its gimbal lock):",
        "",
        "| scenario | measured / flagged | beyond 2x unc | beyond 2x unc, lag allowed | "
        "beyond 10 deg | RMS deg | worst: dof, error, unc (deg) | shoulder near 90: "
        "beyond 2x unc | heading |",
        "|---|---:|---:|---:|---:|---:|---|---:|---|",
    ]
    for r in results:
        o, g = r["other"], r["shoulder_near_90"]
        w = o["worst"][0] if o else None
        worst = f"{w['dof']}, {w['err']}, {w['unc']:.2f}" if w else "-"
        lines.append(
            f"| {r['name']} | {r['counts']['measured']} / {r['counts']['flagged']} | "
            f"{_share(o, 'share_gt_2unc')} | {_share(o, 'share_lag_gt_2unc')} | "
            f"{_share(o, 'share_gt_10')} | {o['rms_deg'] if o else '-'} | {worst} | "
            f"{_share(g, 'share_gt_2unc')} | {r['heading'] or '-'} |"
        )
    return "\n".join(lines) + "\n"
