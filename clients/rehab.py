"""The arm-reaching rehabilitation task of the 000 seed (ch. 6.2) as a game: its rules.

No sockets, no clock: every method takes ``now`` (monotonic seconds), so the
web server (``clients/game.py``) and the tests drive the same rules.

The route. A virtual ball moves along a fixed route that guides the arm
through the seed's procedure (Fig. 6-2/6-3): (a) lift the arm, (b) bend the
elbow and return, (c) bend the wrist and return, (d) arm horizontal to the
side, roll the wrist, return to rest. Each stop of the route is a *key pose*
of the arm; the ball sits where the tip of the hand is in that pose, found by
forward kinematics of the body model (``kinematics/``) built with the
player's own upper-arm and forearm lengths, measured from the live pose, and
placed relative to the player's live shoulder. The key poses are those of the
emulator's ``reach`` routine (``nodes/motion.py``), so an emulated body doing
that routine plays the game.

| # | target           | key pose (deg)                          | reached when                |
|---|------------------|-----------------------------------------|-----------------------------|
| 1 | lift             | shoulder flexion 90 (arm forward)       | hand tip within ``radius_m`` |
| 2 | bend-elbow       | + elbow flexion 90 (forearm up)         | hand tip within ``radius_m`` |
| 3 | straighten-elbow | shoulder flexion 90                     | hand tip within ``radius_m`` |
| 4 | lower            | arm hanging                             | hand tip within ``radius_m`` |
| 5 | bend-wrist       | wrist flexion 60                        | wrist flexion >= 45         |
| 6 | straighten-wrist | arm hanging                             | hand tip within ``radius_m`` |
| 7 | side             | shoulder abduction 90 (arm horizontal)  | hand tip within ``radius_m`` |
| 8 | roll             | + forearm pronation 60                  | forearm pronation >= 45     |
| 9 | lower            | arm hanging                             | hand tip within ``radius_m`` |

Bending and rolling the wrist hardly move the hand tip, and where it goes
depends on the forearm's roll, so those two stops are reached by their angle;
the ball still marks the key pose.

Only measured movement counts. A dof of the pose is *measured* when the
gateway does not flag it, or flags it only ``clamped`` (``pose.is_measured``); any
other flag (``unobserved``, ``held``, ``uncalibrated``) means no measurement
is behind the number. A target *needs* dofs: its gate's angle, or for a
touch the ones that place the hand tip (``TOUCH_DOFS``). A target is reached
only when (1) a pose with every needed dof measured showed the hand *away*
from the target (outside the radius, or below the gate's angle) at or after
the target's cue, and (2) a later such pose shows it *there*, after the ball has
arrived. So an arm that does not move reaches nothing, not even the rest
stops it is already at. Range of motion counts, per dof, only measured
samples.

Timing. A target's cue is the moment the ball leaves for it; it travels for
``travel_s`` and then waits, counting down ``target_timeout_s``. It is reached
as above; its *time-to-target* is from the cue to that moment. When the
countdown ends the target is *missed* if its dofs were measured the whole
time it waited, and *not measured* (with ``waited_for``, the dofs the game
waited for, and ``waited_s``) otherwise: an unmeasured dof never reaches nor
misses a target. While the arm's signal is lost (no pose for ``STALE_S``, or
the gateway flags the arm's sensors stale) the trial is *paused*: the ball and
the countdown stop (from ``GAP_S`` after the last pose), and the paused time is
left out of every time. A trial is
the whole route; it *succeeds* when every target was reached. Each reached
target scores 10 points plus a speed bonus of ``max(0, 10 - whole seconds of
time-to-target)``. After ``rest_s`` the next trial follows by itself. The
first ``practice`` trials are practice, as the seed's first trial is:
recorded but left out of the session summary.

Interruptions. A trial stopped before its end (the player's browser gone,
the therapist's Stop, the game stopped, a new session) is recorded as
*incomplete* with the reason, and the session waits (``paused``) for Start,
which begins the same trial again as its next *attempt* (an interrupted trial
is not resumed: its timings would mean nothing; trials keep their numbers);
so does a rest that ends without an arm signal. The session ends after
``trials`` complete trials beyond practice.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.codecs.pose import PoseFrame, is_measured
from bodynet.core.skeleton import ARM_DOFS, DEFAULT_LENGTHS, build_skeleton

STALE_S = 1.0
GAP_S = 0.3  # no pose for this long: the target's clock stops (the signal is lost at STALE_S)
FLASH_S = 2.0  # how long a target's outcome ("Reached!", "Missed") stays on the page
#: the dofs that place the hand tip: a touch target needs them measured
TOUCH_DOFS = ("shoulder_flexion", "shoulder_abduction", "elbow_flexion")


class GameError(ValueError):
    """A request the game cannot honour now (start without an arm signal...).

    ``cause`` names what must change for it to be honoured (``"signal"``: the
    arm's signal), so a page can clear the message when its cause is gone."""

    def __init__(self, message: str, cause: str = "") -> None:
        super().__init__(message)
        self.cause = cause


PATIENT_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,39}")


