"""The router killed (SIGKILL) and restarted on the same endpoint: every client
comes back by itself, and the recorder loses no raw sample (recovered from the
node publishers' caches) or writes the gap down.

Real processes throughout: ``bodynet router``, an IMU node (left arm) with its
bridge, the gateway as a client, the recorder and the viewer (saving an .rrd).
No timing is asserted; the resume times are printed (run with ``-s``)."""

from __future__ import annotations

import queue
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from service_procs import Services, bodynet
from zenoh_helpers import Liveliness, client, free_port

from bodynet.clients.mcap_store import read_gaps, read_poses, read_raw
from bodynet.core import keys
from bodynet.core.keys import LEFT_ARM
from bodynet.core.profile import IMU_SITES

OUTAGE_S = 1.5  # how long the router stays dead: past the clients' longest retry period
LEFT_ARM_IMU = sorted(s.raw_key for s in IMU_SITES.values() if s.branch == LEFT_ARM)
SENSORS = ",".join(str(n) for n, s in sorted(IMU_SITES.items()) if s.branch == LEFT_ARM)


@pytest.fixture
def services() -> Iterator[Services]:
    s = Services()
    yield s
    s.close()


class Arrivals:
    """Wall time of arrival of every sample on ``key`` (raw samples or poses)."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.times: queue.Queue[int] = queue.Queue()
        self._sub = session.declare_subscriber(key, lambda _: self.times.put(time.time_ns()))

    def first_after(self, t_ns: int, timeout: float = 30.0) -> int:
        """The arrival time of the first sample later than ``t_ns``."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                arrived = self.times.get(timeout=left)
            except queue.Empty:
                break
            if arrived > t_ns:
                return arrived
        raise AssertionError(f"nothing arrived after the router came back ({timeout} s)")

    def count(self, n: int, timeout: float = 30.0) -> None:
        for _ in range(n):
            self.times.get(timeout=timeout)


def test_clients_resume_and_recorder_loses_nothing(services: Services, tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = services.start("router", bodynet("router", "-l", endpoint))
    router.wait_line("listening")
    zen = ["-e", endpoint]
    services.start("node", bodynet("node", "imu", "--sensors", SENSORS, "--routine", "reach",
                                   "--ideal", "--name", "home", *zen))  # fmt: skip
    gateway = services.start("gateway", bodynet("gateway", "--mode", "client", *zen))
    gateway.wait_line("serving")
    observer = client(endpoint)
    raw = Arrivals(observer, "body/arm/left/*/raw")
    poses = Arrivals(observer, keys.pose_key())
    live = Liveliness(observer, keys.all_raw())
    out, rrd = tmp_path / "session.mcap", tmp_path / "view.rrd"
    recorder = services.start("recorder", bodynet("record", "-o", str(out), *zen))
    viewer = services.start("viewer", bodynet("view", "--viewer", "none", "--save", str(rrd), *zen))
    live.wait_for(lambda alive: set(LEFT_ARM_IMU) <= alive, timeout=60)
    poses.count(50, timeout=60)  # two seconds of poses reach the recorder and viewer too
    # the viewer is live before the outage (under load it may start later than the
    # recorder: a view that only ever saw the router come back proves no resuming)
    t_viewing = viewer.wait_line("bodynet view: live, poses arriving", timeout=60)

    t_kill = time.time_ns()
    router.proc.send_signal(signal.SIGKILL)
    router.proc.wait(timeout=10)
    live.wait_for(lambda alive: not alive)  # the clients noticed
    t_noticed = time.time_ns()
    threading.Event().wait(OUTAGE_S)  # a deliberate outage, not a wait for something
    t_start = time.time_ns()
    router = services.start("router-again", bodynet("router", "-l", endpoint))
    t_back = router.wait_line("listening")
    t_raw = raw.first_after(t_back)
    t_pose = poses.first_after(t_back)
    live.wait_for(lambda alive: set(LEFT_ARM_IMU) <= alive)
    t_live = time.time_ns()
    poses.count(75, timeout=60)  # three more seconds of everything
    print(
        f"\nrouter down {(t_back - t_kill) / 1e9:.2f} s (loss noticed in "
        f"{(t_noticed - t_kill) / 1e6:.0f} ms, new router listening {(t_back - t_start) / 1e6:.0f}"
        f" ms after its start); after its "
        f"return: raw samples at the observer {(t_raw - t_back) / 1e6:.0f} ms, poses "
        f"{(t_pose - t_back) / 1e6:.0f} ms, node tokens back by {(t_live - t_back) / 1e6:.0f} ms"
    )
    assert recorder.stop() == 0, recorder.tail()
    assert viewer.stop() == 0, viewer.tail()
    observer.close()

    # the viewer resumed: it showed more poses than it can have had before the outage,
    # those from a second before it said it was live (its first batch is 0.1 s) on
    pose_times = [t for t, _ in read_poses(out)]
    viewed = int(viewer.output[-1].split(":")[1].split()[0])  # "bodynet view: N poses, ..."
    before = sum(1 for t in pose_times if t_viewing - 1_000_000_000 <= t < t_kill)
    assert viewed > before, viewer.tail()

    # the recorder resumed: poses after the router's return
    after = [t for t in pose_times if t > t_back]
    assert after, "no pose recorded after the restart"
    print(f"recorder: first pose (source time) {(after[0] - t_back) / 1e6:.0f} ms after the return")

    check_nothing_lost(out, t_kill, t_back)


def check_nothing_lost(out: Path, t_kill: int, t_back: int) -> None:
    """The outage is in the recording, fetched from the caches; any hole is a gap record."""
    gaps = read_gaps(out)
    for key in LEFT_ARM_IMU:
        samples = [(t, s.seq) for topic, t, s in read_raw(out) if topic == key]
        seqs = sorted(seq for _, seq in samples)
        in_outage = sum(1 for t, _ in samples if t_kill < t < t_back)
        missing = (seqs[-1] - seqs[0] + 1) - len(set(seqs))
        recorded_gaps = sum(g.missing for g in gaps if g.topic == key)
        print(f"{key}: {len(seqs)} samples, {in_outage} from the outage, {missing} missing, "
              f"{recorded_gaps} in gap records")  # fmt: skip
        assert in_outage > 0, f"{key}: nothing from the outage was recovered"
        assert missing == recorded_gaps, "every missing sample is in a gap record"
        assert missing == 0, f"{key}: {missing} samples lost"
