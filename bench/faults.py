"""Faults, each done for real and timed: how long until the system sees it or recovers.

Every scenario runs the parts as the user would (``bodynet node``,
``bodynet gateway``, ``bodynet record`` as separate processes on a loopback
router; the serial device as a pseudo-terminal that vanishes), does the fault
with a signal or an unplug, and waits, with a generous timeout, for the
event that shows it was handled. The time to that event is the measurement;
``tests/test_faults.py`` runs the same scenarios and checks only that the
event came (no timing in tests), ``bodynet bench --only faults`` reports the
times against the targets.

Times are taken where the event arrives (the probe's Zenoh callback,
``time.monotonic()``), from the moment just before the signal is sent.
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from bodynet.bench import harness, machine
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.errors import DecodeError
from bodynet.core.keys import LEFT_ARM, RIGHT_ARM

TARGETS_S = {
    "node_killed": 0.1,
    "node_frozen": 1.5,
    "recorder_killed": 1.0,
    "router_restarted": 1.0,
}
#: How long the router stays dead once the clients have noticed: past their longest
#: retry period (0.5 s), so each is in its backoff when the router comes back.
ROUTER_OUTAGE_S = 1.0


class FaultError(RuntimeError):
    """A scenario's expected event did not come within its timeout."""


def bodynet(*args: str, log: Path) -> subprocess.Popen[bytes]:
    """``bodynet ARGS`` in a new process, its output to ``log``."""
    with log.open("ab") as out:
        return subprocess.Popen([sys.executable, "-m", "bodynet.cli.main", *args],
                                stdout=out, stderr=subprocess.STDOUT)  # fmt: skip


@dataclass
class Processes:
    """Processes a scenario started; each is killed at the end if still running."""

    log: Path
    started: list[subprocess.Popen[bytes]] = field(default_factory=list)

    def start(self, *args: str) -> subprocess.Popen[bytes]:
        self.started.append(bodynet(*args, log=self.log))
        return self.started[-1]

    def close(self) -> None:
        for p in self.started:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGCONT)
                    p.kill()
            p.wait(timeout=30)


class Inbox:
    """What a probe's subscriptions receive, with arrival times, to wait on."""

    def __init__(self) -> None:
        self.queue: queue.SimpleQueue[tuple[float, str, Any]] = queue.SimpleQueue()

    def put(self, key: str, value: Any) -> None:
        self.queue.put((time.monotonic(), key, value))

    def wait(self, match: Callable[[str, Any], bool], timeout: float, what: str) -> float:
        """Arrival time of the first message that ``match``es; ``FaultError`` after ``timeout``."""
        return self.wait_each({what: match}, timeout)[what]

    def wait_each(self, matches: dict[str, Callable[[str, Any], bool]],
                  timeout: float) -> dict[str, float]:  # fmt: skip
        """Arrival time of the first message that matches each of ``matches``, in
        whatever order they come (waiting for one after the other would drop
        what matches the second while the first is awaited); ``FaultError``
        naming what did not come within ``timeout``."""
        deadline = time.monotonic() + timeout
        found: dict[str, float] = {}
        while len(found) < len(matches) and (left := deadline - time.monotonic()) > 0:
            try:
                t, key, value = self.queue.get(timeout=left)
            except queue.Empty:
                break
            for what, match in matches.items():
                if what not in found and match(key, value):
                    found[what] = t
        if missing := [what for what in matches if what not in found]:
            raise FaultError(f"no {' nor '.join(missing)} within {timeout:g} s")
        return found

    def drain(self) -> None:
        with contextlib.suppress(queue.Empty):
            while True:
                self.queue.get_nowait()


@contextlib.contextmanager
def loopback(workdir: Path | None = None) -> Iterator[tuple[str, zenoh.Session, Processes, Path]]:
    """A router on a free port, a probe session, the processes and a work folder."""
    with contextlib.ExitStack() as stack:
        work = workdir or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        endpoint = harness.free_endpoint()
        router = harness.router(endpoint)
        stack.callback(router.close)
        probe = harness.client(endpoint)
        stack.callback(probe.close)
        procs = Processes(work / "processes.log")
        stack.callback(procs.close)
        yield endpoint, probe, procs, work


