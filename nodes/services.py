"""The long-running node services behind ``bodynet bridge``, ``emulate`` and ``node``.

Each function takes explicit arguments and runs until ``stop`` is set (the
command line sets it on Ctrl-C or SIGTERM).

- ``bridge_*``: real or emulated hardware -> Zenoh (one bridge per device).
- ``emulate_*``: emulated hardware only, on a pseudo-terminal or CAN bus, for
  a bridge in another process (or another machine) to open.
- ``run_node``: emulated hardware plus its bridge in one process, and the
  emulator's ground truth on ``body/<limb>/<side>/<site>/truth``.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import can
import zenoh

from bodynet.core.keys import Branch, Site, Stream
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES
from bodynet.nodes.can_bridge import CanBridge
from bodynet.nodes.concentrator_bridge import ConcentratorBridge
from bodynet.nodes.emulator import BodyEmulator, Realism, Truth, imu_tags, smartsuit_sensors
from bodynet.nodes.hardware import (
    CanNodes,
    Clock,
    ConcentratorEmulator,
    ImuCentralEmulator,
    SlcanAdapterEmulator,
    TruthSink,
)
from bodynet.nodes.imu_bridge import ImuCentralBridge
from bodynet.nodes.motion import ROUTINES, Routine

log = logging.getLogger(__name__)


def truth_sink(session: zenoh.Session, sites: Mapping[int, Site]) -> TruthSink:
    """Publishes an emulator's ground truth as JSON on each site's truth key."""
    publishers: dict[int, zenoh.Publisher] = {}

    def put(node: int, truth: Truth, t_ns: int) -> None:
        pub = publishers.get(node)
        if pub is None:
            pub = publishers[node] = session.declare_publisher(sites[node].key(Stream.TRUTH))
        pub.put(
            json.dumps(
                {
                    "t_ns": t_ns,
                    "segment": truth.segment,
                    "segment_quat_wxyz": truth.segment_quat_wxyz,
                    "angles_deg": truth.angles_deg,
                }
            ).encode()
        )

    return put


@dataclass(frozen=True)
class EmulationOptions:
    routine: str | Routine = "random"  # a name in ROUTINES, or a routine
    realism: Realism = field(default_factory=Realism)
    seed: int = 0


def _body(options: EmulationOptions, sensors: Sequence[Any]) -> BodyEmulator:
    routine = ROUTINES[options.routine] if isinstance(options.routine, str) else options.routine
    return BodyEmulator(routine, sensors, realism=options.realism, seed=options.seed)


def bridge_can(
    session: zenoh.Session,
    stop: threading.Event,
    name: str,
    replay: Path | None = None,
    loop: bool = False,
    **bus_args: Any,
) -> None:
    bridge = CanBridge(session, name)
    try:
        if replay is not None:
            bridge.run_replay(replay, stop, loop)
        else:
            bridge.run_bus(stop, **bus_args)
    finally:
        bridge.close()


def bridge_concentrator(
    session: zenoh.Session,
    stop: threading.Event,
    name: str,
    port: str,
    nodes: Sequence[int] = (1, 2, 3),
    baud: int = 115200,
) -> None:
    bridge = ConcentratorBridge(session, name, nodes)
    try:
        bridge.run(port, stop, baud)
    finally:
        bridge.close()


def bridge_imu_central(
    session: zenoh.Session, stop: threading.Event, name: str, port: str, baud: int = 230400
) -> None:
    bridge = ImuCentralBridge(session, name)
    try:
        bridge.run(port, stop, baud)
    finally:
        bridge.close()


def emulate(
    kind: str,
    stop: threading.Event,
    options: EmulationOptions,
    *,
    link: Path | None = None,
    branches: Sequence[Branch] | None = None,
    sensors: Sequence[int] | None = None,
    silent: Sequence[int] = (),
    bus_args: Mapping[str, Any] | None = None,
    truth_session: zenoh.Session | None = None,
) -> None:
    """Run one emulated device until ``stop``: ``slcan``, ``concentrator``,
    ``imu-central`` (on a pseudo-terminal behind ``link``) or ``can`` (on a bus).
    With ``truth_session``, the ground truth is published there too."""
    sites = IMU_SITES if kind == "imu-central" else SMARTSUIT_SITES
    sink = truth_sink(truth_session, sites) if truth_session is not None else None
    if kind == "can":
        with can.Bus(**dict(bus_args or {})) as bus:
            nodes = CanNodes(bus, _body(options, smartsuit_sensors(branches)), truth=sink)
            nodes.start()
            stop.wait()
            nodes.stop()
        return
    assert link is not None
    device: ConcentratorEmulator | ImuCentralEmulator | SlcanAdapterEmulator
    if kind == "slcan":
        device = SlcanAdapterEmulator(link, _body(options, smartsuit_sensors(branches)), truth=sink)
    elif kind == "concentrator":
        body = _body(options, smartsuit_sensors(branches))
        device = ConcentratorEmulator(link, body, truth=sink, silent=silent)
    else:
        device = ImuCentralEmulator(link, _body(options, imu_tags(sensors, branches)), truth=sink)
    device.start()
    print(f"emulated {kind} on {device.link} -> {device.link.resolve()}", flush=True)
    stop.wait()
    device.stop()


@dataclass(frozen=True)
class NodePlan:
    """What ``bodynet node`` runs: which sensors, over which transport."""

    system: str  # "smartsuit" or "imu"
    via: str  # smartsuit: "can", "slcan", "concentrator"; imu: "imu-central"
    branches: tuple[Branch, ...] | None = None
    sensors: tuple[int, ...] | None = None


def body_plan() -> list[NodePlan]:
    """The demo body: SmartSuit arms (left over CAN, right through the Data
    Concentrator) and IMU tags for the trunk and legs."""
    from bodynet.core.keys import LEFT_ARM, RIGHT_ARM

    trunk_and_legs = tuple(n for n, s in IMU_SITES.items() if s.branch not in (LEFT_ARM, RIGHT_ARM))
    return [
        NodePlan("smartsuit", "can", (LEFT_ARM,)),
        NodePlan("smartsuit", "concentrator", (RIGHT_ARM,)),
        NodePlan("imu", "imu-central", sensors=trunk_and_legs),
    ]


def run_node(
    session: zenoh.Session,
    stop: threading.Event,
    plans: Sequence[NodePlan],
    options: EmulationOptions,
    name: str = "node",
) -> None:
    """Emulated hardware and its bridge for each plan, with ground truth, until ``stop``."""
    clock = Clock()
    threads: list[threading.Thread] = []
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(TemporaryDirectory(prefix="bodynet-")))
        for i, plan in enumerate(plans):
            label = f"{name}-{plan.via}-{i}"
            if plan.system == "imu":
                sensors = imu_tags(plan.sensors, plan.branches)
                sink = truth_sink(session, IMU_SITES)
            else:
                sensors = smartsuit_sensors(plan.branches)
                sink = truth_sink(session, SMARTSUIT_SITES)
            body = _body(options, sensors)
            target: Any
            if plan.via == "can":
                channel = f"bodynet-{label}-{time.monotonic_ns()}"
                bus = stack.enter_context(can.Bus(interface="virtual", channel=channel))
                emulator: Any = CanNodes(bus, body, clock, sink)
                target, kwargs = bridge_can, {"interface": "virtual", "channel": channel}
            elif plan.via == "slcan":
                emulator = SlcanAdapterEmulator(tmp / label, body, clock, sink)
                target = bridge_can
                kwargs = {"interface": "slcan", "channel": str(tmp / label), "sleep_after_open": 0}
            elif plan.via == "concentrator":
                emulator = ConcentratorEmulator(tmp / label, body, clock, sink)
                nodes = tuple(s.node for s in sensors)
                target, kwargs = bridge_concentrator, {"port": str(tmp / label), "nodes": nodes}
            else:
                emulator = ImuCentralEmulator(tmp / label, body, clock, sink)
                target, kwargs = bridge_imu_central, {"port": str(tmp / label)}
            emulator.start()
            stack.callback(emulator.stop)
            thread = threading.Thread(
                target=target, args=(session, stop, label), kwargs=kwargs, name=label, daemon=True
            )
            thread.start()
            threads.append(thread)
            log.info(
                "%s: %d emulated %s sensors via %s", label, len(sensors), plan.system, plan.via
            )
        stop.wait()
        for thread in threads:
            thread.join(timeout=5)
