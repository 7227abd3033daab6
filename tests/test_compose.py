"""docker-compose.yml, run without Docker: every service's command as a local
process, with the same arguments and environment.

What changes on the way from containers to processes: host names become
127.0.0.1 and published ports free loopback ports (other tests may hold 7447
or 9090); named volumes become directories under tmp; the router, which is the
official eclipse/zenoh image (zenohd is not on PyPI), becomes
``bodynet router`` reading the same mounted config file, listening on the
loopback port instead. Then poses must reach the recorder (its MCAP read back
after it stops), the web viewer and the game must serve their pages, and
stopping one branch's service must show on ``body/@topology``. Every service's
command must exist in this build: one that does not fails the test.
"""

from __future__ import annotations

import json
import signal
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from service_procs import Service, Services, bodynet
from zenoh_helpers import Collector, Liveliness, client, free_port

from bodynet.cli.main import build_parser
from bodynet.clients.mcap_store import read_poses, read_raw
from bodynet.core import keys
from bodynet.core.keys import LEFT_ARM, RIGHT_ARM
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = ROOT / "docker-compose.yml"
BRANCH_SERVICES = ("node-left-arm", "node-right-arm", "node-left-leg", "node-right-leg",
                   "node-trunk")  # fmt: skip


@dataclass
class Local:
    """A compose service as a local process: its argv and environment."""

    name: str
    argv: list[str]
    env: dict[str, str]


def bodynet_commands() -> set[str]:
    parser = build_parser()
    return {name for a in parser._subparsers._group_actions for name in a.choices}  # type: ignore[union-attr]


def localise(compose: dict, tmp: Path) -> tuple[dict[str, Local], str]:  # type: ignore[type-arg]
    """Every service as a local process; returns them and the router's endpoint."""
    services = compose["services"]
    ports: dict[tuple[str, str], str] = {}  # (service, container port) -> free loopback port
    for name, svc in services.items():
        for mapping in svc.get("ports", []):
            container = str(mapping).split(":")[-1]
            ports[(name, container)] = str(free_port())
    hosts = {f"{name}:{c}": f"127.0.0.1:{p}" for (name, c), p in ports.items()}
    volumes: dict[str, str] = {}

    def local(text: str, name: str, svc_ports: dict[str, str]) -> str:
        for host, loopback in hosts.items():
            text = text.replace(host, loopback)
        if text in svc_ports:
            return svc_ports[text]
        for container_path, host_path in volumes.items():
            if text.startswith(container_path):
                return host_path + text[len(container_path) :]
        return text

    out: dict[str, Local] = {}
    router_endpoint = ""
    for name, svc in services.items():
        volumes = {}
        for volume in svc.get("volumes", []):
            source, target = volume.split(":")[:2]
            if source.startswith("."):  # a bind mount of a file of the repository
                volumes[target] = str((ROOT / source).resolve())
            else:  # a named volume
                (tmp / source).mkdir(exist_ok=True)
                volumes[target] = str(tmp / source)
        svc_ports = {c: p for (n, c), p in ports.items() if n == name}
        env = {k: local(str(v), name, {}) for k, v in svc.get("environment", {}).items()}
        args = [local(str(a), name, svc_ports) for a in svc.get("command", [])]
        if str(svc.get("image", "")).startswith("eclipse/zenoh"):
            router_endpoint = f"tcp/127.0.0.1:{svc_ports['7447']}"
            out[name] = Local(name, bodynet("router", *args, "-l", router_endpoint), env)
        else:
            out[name] = Local(name, bodynet(*args), env)
    return out, router_endpoint


def fetch(url: str) -> tuple[int, str, str]:
    """GET ``url``: status, content type and body (as text)."""
    with urllib.request.urlopen(url, timeout=30) as page:
        body = page.read().decode("utf-8", errors="replace")
        return page.status, page.headers.get("Content-Type", ""), body


def check_viewer_page(viewer: Service, spec: Local) -> str:
    """The web viewer's page, fetched from the address the viewer prints (on the
    published web port), is Rerun's web viewer; returns that address."""
    viewer.wait_line("web viewer at", timeout=60)
    line = next(ln for ln in viewer.output if "web viewer at" in ln)
    url = line.split("web viewer at ", 1)[1].strip()
    web_port = spec.argv[spec.argv.index("--web-port") + 1]
    assert url.startswith(f"http://127.0.0.1:{web_port}/"), url
    status, kind, html = fetch(url)
    assert status == 200
    assert kind.startswith("text/html"), kind
    # Rerun's bundled web viewer: its title, and the wasm-bindgen loader of re_viewer
    assert "<title>Rerun Viewer</title>" in html, html[:300]
    assert 'src="re_viewer.js"' in html, html[:300]
    return url


