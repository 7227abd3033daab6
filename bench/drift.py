"""Calibration on real frames, measured on emulated suits (``bench --only drift``).

Two parts, no network (the gateway's own calibration, heading search, drift
correction and solver, called directly on emulated samples with a truth):

- **headings**: tags sharing one earth frame (magnetometer-based), the subject
  facing every 30 deg around the circle; a still T-pose, then a knee bends.
  Per facing: the heading found, the time from the first hinge movement to it,
  and the joints' error against the truth from then on.
- **drift**: 6-axis tags reset together, each then drifting at its own rate
  within +/- ``drift`` deg/min; the subject walks for ``minutes``. The joints'
  error against the truth, minute by minute, with and without the knee's hinge
  correction (:class:`~bodynet.gateway.heading.JointDrift`), and each joint
  group's fitted slope (deg/min) of its error; then with the three-dof joints'
  twist held too (hips, shoulders, lumbar, neck); and walking with twists held
  throughout (toes out, the head turned), IMU tags alone against the hybrid
  suit (the SmartSuit encoders at the hips and shoulders).
- **independent**: 6-axis tags each with a heading of its own that nothing gives
  (found from the N-pose and the motions that follow: a walk with reaches, a
  bow) and drifting; the same error by minute over ``minutes``, three seeds.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bodynet.core.keys import LEFT_ARM, LEFT_LEG, RIGHT_ARM, RIGHT_LEG
from bodynet.core.messages import RawSample
from bodynet.core.skeleton import CALIBRATION_POSES
from bodynet.core.subject import Profile
from bodynet.gateway.heading import BodyHeading, calibrate_window
from bodynet.gateway.solver import BodySolver
from bodynet.nodes.emulator import BodyEmulator, Headings, Realism, imu_tags, smartsuit_sensors
from bodynet.nodes.motion import ROUTINES, Routine, heading_protocol, keyframes

#: joint groups whose error is reported (dofs by name stem)
GROUPS = {
    "knee": ("knee_flexion",),
    "ankle": ("ankle_flexion", "ankle_inversion"),
    "elbow, wrist": ("elbow", "wrist"),
    "hip": ("hip_flexion", "hip_abduction", "hip_rotation"),
    "shoulder": ("shoulder",),
    "trunk": ("lumbar", "neck"),
}


#: held through the twisted walk: toes out, the head turned
TWISTS = {"left_hip_rotation_deg": 15.0, "right_hip_rotation_deg": 15.0,
          "neck_rotation_deg": 20.0}  # fmt: skip


def _samples(body: BodyEmulator, t: float) -> dict[Any, RawSample]:
    readings, _ = body.sample(t)
    return {s.site: RawSample(r, 0, round(t * 1e9))
            for s, r in zip(body.sensors, readings, strict=True)}  # fmt: skip


def _calibrated(body: BodyEmulator, profile: Profile, start: float, end: float,
                rate_hz: float, pose: str = "tpose") -> Profile:  # fmt: skip
    window: dict[Any, list[Any]] = {}
    for t in np.arange(start, end, 1 / rate_hz):
        for site, sample in _samples(body, float(t)).items():
            if hasattr(sample.reading, "wxyz"):  # a hybrid suit's encoders need none
                window.setdefault(site, []).append((float(t), sample.reading.wxyz))
    return calibrate_window(window, profile, pose).apply(profile, pose)


def heading_tick(heading: BodyHeading, solver: BodySolver, t_s: float,
                 samples: Mapping[Any, RawSample]) -> BodySolver:  # fmt: skip
    """The gateway's heading step for the tick at ``t_s`` (as the live gateway and
    ``bodynet process`` take it): a heading found (or ``auto`` switched to tags'
    own headings) is a new calibration, a new solver; a turn of drifting tags is
    held in the body's solver. Returns the body's solver from then on."""
    step = heading.step(t_s, samples, solver.profile)
    if step is not None and step[0] in ("found", "switched"):
        solver = BodySolver(step[1])
    if step is not None:
        heading.hold(solver, step[1])
    return solver


def measured_errors(angles: Mapping[str, float], flags: Mapping[str, str],
            truth: Mapping[str, float]) -> dict[str, float]:  # fmt: skip
    """Measured dofs' errors, but a shoulder's flexion and rotation near its gimbal
    lock (abduction past 50 deg: one axis, split anyhow by noise)."""
    locked = {
        f"{side}_shoulder_{dof}_deg"
        for side in ("left", "right")
        for dof in ("flexion", "rotation")
        if truth.get(f"{side}_shoulder_abduction_deg", 0) > 50
    }
    return {n: abs(v - truth.get(n, 0.0)) for n, v in angles.items()
            if n not in locked and flags.get(n, "clamped") == "clamped"}  # fmt: skip


def headings(step_deg: int = 30, rate_hz: float = 50.0, seed: int = 4) -> list[dict[str, Any]]:
    """The subject facing every ``step_deg`` (tags sharing one frame): per facing,
    the heading found and the joints' error after it."""
    held = dict(CALIBRATION_POSES["tpose"])
    move = {"left_knee_flexion_deg": 60.0, "left_hip_flexion_deg": 30.0,
            "left_shoulder_abduction_deg": 30.0, "right_shoulder_abduction_deg": 30.0,
            "lumbar_flexion_deg": 15.0, "right_elbow_flexion_deg": 40.0}  # fmt: skip
    routine = Routine("pose-then-knee", "", keyframes(
        [(0.0, held), (1.0, held), (2.0, move), (3.5, {"left_knee_flexion_deg": 10.0})],
        loop=False))  # fmt: skip
    rows = []
    for facing in range(0, 360, step_deg):
        body = BodyEmulator(routine, imu_tags(), realism=Realism(facing_deg=float(facing)),
                            seed=seed)  # fmt: skip
        heading = BodyHeading(_calibrated(body, Profile(), 0.2, 0.95, rate_hz))
        solver = BodySolver(heading.profile)
        errors: list[float] = []
        for t in np.arange(1.0, 3.5, 1 / rate_hz):
            samples = _samples(body, float(t))
            found = heading.update(float(t), samples)
            if found is not None:
                solver = BodySolver(found)
            out = solver.solve(samples)
            if heading.how == "found":
                errors += measured_errors(out.angles_deg, out.flags, body.angles(float(t))).values()
        state = heading.state()
        rows.append({
            "facing_deg": facing, "state": state["state"],
            "heading_error_deg": None if state["deg"] is None
            else round(abs((state["deg"] - facing + 180) % 360 - 180), 2),
            "found_after_s": None if state.get("found_t") is None
            else round(state["found_t"] - state["first_move_t"], 2),
            "max_error_deg": round(max(errors), 2) if errors else None,
            "rms_error_deg": round(math.sqrt(float(np.mean(np.square(errors)))), 2)
            if errors else None,
        })  # fmt: skip
    return rows


