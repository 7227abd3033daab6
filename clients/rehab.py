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

| # | target      | key pose (deg)                          | reached when                     |
|---|-------------|-----------------------------------------|----------------------------------|
| 1 | lift        | shoulder flexion 90 (arm forward)       | hand tip within ``radius_m``     |
| 2 | bend-elbow  | + elbow flexion 90 (forearm up)         | hand tip within ``radius_m``     |
| 3 | lift        | shoulder flexion 90                     | hand tip within ``radius_m``     |
| 4 | rest        | arm hanging                             | hand tip within ``radius_m``     |
| 5 | bend-wrist  | wrist flexion 60                        | wrist flexion >= 45              |
| 6 | rest        | arm hanging                             | hand tip within ``radius_m``     |
| 7 | side        | shoulder abduction 90 (arm horizontal)  | hand tip within ``radius_m``     |
| 8 | roll        | + forearm pronation 60                  | forearm pronation >= 45          |
| 9 | rest        | arm hanging                             | hand tip within ``radius_m``     |

Bending and rolling the wrist hardly move the hand tip, and where it goes
depends on the forearm's roll, so those two stops are reached by their angle;
the ball still marks the key pose.

Timing. A target's cue is the moment the ball leaves for it; it travels for
``travel_s`` and then waits. It is reached when the player's hand touches it
after it has arrived (or the angle passes the threshold); its
*time-to-target* is from the cue to that moment. A target not reached within
``target_timeout_s`` of arriving is missed and the ball moves on. A trial is
the whole route; it *succeeds* when every target was reached. Each reached
target scores 10 points plus a speed bonus of ``max(0, 10 - whole seconds of
time-to-target)``. After ``rest_s`` the next trial follows by itself. The
range of motion (min, max, range of every arm angle) is taken over the
trial's poses. The first ``practice`` trials are practice,
as the seed's first trial is: recorded but left out of the session summary.