def _subscribe(probe: zenoh.Session, inbox: Inbox, key: str, decode: Callable[[bytes], Any]) -> Any:
    def on_sample(sample: zenoh.Sample) -> None:
        with contextlib.suppress(DecodeError, ValueError):
            inbox.put(str(sample.key_expr), decode(sample.payload.to_bytes()))

    return probe.declare_subscriber(key, on_sample)


def _liveliness(probe: zenoh.Session, inbox: Inbox) -> Any:
    return probe.liveliness().declare_subscriber(
        keys.all_raw(),
        lambda s: inbox.put(str(s.key_expr), s.kind == zenoh.SampleKind.PUT),
        history=True,
    )


def _branch_keys(branch: keys.Branch) -> set[str]:
    from bodynet.core.profile import SMARTSUIT_SITES

    return {s.raw_key for s in SMARTSUIT_SITES.values() if s.branch == branch}


def _states(topology: dict[str, Any], wanted: set[str]) -> set[str]:
    """The states the topology gives the ``wanted`` keys (``missing`` if absent)."""
    nodes: dict[str, Any] = {}
    for branch in topology.get("branches", {}).values():
        nodes.update(branch.get("nodes", {}))
    return {nodes[k]["state"] if k in nodes else "missing" for k in wanted}


def _arm(procs: Processes, endpoint: str, branch: str) -> subprocess.Popen[bytes]:
    return procs.start("node", "smartsuit", "--branch", branch, "--via", "can", "--routine",
                       "reach", "--ideal", "--name", branch, "-e", endpoint)  # fmt: skip


def _gateway(procs: Processes, endpoint: str, *extra: str) -> subprocess.Popen[bytes]:
    return procs.start("gateway", "--mode", "client", "-e", endpoint, *extra)


def node_killed(timeout: float = 60.0) -> dict[str, Any]:
    """SIGKILL a node process: its liveliness tokens go, and the gateway's
    topology says ``gone``."""
    with loopback() as (endpoint, probe, procs, _):
        inbox = Inbox()
        subs = [_liveliness(probe, inbox), _subscribe(probe, inbox, keys.TOPOLOGY, json.loads)]
        _gateway(procs, endpoint)
        victim = _arm(procs, endpoint, "left-arm")
        left = _branch_keys(LEFT_ARM)
        inbox.wait(lambda k, v: k == keys.TOPOLOGY and _states(v, left) == {"alive"}, timeout,
                   "topology with the node alive")  # fmt: skip
        inbox.drain()
        t0 = time.monotonic()
        victim.kill()
        gone: set[str] = set()

        def tokens_gone(key: str, value: Any) -> bool:
            if key in left and value is False:
                gone.add(key)
            return gone == left

        # the gateway's topology may come before the probe's own tokens go
        came = inbox.wait_each({
            "liveliness tokens gone": tokens_gone,
            "topology with the node gone":
                lambda k, v: k == keys.TOPOLOGY and _states(v, left) == {"gone"},
        }, timeout)  # fmt: skip
        t_token, t_topo = came["liveliness tokens gone"], came["topology with the node gone"]
        for sub in subs:
            sub.undeclare()
    return {"liveliness_s": t_token - t0, "topology_s": max(t_topo, t_token) - t0}


def node_frozen(timeout: float = 60.0) -> dict[str, Any]:
    """SIGSTOP one node process of two: the gateway's poses flag its sites stale
    (the other's keep flowing); SIGCONT: they are fresh again."""
    with loopback() as (endpoint, probe, procs, _):
        inbox = Inbox()
        subs = [_subscribe(probe, inbox, keys.pose_key(), pose.decode)]
        _gateway(procs, endpoint)
        victim = _arm(procs, endpoint, "left-arm")
        _arm(procs, endpoint, "right-arm")
        left, both = _branch_keys(LEFT_ARM), _branch_keys(LEFT_ARM) | _branch_keys(RIGHT_ARM)
        inbox.wait(lambda k, v: both <= set(v.sources) and not v.stale, timeout,
                   "poses of both arms")  # fmt: skip
        inbox.drain()
        t0 = time.monotonic()
        victim.send_signal(signal.SIGSTOP)
        t_stale = inbox.wait(lambda k, v: left <= set(v.stale), timeout, "stale flags")
        right_after = inbox.wait(lambda k, v: not set(v.stale) & _branch_keys(RIGHT_ARM),
                                 timeout, "the right arm going on")  # fmt: skip
        t1 = time.monotonic()
        victim.send_signal(signal.SIGCONT)
        t_back = inbox.wait(lambda k, v: not v.stale, timeout, "fresh poses after SIGCONT")
        for sub in subs:
            sub.undeclare()
    return {"stale_s": t_stale - t0, "fresh_again_s": t_back - t1,
            "other_branch_flowed": right_after > t0}  # fmt: skip


