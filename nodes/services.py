"""The long-running node services behind ``bodynet bridge``, ``emulate`` and ``node``.

Each function takes explicit arguments and runs until ``stop`` is set (the
command line sets it on Ctrl-C or SIGTERM).

- ``bridge``: real or emulated hardware -> Zenoh, any registered source
  (``nodes.sources``), one bridge per device.
- ``emulate``: emulated hardware only, on a pseudo-terminal, CAN bus or UDP,
  for a bridge in another process (or another machine) to open.
- ``run_node``: emulated hardware plus its bridge in one process, and the
  emulator's ground truth on ``body/<limb>/<side>/<site>/truth``.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import zenoh

from bodynet.core.keys import Branch, Site, Stream
from bodynet.core.profile import IMU_SITES
from bodynet.nodes import sources
from bodynet.nodes.emulator import BodyEmulator, Realism, Truth
from bodynet.nodes.hardware import Clock, TruthSink
from bodynet.nodes.motion import ROUTINES, Routine
from bodynet.nodes.timing import LinkTiming

log = logging.getLogger(__name__)


def bridge(session: zenoh.Session, stop: threading.Event, source_name: str, name: str,
           args: argparse.Namespace) -> None:  # fmt: skip
    """Run the bridge of the registered source ``source_name`` until ``stop``."""
    sources.get(source_name)().bridge(session, stop, name, args)


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
    """What emulated hardware does: its body's motion, how its sensors fall short
    of ideal ones (``realism``) and how its link's timing does (``timing``: by
    default an ideal link, lock-step and lossless; ``bodynet emulate`` and
    ``node`` default to ``LinkTiming.realistic()``)."""

    routine: str | Routine = "random"  # a name in ROUTINES, or a routine
    realism: Realism = field(default_factory=Realism)
    seed: int = 0
    timing: LinkTiming = field(default_factory=LinkTiming)


def _body(options: EmulationOptions, sensors: Sequence[Any]) -> BodyEmulator:
    routine = ROUTINES[options.routine] if isinstance(options.routine, str) else options.routine
    return BodyEmulator(routine, sensors, realism=options.realism, seed=options.seed)


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
    **device_args: Any,
) -> None:
    """Run one emulated device until ``stop``: any device a registered source
    offers (``slcan``, ``concentrator``, ``imu-central`` on a pseudo-terminal
    behind ``link``, ``can`` on a bus...). With ``truth_session``, the ground
    truth is published there too."""
    source = sources.by_device(kind)()
    emulated = source.emulated_sensors(sensors, branches)
    sites = {s.node: s.site for s in emulated}
    sink = truth_sink(truth_session, sites) if truth_session is not None else None
    body = _body(options, emulated)
    opts = {"link": link, "silent": silent, "bus_args": bus_args, **device_args,
            "timing": options.timing}  # fmt: skip
    device = source.emulator(kind, body, sink, opts)
    device.start()
    where = device.link
    if isinstance(where, Path):
        print(f"emulated {kind} on {where} -> {where.resolve()}", flush=True)
    else:
        print(f"emulated {kind} on {where}", flush=True)
    stop.wait()
    device.stop()


@dataclass(frozen=True)
class NodePlan:
    """What ``bodynet node`` runs: which sensors, over which emulated device."""

    system: str  # "smartsuit", "imu"...: what the sensors are (for the log)
    via: str  # an emulated device of a registered source: "can", "slcan", "imu-central"...
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
    batch_s: float = 0.0,
) -> None:
    """Emulated hardware and its bridge for each plan, with ground truth, until
    ``stop``; the bridges' samples in batches of ``batch_s`` at most if not 0."""
    clock = Clock()
    threads: list[threading.Thread] = []
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(TemporaryDirectory(prefix="bodynet-")))
        for i, plan in enumerate(plans):
            label = f"{name}-{plan.via}-{i}"
            source = sources.by_device(plan.via)()
            sensors = source.emulated_sensors(plan.sensors, plan.branches)
            body = _body(options, sensors)
            truth = truth_sink(session, {s.node: s.site for s in sensors})
            emulator, target, kwargs = source.node(
                plan.via, body, tmp, clock, truth, sensors, label, timing=options.timing
            )
            emulator.start()
            stack.callback(emulator.stop)
            thread = threading.Thread(target=target, args=(session, stop, label),
                                      kwargs={**kwargs, "batch_s": batch_s}, name=label,
                                      daemon=True)  # fmt: skip
            thread.start()
            threads.append(thread)
            log.info(
                "%s: %d emulated %s sensors via %s", label, len(sensors), plan.system, plan.via
            )
        stop.wait()
        for thread in threads:
            thread.join(timeout=5)