Interruptions. A trial stopped before its end (the player's browser gone,
the player's abort, the game stopped) is recorded as *incomplete* with the
reason, and the session waits (``paused``) for the player to press Start,
which begins a new trial (an interrupted trial is not resumed: its timings
would mean nothing); so does a rest that ends without an arm signal. The
session ends after ``trials`` complete trials beyond practice. While no pose
arrives for ``STALE_S`` (or the gateway flags the arm's sensors stale) the
arm is *stale*: targets are not reached by stale poses and the stale time is
recorded with the trial.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bodynet.core.codecs.pose import PoseFrame
from bodynet.core.skeleton import ARM_DOFS, DEFAULT_LENGTHS, build_skeleton

STALE_S = 1.0


class GameError(ValueError):
    """A request the game cannot honour now (start without an arm signal...)."""


@dataclass(frozen=True, slots=True)
class Target:
    """One stop of the route: a key pose of the arm (dof stem -> degrees)."""

    name: str
    cue: str
    pose: Mapping[str, float]
    gate: tuple[str, float] | None = None  # (dof stem, least angle) instead of touching


ROUTE: tuple[Target, ...] = (
    Target("lift", "Lift your arm forward", {"shoulder_flexion": 90.0}),
    Target("bend-elbow", "Bend your elbow up", {"shoulder_flexion": 90.0, "elbow_flexion": 90.0}),
    Target("lift", "Straighten your elbow", {"shoulder_flexion": 90.0}),
    Target("rest", "Lower your arm", {}),
    Target("bend-wrist", "Bend your wrist", {"wrist_flexion": 60.0}, ("wrist_flexion", 45.0)),
    Target("rest", "Straighten your wrist", {}),
    Target("side", "Raise your arm to the side", {"shoulder_abduction": 90.0}),
    Target("roll", "Roll your wrist, palm up",
           {"shoulder_abduction": 90.0, "elbow_pronation": 60.0}, ("elbow_pronation", 45.0)),
    Target("rest", "Lower your arm", {}),
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

    @property
    def lengths(self) -> tuple[float, float]:
        """Upper arm and forearm lengths (m), as the gateway's profile has them."""
        return (
            float(np.linalg.norm(self.elbow - self.shoulder)),
            float(np.linalg.norm(self.wrist - self.elbow)),
        )


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
    return ArmPose(shoulder, elbow, wrist, tip, angles, bool(frame.stale))


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


def _rest_offset(side: str, upperarm_m: float, forearm_m: float) -> np.ndarray:
    return route_offsets(side, upperarm_m, forearm_m)[[t.name for t in ROUTE].index("rest")]


@dataclass
class TargetResult:
    name: str
    reached: bool = False
    time_to_target_s: float | None = None
    points: int = 0


@dataclass
class TrialResult:
    """One trial as saved: the targets, score, range of motion and what went wrong."""

    number: int
    practice: bool
    started_utc: str
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
    """Min, max and range (deg) of every arm dof over the samples."""
    rom: dict[str, dict[str, float]] = {}
    for dof in ARM_DOFS:
        values = np.array([s[dof] for s in samples if dof in s], dtype=float)
        if values.size:
            lo, hi = float(values.min()), float(values.max())
            rom[dof] = {"min": round(lo, 2), "max": round(hi, 2), "range": round(hi - lo, 2)}
    return rom


class RehabGame:
    """The game's state and rules for one player's arm (see the module docstring)."""

    def __init__(self, side: str = "left", trials: int = 10, practice: int = 0,
                 radius_m: float = 0.12, target_timeout_s: float = 20.0,
                 travel_s: float = 0.6, rest_s: float = 0.5) -> None:  # fmt: skip
        if side not in ("left", "right"):
            raise GameError(f"no arm {side!r}: left or right")
        if trials < 1 or practice < 0:
            raise GameError("trials must be at least 1 and practice at least 0")
        self.side = side
        self.trials = trials
        self.practice = practice
        self.radius_m = radius_m
        self.target_timeout_s = target_timeout_s
        self.travel_s = travel_s
        self.rest_s = rest_s
        #: ready -> running -> rest -> running ... -> finished; an interrupted trial -> paused
        self.state = "ready"
        self.results: list[TrialResult] = []
        self.revision = 0  # bumped whenever ``results`` changes
        self.arm: ArmPose | None = None
        self.arm_at: float | None = None
        self.rejected = 0  # pose messages that were not poses of this arm
        self._trial: TrialResult | None = None
        self._trial_t0 = 0.0
        self._offsets = np.zeros((len(ROUTE), 3))
        self._from = np.zeros(3)  # where the ball left from
        self._index = 0
        self._cue_at = 0.0
        self._samples: list[Mapping[str, float]] = []
        self._last_tick: float | None = None
        self._next_at = 0.0  # when the rest between trials ends

    # --- inputs ------------------------------------------------------------------
    def on_pose(self, arm: ArmPose, now: float) -> None:
        """A pose of the player's arm arrived at ``now``."""
        self.arm, self.arm_at = arm, now
        if self.state != "running" or arm.stale_sources:
            return
        self._samples.append(arm.angles)
        if now >= self._cue_at + self.travel_s and self._touches(arm):
            self._reached(now)

    def start(self, now: float) -> None:
        """Begin the next trial (the player pressed Start)."""
        if self.state in ("running", "rest"):
            raise GameError("a trial is already running")
        if self.state == "finished":
            raise GameError("the session is over")
        self._begin(now)

    def _begin(self, now: float) -> None:
        if not self.arm_live(now) or self.arm is None:
            raise GameError("no live signal from the arm: is the gateway running?")
        self._offsets = route_offsets(self.side, *(round(x, 3) for x in self.arm.lengths))
        number = len(self.results) + 1
        self._trial = TrialResult(
            number,
            practice=self._complete_count(practice=True) < self.practice,
            started_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            targets=[TargetResult(t.name) for t in ROUTE],
        )
        self._trial_t0 = now
        self._samples = [self.arm.angles]
        self._from = self.arm.tip - self.arm.shoulder
        self._index = 0
        self._cue_at = now
        self.state = "running"

    def abort(self, now: float, reason: str) -> None:
        """Stop the running trial, recorded as incomplete; the session waits for Start."""
        if self.state == "running":
            self._end_trial(now, complete=False, reason=reason)
        if self.state in ("running", "rest"):
            self.state = "paused"

    def tick(self, now: float) -> None:
        """Advance the clock: stale time, and targets that time out."""
        last, self._last_tick = self._last_tick, now
        if self.state == "rest" and now >= self._next_at:
            try:
                self._begin(now)
            except GameError:  # no arm signal: the player starts again when it is back
                self.state = "paused"
        if self.state != "running" or self._trial is None:
            return
        if last is not None and not self.arm_live(now):
            self._trial.stale_s += now - max(last, self._trial_t0)
        if now > self._cue_at + self.travel_s + self.target_timeout_s:
            self._advance(now)

    # --- queries -----------------------------------------------------------------
    def arm_live(self, now: float) -> bool:
        return (
            self.arm is not None
            and self.arm_at is not None
            and now - self.arm_at <= STALE_S
            and not self.arm.stale_sources
        )

    def ball(self, now: float) -> np.ndarray | None:
        """Where the ball is, from the live shoulder (m), or None between trials."""
        if self.state != "running":
            return None
        goal = self._offsets[self._index]
        w = min(1.0, (now - self._cue_at) / self.travel_s) if self.travel_s > 0 else 1.0
        w = 0.5 - 0.5 * math.cos(math.pi * w)
        return np.asarray((1 - w) * self._from + w * goal)

    def snapshot(self, now: float) -> dict[str, Any]:
        """The compact state the browser draws (points relative to the shoulder)."""
        arm = None
        if self.arm is not None and self.arm_at is not None:
            a = self.arm
            arm = {
                "pts": [_r3(p - a.shoulder) for p in (a.shoulder, a.elbow, a.wrist, a.tip)],
                "stale": not self.arm_live(now),
                "age_s": round(now - self.arm_at, 2),
                "deg": {k: round(v, 1) for k, v in a.angles.items()},
            }
        out: dict[str, Any] = {
            "t": "state",
            "state": self.state,
            "side": self.side,
            "arm": arm,
            "radius_m": self.radius_m,
            "done": self._complete_count(practice=False),
            "score": sum(t.score for t in self.results if t.complete and not t.practice),
            "of": self.trials,
            "revision": self.revision,
        }
        ball = self.ball(now)
        if ball is not None and self._trial is not None:
            target = ROUTE[self._index]
            out["ball"] = _r3(ball)
            out["target"] = {
                "i": self._index + 1,
                "n": len(ROUTE),
                "name": target.name,
                "cue": target.cue,
                "arrived": now >= self._cue_at + self.travel_s,
                "elapsed_s": round(now - self._cue_at, 2),
            }
            out["trial"] = {
                "number": self._trial.number,
                "practice": self._trial.practice,
                "score": sum(t.points for t in self._trial.targets),
            }
        return out

    def summary(self) -> dict[str, Any]:
        """The session's results: every trial, and totals over complete non-practice ones."""
        counted = [t for t in self.results if t.complete and not t.practice]
        ttt = [x.time_to_target_s for t in counted for x in t.targets
               if x.time_to_target_s is not None]  # fmt: skip
        return {
            "arm": self.side,
            "finished": self.state == "finished",
            "trials_planned": self.trials,
            "practice_trials": self.practice,
            "route": [
                {
                    "name": t.name,
                    "cue": t.cue,
                    "pose_deg": dict(t.pose),
                    "gate": list(t.gate) if t.gate else None,
                }
                for t in ROUTE
            ],
            "radius_m": self.radius_m,
            "target_timeout_s": self.target_timeout_s,
            "complete_trials": len(counted),
            "successful_trials": sum(t.success for t in counted),
            "score": sum(t.score for t in counted),
            "mean_time_to_target_s": round(float(np.mean(ttt)), 3) if ttt else None,
            "trials": [t.to_json() for t in self.results],
        }

    # --- the rules -----------------------------------------------------------------
    def _touches(self, arm: ArmPose) -> bool:
        target = ROUTE[self._index]
        if target.gate is not None:
            dof, least = target.gate
            return arm.angles.get(dof, -math.inf) >= least
        offset = arm.tip - arm.shoulder
        return bool(np.linalg.norm(offset - self._offsets[self._index]) <= self.radius_m)

    def _reached(self, now: float) -> None:
        assert self._trial is not None
        result = self._trial.targets[self._index]
        result.reached = True
        result.time_to_target_s = round(now - self._cue_at, 3)
        result.points = points_for(now - self._cue_at)
        self._advance(now)

    def _advance(self, now: float) -> None:
        ball = self.ball(now)
        if ball is not None:
            self._from = ball
        self._index += 1
        self._cue_at = now
        if self._index == len(ROUTE):
            self._end_trial(now, complete=True, reason="")
            done = self._complete_count(practice=False) >= self.trials
            self.state = "finished" if done else "rest"
            self._next_at = now + self.rest_s

    def _end_trial(self, now: float, complete: bool, reason: str) -> None:
        trial = self._trial
        assert trial is not None
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


def _r3(v: np.ndarray) -> list[float]:
    return [round(float(c), 3) for c in v]
