"""The live gateway's heading searches, run aside from its worker.

While a body's tags' headings are searched (gateway/heading.py), a fit over a
window of samples costs from a few to a few hundred ms of CPU. Run in the
worker, it stalled every body's ticks as long. :class:`AsideFits` runs them in
a thread of their own; the search takes each result at the first tick after
it is done. The fits' time goes to numpy's large array operations, which
release the interpreter's lock: measured (docs/calibration.md), the other
bodies' poses stalled less with the fits in a thread than in a process of
their own, which competes for the machine's cores and must start first."""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import Any


class AsideFits:
    """The fits of every body's heading search (gateway/heading.py's ``Fits``), one
    at a time in a thread started at the first fit and ended with :meth:`close`."""

    def __init__(self, executor: Callable[[], Executor] | None = None) -> None:
        """``executor``: what makes the pool (the benchmark's: a process's)."""
        self._make = executor or (lambda: ThreadPoolExecutor(1, "heading-search"))
        self._pool: Executor | None = None
        self._lock = threading.Lock()

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Future[Any]:
        """``fn(*args)`` in the pool; its Future."""
        with self._lock:
            if self._pool is None:
                self._pool = self._make()
            return self._pool.submit(fn, *args)

    def close(self) -> None:
        """End the pool (a fit still running is left to end on its own)."""
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None
