"""Loopback Zenoh for tests: a router on a free port, clients, collectors, and
services running in threads."""

from __future__ import annotations

import contextlib
import json
import queue
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from bodynet.core.codecs import raw_sample
from bodynet.session import open_session, session_config


def wait_until(done: Callable[[], bool], timeout: float = 10.0, what: str = "") -> None:
    """Poll ``done`` until it holds; fail naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def wait_matching(session: zenoh.Session, key: str, timeout: float = 10.0) -> None:
    """Wait until a subscriber for ``key`` is known to ``session`` (its
    declaration has reached the router): a put then reaches it."""
    publisher = session.declare_publisher(key)
    try:
        wait_until(lambda: publisher.matching_status.matching, timeout, f"a subscriber of {key}")
    finally:
        publisher.undeclare()


class Running:
    """``service(stop)`` in a thread, ``stop`` a :class:`threading.Event`, as every
    bodynet service takes it; :meth:`stop` sets it and waits for the service to end."""

    def __init__(self, service: Callable[[threading.Event], object], timeout: float = 15.0) -> None:
        self.stop_event = threading.Event()
        self.timeout = timeout
        self.thread = threading.Thread(target=service, args=(self.stop_event,), daemon=True)
        self.thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(timeout=self.timeout)
        assert not self.thread.is_alive(), "the service did not stop"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def client(endpoint: str) -> zenoh.Session:
    return open_session(session_config("client", connect=[endpoint]))


class Collector:
    """Everything a subscription receives, decoded, in a queue to wait on."""

    def __init__(self, session: zenoh.Session, key: str, decode: Callable[[bytes], Any]) -> None:
        self.queue: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.seen: list[tuple[str, Any]] = []
        self._sub = session.declare_subscriber(
            key, lambda s: self.queue.put((str(s.key_expr), decode(s.payload.to_bytes())))
        )

    def wait_for(
        self, done: Callable[[list[tuple[str, Any]]], bool], timeout: float = 10.0
    ) -> list[tuple[str, Any]]:
        """Collect until ``done(seen)`` holds; fail after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while not done(self.seen):
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(
                    f"timed out; got {len(self.seen)}: {str(self.seen[-2:])[:600]}"
                )
            with contextlib.suppress(queue.Empty):
                self.seen.append(self.queue.get(timeout=left))
        return self.seen

    def drained(self) -> list[tuple[str, Any]]:
        """Everything received so far, without waiting."""
        while True:
            try:
                self.seen.append(self.queue.get_nowait())
            except queue.Empty:
                return self.seen

    def close(self) -> None:
        self._sub.undeclare()


def raw_collector(session: zenoh.Session, key: str = "body/**") -> Collector:
    return Collector(session, key, raw_sample.decode)


def health_collector(session: zenoh.Session) -> Collector:
    return Collector(session, "body/@health/**", json.loads)


class Liveliness:
    """Liveliness events (key, alive) of tokens under ``key``."""

    def __init__(self, session: zenoh.Session, key: str = "body/**") -> None:
        self.events: queue.Queue[tuple[str, bool]] = queue.Queue()
        self.alive: set[str] = set()
        self._sub = session.liveliness().declare_subscriber(
            key,
            lambda s: self.events.put((str(s.key_expr), s.kind == zenoh.SampleKind.PUT)),
            history=True,
        )

    def wait_for(self, done: Callable[[set[str]], bool], timeout: float = 10.0) -> set[str]:
        deadline = time.monotonic() + timeout
        while not done(self.alive):
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"timed out; alive: {sorted(self.alive)}")
            try:
                key, alive = self.events.get(timeout=left)
            except queue.Empty:
                continue
            (self.alive.add if alive else self.alive.discard)(key)
        return self.alive

    def close(self) -> None:
        self._sub.undeclare()