def check_patient(text: str) -> str:
    """A patient's id as it goes into file names: 1-40 letters, digits, ``-``, ``_``
    (empty: none). ``GameError`` otherwise."""
    text = text.strip()
    if text and not PATIENT_RE.fullmatch(text):
        raise GameError(
            f"a patient id is 1-40 letters, digits, '-' or '_' (no spaces), not {text[:60]!r}",
            "patient",
        )
    return text


@dataclass(frozen=True, slots=True)
class Target:
    """One stop of the route: a key pose of the arm (dof stem -> degrees)."""

    name: str
    cue: str
    pose: Mapping[str, float]
    gate: tuple[str, float] | None = None  # (dof stem, least angle) instead of touching

    @property
    def needs(self) -> tuple[str, ...]:
        """The dofs that must be measured for this target to be reached or missed."""
        return (self.gate[0],) if self.gate else TOUCH_DOFS


ROUTE: tuple[Target, ...] = (
    Target("lift", "Lift your arm forward", {"shoulder_flexion": 90.0}),
    Target("bend-elbow", "Bend your elbow up", {"shoulder_flexion": 90.0, "elbow_flexion": 90.0}),
    Target("straighten-elbow", "Straighten your elbow", {"shoulder_flexion": 90.0}),
    Target("lower", "Lower your arm", {}),
    Target("bend-wrist", "Bend your wrist", {"wrist_flexion": 60.0}, ("wrist_flexion", 45.0)),
    Target("straighten-wrist", "Straighten your wrist", {}),
    Target("side", "Raise your arm to the side", {"shoulder_abduction": 90.0}),
    Target("roll", "Roll your wrist, palm up",
           {"shoulder_abduction": 90.0, "elbow_pronation": 60.0}, ("elbow_pronation", 45.0)),
    Target("lower", "Lower your arm", {}),
)  # fmt: skip


@dataclass(frozen=True, slots=True)
class ArmPose:
    """The arm of one pose message: points in metres (world frame), angles by dof stem."""

    shoulder: np.ndarray
    elbow: np.ndarray
    wrist: np.ndarray
    tip: np.ndarray
    angles: Mapping[str, float]
    stale_sources: bool  # the gateway flags some of the arm's sensors stale
    measured: frozenset[str] = frozenset(ARM_DOFS)  # the stems with a measurement behind

    @property
    def lengths(self) -> tuple[float, float]:
        """Upper arm and forearm lengths (m), as the gateway's profile has them."""
        return (
            float(np.linalg.norm(self.elbow - self.shoulder)),
            float(np.linalg.norm(self.wrist - self.elbow)),
        )

    def unmeasured(self, dofs: tuple[str, ...]) -> list[str]:
        """Those of ``dofs`` without a measurement in this pose."""
        return [d for d in dofs if d not in self.measured]


