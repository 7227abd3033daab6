"""Remote subscribers across hosts: network namespaces joined by veth pairs.

- "laptop": the router and the gateway (a client of it), on 10.77.x.1;
- "home": the subject's nodes (all 15 IMU tags: the whole body), reaching the
  laptop over its own link;
- "clinic": a therapist's recorder, over another link: first one of
  ``body/arm/left/**``, which must get the left arm and nothing else, then one
  of ``body/**``, what the clinic would get if it took everything;
- the test process itself (the root namespace) watches through a third link.

Home and clinic have no route to each other: everything goes through the
laptop's router. What the clinic subscribes to is what crosses its link: the
kernel's byte counter of the clinic's end of the link, over a fixed window
with each recorder, shows the router forwarding the arm only (a recorder of
``body/arm/left/**`` only ever sees matching keys, whatever reaches it, so its
file alone proves nothing about routing). Skips with the reason where
namespaces cannot be made (not root, no ``ip``, no permission); the namespaces
go away at teardown, whatever happened.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader
from service_procs import Services, bodynet
from zenoh_helpers import Collector, Liveliness, client

from bodynet.cli.main import build_parser
from bodynet.clients.mcap_store import read_poses, read_raw
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.core.keys import LEFT_ARM, LEFT_LEG
from bodynet.core.profile import IMU_SITES

SESSION_FLAGS = {"-e", "--connect", "-l", "--listen", "--mode", "-c", "--config"}
# no Zenoh session: files in, files out (every `export FORMAT` too); the demo runs its own
OFFLINE = {"decode", "demo", "process", "report", "certs", "bench"}
PORT = 7447
WINDOW_S = 5.0  # each measuring window of the clinic's link
RAW_FLOWING_B = 16_384  # a recording grown this much holds raw samples, not only its start

# one at a time under `make test`'s two processes: links from this namespace take 10.77.n.0/24
pytestmark = pytest.mark.xdist_group("netns")


def _leaves(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield " ".join(path), parser
    for action in subs:
        for name, sub in action.choices.items():
            yield from _leaves(sub, (*path, name))


def test_every_networked_command_takes_the_session_flags() -> None:
    commands = dict(_leaves(build_parser()))
    assert {"record", "view", "gateway"} <= set(commands)
    for name, parser in commands.items():
        if name in OFFLINE or name.startswith("export "):
            continue
        flags = {o for a in parser._actions for o in a.option_strings}
        assert flags >= SESSION_FLAGS, f"bodynet {name} lacks {sorted(SESSION_FLAGS - flags)}"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


class Hosts:
    """Namespaces as hosts; ``link(a, b, n)`` joins two with 10.77.n.1 (a) and .2 (b)."""

    def __init__(self) -> None:
        self.tag = f"bn{os.getpid() % 100000}"
        self.names: list[str] = []
        self.veths: list[str] = []

    def add(self, host: str) -> str:
        name = f"{self.tag}-{host}"
        _ip("netns", "add", name)
        self.names.append(name)
        _ip("-n", name, "link", "set", "lo", "up")
        return name

    def link(self, a: str | None, b: str, n: int) -> tuple[str, str]:
        """Join namespace ``a`` (None: this one) to ``b``; returns their addresses."""
        left, right = f"{self.tag}{n}a", f"{self.tag}{n}b"
        _ip("link", "add", left, "type", "veth", "peer", "name", right)
        self.veths.append(left)
        _ip("link", "set", right, "netns", b)
        ip_a = ["ip"] if a is None else ["ip", "-n", a]
        if a is not None:
            _ip("link", "set", left, "netns", a)
        for cmd, dev, addr in (
            (ip_a, left, f"10.77.{n}.1"),
            (["ip", "-n", b], right, f"10.77.{n}.2"),
        ):
            subprocess.run([*cmd, "addr", "add", f"{addr}/24", "dev", dev], check=True, timeout=30)
            subprocess.run([*cmd, "link", "set", dev, "up"], check=True, timeout=30)
        return f"10.77.{n}.1", f"10.77.{n}.2"

    def far_end(self, n: int) -> str:
        """The interface of link ``n`` on its host ``b``."""
        return f"{self.tag}{n}b"

    def close(self) -> None:
        for veth in self.veths:  # those still here (one end in this namespace)
            subprocess.run(["ip", "link", "del", veth], check=False, capture_output=True)
        for name in self.names:
            subprocess.run(["ip", "netns", "del", name], check=False, capture_output=True)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) to make network namespaces")
    made = Hosts()
    try:
        made.add("probe")
    except subprocess.CalledProcessError as exc:
        made.close()
        pytest.skip(f"cannot make a network namespace here: {exc.stderr.strip()}")
    made.close()
    made.names.clear()
    yield made
    made.close()


@pytest.fixture
def services() -> Iterator[Services]:
    s = Services()
    yield s
    s.close()


def in_ns(ns: str, *args: str) -> list[str]:
    """``bodynet ARGS`` run on the host ``ns``."""
    return ["ip", "netns", "exec", ns, *bodynet(*args)]


def wait_for_file(path: Path, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < deadline, f"{path} never appeared"
        threading.Event().wait(0.05)


def wait_for_data(path: Path, timeout: float = 60, grown: int = 0) -> None:
    """Until the recording at ``path`` grows by more than ``grown`` bytes (its
    recorder flushes a chunk of messages every half second): the recorder is
    receiving (with ``grown``, more than the topology it asks for at its start)."""
    wait_for_file(path, timeout)
    first = path.stat().st_size
    deadline = time.monotonic() + timeout
    while path.stat().st_size <= first + grown:
        assert time.monotonic() < deadline, f"nothing recorded in {path}"
        threading.Event().wait(0.05)


def rx_bytes(ns: str, dev: str) -> int:
    """Bytes the kernel has counted in on ``dev`` of the host ``ns`` (every frame:
    Ethernet, IP and TCP headers, Zenoh framing and payloads)."""
    out = subprocess.run(["ip", "-n", ns, "-s", "-j", "link", "show", "dev", dev],
                         check=True, capture_output=True, text=True, timeout=30).stdout  # fmt: skip
    return int(json.loads(out)[0]["stats64"]["rx"]["bytes"])


class Flow:
    """What the laptop's router forwards of the body (``body/**``), as the test
    process sees it over its own link: bytes (payload and key) and messages per key."""

    def __init__(self, session: zenoh.Session) -> None:
        self._lock = threading.Lock()
        self.bytes = 0
        self.counts: Counter[str] = Counter()
        self.smallest: dict[str, int] = {}  # key -> its smallest payload seen
        self._sub = session.declare_subscriber("body/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key, size = str(sample.key_expr), len(sample.payload.to_bytes())
        with self._lock:
            self.bytes += size + len(key)
            self.counts[key] += 1
            self.smallest[key] = min(size, self.smallest.get(key, size))

    def snapshot(self) -> tuple[int, Counter[str]]:
        with self._lock:
            return self.bytes, self.counts.copy()


@dataclass
class Window:
    """One measuring window: bytes in on the clinic's link, and the body's flow
    at the laptop meanwhile (bytes, messages per key)."""

    link: int
    body: int
    counts: Counter[str]


def measure(ns: str, dev: str, flow: Flow) -> Window:
    """The clinic's link and the body's flow over ``WINDOW_S`` seconds."""
    rx0, (body0, counts0) = rx_bytes(ns, dev), flow.snapshot()
    threading.Event().wait(WINDOW_S)
    rx1, (body1, counts1) = rx_bytes(ns, dev), flow.snapshot()
    return Window(rx1 - rx0, body1 - body0, counts1 - counts0)


def recorded_payload(path: Path, smallest: dict[str, int]) -> int:
    """At least the payload bytes that reached the recorder of ``path``: each
    message it holds at the smallest size the laptop saw on its key."""
    with path.open("rb") as f:
        counts = Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages())
    return sum(n * smallest[topic] for topic, n in counts.items() if topic in smallest)


@pytest.mark.timeout(300)
def test_selective_subscription_across_hosts(
    hosts: Hosts, services: Services, tmp_path: Path
) -> None:
    laptop, clinic, home = hosts.add("laptop"), hosts.add("clinic"), hosts.add("home")
    clinic_gw, _ = hosts.link(laptop, clinic, 1)
    clinic_dev = hosts.far_end(1)  # what the clinic receives comes in here, and only here
    home_gw, _ = hosts.link(laptop, home, 2)
    _, laptop_addr = hosts.link(None, laptop, 3)  # the test process watches over its own link

    router = services.start("router", in_ns(laptop, "router", "-l", f"tcp/0.0.0.0:{PORT}"))
    router.wait_line("listening")
    local = f"tcp/127.0.0.1:{PORT}"
    services.start("gateway", in_ns(laptop, "gateway", "--mode", "client", "-e", local))
    to_laptop = f"tcp/{home_gw}:{PORT}"
    services.start("home", in_ns(home, "node", "imu", "-e", to_laptop))  # the whole body

    watcher = client(f"tcp/{laptop_addr}:{PORT}")
    live = Liveliness(watcher, keys.all_raw())
    every = {s.raw_key for s in IMU_SITES.values()}
    left_arm = {s.raw_key for s in IMU_SITES.values() if s.branch == LEFT_ARM}
    live.wait_for(lambda alive: every <= alive, timeout=90)
    poses = Collector(watcher, keys.pose_key(LEFT_ARM), pose.decode)
    poses.wait_for(lambda s: len(s) >= 10, timeout=60)
    flow = Flow(watcher)

    remote = f"tcp/{clinic_gw}:{PORT}"
    arm_out, body_out = tmp_path / "clinic-arm.mcap", tmp_path / "clinic-body.mcap"
    before = rx_bytes(clinic, clinic_dev)
    arm_rec = services.start("clinic-arm", in_ns(clinic, "record", "-o", str(arm_out),
                                                  "body/arm/left/**", "-e", remote))  # fmt: skip
    wait_for_data(arm_out)
    arm = measure(clinic, clinic_dev, flow)
    assert arm_rec.stop() == 0, arm_rec.tail()
    arm_lifetime = rx_bytes(clinic, clinic_dev) - before  # the arm recorder's whole session

    body_rec = services.start("clinic-body", in_ns(clinic, "record", "-o", str(body_out),
                                                    "body/**", "-e", remote))  # fmt: skip
    # the whole body's samples flowing in (a window begun on the recorder's first
    # chunk, its topology, once carried 0.17 of the body's flow)
    wait_for_data(body_out, grown=RAW_FLOWING_B)
    body = measure(clinic, clinic_dev, flow)
    assert body_rec.stop() == 0, body_rec.tail()
    watcher.close()

    # the clinic's recording: the left arm, nothing else
    topics = {topic for topic, _, _ in read_raw(arm_out)}
    assert topics == left_arm
    arm_poses = list(read_poses(arm_out, keys.pose_key(LEFT_ARM)))
    assert arm_poses, "the left arm's poses reach the clinic"
    assert list(read_poses(arm_out, keys.pose_key())) == []  # not subscribed: not sent
    # meanwhile the whole body flowed from home to the gateway, the leg included
    assert every <= set(arm.counts), sorted(every - set(arm.counts))
    assert arm.counts[keys.pose_key(LEFT_LEG)] > 0, "the gateway poses the leg all the while"

    # What crossed the clinic's link. One arm is 3 of the 15 nodes (raw samples
    # of 62 B, ground truth of ~280 B, publisher heartbeats) and 1 of the 6 pose
    # keys, ~1.1 kB of the ~9.7 kB of poses a tick (body/pose alone carries every
    # joint, 4.6 kB): a seventh of the body's payload, and the protocol's share
    # (frame headers, TCP acknowledgements, keepalives) goes with the messages
    # or is a small constant (the arm's link measured 0.19 of the body's flow).
    # Under half, of the body's flow at the laptop and of what the same link
    # carries for `body/**` (per byte of that flow in the same window, so a
    # change of pace between windows is no matter), leaves more than twice that
    # share: no flake, and forwarding the body, or even half of it, to the arm's
    # recorder fails.
    arm_share, body_share = arm.link / arm.body, body.link / body.body
    assert arm_share < 0.5, (arm, body)
    assert arm_share < body_share / 2, (arm, body)
    recorded = recorded_payload(arm_out, flow.smallest)
    assert 0 < recorded <= arm_lifetime, "at least what the clinic recorded crossed its link"

    # subscribed to everything, the clinic gets the whole body, the leg's poses too
    assert {topic for topic, _, _ in read_raw(body_out)} == every
    frames = [frame for _, frame in read_poses(body_out)]
    assert frames, "whole-body poses reach the clinic"
    leg_sources = {k for frame in frames for k in frame.sources if k.startswith("body/leg/left/")}
    assert leg_sources, "the leg flows to the gateway"
    print(f"\nclinic link over {WINDOW_S:.0f} s: {arm.link} B with body/arm/left/** "
          f"(body flow at the laptop {arm.body} B), {body.link} B with body/** "
          f"({body.body} B); shares {arm_share:.2f} vs {body_share:.2f}; "
          f"arm recorder's session {arm_lifetime} B >= {recorded} B of payload recorded "
          f"({len(arm_poses)} arm poses, raw of {len(topics)} sites)")  # fmt: skip