@pytest.fixture
def services() -> Iterator[Services]:
    s = Services()
    yield s
    s.close()


def test_compose_file_shape() -> None:
    compose = yaml.safe_load(COMPOSE.read_text())
    services = compose["services"]
    assert services["router"]["image"].startswith("eclipse/zenoh")
    for name in ("gateway", *BRANCH_SERVICES, "recorder", "viewer", "game"):
        assert name in services, f"no {name} service"
        assert services[name]["environment"]["BODYNET_ZENOH_CONNECT"] == "tcp/router:7447"
    assert services["gateway"]["command"][:3] == ["gateway", "--mode", "client"]


def test_compose_services_as_local_processes(services: Services, tmp_path: Path) -> None:
    compose = yaml.safe_load(COMPOSE.read_text())
    local, endpoint = localise(compose, tmp_path)
    assert {"game", "viewer", "recorder"} <= set(local), sorted(local)
    known = bodynet_commands()
    missing = {n: s.argv[1] for n, s in local.items() if s.argv[1] not in known}
    assert not missing, f"compose services whose `bodynet` command is missing: {missing}"

    router = services.start("router", local["router"].argv)
    router.wait_line("listening")
    observer = client(endpoint)
    live = Liveliness(observer, keys.all_raw())
    topology = Collector(observer, keys.TOPOLOGY, json.loads)
    started: dict[str, Service] = {}
    for name, svc in local.items():
        if name != "router":
            started[name] = services.start(name, svc.argv, env=svc.env)

    # the compose file's body: SmartSuit arms, IMU tags on the legs and trunk
    arms = (LEFT_ARM, RIGHT_ARM)
    expected = {s.raw_key for s in SMARTSUIT_SITES.values() if s.branch in arms} | {
        s.raw_key for s in IMU_SITES.values() if s.branch not in arms
    }
    live.wait_for(lambda alive: expected <= alive, timeout=120)
    poses = Collector(observer, keys.pose_key(), lambda b: None)
    poses.wait_for(lambda s: len(s) >= 100, timeout=60)
    viewer_url = check_viewer_page(started["viewer"], local["viewer"])
    started["game"].wait_line("bodynet game: http", timeout=60)
    port = local["game"].argv[local["game"].argv.index("--http-port") + 1]
    status, _, _ = fetch(f"http://127.0.0.1:{port}/")  # the game's page, on its published port
    assert status == 200

    def alive_branches(seen: list[tuple[str, dict]]) -> set[str]:  # type: ignore[type-arg]
        """Branches with a live node in the latest topology."""
        branches = seen[-1][1]["branches"] if seen else {}
        return {b for b, info in branches.items()
                if any(n["state"] == "alive" for n in info["nodes"].values())}  # fmt: skip

    five = {str(b) for b in keys.BRANCHES}
    topology.wait_for(lambda seen: alive_branches(seen) == five, timeout=60)
    # `docker compose stop node-right-arm`: SIGTERM; the branch goes, live
    assert started["node-right-arm"].stop(signal.SIGTERM) == 0
    topology.wait_for(lambda seen: alive_branches(seen) == five - {str(RIGHT_ARM)}, timeout=30)
    right = {s.raw_key for s in SMARTSUIT_SITES.values() if s.branch == RIGHT_ARM}
    assert not (right & live.wait_for(lambda alive: not (right & alive)))

    for name, service in started.items():  # nothing else fell over meanwhile
        if name != "node-right-arm":
            assert service.proc.poll() is None, f"{name} ended:\n{service.tail()}"
    assert started["recorder"].stop(signal.SIGTERM) == 0, started["recorder"].tail()
    observer.close()
    out = tmp_path / "recordings" / "bodynet.mcap"
    recorded = list(read_poses(out))
    topics = {topic for topic, _, _ in read_raw(out)}
    print(f"\nrecorder: {len(recorded)} poses, raw samples of {len(topics)} sites; "
          f"web viewer at {viewer_url}")  # fmt: skip
    assert len(recorded) > 10, "poses reach the recorder"
    assert expected <= topics, sorted(expected - topics)