def recorder_killed(timeout: float = 60.0) -> dict[str, Any]:
    """SIGKILL ``bodynet record`` mid-write; ``bodynet record --salvage`` keeps
    everything up to its last flushed chunk. Lost: the source time between the
    last salvaged sample and the last sample a probe on the same router had
    received when the kill came."""
    from bodynet.clients.mcap_store import count_messages, read_raw
    from bodynet.clients.mcap_store import salvage as salvage_file

    with loopback() as (endpoint, probe, procs, work):
        inbox = Inbox()
        sub = _subscribe(probe, inbox, keys.all_raw(), raw_sample.decode)
        _arm(procs, endpoint, "left-arm")
        out = work / "crash.mcap"
        rec = procs.start("record", "-o", str(out), "-e", endpoint)
        inbox.wait(lambda k, v: True, timeout, "raw samples")
        deadline = time.monotonic() + timeout
        while not (out.exists() and out.stat().st_size > 20_000):  # some chunks written
            if time.monotonic() > deadline:
                raise FaultError(f"the recorder wrote nothing within {timeout:g} s")
            threading.Event().wait(0.05)
        t_kill, killed_ns = time.monotonic(), time.time_ns()
        rec.kill()
        rec.wait(timeout=timeout)
        published: set[tuple[str, int, int]] = set()  # what the probe saw go by
        received_at_kill = 0  # newest source time the probe had received when the kill came
        with contextlib.suppress(queue.Empty):
            while True:
                arrived, key, s = inbox.queue.get_nowait()
                if s.t_ns <= killed_ns:
                    published.add((key, s.seq, s.t_ns))
                if arrived <= t_kill:
                    received_at_kill = max(received_at_kill, s.t_ns)
        sub.undeclare()
        if not received_at_kill:
            raise FaultError("the probe received no sample before the kill")
        fixed = work / "fixed.mcap"
        salvage = subprocess.run([sys.executable, "-m", "bodynet.cli.main", "record", "--salvage",
                                  str(out), "-o", str(fixed)], capture_output=True, text=True,
                                 timeout=timeout, check=False)  # fmt: skip
        if salvage.returncode != 0:
            raise FaultError(f"salvage failed: {salvage.stderr.strip()}")
        samples = list(read_raw(fixed))
        # every message (raw samples, and any gap record the recorder wrote) comes through
        whole = salvage_file(fixed, work / "again.mcap") == count_messages(fixed)
    if not samples:
        raise FaultError("nothing salvaged")
    kept = {(topic, s.seq, s.t_ns) for topic, _, s in samples}
    first_kept = min(t for _, _, t in kept)
    last_kept = max(t for _, _, t in kept)
    # published while the recorder ran (after its first sample, up to its last flushed one)
    # but not in the file: lost by the recorder, not by its being killed
    missing_inside = sum(1 for p in published if first_kept <= p[2] <= last_kept and p not in kept)
    # Lost: from the newest sample in the salvaged file to the newest one a subscriber of
    # the same router (the probe) had received when the kill came; a proxy for what the
    # recorder itself had received, which cannot be seen from outside it. Against the
    # kill's wall time instead (``lost_vs_kill_s``) the loss would also count how far the
    # whole pipeline lags behind the source clock, which on a loaded machine is not what
    # the recorder failed to flush.
    return {"salvaged": len(samples), "missing_inside": missing_inside, "salvage_is_whole": whole,
            "lost_s": max(0.0, (received_at_kill - last_kept) / 1e9),
            "lost_vs_kill_s": max(0.0, (killed_ns - last_kept) / 1e9)}  # fmt: skip


