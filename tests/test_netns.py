"""Remote subscribers across hosts: network namespaces joined by veth pairs.

- "laptop": the router and the gateway (a client of it), on 10.77.x.1;
- "home": the subject's nodes (IMU tags of the left arm and left leg),
  reaching the laptop over its own link;
- "clinic": a therapist's recorders, over another link: one subscribes only
  to ``body/arm/left/**`` and must get nothing else, the other to the
  whole-body pose, which shows the leg flowing to the gateway all the while;
- the test process itself (the root namespace) watches through a third link.

Home and clinic have no route to each other: everything goes through the
laptop's router. Skips with the reason where namespaces cannot be made (not
root, no ``ip``, no permission); the namespaces go away at teardown, whatever
happened.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
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
SENSORS = ",".join(str(n) for n, s in sorted(IMU_SITES.items()) if s.branch in (LEFT_ARM, LEFT_LEG))
PORT = 7447


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


def test_selective_subscription_across_hosts(
    hosts: Hosts, services: Services, tmp_path: Path
) -> None:
    laptop, clinic, home = hosts.add("laptop"), hosts.add("clinic"), hosts.add("home")
    clinic_gw, _ = hosts.link(laptop, clinic, 1)
    home_gw, _ = hosts.link(laptop, home, 2)
    _, laptop_addr = hosts.link(None, laptop, 3)  # the test process watches over its own link

    router = services.start("router", in_ns(laptop, "router", "-l", f"tcp/0.0.0.0:{PORT}"))
    router.wait_line("listening")
    local = f"tcp/127.0.0.1:{PORT}"
    services.start("gateway", in_ns(laptop, "gateway", "--mode", "client", "-e", local))
    to_laptop = f"tcp/{home_gw}:{PORT}"
    services.start("home", in_ns(home, "node", "imu", "--sensors", SENSORS, "-e", to_laptop))

    watcher = client(f"tcp/{laptop_addr}:{PORT}")
    live = Liveliness(watcher, keys.all_raw())
    wanted = {s.raw_key for s in IMU_SITES.values() if s.branch in (LEFT_ARM, LEFT_LEG)}
    live.wait_for(lambda alive: wanted <= alive, timeout=90)
    poses = Collector(watcher, keys.pose_key(LEFT_ARM), pose.decode)
    poses.wait_for(lambda s: len(s) >= 10, timeout=60)

    remote = f"tcp/{clinic_gw}:{PORT}"
    arm_out, body_out = tmp_path / "clinic-arm.mcap", tmp_path / "clinic-body.mcap"
    arm_rec = services.start("clinic-arm", in_ns(clinic, "record", "-o", str(arm_out),
                                                  "body/arm/left/**", "-e", remote))  # fmt: skip
    body_rec = services.start("clinic-body", in_ns(clinic, "record", "-o", str(body_out),
                                                    keys.pose_key(), "-e", remote))  # fmt: skip
    wait_for_file(arm_out)
    wait_for_file(body_out)
    n = len(poses.seen)
    poses.wait_for(lambda s: len(s) >= n + 75)  # three seconds more, recorded at the clinic
    assert arm_rec.stop() == 0, arm_rec.tail()
    assert body_rec.stop() == 0, body_rec.tail()
    watcher.close()

    topics = {topic for topic, _, _ in read_raw(arm_out)}
    assert topics == {s.raw_key for s in IMU_SITES.values() if s.branch == LEFT_ARM}
    arm_poses = list(read_poses(arm_out, keys.pose_key(LEFT_ARM)))
    assert arm_poses, "the left arm's poses reach the clinic"
    assert list(read_poses(arm_out, keys.pose_key())) == []  # not subscribed: not sent
    body = [frame for _, frame in read_poses(body_out)]
    assert body, "whole-body poses reach the clinic"
    leg_sources = {k for frame in body for k in frame.sources if k.startswith("body/leg/left/")}
    assert leg_sources, "the leg flows to the gateway while the clinic records only the arm"
    print(f"\nclinic: {len(topics)} left-arm raw topics, {len(arm_poses)} arm poses; "
          f"{len(body)} body poses with leg sources {sorted(leg_sources)}")  # fmt: skip