def arm_pose(
    frame: PoseFrame, side: str, hand_length_m: float = DEFAULT_LENGTHS["hand"]
) -> ArmPose:
    """The ``side`` arm of a (branch or body) pose; ``GameError`` if it lacks it."""
    try:
        shoulder, elbow, wrist = (np.array(frame.joints_m[f"{side}_{j}"], dtype=float)
                                  for j in ("shoulder", "elbow", "wrist"))  # fmt: skip
        _, hand_q = frame.segments[f"{side}_hand"]
    except KeyError as exc:
        raise GameError(f"the pose has no {side} arm ({exc.args[0]} missing)") from None
    # the hand's long axis is -Z of its segment frame (core/skeleton.py)
    tip = wrist + Rotation.from_quat(hand_q, scalar_first=True).apply((0.0, 0.0, -hand_length_m))
    prefix = f"{side}_"
    angles = {
        name.removeprefix(prefix).removesuffix("_deg"): value
        for name, value in frame.angles_deg.items()
        if name.startswith(prefix)
    }
    measured = frozenset(d for d in angles if is_measured(frame, f"{prefix}{d}_deg"))
    return ArmPose(shoulder, elbow, wrist, tip, angles, bool(frame.stale), measured)


@lru_cache(maxsize=16)
def route_offsets(side: str, upperarm_m: float, forearm_m: float) -> np.ndarray:
    """Hand-tip position of each key pose of ``ROUTE``, from the shoulder (n, 3), by
    forward kinematics of the body model with these segment lengths."""
    from bodynet.kinematics.model import BodyModel, SiteMount

    skeleton = build_skeleton({"upperarm": upperarm_m, "forearm": forearm_m})
    model = BodyModel(skeleton, [SiteMount("tip", f"{side}_hand", 1.0)])
    frames = [model.segment_frames[f"{side}_upperarm"], model.site_frames["tip"]]
    out = []
    for target in ROUTE:
        q = model.q({f"{side}_{stem}_deg": v for stem, v in target.pose.items()})
        _, (shoulder, tip) = model.frame_placements(q, frames)
        out.append(tip - shoulder)
    return np.array(out)


@dataclass
class TargetResult:
    """One target of a trial as saved. ``outcome``: reached, missed, not measured
    (the countdown ended while a needed dof had no measurement: see ``waited_for``),
    or "" (the trial stopped before it)."""

    name: str
    cue: str = ""
    reached: bool = False
    outcome: str = ""
    time_to_target_s: float | None = None
    points: int = 0
    waited_for: list[str] = field(default_factory=list)
    waited_s: float = 0.0  # of its countdown, without a measurement of waited_for
    paused_s: float = 0.0  # signal lost while it was the target


@dataclass
class TrialResult:
    """One trial as saved: the targets, score, range of motion and what went wrong.

    ``number`` counts practice and scored trials apart ("practice 1", "1", "2"...);
    a trial that was stopped and started again keeps its number, with ``attempt`` 2..."""

    number: int
    practice: bool
    started_utc: str
    attempt: int = 1
    complete: bool = False
    reason: str = ""  # why it is incomplete
    success: bool = False
    duration_s: float = 0.0
    score: int = 0
    targets: list[TargetResult] = field(default_factory=list)
    rom_deg: dict[str, dict[str, float]] = field(default_factory=dict)
    poses: int = 0
    stale_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def points_for(time_to_target_s: float) -> int:
    """10 for the reach, plus up to 10 for speed (see the module docstring)."""
    return 10 + max(0, 10 - int(time_to_target_s))