def gateway_restarted(timeout: float = 60.0) -> dict[str, Any]:
    """Calibrate the IMU mounts (T-pose, saved to ``--profile``), SIGKILL the
    gateway, start it again on the same profile: poses resume with the same
    calibration. Segment orientations are compared, before calibration (random
    tag mounts: wrong), after it, and after the restart."""
    with loopback() as (endpoint, probe, procs, work):
        inbox = Inbox()
        sub = _subscribe(probe, inbox, keys.pose_key(), pose.decode)
        profile = work / "subject.toml"
        gw = _gateway(procs, endpoint, "--profile", str(profile))
        procs.start("node", "imu", "--sensors", "1-15", "--routine", "tpose", "-e", endpoint)
        frames: list[pose.PoseFrame] = []

        def whole(key: str, frame: Any) -> bool:
            frames.append(frame)
            return len(frame.sources) == 15

        inbox.wait(whole, timeout, "poses of the whole body")
        before = frames[-1]
        replies = list(probe.get(f"{keys.CALIBRATE_TPOSE}?seconds=1", timeout=timeout))
        result = json.loads(replies[0].ok.payload.to_bytes()) if replies and replies[0].ok else {}
        if not result.get("ok"):
            raise FaultError(f"T-pose calibration failed: {result}")
        inbox.drain()
        n = len(frames)  # poses solved before the new calibration may still be on their way
        inbox.wait(lambda k, v: whole(k, v) and len(frames) > n + 20, timeout,
                   "poses after calibration")  # fmt: skip
        calibrated = frames[-1]
        gw.kill()
        gw.wait(timeout=timeout)
        inbox.drain()
        t0 = time.monotonic()
        _gateway(procs, endpoint, "--profile", str(profile))
        t_first = inbox.wait(whole, timeout, "poses after the restart")
        after = frames[-1]
        sub.undeclare()

    def max_angle_deg(a: pose.PoseFrame, b: pose.PoseFrame) -> float:
        """Largest rotation between the two frames' segments. The arms are left out:
        in T-pose the shoulders sit in gimbal lock, where a gateway without history
        (just restarted) may split the same rotation differently and the range of
        motion clamps the parts differently."""
        worst = 0.0
        for name, (_, qa) in a.segments.items():
            if any(part in name for part in ("upperarm", "forearm", "hand")):
                continue
            qb = b.segments[name][1]
            dot = min(1.0, abs(sum(x * y for x, y in zip(qa, qb, strict=True))))
            worst = max(worst, math.degrees(2 * math.acos(dot)))
        return worst

    return {"calibrated_sensors": len(result["calibrated"]), "resume_s": t_first - t0,
            "restart_vs_calibrated_deg": max_angle_deg(after, calibrated),
            "uncalibrated_vs_calibrated_deg": max_angle_deg(before, calibrated)}  # fmt: skip


Lines = queue.SimpleQueue[tuple[float, int, bytes]]  # (monotonic, wall ns, line)


def _router(procs: Processes, endpoint: str) -> tuple[subprocess.Popen[bytes], Lines]:
    """``bodynet router -l ENDPOINT`` with its output lines read as they come, each
    stamped with its arrival (monotonic, wall ns)."""
    proc = subprocess.Popen([sys.executable, "-m", "bodynet.cli.main", "router", "-l", endpoint],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)  # fmt: skip
    procs.started.append(proc)
    lines: Lines = queue.SimpleQueue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put((time.monotonic(), time.time_ns(), line))

    threading.Thread(target=read, daemon=True, name="router-output").start()
    return proc, lines


def _listen_socket(endpoint: str) -> bool:
    """Whether a TCP socket listens on ``endpoint``'s loopback port (Linux: ``/proc/net/tcp``)."""
    port = int(endpoint.rsplit(":", 1)[1])
    try:
        return f":{port:04X} 00000000:0000 0A" in Path("/proc/net/tcp").read_text()
    except OSError:
        return False


