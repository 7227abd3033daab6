"""A background thread with a stop event: what every emulated device runs on."""

from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)


class Loop:
    """A background thread with a stop event (``run`` is its work)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self.stop_event.clear()
        self._thread = threading.Thread(target=self._guarded, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _guarded(self) -> None:
        try:
            self.run()
        except Exception:
            log.exception("%s stopped", self.name)

    def run(self) -> None:
        raise NotImplementedError
