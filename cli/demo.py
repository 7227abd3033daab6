"""The main job, until the gateway lands: the body network live on one machine.

An embedded Zenoh router, an emulated full body made of both source systems
(SmartSuit left arm over CAN, right arm through the Data Concentrator, IMU
tags for trunk and legs, each on its real transport and bridge), and a live
table of what each key carries, read back from Zenoh as any client would.
"""

from __future__ import annotations

import threading
import time
from collections import Counter

import zenoh

from bodynet.core import keys
from bodynet.core.codecs import raw_sample
from bodynet.core.errors import DecodeError
from bodynet.core.messages import OleAccel
from bodynet.nodes.services import EmulationOptions, body_plan, run_node
from bodynet.session import open_session, session_config


def _describe(sample: raw_sample.RawSample) -> str:
    r = sample.reading
    if isinstance(r, OleAccel):
        return f"encoder {r.encoder:6d}  accel {r.accel}"
    return "quat " + " ".join(f"{c:+.3f}" for c in r.wxyz)


def run_demo(endpoint: str, routine: str, seconds: float | None, stop: threading.Event) -> int:
    """Run router, emulated body and a live view of its keys until ``stop`` (or ``seconds``)."""
    router = open_session(session_config("router", listen=[endpoint]))
    node = open_session(session_config("client", connect=[endpoint]))
    viewer = open_session(session_config("client", connect=[endpoint]))
    counts: Counter[str] = Counter()
    latest: dict[str, str] = {}

    def on_raw(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            latest[key] = _describe(raw_sample.decode(sample.payload.to_bytes()))
        except DecodeError as exc:
            latest[key] = f"rejected: {exc}"
        counts[key] += 1

    sub = viewer.declare_subscriber(keys.all_raw(), on_raw)
    thread = threading.Thread(
        target=run_node, daemon=True, args=(node, stop, body_plan(), EmulationOptions(routine))
    )
    thread.start()
    print(f"bodynet demo: router on {endpoint}; emulated body doing {routine!r}.")
    print(
        "Subscribe from elsewhere with: bodynet ... -e " + endpoint.replace("127.0.0.1", "<host>")
    )
    start = time.monotonic()
    last = dict(counts)
    while not stop.wait(1.0):
        now = dict(counts)
        print(f"\n-- t = {time.monotonic() - start:4.1f} s: {len(now)} live keys")
        for key in sorted(now):
            print(f"   {key:34} {now[key] - last.get(key, 0):4d} Hz   {latest.get(key, '')}")
        last = now
        if seconds is not None and time.monotonic() - start >= seconds:
            stop.set()
    thread.join(timeout=10)
    sub.undeclare()
    for session in (viewer, node, router):
        session.close()
    return 0