def drift(
    minutes: float = 10.0,
    drift_deg_per_min: float = 5.0,
    rate_hz: float = 10.0,
    seed: int = 5,
    correct: bool | str = True,
    twisted: bool = False,
    hybrid: bool = False,
) -> dict[str, Any]:
    """6-axis tags drifting apart while the subject walks: the joints' error
    against the truth by minute, and each group's fitted slope (deg/min).
    ``correct``: False (none), "hinges" (the knees', ankles', elbows' and wrists'
    constraints only) or True (those and the three-dof joints' twist).
    ``twisted``: walking with twists held throughout (``TWISTS``: toes out, the
    head turned), which the three-dof joints' mean twist takes for drift;
    ``hybrid``: the limbs' SmartSuit modules too (hips' and shoulders' encoders)."""
    walk = ROUTINES["walk"].angles
    held = dict(CALIBRATION_POSES["tpose"])
    twists = TWISTS if twisted else {}
    routine = Routine("pose-then-walk", "",
                      lambda t: held if t < 1.0 else {**walk(t - 1.0), **twists})  # fmt: skip
    realism = Realism(yaw_drift_deg_per_min=drift_deg_per_min, headings=Headings.DRIFTING)
    modules = smartsuit_sensors([LEFT_ARM, RIGHT_ARM, LEFT_LEG, RIGHT_LEG]) if hybrid else []
    body = BodyEmulator(routine, [*imu_tags(), *modules], realism=realism, seed=seed)
    # reset together facing +X of their first frame: the start heading is known
    profile = _calibrated(body, Profile(heading="fixed"), 0.2, 0.95, 50.0)
    drift_mode = {False: "off", "hinges": "hinges", True: "joints"}[correct]
    profile = replace(profile, drift=drift_mode)
    solver = BodySolver(profile)
    heading = BodyHeading(profile)  # the gateway's and `bodynet process`'s own step
    times, groups = [], {g: [] for g in GROUPS}  # type: ignore[var-annotated]
    for t in np.arange(1.0, 1.0 + 60.0 * minutes, 1 / rate_hz):
        samples = _samples(body, float(t))
        out = solver.solve(samples)
        errors = measured_errors(out.angles_deg, out.flags, body.angles(float(t)))
        times.append((float(t) - 1.0) / 60.0)
        for group, stems in GROUPS.items():
            mine = [e for n, e in errors.items() if any(s in n for s in stems)]
            groups[group].append(max(mine) if mine else math.nan)
        solver = heading_tick(heading, solver, float(t), samples)
    minutes_at = np.array(times)
    out_groups = {}
    for group, errs in groups.items():
        e = np.array(errs)
        per_minute = [round(float(np.nanmax(e[(minutes_at >= m) & (minutes_at < m + 1)])), 2)
                      for m in range(math.ceil(minutes))]  # fmt: skip
        slope = float(np.polyfit(minutes_at, e, 1)[0]) if np.isfinite(e).all() else math.nan
        out_groups[group] = {"max_by_minute_deg": per_minute, "slope_deg_per_min": round(slope, 3)}
    return {"corrected": correct, "minutes": minutes, "drift_deg_per_min": drift_deg_per_min,
            "twisted": twisted, "hybrid": hybrid, "groups": out_groups}  # fmt: skip