def range_of_motion(samples: list[Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Min, max and range (deg) of every arm dof over the samples (each sample holds
    only measured dofs), and how many samples measured it."""
    rom: dict[str, dict[str, float]] = {}
    for dof in ARM_DOFS:
        values = np.array([s[dof] for s in samples if dof in s], dtype=float)
        if values.size:
            lo, hi = float(values.min()), float(values.max())
            rom[dof] = {"min": round(lo, 2), "max": round(hi, 2), "range": round(hi - lo, 2),
                        "samples": int(values.size)}  # fmt: skip
    return rom


def plural(n: int, word: str, many: str | None = None) -> str:
    """``1 trial``, ``2 trials``."""
    return f"{n} {word if n == 1 else many or word + 's'}"


@dataclass
class _Run:
    """The current target's working state."""

    away: bool = False  # a measured pose showed the hand away from it since the cue
    paused_s: float = 0.0
    measured_s: float = 0.0  # of the countdown, with the needed dofs measured
    waiting_s: float = 0.0  # of the countdown, without
    waited_for: set[str] = field(default_factory=set)

    @property
    def counted_s(self) -> float:
        """Of the countdown, gone."""
        return self.measured_s + self.waiting_s


class RehabGame:
    """The game's state and rules for one player's arm (see the module docstring)."""

    def __init__(self, side: str = "left", trials: int = 10, practice: int = 0,
                 radius_m: float = 0.12, target_timeout_s: float = 20.0, travel_s: float = 0.6,
                 rest_s: float = 0.5, patient: str = "") -> None:  # fmt: skip
        if side not in ("left", "right"):
            raise GameError(f"no arm {side!r}: left or right")
        if trials < 1 or practice < 0:
            raise GameError("trials must be at least 1 and practice at least 0")
        for name, value in (("radius", radius_m), ("target timeout", target_timeout_s)):
            if not (math.isfinite(value) and value > 0):
                raise GameError(f"the {name} must be a finite number above 0, not {value}")
        self.side = side
        self.trials = trials
        self.practice = practice
        self.radius_m = radius_m
        self.target_timeout_s = target_timeout_s
        self.travel_s = travel_s
        self.rest_s = rest_s
        self.patient = patient
        self.started_utc = _utc()
        #: ready -> running -> rest -> running ... -> finished; an interrupted trial -> paused
        self.state = "ready"
        self.results: list[TrialResult] = []
        self.revision = 0  # bumped whenever ``results`` changes
        self.arm: ArmPose | None = None
        self.arm_at: float | None = None
        self._trial: TrialResult | None = None
        self._trial_t0 = 0.0
        self._offsets = np.zeros((len(ROUTE), 3))
        self._from = np.zeros(3)  # where the ball left from
        self._index = 0
        self._cue_at = 0.0
        self._run = _Run()
        self._samples: list[Mapping[str, float]] = []
        self._last_tick: float | None = None
        self._next_at = 0.0  # when the rest between trials ends
        self._flash: dict[str, Any] | None = None  # the last target's outcome, and when

    # --- inputs ------------------------------------------------------------------
    def on_pose(self, arm: ArmPose, now: float) -> None:
        """A pose of the player's arm arrived at ``now``."""
        self.arm, self.arm_at = arm, now
        if self.state != "running" or arm.stale_sources:
            return
        self._samples.append({d: v for d, v in arm.angles.items() if d in arm.measured})
        if self._observe(arm) and self._run.away and self._arrived(now):
            self._reached(now)

    def _observe(self, arm: ArmPose) -> bool:
        """Is the hand at the current target in this pose? (False if not measured);
        a measured pose away from it is noted."""
        if arm.unmeasured(ROUTE[self._index].needs):
            return False
        there = self._there(arm)
        self._run.away |= not there
        return there

    def start(self, now: float) -> None:
        """Begin the next trial (Start was pressed)."""
        if self.state in ("running", "rest"):
            raise GameError("a trial is already running")
        if self.state == "finished":
            raise GameError("the session is over: start a new session")
        self._begin(now)

    def _begin(self, now: float) -> None:
        if not self.arm_live(now) or self.arm is None:
            raise GameError("no live signal from the arm: are its sensors on?", "signal")
        self._offsets = route_offsets(self.side, *(round(x, 3) for x in self.arm.lengths))
        practice = self._complete_count(practice=True) < self.practice
        number = self._complete_count(practice) + 1
        attempt = 1 + sum(t.practice == practice and t.number == number for t in self.results)
        self._trial = TrialResult(
            number, practice, _utc(), attempt,
            targets=[TargetResult(t.name, t.cue) for t in ROUTE],
        )  # fmt: skip
        self._trial_t0 = now
        self._samples = [{d: v for d, v in self.arm.angles.items() if d in self.arm.measured}]
        self._from = self.arm.tip - self.arm.shoulder
        self._index = 0
        self._cue(now)
        self._last_tick = now
        self._flash = None
        self.state = "running"

    def abort(self, now: float, reason: str) -> None:
        """Stop the running trial, recorded as incomplete with ``reason``; the session
        waits for Start."""
        if self.state == "running":
            self._end_trial(now, complete=False, reason=reason)
        if self.state in ("running", "rest"):
            self.state = "paused"

    def tick(self, now: float) -> None:
        """Advance the clock: paused time, countdowns, targets that time out."""
        last, self._last_tick = self._last_tick, now
        if self.state == "rest" and now >= self._next_at:
            try:
                self._begin(now)
            except GameError:  # no arm signal: Start again when it is back
                self.state = "paused"
            return
        if self.state != "running" or self._trial is None or last is None:
            return
        dt = max(0.0, now - last)
        run = self._run
        if not self.arm_live(now):
            self._trial.stale_s += dt
        if not self._fresh(now):  # paused: neither the ball nor the countdown runs
            run.paused_s += dt
            return
        if not self._arrived(now):
            return
        assert self.arm is not None
        missing = self.arm.unmeasured(ROUTE[self._index].needs)
        if missing:
            run.waiting_s += dt
            run.waited_for.update(missing)
        else:
            run.measured_s += dt
        if run.counted_s >= self.target_timeout_s:
            self._timed_out(now)

    # --- queries -----------------------------------------------------------------
    def arm_live(self, now: float) -> bool:
        return (
            self.arm is not None
            and self.arm_at is not None
            and now - self.arm_at <= STALE_S
            and not self.arm.stale_sources
        )

    def _fresh(self, now: float) -> bool:
        """Are poses arriving (the last one within ``GAP_S``, not flagged stale)?"""
        return self.arm_live(now) and self.arm_at is not None and now - self.arm_at <= GAP_S

    def _active(self, now: float) -> float:
        """Seconds since the current target's cue, paused time left out."""
        return max(0.0, now - self._cue_at - self._run.paused_s)

    def _arrived(self, now: float) -> bool:
        return self._active(now) >= self.travel_s

    def ball(self, now: float) -> np.ndarray | None:
        """Where the ball is, from the live shoulder (m), or None between trials."""
        if self.state != "running":
            return None
        goal = self._offsets[self._index]
        w = min(1.0, self._active(now) / self.travel_s) if self.travel_s > 0 else 1.0
        w = 0.5 - 0.5 * math.cos(math.pi * w)
        return np.asarray((1 - w) * self._from + w * goal)

    def snapshot(self, now: float) -> dict[str, Any]:
        """The compact state the browser draws (points relative to the shoulder)."""
        arm = None
        live = self.arm_live(now)
        if self.arm is not None and self.arm_at is not None:
            a = self.arm
            arm = {
                "pts": [_r3(p - a.shoulder) for p in (a.shoulder, a.elbow, a.wrist, a.tip)],
                "stale": not live,
                "age_s": round(now - self.arm_at, 2),
                "deg": {k: round(v, 1) for k, v in a.angles.items()},
                "unmeasured": sorted(set(a.angles) - a.measured),
            }
        out: dict[str, Any] = {
            "t": "state",
            "state": self.state,
            "side": self.side,
            "patient": self.patient,
            "arm": arm,
            "radius_m": self.radius_m,
            "done": self._complete_count(practice=False),
            "score": sum(t.score for t in self.results if t.complete and not t.practice),
            "of": self.trials,
            "revision": self.revision,
        }
        if self._flash is not None and now - self._flash["at"] <= FLASH_S:
            out["flash"] = {k: v for k, v in self._flash.items() if k != "at"}
        ball = self.ball(now)
        if ball is not None and self._trial is not None:
            target = ROUTE[self._index]
            run = self._run
            arrived = self._arrived(now)
            waiting = self.arm.unmeasured(target.needs) if (self.arm and live) else []
            out["ball"] = _r3(ball)
            out["target"] = {
                "i": self._index + 1,
                "n": len(ROUTE),
                "name": target.name,
                "cue": target.cue,
                "arrived": arrived,
                "elapsed_s": round(self._active(now), 2),
                "left_s": round(max(0.0, self.target_timeout_s - run.counted_s), 1),
                "timeout_s": self.target_timeout_s,
                "paused": not live,
                "waiting_for": waiting if arrived else [],
            }
            out["trial"] = {
                "number": self._trial.number,
                "practice": self._trial.practice,
                "attempt": self._trial.attempt,
                "score": sum(t.points for t in self._trial.targets),
            }
        return out

    def summary(self) -> dict[str, Any]:
        """The session's results: every trial, and totals over complete non-practice ones."""
        counted = [t for t in self.results if t.complete and not t.practice]
        ttt = [x.time_to_target_s for t in counted for x in t.targets
               if x.time_to_target_s is not None]  # fmt: skip
        return {
            "patient": self.patient,
            "arm": self.side,
            "started_utc": self.started_utc,
            "finished": self.state == "finished",
            "trials_planned": self.trials,
            "practice_trials": self.practice,
            "route": [
                {
                    "name": t.name,
                    "cue": t.cue,
                    "pose_deg": dict(t.pose),
                    "gate": list(t.gate) if t.gate else None,
                    "needs": list(t.needs),
                }
                for t in ROUTE
            ],
            "radius_m": self.radius_m,
            "target_timeout_s": self.target_timeout_s,
            "units": {"rom_deg": "deg", "time": "s", "radius_m": "m"},
            "complete_trials": len(counted),
            "successful_trials": sum(t.success for t in counted),
            "targets_reached": sum(x.reached for t in counted for x in t.targets),
            "targets": sum(len(t.targets) for t in counted),
            "score": sum(t.score for t in counted),
            "mean_time_to_target_s": round(float(np.mean(ttt)), 3) if ttt else None,
            "trials": [t.to_json() for t in self.results],
        }

    # --- the rules -----------------------------------------------------------------
    def _there(self, arm: ArmPose) -> bool:
        target = ROUTE[self._index]
        if target.gate is not None:
            dof, least = target.gate
            return arm.angles[dof] >= least
        offset = arm.tip - arm.shoulder
        return bool(np.linalg.norm(offset - self._offsets[self._index]) <= self.radius_m)

    def _reached(self, now: float) -> None:
        assert self._trial is not None
        result = self._trial.targets[self._index]
        t = self._active(now)
        result.reached = True
        result.outcome = "reached"
        result.time_to_target_s = round(t, 3)
        result.points = points_for(t)
        self._advance(now)

    def _timed_out(self, now: float) -> None:
        assert self._trial is not None
        result = self._trial.targets[self._index]
        run = self._run
        result.outcome = "not measured" if run.waiting_s > 0 else "missed"
        self._advance(now)

    def _cue(self, now: float) -> None:
        """The ball leaves for the current target: the pose of this moment counts."""
        self._cue_at = now
        self._run = _Run()
        if self._index < len(ROUTE) and self.arm is not None and not self.arm.stale_sources:
            self._observe(self.arm)

    def _close_target(self, now: float) -> None:
        """Copy the current target's waits into its result."""
        assert self._trial is not None
        result = self._trial.targets[self._index]
        run = self._run
        result.waited_for = sorted(run.waited_for)
        result.waited_s = round(run.waiting_s, 3)
        result.paused_s = round(run.paused_s, 3)

    def _advance(self, now: float) -> None:
        assert self._trial is not None
        self._close_target(now)
        result = self._trial.targets[self._index]
        self._flash = {"outcome": result.outcome, "i": self._index + 1, "cue": result.cue,
                       "waited_for": result.waited_for, "at": now}  # fmt: skip
        ball = self.ball(now)
        if ball is not None:
            self._from = ball
        self._index += 1
        self._cue(now)
        if self._index == len(ROUTE):
            self._end_trial(now, complete=True, reason="")
            done = self._complete_count(practice=False) >= self.trials
            self.state = "finished" if done else "rest"
            self._next_at = now + self.rest_s

    def _end_trial(self, now: float, complete: bool, reason: str) -> None:
        trial = self._trial
        assert trial is not None
        if not complete and self._index < len(ROUTE):
            self._close_target(now)
        trial.complete = complete
        trial.reason = reason
        trial.success = complete and all(t.reached for t in trial.targets)
        trial.duration_s = round(now - self._trial_t0, 3)
        trial.score = sum(t.points for t in trial.targets)
        trial.rom_deg = range_of_motion(self._samples)
        trial.poses = len(self._samples)
        trial.stale_s = round(trial.stale_s, 3)
        self.results.append(trial)
        self.revision += 1
        self._trial = None

    def _complete_count(self, practice: bool) -> int:
        return sum(t.complete and t.practice == practice for t in self.results)


def _utc() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _r3(v: np.ndarray) -> list[float]:
    return [round(float(c), 3) for c in v]
