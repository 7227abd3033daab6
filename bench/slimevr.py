"""How many SlimeVR trackers, at what rate, one bridge process takes with no loss.

A router and ``bodynet bridge slimevr`` run as processes of their own; this
process plays N trackers (one UDP socket each: handshake, then one rotation
packet per tracker per period, all from one loop) for ``seconds``, then reads
the bridge's health: every packet sent must have been published (samples) with
no gap. Run: ``python -m bodynet.bench.slimevr 30 200 10`` (trackers, Hz, s); 30 is
the most one body holds (one tracker a site).
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil

from bodynet.core.codecs import slimevr as codec
from bodynet.core.keys import BRANCHES, SITES, Site

#: every site of the key space (30): one tracker each, the most one body holds
ALL_SITES = [Site(b, name) for b in BRANCHES for name in SITES[b.limb]]


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _connect(mac: bytes, udp: tuple[str, int]) -> socket.socket:
    """A tracker's socket, once the bridge has answered its handshake."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.2)
    hs = codec.Handshake(mac, 2, 10, 2, 17, "bench")
    for _ in range(50):  # the bridge may still be starting
        sock.sendto(codec.encode_handshake(0, hs), udp)
        try:
            if sock.recv(128).startswith(codec.HANDSHAKE_MAGIC):
                break
        except TimeoutError:
            continue
    sock.setblocking(False)
    return sock


def _stream(socks: list[socket.socket], udp: tuple[str, int], rate_hz: float,
            seconds: float) -> tuple[int, int]:  # fmt: skip
    """One rotation per tracker per period for ``seconds``: (sent, periods late)."""
    period = 1.0 / rate_hz
    sent = late = number = 0
    start = next_t = time.monotonic()
    while time.monotonic() - start < seconds:
        number += 1
        for sock in socks:
            sock.sendto(codec.encode_rotation(number, 0, (0.0, 0.0, 0.0, 1.0)), udp)
            sent += 1
        next_t += period
        wait = next_t - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        else:
            late += 1
    return sent, late


def run(trackers: int = 30, rate_hz: float = 200.0, seconds: float = 10.0) -> dict[str, object]:
    from bodynet.session import open_session, session_config

    bodynet = str(Path(sys.executable).with_name("bodynet"))
    endpoint = f"tcp/127.0.0.1:{_free_port(socket.SOCK_STREAM)}"
    udp = ("127.0.0.1", _free_port(socket.SOCK_DGRAM))
    if trackers > len(ALL_SITES):
        raise ValueError(f"at most {len(ALL_SITES)} trackers: one per site of a body")
    sites = ALL_SITES
    macs = [bytes([2, 0, 0, 0, i >> 8, i & 0xFF]) for i in range(trackers)]
    assign = []
    for i, mac in enumerate(macs):
        site = sites[i % len(sites)]
        assign += ["--assign", f"{codec.tracker_id(mac, 0)}={site.branch}/{site.name}"]
    router = subprocess.Popen([bodynet, "router", "-l", endpoint])
    procs = [router]
    try:
        time.sleep(1.0)
        bridge = subprocess.Popen([bodynet, "bridge", "slimevr", "--udp", f"{udp[0]}:{udp[1]}",
                                   "--name", "bench", "-e", endpoint, *assign])  # fmt: skip
        procs.append(bridge)
        session = open_session(session_config("client", connect=[endpoint]))
        health: list[dict[str, object]] = []
        session.declare_subscriber(
            "body/@health/bench", lambda s: health.append(json.loads(s.payload.to_bytes()))
        )
        socks = [_connect(mac, udp) for mac in macs]
        cpu = psutil.Process(bridge.pid)
        cpu.cpu_percent()
        start = time.monotonic()
        sent, late = _stream(socks, udp, rate_hz, seconds)
        elapsed = time.monotonic() - start
        bridge_cpu = cpu.cpu_percent()
        time.sleep(2.5)  # the last health (once a second) after the last sample
        last = health[-1] if health else {"nodes": {}}
        nodes = last["nodes"]
        assert isinstance(nodes, dict)
        samples = sum(int(n["samples"]) for n in nodes.values())
        gaps = sum(int(n["gaps"]) for n in nodes.values())
        session.close()
        return {
            "trackers": trackers, "rate_hz": rate_hz, "seconds": round(elapsed, 2),
            "sent": sent, "published": samples, "gaps": gaps, "lost": sent - samples,
            "sender_late_periods": late, "bridge_cpu_percent": bridge_cpu,
            "packets_per_s": round(sent / elapsed),
        }  # fmt: skip
    finally:
        for proc in reversed(procs):
            proc.terminate()
            proc.wait(10)


if __name__ == "__main__":
    args = [float(a) for a in sys.argv[1:]]
    print(json.dumps(run(int(args[0]) if args else 30, *(args[1:3] or [200.0, 10.0]))))