def _ready(proc: subprocess.Popen[bytes], lines: Lines, endpoint: str,
           timeout: float) -> tuple[float, int, float]:  # fmt: skip
    """When (monotonic, wall ns) the router could take connections, and how much
    later it printed its listening line. Ready is when its listening socket
    appears (polled every 2 ms): ``bodynet router`` prints the line once
    ``zenoh.open`` has returned, about 0.5 s after that (0.49-0.50 s in runs
    here), by which time the clients are often back. Without ``/proc/net/tcp``,
    the line itself."""
    socket_at: tuple[float, int] | None = None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if socket_at is None and _listen_socket(endpoint):
            socket_at = time.monotonic(), time.time_ns()
        try:
            t, wall_ns, line = lines.get(timeout=0.002)
        except queue.Empty:
            if proc.poll() is not None:
                raise FaultError(f"the router exited ({proc.returncode})") from None
            continue
        if b"listening" in line:
            ready = socket_at or (t, wall_ns)
            return ready[0], ready[1], t - ready[0]
    raise FaultError(f"the router was not listening within {timeout:g} s")


def _grows(path: Path, than: int, timeout: float, what: str) -> Callable[[], float]:
    """Watch, from now on, for ``path`` to be larger than ``than`` bytes (polled
    every 10 ms in a thread, so that the time is taken when it happens, whatever
    the caller waits on meanwhile); the returned call waits for it and gives when."""
    seen: list[float] = []
    deadline = time.monotonic() + timeout

    def watch() -> None:
        while time.monotonic() < deadline:
            with contextlib.suppress(FileNotFoundError):
                if path.stat().st_size > than:
                    seen.append(time.monotonic())
                    return
            threading.Event().wait(0.01)

    thread = threading.Thread(target=watch, daemon=True, name="file-growth")
    thread.start()

    def when() -> float:
        thread.join(max(0.0, deadline - time.monotonic()) + 1)
        if not seen:
            raise FaultError(f"no {what} within {timeout:g} s")
        return seen[0]

    return when


def _nth(n: int) -> Callable[[str, Any], bool]:
    """A match for the ``n``-th message waited on."""
    seen = [0]

    def match(key: str, value: Any) -> bool:
        seen[0] += 1
        return seen[0] >= n

    return match


