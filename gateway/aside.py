"""The live gateway's heading searches, run aside from its worker.

While a body's tags' headings are searched (gateway/heading.py), a fit over a
window of samples costs from a few to a few hundred ms of CPU. Run in the
worker, it stalls every body's ticks as long. :class:`AsideFits` runs them in
a process of its own (a thread would share the interpreter's lock with the
worker: docs/heading.md gives the stalls measured); the search takes each
result at the first tick after it is done."""

from __future__ import annotations

import logging
import multiprocessing
import threading
from collections.abc import Callable
from concurrent.futures import BrokenExecutor, Executor, Future, ProcessPoolExecutor
from typing import Any

log = logging.getLogger(__name__)


def _ready() -> None:
    """Nothing: the process's first task, which imports the searches' modules."""
    import bodynet.gateway.heading  # noqa: F401


class AsideFits:
    """The fits of every body's heading search (gateway/heading.py's ``Fits``), in
    one process started at the first fit (spawned: the gateway's process holds
    Zenoh's threads, which a fork would copy mid-flight) and ended with
    :meth:`close`; a process that died is replaced at the next fit (the fits
    it had are lost, and asked for again by the next samples)."""

    def __init__(self, executor: Callable[[], Executor] | None = None) -> None:
        """``executor``: what makes the pool (tests: a thread's, to hold a fit)."""
        self._make = executor or self._process
        self._pool: Executor | None = None
        self._lock = threading.Lock()

    @staticmethod
    def _process() -> Executor:
        pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        pool.submit(_ready)  # its imports begin now, not in the first fit's time
        return pool

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future[Any]:
        """``fn(*args)`` in the pool; its Future."""
        with self._lock:
            if self._pool is None:
                self._pool = self._make()
            try:
                return self._pool.submit(fn, *args)
            except BrokenExecutor:  # its process died: a new one
                log.warning("gateway: the heading searches' process was lost; starting another")
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = self._make()
                return self._pool.submit(fn, *args)

    def close(self) -> None:
        """End the pool (a fit still running is left to end on its own)."""
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
