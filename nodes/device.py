"""Keeping a device open: say once that it is gone, retry with backoff, resume."""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from typing import TypeVar

from bodynet.nodes.publisher import SitePublisher

log = logging.getLogger(__name__)

D = TypeVar("D")

BACKOFF_S = (0.1, 2.0)


def keep_connected(
    publisher: SitePublisher,
    open_device: Callable[[], D],
    serve: Callable[[D], None],
    close: Callable[[D], None],
    errors: tuple[type[BaseException], ...],
    stop: threading.Event,
    backoff_s: tuple[float, float] = BACKOFF_S,
) -> None:
    """Open the device and ``serve`` it until ``stop``; on one of ``errors``
    report the loss once (log and health), then retry with exponential backoff.
    ``serve`` returns when ``stop`` is set."""
    name = publisher.name
    delay, reported = backoff_s[0], False
    while not stop.is_set():
        try:
            device = open_device()
        except errors as exc:
            if not reported:
                log.warning("%s: device unavailable (%s); retrying until it is back", name, exc)
                reported = True
            publisher.set_device("disconnected")
            stop.wait(delay)
            delay = min(delay * 2, backoff_s[1])
            continue
        if reported:
            log.warning("%s: device is back", name)
        else:
            log.info("%s: device connected", name)
        publisher.set_device("connected")
        delay, reported = backoff_s[0], False
        try:
            serve(device)
        except errors as exc:
            log.warning("%s: device lost (%s); retrying until it is back", name, exc)
            reported = True
            publisher.set_device("disconnected")
        finally:
            with contextlib.suppress(*errors):
                close(device)
