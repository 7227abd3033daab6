"""bodynet services as real processes for the deployment tests: start one, wait
for a line it prints (stamped with the wall time it was read), stop it."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

BODYNET = Path(sys.executable).with_name("bodynet")


class Service:
    """One process; its stdout and stderr lines go to a queue as (wall ns, line)."""

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        env: Mapping[str, str] | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.name = name
        self.argv = list(argv)
        self.lines: queue.Queue[tuple[int, str]] = queue.Queue()
        self.output: list[str] = []
        self.proc = subprocess.Popen(
            self.argv,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, **(env or {})},
            cwd=cwd,
        )
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"read-{name}")
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line.rstrip())
            self.lines.put((time.time_ns(), line.rstrip()))

    def wait_line(self, text: str, timeout: float = 30.0) -> int:
        """The wall time (ns) at which a line containing ``text`` was read."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                t_ns, line = self.lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                if self.proc.poll() is not None and self.lines.empty():
                    break
                continue
            if text in line:
                return t_ns
        raise AssertionError(f"{self.name} never printed {text!r}; output:\n{self.tail()}")

    def tail(self, n: int = 30) -> str:
        return "\n".join(self.output[-n:])

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Signal the process and wait for it; killed if it does not end in time."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait(timeout=10)
        self._reader.join(timeout=5)
        return code

    def kill(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            self.proc.kill()
        self.proc.wait(timeout=10)


class Services:
    """Services started by a test, killed at teardown whatever happened."""

    def __init__(self) -> None:
        self.all: list[Service] = []

    def start(self, name: str, argv: Sequence[str], **kw: object) -> Service:
        service = Service(name, argv, **kw)  # type: ignore[arg-type]
        self.all.append(service)
        return service

    def close(self) -> None:
        for service in reversed(self.all):
            if service.proc.poll() is None:
                service.kill()


def bodynet(*args: str) -> list[str]:
    return [str(BODYNET), *args]


def ended(proc: subprocess.Popen[str], timeout_s: float) -> tuple[int, str]:
    """The exit code and stderr of ``proc``, read while it ends (a pipe nobody
    reads would hold a chatty process at its next write). Not ended within
    ``timeout_s``: what it had said, and where each of its threads was
    (``PYTHONFAULTHANDLER``'s dump on SIGABRT)."""
    try:
        _, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        try:
            said = proc.communicate(timeout=10)[1]
        except subprocess.TimeoutExpired:
            proc.kill()
            said = proc.communicate()[1]
        raise AssertionError(f"not ended {timeout_s:g} s after SIGTERM; it said: {said}") from None
    return proc.returncode, err