def _stop(proc: subprocess.Popen[bytes], timeout: float) -> None:
    """SIGINT, as Ctrl-C: the process closes its files and ends."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise FaultError(f"{proc.args!r} did not stop within {timeout:g} s") from None


def router_restarted(timeout: float = 60.0) -> dict[str, Any]:
    """SIGKILL the ``bodynet router`` under a node process, the gateway, the
    recorder and an observing client (the probe, subscribed to raw samples,
    poses and liveliness like a viewer); once the clients have noticed and
    ``ROUTER_OUTAGE_S`` more, start a router again on the same endpoint: each
    client resumes by itself. Times from the new router being ready (its
    listening socket up, see ``_ready``; the listening line comes later) to:
    raw samples and fresh poses at the probe, the node's tokens back, the
    recording growing on disk again (polled every 10 ms; by then its open
    chunk is older than 0.5 s, so the first message the recorder takes is
    flushed at once), and the first pose in the recording made after the
    router's return (its source time, read from the file once the recorder is
    stopped: about when the recorder took poses again, less one hop)."""
    from bodynet.clients.mcap_store import read_poses

    with contextlib.ExitStack() as stack:
        work = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        endpoint = harness.free_endpoint()
        procs = Processes(work / "processes.log")
        stack.callback(procs.close)
        router, lines = _router(procs, endpoint)
        _ready(router, lines, endpoint, timeout)
        probe = harness.client(endpoint)
        stack.callback(probe.close)
        raw, poses, tokens = Inbox(), Inbox(), Inbox()
        subs = [_subscribe(probe, raw, keys.all_raw(), raw_sample.decode),
                _subscribe(probe, poses, keys.pose_key(), pose.decode),
                _liveliness(probe, tokens)]  # fmt: skip
        for sub in subs:
            stack.callback(sub.undeclare)
        _gateway(procs, endpoint)
        _arm(procs, endpoint, "left-arm")
        out = work / "session.mcap"
        rec = procs.start("record", "-o", str(out), "-e", endpoint)
        left = _branch_keys(LEFT_ARM)
        alive: set[str] = set()

        def tokens_are(state: bool) -> Callable[[str, Any], bool]:
            def match(key: str, value: Any) -> bool:
                (alive.add if value else alive.discard)(key)
                return (left <= alive) if state else not (alive & left)

            return match

        def fresh(key: str, frame: Any) -> bool:
            return left <= set(frame.sources) and not set(frame.stale) & left

        tokens.wait(tokens_are(True), timeout, "the node's liveliness tokens")
        poses.wait(fresh, timeout, "poses of the left arm")
        raw.wait(lambda k, v: True, timeout, "raw samples")
        _grows(out, out.stat().st_size if out.exists() else 0, timeout, "recording written")()
        t_kill = time.monotonic()
        router.kill()
        router.wait(timeout=timeout)
        tokens.wait(tokens_are(False), timeout, "the tokens gone with the router")  # noticed
        threading.Event().wait(ROUTER_OUTAGE_S)  # a deliberate outage, not a wait for something
        raw.drain()
        poses.drain()
        written = _grows(out, out.stat().st_size, timeout, "recording written after the restart")
        t_start = time.monotonic()
        router, lines = _router(procs, endpoint)
        t_back, back_ns, line_lag = _ready(router, lines, endpoint, timeout)
        t_raw = raw.wait(lambda k, v: True, timeout, "raw samples after the restart")
        t_pose = poses.wait(fresh, timeout, "fresh poses after the restart")
        t_tokens = tokens.wait(tokens_are(True), timeout, "the node's tokens after the restart")
        t_written = written()
        poses.wait(_nth(50), timeout, "poses going on after the restart")  # for the recorder too
        _stop(rec, timeout)
        recorded = [t for t, _ in read_poses(out) if t > back_ns]
    if not recorded:
        raise FaultError("the recorder wrote no pose made after the restart")
    return {"raw_s": t_raw - t_back, "poses_s": t_pose - t_back, "tokens_s": t_tokens - t_back,
            "recorder_s": (min(recorded) - back_ns) / 1e9, "recorder_on_disk_s": t_written - t_back,
            "poses_recorded_after": len(recorded), "outage_s": t_back - t_kill,
            "router_start_s": t_back - t_start, "listening_line_lag_s": line_lag}  # fmt: skip


def serial_replugged(timeout: float = 60.0) -> dict[str, Any]:
    """Unplug the IMU central's serial device (its pseudo-terminal vanishes)
    and plug it back: the bridge says so on its health key and resumes by itself."""
    from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
    from bodynet.nodes.hardware import ImuCentralEmulator
    from bodynet.nodes.imu_bridge import ImuCentralBridge
    from bodynet.nodes.motion import ROUTINES

    with loopback() as (_, probe, _procs, work):
        inbox = Inbox()
        subs = [_subscribe(probe, inbox, keys.all_raw(), raw_sample.decode),
                _subscribe(probe, inbox, f"{keys.HEALTH}/**", json.loads)]  # fmt: skip
        body = BodyEmulator(ROUTINES["tpose"], imu_tags([1, 2]), realism=Realism.ideal())
        central = ImuCentralEmulator(work / "imu", body, tick_s=0.01)
        central.start()
        bridge = ImuCentralBridge(probe, "replug")
        stop = threading.Event()
        thread = threading.Thread(target=bridge.run, args=(str(central.link), stop), daemon=True)
        thread.start()
        seqs: list[int] = []

        def raw_of_node_1(key: str, value: Any) -> bool:
            if not key.startswith(f"{keys.HEALTH}/") and value.reading.node == 1:
                seqs.append(value.seq)
            return len(seqs) >= 10

        def device(state: str) -> Callable[[str, Any], bool]:
            def match(key: str, value: Any) -> bool:
                raw_of_node_1(key, value)
                return key.startswith(f"{keys.HEALTH}/") and value.get("device") == state

            return match

        try:
            inbox.wait(raw_of_node_1, timeout, "samples")
            t0 = time.monotonic()
            central.port.unplug()
            t_lost = inbox.wait(device("disconnected"), timeout, "the device reported lost")
            n = len(seqs)
            t1 = time.monotonic()
            central.port.plug()
            t_back = inbox.wait(device("connected"), timeout, "the device reported back")
            t_data = inbox.wait(lambda k, v: raw_of_node_1(k, v) and len(seqs) > n, timeout,
                                "samples after the replug")  # fmt: skip
        finally:
            stop.set()
            thread.join(timeout=10)
            central.stop()
            bridge.close()
            for sub in subs:
                sub.undeclare()
    return {"reported_lost_s": t_lost - t0, "reported_back_s": t_back - t1,
            "data_again_s": t_data - t1, "seq_rising": seqs == sorted(seqs)}  # fmt: skip


SCENARIOS: dict[str, Callable[..., dict[str, Any]]] = {
    "node_killed": node_killed,
    "node_frozen": node_frozen,
    "recorder_killed": recorder_killed,
    "gateway_restarted": gateway_restarted,
    "router_restarted": router_restarted,
    "serial_replugged": serial_replugged,
}


def run(out_dir: Path = Path("bench-results"), repeat: int = 3,
        only: Sequence[str] = ()) -> dict[str, Any]:  # fmt: skip
    """Each scenario (or those named in ``only``) ``repeat`` times; the worst
    time of each against its target; writes ``faults.json`` and ``faults.md``."""
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in SCENARIOS}
    for name, scenario in SCENARIOS.items():
        if only and name not in only:
            continue
        for _ in range(repeat):
            try:
                runs[name].append(scenario())
            except FaultError as exc:
                runs[name].append({"error": str(exc)})

    def worst(name: str, field_: str) -> float:
        values = [r[field_] for r in runs[name] if field_ in r]
        return max(values) if values and len(values) == len(runs[name]) else float("nan")

    target = TARGETS_S.get
    rows = [  # what, scenario, field of its result, target
        ("node killed (SIGKILL): liveliness token gone", "node_killed", "liveliness_s",
         target("node_killed")),
        ("node killed (SIGKILL): gateway topology says gone", "node_killed", "topology_s",
         target("node_killed")),
        ("node frozen (SIGSTOP): poses flag it stale", "node_frozen", "stale_s",
         target("node_frozen")),
        ("node resumed (SIGCONT): fresh poses", "node_frozen", "fresh_again_s", None),
        ("recorder killed (SIGKILL): source time lost after salvage", "recorder_killed",
         "lost_s", target("recorder_killed")),
        ("gateway killed and restarted: first pose, same calibration", "gateway_restarted",
         "resume_s", None),
        ("router killed and restarted: raw samples at an observer", "router_restarted", "raw_s",
         target("router_restarted")),
        ("router killed and restarted: fresh poses at an observer", "router_restarted", "poses_s",
         target("router_restarted")),
        ("router killed and restarted: recording grows again", "router_restarted",
         "recorder_on_disk_s", target("router_restarted")),
        ("serial device unplugged: reported lost", "serial_replugged", "reported_lost_s", None),
        ("serial device plugged back: samples again", "serial_replugged", "data_again_s", None),
    ]  # fmt: skip

    def cell(name: str, field_: str) -> str:
        # a run that failed is reported as such, never left out of the table
        errors = [r["error"] for r in runs[name] if "error" in r]
        if errors:
            return f"failed {len(errors)} of {repeat}: {errors[0][:120]}"
        return f"{worst(name, field_):.3f}"

    table = f"| fault | worst of {repeat} s | target s |\n|---|---:|---:|\n" + "".join(
        f"| {what} | {cell(name, field_)} | {'' if goal is None else goal} |\n"
        for what, name, field_, goal in rows
        if runs[name]
    )
    result = {"machine": machine.describe(), "repeat": repeat, "runs": runs,
              "rows": [{"fault": w, "worst_s": worst(n, f), "target_s": g}
                       for w, n, f, g in rows if runs[n]]}  # fmt: skip
    print(f"\nFaults, worst of {repeat} ({machine.line(result['machine'])})\n\n{table}")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "faults.json").write_text(json.dumps(result, indent=2))
    (out_dir / "faults.md").write_text(table)
    return result


if __name__ == "__main__":  # one scenario by name, for a quick look
    print(json.dumps(SCENARIOS[sys.argv[1]](), indent=2))
