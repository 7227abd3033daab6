"""The gateway's work per body and tick, bodies solved together against one at a time.

No network: the tick work alone (solve, build the pose message, encode it) on
the same samples, in the same run. ``alone`` solves each body by itself, as a
gateway does when its bodies come due one by one; ``batched`` solves them in
one call, as the gateway does when several are due at once (under load, the
samples of many bodies wait while it solves). The ratio is the figure to read.

Both run tick after tick, the code and data hot in the caches. A gateway ticks
every 10 ms and waits between, and here a tick's CPU grows with the wait
(caches refilled: on this shared VM, 2-3x after 9 ms, spinning or sleeping):
``paced`` solves the batch once a period, as live, and counts the CPU of the
ticks alone; beside it, one compiled call on the same bodies (their forward
kinematics) paced the same way: what the time away costs a tick that is a
single compiled pass. Unsynchronised bodies come due in ever other sets (see
gateway/rounds.py), so each number of bodies is measured twice: all of them
due every tick, and a new set of them each tick (:func:`due_sets`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bodynet.core.messages import RawSample, Source
from bodynet.core.subject import Profile
from bodynet.gateway import kernels
from bodynet.gateway.frames import whole_body_message
from bodynet.gateway.heading import calibrate_window
from bodynet.gateway.solver import BodySolver, solve_bodies
from bodynet.nodes.emulator import BodyEmulator, imu_tags
from bodynet.nodes.motion import ROUTINES

FRAMES = 100  # a second of motion at 100 Hz, looped


def _bodies(n: int) -> list[tuple[Profile, list[dict[Any, RawSample]]]]:
    """``n`` calibrated IMU bodies walking, each with its own tags (mounts and
    noise: seeded by body) and calibrated on its own still window, as the
    gateway calibrates a suit (its mounts and its tags' scatter, which their
    joints' uncertainty carries): each one's profile and a second of sample
    frames. Each body's samples come in an order of its own, as the gateway
    keeps a body's sites in the order their first samples came in (its nodes'
    phases)."""
    out = []
    for b in range(n):
        tags = imu_tags()
        np.random.default_rng(b).shuffle(tags)  # type: ignore[arg-type]
        still = BodyEmulator(ROUTINES["tpose"], tags, seed=3 + b)
        window: dict[Any, list[Any]] = {}
        for k in range(50):
            for tag, r in zip(tags, still.sample(k / 100)[0], strict=True):
                window.setdefault(tag.site, []).append((k / 100, r.wxyz))  # type: ignore[union-attr]
        fixed = Profile(heading="fixed")  # the subject faces +X of the tags' shared frame
        profile = calibrate_window(window, fixed).apply(fixed)
        body = BodyEmulator(ROUTINES["walk"], tags, seed=3 + b)
        frames = []
        for k in range(FRAMES):
            readings, _ = body.sample(k / 100)
            frames.append({tag.site: RawSample(r, k, k * 10_000_000, Source.IMU_CENTRAL)
                           for tag, r in zip(tags, readings, strict=True)})  # fmt: skip
        out.append((profile, frames))
    return out


def _tick(work: list[tuple[BodySolver, dict[Any, RawSample]]], seq: int) -> None:
    for output in solve_bodies(work):
        whole_body_message(output, seq, [])


#: how many sets of bodies due together :func:`due_sets` draws: a minute of
#: ticks, so that a run sees sets as new as live (where timing draws them, and a
#: set seldom comes again), not a loop of a few it could remember
SETS = 6000


def due_sets(bodies: int, varying: bool) -> list[list[int]]:
    """Which of ``bodies`` are due together, tick after tick (looped): all of
    them, or (``varying``) between half and all but one, a different set each
    tick, as unsynchronised bodies come due (seeded)."""
    if not varying:
        return [list(range(bodies))]
    rng = np.random.default_rng(0)
    return [sorted(rng.choice(bodies, int(rng.integers(max(1, bodies // 2), bodies)),
                              replace=False).tolist())
            for _ in range(SETS)]  # fmt: skip


Bodies = list[tuple[Profile, list[dict[Any, RawSample]]]]


def _per_body_tick_us(bodies: Bodies, seconds: float, batched: bool,
                      varying: bool = False) -> float:  # fmt: skip
    solvers = [BodySolver(profile) for profile, _ in bodies]
    sets = due_sets(len(bodies), varying)
    ticks, solved, start = 0, 0, time.perf_counter()
    while time.perf_counter() - start < seconds or ticks < 3:
        work = [(solvers[b], bodies[b][1][(ticks + b) % FRAMES])
                for b in sets[ticks % len(sets)]]  # fmt: skip
        if batched:
            _tick(work, ticks)
        else:
            for one in work:
                _tick([one], ticks)
        ticks += 1
        solved += len(work)
    return 1e6 * (time.perf_counter() - start) / solved


PERIOD_S = 0.01  # the gateway's tick at 100 Hz


def _paced(seconds: float, job: Callable[[int], tuple[Callable[[], object], int]]) -> float:
    """CPU per body-tick of tick after tick run once a period, sleeping between:
    ``job(tick)`` gives the tick's work (made before its CPU is counted) and its
    number of bodies."""
    ticks, solved, cpu, start = 0, 0, 0.0, time.perf_counter()
    while time.perf_counter() - start < seconds or ticks < 3:
        work, n = job(ticks)
        due = start + (ticks + 1) * PERIOD_S
        c = time.thread_time()
        work()
        cpu += time.thread_time() - c
        ticks += 1
        solved += n
        time.sleep(max(0.0, due - time.perf_counter()))
    return 1e6 * cpu / solved


def _paced_per_body_tick_us(bodies: Bodies, seconds: float, varying: bool = False) -> float:
    """CPU per body-tick of the batch solved once a period, sleeping between."""
    solvers = [BodySolver(profile) for profile, _ in bodies]
    sets = due_sets(len(bodies), varying)

    def job(tick: int) -> tuple[Callable[[], object], int]:
        work = [(solvers[b], bodies[b][1][(tick + b) % FRAMES])
                for b in sets[tick % len(sets)]]  # fmt: skip
        return (lambda: _tick(work, tick)), len(work)

    return _paced(seconds, job)


def _paced_compiled_us(bodies: Bodies, seconds: float, varying: bool = False) -> float:
    """CPU per body-tick of one compiled call on the same bodies once a period,
    sleeping between: their forward kinematics (``kernels.forward_poses``) from
    a tick's angles, the floor of what the time away costs a tick that is one
    compiled pass (the Python tick's ratio to it is what its Python costs)."""
    (profile, frames), n = bodies[0], len(bodies)
    solver = BodySolver(profile)
    chain = solver.model.chain
    sets = due_sets(n, varying)
    angles = np.zeros((n, len(solver.names.angles) + 1))
    angles[:, :-1] = solve_bodies([(solver, frames[0])])[0].angles  # a walking body's
    segments, roots = np.zeros((0, 3, 3)), np.full(n, -1)
    root_z = np.full(n, chain.root_z)
    offsets = np.repeat(chain.offsets[None], n, 0)
    floor = np.repeat(chain.floor_points[None], n, 0)

    def job(tick: int) -> tuple[Callable[[], object], int]:
        n = len(sets[tick % len(sets)])
        args = (angles[:n], segments, roots[:n], root_z[:n], chain.parents, chain.axes,
                offsets[:n], chain.segment_joints, chain.floor_joints, floor[:n])  # fmt: skip
        return (lambda: kernels.forward_poses(*args)), n

    return _paced(seconds, job)


def run(seconds: float = 2.0, out_dir: Path = Path("bench-results"),
        bodies: tuple[int, ...] = (1, 5, 20)) -> dict[str, Any]:  # fmt: skip
    """Measure each number of bodies alone, batched, and batched once a period,
    all of them due each tick and (three bodies or more) varying sets of them
    (:func:`due_sets`); print a table; write solver.{json,md}."""
    suits = _bodies(max(bodies))
    rows = []
    for n, varying in [(n, v) for n in bodies for v in (False, True) if n >= 3 or not v]:
        alone = _per_body_tick_us(suits[:n], seconds, False, varying)
        batched = _per_body_tick_us(suits[:n], seconds, True, varying)
        paced = _paced_per_body_tick_us(suits[:n], seconds, varying)
        compiled = _paced_compiled_us(suits[:n], seconds, varying)
        sizes = [len(s) for s in due_sets(n, varying)]
        rows.append({"bodies": n, "varying": varying, "due": (min(sizes), max(sizes)),
                     "alone_us": alone, "batched_us": batched,
                     "speedup": alone / batched,
                     "body_ticks_per_s_batched": 1e6 / batched,
                     "paced_us": paced, "paced_over_batched": paced / batched,
                     "paced_compiled_us": compiled})  # fmt: skip
    lines = ["| bodies due together | one at a time us per body-tick | batched us per body-tick "
             "| speed-up | body-ticks/s on one core (batched) | batched once a period: CPU us "
             "per body-tick | paced / back to back | paced, one compiled call instead: CPU us "
             "per body-tick |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        lo, hi = r["due"]
        due = f"{lo}-{hi} of {r['bodies']}, a new set each tick" if r["varying"] else r["bodies"]
        lines.append(f"| {due} | {r['alone_us']:.0f} | {r['batched_us']:.0f} "
                     f"| {r['speedup']:.2f} | {r['body_ticks_per_s_batched']:.0f} "
                     f"| {r['paced_us']:.0f} | {r['paced_over_batched']:.2f} "
                     f"| {r['paced_compiled_us']:.1f} |")  # fmt: skip
    table = "\n".join(lines) + "\n"
    print(f"Gateway tick work per body (solve, pose message, encode), IMU body of 15 tags, "
          f"{seconds:g} s each\n\n{table}")  # fmt: skip
    result = {"seconds": seconds, "runs": rows}
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "solver.json").write_text(json.dumps(result, indent=2))
    (out_dir / "solver.md").write_text(table)
    return result
