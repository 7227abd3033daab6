"""The main job: the whole body network live on one machine.

The gateway with its embedded Zenoh router; an emulated full body made of
both source systems on their real transports (SmartSuit left arm over CAN,
right arm through the Data Concentrator, IMU tags for trunk and legs), which
stands in T-pose for the first seconds while the gateway calibrates, then
moves; a recorder writing everything to MCAP; and a live table of joint
angles read back from the gateway's poses, as any client would.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from bodynet.clients.recorder import Recorder
from bodynet.clients.view import GRPC_PORT, WEB_PORT, Viewer, check_free, view_live
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.errors import DecodeError
from bodynet.core.skeleton import TPOSE
from bodynet.gateway.service import Gateway
from bodynet.nodes.motion import ROUTINES, Routine, eased, keyframes
from bodynet.nodes.services import EmulationOptions, body_plan, run_node
from bodynet.session import SessionError, open_session, session_config
from bodynet.session.outputs import PendingOutput, check_output

TPOSE_S = 4.0
#: The demo asks the gateway to calibrate from this many still seconds, ending
#: CALIBRATION_SLACK_S before the T-pose does (the body's clock starts with its
#: nodes): a window that took in the first movement would be refused.
CALIBRATION_S = 1.5
CALIBRATION_SLACK_S = 1.0
SHOWN = ("lumbar_flexion_deg", "left_shoulder_flexion_deg", "left_shoulder_abduction_deg",
         "left_elbow_flexion_deg", "right_shoulder_abduction_deg", "right_elbow_flexion_deg",
         "left_hip_flexion_deg", "left_knee_flexion_deg", "right_knee_flexion_deg")  # fmt: skip


def _say_where(endpoint: str, record: Path, routine: str, address: str, rrd: Path | None) -> None:
    print(f"bodynet demo: gateway and router on {endpoint}; recording to {record}")
    if address:
        print(f"  live view: the web viewer at {address}")
    if rrd is not None:
        print(f"  live view saved to {rrd} (open it with: .venv/bin/rerun {rrd})")
    print(f"  emulated body: T-pose for {TPOSE_S:g} s (the gateway calibrates), a knee bend "
          f"(it finds where the subject faces), then {routine!r}")  # fmt: skip
    print(
        "  table: 'uncal' not calibrated yet, 'held' gravity cannot see it now (last value held),"
        " '--' not measured"
    )
    print(
        f"  poses: {keys.pose_key()} and {keys.all_poses()}; from another machine: "
        f"-e {endpoint.replace('127.0.0.1', '<this-host>')} (gateway -l tcp/0.0.0.0:7447)"
    )


#: What the table prints instead of a number with no measurement behind it.
MARKS = {pose.UNCALIBRATED: "uncal", pose.UNOBSERVED: "--", pose.HELD: "held"}


def _cell(frame: pose.PoseFrame, name: str) -> str:
    """One angle of the table: its number if measured, else a mark saying why not."""
    if name not in frame.angles_deg:
        return f"{'--':>6}"
    if not pose.is_measured(frame, name):
        flag = frame.flags[name]
        return f"{MARKS.get(flag, flag[:6]):>6}"
    return f"{frame.angles_deg[name]:6.1f}"


def _status_line(elapsed: float, frame: pose.PoseFrame, recorded: int) -> str:
    cells = "  ".join(f"{n.removesuffix('_deg')} {_cell(frame, n)}" for n in SHOWN)
    return (
        f"-- t {elapsed:5.1f} s  tick {frame.seq:6d}  sources {len(frame.sources):2d}  "
        f"stale {len(frame.stale)}  recorded {recorded}\n   {cells}"
    )


#: After the T-pose, a knee bend and back, arms still out: a hinge's motion is what
#: tells the gateway where the subject faces (docs/calibration.md), as a clinician
#: would ask of a patient after the calibration pose.
KNEE_BEND = keyframes(
    [
        (0.0, {}),
        (
            1.0,
            {
                "left_knee_flexion_deg": 45.0,
                "right_knee_flexion_deg": 45.0,
                "left_hip_flexion_deg": 20.0,
                "right_hip_flexion_deg": 20.0,
            },
        ),
        (2.0, {}),
    ],
    loop=False,
)
KNEE_BEND_S = 2.0
EASE_S = 1.0  # from the T-pose into the routine: a limb moves, it does not jump


def demo_motion(moves: Callable[[float], dict[str, float]]) -> Callable[[float], dict[str, float]]:
    """The demo's script: T-pose for ``TPOSE_S``, the knee bend, then ``moves``,
    eased into from the T-pose over ``EASE_S``."""

    def angles(t: float) -> dict[str, float]:
        if t < TPOSE_S:
            return dict(TPOSE)
        if t < TPOSE_S + KNEE_BEND_S:
            return {**TPOSE, **KNEE_BEND(t - TPOSE_S)}
        t -= TPOSE_S + KNEE_BEND_S
        now = moves(t)
        if t >= EASE_S:
            return now
        return eased(TPOSE, now, t / EASE_S)

    return angles


def run_demo(endpoint: str, routine: str, seconds: float | None, record: Path,
             stop: threading.Event, viewer_mode: str = "auto", rrd: Path | None = None,
             web_port: int | None = None) -> int:  # fmt: skip
    """Run everything until ``stop`` (Ctrl-C) or for ``seconds``. The live view
    is a window where there is a display, else the web viewer plus a saved
    ``.rrd`` (``viewer_mode`` "none": the ``.rrd`` only). An output that cannot
    be written, a port in use: one line, exit 2, and what had started is stopped."""
    if viewer_mode == "auto":
        viewer_mode = "native" if os.environ.get("DISPLAY") else "web"
    if viewer_mode != "native" and rrd is None:
        rrd = record.with_suffix(".rrd")
    with contextlib.ExitStack() as stack:
        try:
            for output in (record, rrd):
                if output is not None:  # before anything starts: it can be, and is, made
                    check_output(output)
                    PendingOutput(output).discard()  # a folder that takes no file: /proc
            if viewer_mode == "web":  # `view` has --grpc-port for Rerun's data port; the demo not
                check_free(web_port or WEB_PORT, "--web-port")
                check_free(GRPC_PORT, "Rerun's data port, fixed in the demo; free it, or "
                                       "--viewer none")  # fmt: skip
            parts = _start(stack, endpoint, routine, record, stop, viewer_mode, rrd, web_port)
        except (OSError, SessionError) as exc:
            stop.set()
            why: object = exc
            if isinstance(exc, OSError) and exc.filename and exc.strerror:
                why = f"cannot write {exc.filename}: {exc.strerror}"
            print(f"bodynet demo: {why}", file=sys.stderr)
            return 2
        _say_where(endpoint, parts.record, routine, parts.viewer.address, rrd)
        _show(parts, seconds, stop)
        parts.complete = True
    print(f"bodynet demo: stopped; {parts.recorder.messages} messages in {parts.record}")
    return 0


@dataclass
class _Parts:
    """What the demo started (each stopped by the exit stack it was started in)."""

    client: zenoh.Session
    recorder: Recorder
    viewer: Viewer
    record: Path
    start: float  # the emulated body's clock (monotonic s): it starts with its nodes
    latest: dict[str, pose.PoseFrame] = field(default_factory=dict)
    complete: bool = False  # the live view's .rrd is kept only if it ran to its end


def _start(stack: contextlib.ExitStack, endpoint: str, routine: str, record: Path,
           stop: threading.Event, viewer_mode: str, rrd: Path | None,
           web_port: int | None) -> _Parts:  # fmt: skip
    """Start the router and gateway, the live view, the recorder and the body, in
    an order where what fails most often (a port, an output) fails first."""

    def thread(target: Callable[..., object], *args: object) -> None:
        t = threading.Thread(target=target, args=args, daemon=True)
        t.start()
        stack.callback(lambda: (stop.set(), t.join(timeout=10)))

    gw_session = open_session(session_config("router", listen=[endpoint]))
    stack.callback(gw_session.close)
    client = open_session(session_config("client", connect=[endpoint]))
    stack.callback(client.close)
    viewer = Viewer.start(viewer_mode, rrd, web_port=web_port)
    ran: list[_Parts] = []  # the parts, once all are made (a recorder that fails: none)
    stack.callback(lambda: viewer.close(keep=any(p.complete for p in ran)))
    recorder = Recorder(client, record)
    stack.callback(recorder.close)
    parts = _Parts(client, recorder, viewer, recorder.files[0], 0.0)  # files[0]: a free name
    ran.append(parts)
    gateway = Gateway(gw_session)
    stack.callback(gateway.close)
    thread(gateway.run, stop)
    node_session = open_session(session_config("client", connect=[endpoint]))
    stack.callback(node_session.close)
    scripted = Routine("demo", "", demo_motion(ROUTINES[routine].angles))
    parts.start = time.monotonic()
    thread(run_node, node_session, stop, body_plan(), EmulationOptions(scripted))
    thread(view_live, client, viewer, stop)

    def on_pose(sample: zenoh.Sample) -> None:
        with contextlib.suppress(DecodeError):  # the demo shows poses; others are the gateway's
            parts.latest["body"] = pose.decode(sample.payload.to_bytes())

    stack.callback(client.declare_subscriber(keys.pose_key(), on_pose).undeclare)
    return parts


def _show(parts: _Parts, seconds: float | None, stop: threading.Event) -> None:
    """The table, a line a second, until ``stop`` or ``seconds``; the T-pose
    calibration asked for on time (in the body's clock)."""
    calibrated = False
    calibrate_at = TPOSE_S - CALIBRATION_SLACK_S
    wait_s = 0.0
    while not stop.wait(wait_s):
        elapsed = time.monotonic() - parts.start
        if not calibrated and elapsed >= calibrate_at:
            calibrated = True
            replies = list(parts.client.get(f"{keys.CALIBRATE_TPOSE}?seconds={CALIBRATION_S}",
                                            timeout=10))  # fmt: skip
            result = (
                json.loads(replies[0].ok.payload.to_bytes()) if replies and replies[0].ok else {}
            )
            print(f"\n  T-pose calibration: {len(result.get('calibrated', []))} sensors"
                  + (f" (refused: {result['error']})" if result.get("error") else "")
                  + ("; the heading is found when a knee bends"
                     if result.get("heading", {}).get("state") == "unknown" else ""))  # fmt: skip
        frame = parts.latest.get("body")
        if frame is not None:
            print(_status_line(elapsed, frame, parts.recorder.messages))
        if seconds is not None and elapsed >= seconds:
            stop.set()
        # a line a second, and the calibration asked for on time however long the
        # viewer took to start
        left = calibrate_at - (time.monotonic() - parts.start)
        wait_s = 1.0 if calibrated else max(0.0, min(1.0, left))
