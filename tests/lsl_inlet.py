"""An LSL recorder in another process, for the tests of ``bodynet lsl``: it
resolves streams by ``source_id``, opens inlets with recovery (as LabRecorder
does) and sends back each stream's description and every sample it pulls."""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: liblsl on loopback only: discovery by broadcast on this machine, the one
#: known peer this machine, no IPv6; errors only in the log.
LSL_CONFIG = """[ports]
IPv6 = disable
[multicast]
ResolveScope = machine
KnownPeers = {127.0.0.1}
[log]
level = -3
"""


def loopback_lsl(tmp: Path) -> None:
    """Point liblsl (of this process and of children started after) at the
    loopback configuration; before the first outlet or inlet is made."""
    cfg = tmp / "lsl_api.cfg"
    cfg.write_text(LSL_CONFIG)
    os.environ["LSLAPICFG"] = str(cfg)


def _channels(info: Any) -> list[dict[str, str]]:
    out = []
    ch = info.desc().child("channels").child("channel")
    while not ch.empty():
        out.append({k: ch.child_value(k) for k in ("label", "type", "unit", "object")})
        ch = ch.next_sibling()
    return out


def recorder(source_ids: Sequence[str], out: Any, ready: Any, stop: Any) -> None:
    """Pull every stream of ``source_ids`` until ``stop`` is set and nothing comes
    for 0.5 s. Puts ``("info", sid, dict)`` once per stream, then
    ``("data", sid, samples, timestamps, time_correction)`` per chunk."""
    import pylsl

    found: dict[str, Any] = {}
    for sid in source_ids:  # by source id, as LabRecorder finds a stream again
        infos = pylsl.resolve_byprop("source_id", sid, timeout=30)
        if not infos:
            out.put(("error", sid, "not resolved"))
            ready.set()
            return
        found[sid] = infos[0]
    inlets = {}
    for sid in source_ids:
        inlet = pylsl.StreamInlet(found[sid], max_buflen=60, recover=True)
        inlet.open_stream(timeout=30)
        info = inlet.info(timeout=30)
        out.put(("info", sid, {"name": info.name(), "type": info.type(),
                               "source_id": info.source_id(), "channels": _channels(info),
                               "uid": info.uid()}))  # fmt: skip
        inlets[sid] = inlet
    ready.set()
    quiet_since: float | None = None
    while True:
        got = False
        for sid, inlet in inlets.items():
            samples, stamps = inlet.pull_chunk(timeout=0.05)
            if stamps:
                got = True
                out.put(("data", sid, samples, stamps, inlet.time_correction(timeout=5)))
        if got:
            quiet_since = None
        elif stop.is_set():
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since > 0.5:
                break
    for inlet in inlets.values():
        inlet.close_stream()
    out.put(("done", "", None))


class Recorder:
    """:func:`recorder` in a spawned process, its messages gathered here."""

    def __init__(self, source_ids: Sequence[str]) -> None:
        ctx = mp.get_context("spawn")
        self.queue: Any = ctx.Queue()
        self.ready = ctx.Event()
        self.stop_event = ctx.Event()
        args = (list(source_ids), self.queue, self.ready, self.stop_event)
        self.proc = ctx.Process(target=recorder, daemon=True, args=args)
        self.proc.start()
        self.info: dict[str, dict[str, Any]] = {}
        self.samples: dict[str, list[tuple[list[float], float]]] = {s: [] for s in source_ids}
        self.done = False

    def wait_ready(self, timeout: float = 60.0) -> None:
        assert self.ready.wait(timeout), "the LSL recorder never connected"
        deadline = time.monotonic() + 10
        while len(self.info) < len(self.samples) and time.monotonic() < deadline:
            self.pump(0.2)  # the infos were put before ready was set
        assert len(self.info) == len(self.samples), f"resolved only {sorted(self.info)}"

    def pump(self, timeout: float) -> None:
        """Take what the process sent, waiting up to ``timeout`` for the first."""
        import queue as q

        block = timeout > 0
        while True:
            try:
                msg = self.queue.get(timeout=timeout) if block else self.queue.get_nowait()
            except q.Empty:
                return
            block = False
            if msg[0] == "info":
                self.info[msg[1]] = msg[2]
            elif msg[0] == "data":
                _, sid, samples, stamps, correction = msg
                self.samples[sid].extend(zip(samples, [t + correction for t in stamps],
                                             strict=True))  # fmt: skip
            elif msg[0] == "done":
                self.done = True
            else:
                raise AssertionError(f"LSL recorder: {msg}")

    def wait_for(self, sid: str, n: int, timeout: float = 30.0) -> None:
        """Until stream ``sid`` has at least ``n`` samples."""
        deadline = time.monotonic() + timeout
        while len(self.samples[sid]) < n:
            left = deadline - time.monotonic()
            assert left > 0, f"{sid}: {len(self.samples[sid])} samples of {n}"
            self.pump(min(left, 0.5))

    def wait_since(self, sid: str, since: float, n: int, timeout: float = 30.0) -> None:
        """Until stream ``sid`` has ``n`` samples stamped after ``since`` (LSL's
        clock): sent after that moment, whatever was still on its way here then."""
        deadline = time.monotonic() + timeout
        while (got := sum(t > since for _, t in self.samples[sid])) < n:
            left = deadline - time.monotonic()
            assert left > 0, f"{sid}: {got} samples of {n} since {since:.3f}"
            self.pump(min(left, 0.5))

    def finish(self, timeout: float = 30.0) -> None:
        """Stop once the streams are drained; gather everything."""
        self.stop_event.set()
        deadline = time.monotonic() + timeout
        while not self.done and time.monotonic() < deadline:
            self.pump(0.5)
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.kill()
        assert self.done, "the LSL recorder did not finish"