def _worst(errors: np.ndarray) -> float:
    """The largest of ``errors`` (deg, rounded), NaN where none was measured (a
    group whose tags' headings are not found yet)."""
    measured = errors[np.isfinite(errors)]
    return round(float(measured.max()), 2) if measured.size else math.nan


def independent(minutes: float = 10.0, drift_deg_per_min: float = 5.0, rate_hz: float = 20.0,
                seed: int = 1) -> dict[str, Any]:  # fmt: skip
    """6-axis tags each with a heading of its own (none known at calibration) and
    drifting within +/- ``drift_deg_per_min``: an N-pose, then the protocol that
    finds every tag's heading (walking with both arms reaching, a bow at 30 s),
    then walking and reaching to the end; the joints' error against the truth by
    minute from 40 s (every heading found by then), and its fitted slope. At 20 Hz
    or more: the bow's search takes a sample every 50 ms."""
    realism = Realism(yaw_drift_deg_per_min=drift_deg_per_min, headings=Headings.INDEPENDENT)
    body = BodyEmulator(heading_protocol(bow_at_s=31.0), imu_tags(), realism=realism, seed=seed)
    own = Profile(heading="independent", pose="npose")
    heading = BodyHeading(_calibrated(body, own, 0.2, 0.95, 50.0, "npose"))
    solver = BodySolver(heading.profile)
    start = 40.0
    times, groups = [], {g: [] for g in GROUPS}  # type: ignore[var-annotated]
    worst: dict[str, float] = {}
    for t in np.arange(1.0, start + 60.0 * minutes, 1 / rate_hz):
        samples = _samples(body, float(t))
        solver = heading_tick(heading, solver, float(t), samples)
        out = solver.solve(samples)
        if t < start:
            continue
        errors = measured_errors(out.angles_deg, out.flags, body.angles(float(t)))
        for name, e in errors.items():
            worst[name] = max(worst.get(name, 0.0), e)
        times.append((float(t) - start) / 60.0)
        for group, stems in GROUPS.items():
            mine = [e for n, e in errors.items() if any(s in n for s in stems)]
            groups[group].append(max(mine) if mine else math.nan)
    minutes_at = np.array(times)
    out_groups = {}
    for group, errs in groups.items():
        e = np.array(errs)
        per_minute = [_worst(e[(minutes_at >= m) & (minutes_at < m + 1)])
                      for m in range(math.ceil(minutes))]  # fmt: skip
        slope = float(np.polyfit(minutes_at, e, 1)[0]) if np.isfinite(e).all() else math.nan
        out_groups[group] = {"max_by_minute_deg": per_minute, "slope_deg_per_min": round(slope, 3)}
    name, deg = max(worst.items(), key=lambda kv: kv[1], default=("", math.nan))
    return {"seed": seed, "minutes": minutes, "drift_deg_per_min": drift_deg_per_min,
            "unknown": sorted(heading.unknown), "groups": out_groups,
            "worst": {"dof": name, "deg": round(deg, 2)}}  # fmt: skip


def run(out_dir: Path, minutes: float = 10.0) -> dict[str, Any]:
    """Every part; ``drift.json`` and ``drift.md`` in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {
        "headings": headings(),
        "drift": [
            drift(minutes, correct=False),
            drift(minutes, correct="hinges"),
            drift(minutes, correct=True),
        ],
        "twisted": [
            drift(minutes, correct=True, twisted=True),
            drift(minutes, correct=True, twisted=True, hybrid=True),
        ],
        "independent": [independent(minutes, seed=seed) for seed in (1, 2, 3)],
    }
    (out_dir / "drift.json").write_text(json.dumps(result, indent=2))
    lines = ["Subject facing every 30 deg, tags sharing one frame (T-pose, then a knee bends):",
             "", "| facing | heading error | found after first hinge movement | "
             "joint error max / RMS after |", "|---|---|---|---|"]  # fmt: skip
    for r in result["headings"]:
        lines.append(
            f"| {r['facing_deg']} deg | {r['heading_error_deg']} deg | "
            f"{r['found_after_s']} s | {r['max_error_deg']} / {r['rms_error_deg']} deg |"
        )
    rate = result["drift"][0]["drift_deg_per_min"]
    lines += [
        "",
        f"6-axis tags drifting apart (each within +/- {rate} deg/min), walking "
        f"{minutes:g} min: worst error per group, first and last "
        "minute, and the fitted slope of the error:",
        "",
        "| group | without correction | hinge and two-dof joints held (knee, ankle, elbow, "
        "wrist) | and the three-dof joints' twist (hip, shoulder, lumbar, neck) |",
        "|---|---|---|---|",
    ]
    for group in GROUPS:
        cells = [
            f"{g['max_by_minute_deg'][0]} -> {g['max_by_minute_deg'][-1]} deg, "
            f"{g['slope_deg_per_min']} deg/min"
            for g in (run["groups"][group] for run in result["drift"])
        ]
        lines.append(f"| {group} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Walking with twists held throughout (hips turned out "
        f"{TWISTS['left_hip_rotation_deg']:g} deg, the head turned "
        f"{TWISTS['neck_rotation_deg']:g} deg), every joint's hold on:",
        "",
        "| group | IMU tags | hybrid suit (the limbs' SmartSuit encoders too) |",
        "|---|---|---|",
    ]
    for group in GROUPS:
        cells = [
            f"{g['max_by_minute_deg'][0]} -> {g['max_by_minute_deg'][-1]} deg, "
            f"{g['slope_deg_per_min']} deg/min"
            for g in (run["groups"][group] for run in result["twisted"])
        ]
        lines.append(f"| {group} | " + " | ".join(cells) + " |")
    runs = result["independent"]
    lines += [
        "",
        f"6-axis tags each with a heading of its own, none known (+/- {rate} deg/min): an "
        "N-pose, walking and reaching, a bow at 30 s, walking and reaching on; from 40 s "
        f"to {minutes:g} min later, worst error per group, first and last minute, and the "
        "fitted slope:",
        "",
        "| group | " + " | ".join(f"seed {r['seed']}" for r in runs) + " |",
        "|---|" + "---|" * len(runs),
    ]
    for group in GROUPS:
        cells = [
            f"{g['max_by_minute_deg'][0]} -> {g['max_by_minute_deg'][-1]} deg (worst "
            f"{max(g['max_by_minute_deg'])}), {g['slope_deg_per_min']} deg/min"
            for g in (r["groups"][group] for r in runs)
        ]
        lines.append(f"| {group} | " + " | ".join(cells) + " |")
    lines.append("| worst joint | " + " | ".join(
        f"{r['worst']['dof']} {r['worst']['deg']} deg" + (
            f" ({len(r['unknown'])} tags never found)" if r["unknown"] else "")
        for r in runs) + " |")  # fmt: skip
    (out_dir / "drift.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return result
