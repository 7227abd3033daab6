"""Keeping a device open: say once that it is gone, retry with backoff, resume;
and saying when a device sends bytes of which nothing decodes (a wrong baud rate)."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import stat
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, TypeVar

from bodynet.core.errors import RejectCounts

if TYPE_CHECKING:  # not at run time: can_transport's DeviceError is read offline, without Zenoh
    from bodynet.nodes.publisher import SitePublisher

log = logging.getLogger(__name__)

D = TypeVar("D")

#: first and longest wait between two tries of opening a device that is not there: an
#: absent device costs a failed open() every 0.5 s (said once), a replugged one is
#: found within 0.5 s of its return
BACKOFF_S = (0.1, 0.5)
#: bytes coming without anything decoded for this long are said on the console...
NO_DECODE_S = 2.0
#: ...again at most this often while it lasts
NO_DECODE_REPEAT_S = 30.0
#: what an open() of a port another program holds fails with: flock's EWOULDBLOCK
#: (pyserial's ``exclusive=True``), the kernel's EBUSY (a terminal made exclusive)
IN_USE_ERRNOS = frozenset({errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY})


class DeviceError(OSError):
    """A device that can never open as given (a CAN interface whose driver is not
    installed, a folder or a regular file given as a serial port): retrying would
    not help."""


def never_opens(exc: BaseException, path: str | None = None) -> str | None:
    """Why the error ``exc`` of opening a device will not go away by waiting, or
    None if it may (a device unplugged, busy or not up yet: retried).

    ``path``: the device's path if it has one (a serial port), to say what it
    is instead."""
    for seen, code in _causes(exc):
        if isinstance(seen, DeviceError):  # said by the opener (a CAN driver missing)
            return str(seen)
        if code == errno.EAFNOSUPPORT:
            return f"{seen.args[-1] if seen.args else seen} (this kernel has no SocketCAN?)"
        if code in (errno.EISDIR, errno.ENOTTY):
            return _not_a_port(path) or str(seen)
    return None


def in_use(exc: BaseException) -> bool:
    """Whether the error ``exc`` of opening a device says another program holds it."""
    return any(code in IN_USE_ERRNOS for _, code in _causes(exc))


def _causes(exc: BaseException) -> Iterator[tuple[BaseException, object]]:
    """``exc`` and what caused it, a few deep (python-can wraps pyserial's error,
    which wraps the OS's), each with its error number (or first argument)."""
    seen: BaseException | None = exc
    for _ in range(5):
        if seen is None:
            return
        yield seen, getattr(seen, "errno", None) or (seen.args[0] if seen.args else None)
        seen = seen.__cause__ or seen.__context__


def _not_a_port(path: str | None) -> str | None:
    """What ``path`` is, if it is something other than a serial port."""
    try:
        mode = os.stat(path).st_mode if path else None
    except OSError:
        return None
    if mode is None:
        return None
    what = ("a folder" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode)
            else "a device that is not a terminal")  # fmt: skip
    return f"{path} is not a serial port: it is {what}"


def keep_connected(
    publisher: SitePublisher,
    open_device: Callable[[], D],
    serve: Callable[[D], None],
    close: Callable[[D], None],
    errors: tuple[type[BaseException], ...],
    stop: threading.Event,
    backoff_s: tuple[float, float] = BACKOFF_S,
    path: str | None = None,
) -> None:
    """Open the device and ``serve`` it until ``stop``; on one of ``errors``
    report the loss once (log and health), then retry with exponential backoff.
    A failure to open of another kind than the one already said (the port back
    but held by another program) is said too, once. ``serve`` returns when
    ``stop`` is set. An error that waiting cannot mend (:func:`never_opens`;
    ``path`` is the device's, if it has one) raises :class:`DeviceError` instead."""
    name = publisher.name
    delay = backoff_s[0]
    said: set[str] = set()  # the kinds of failure said during this outage
    while not stop.is_set():
        try:
            device = open_device()
        except errors as exc:
            if why := never_opens(exc, path):
                raise DeviceError(f"cannot open the device: {why}") from None
            if (kind := _kind(exc)) not in said:
                if said != {_LOST}:  # the first failure after a loss is the loss's
                    log.warning("%s: device unavailable (%s); retrying until it is back",
                                name, exc)  # fmt: skip
                said.add(kind)
            publisher.set_device("disconnected")
            stop.wait(delay)
            delay = min(delay * 2, backoff_s[1])
            continue
        if said:
            log.warning("%s: device is back", name)
        else:
            log.info("%s: device connected", name)
        publisher.set_device("connected")
        delay, said = backoff_s[0], set()
        try:
            serve(device)
        except errors as exc:
            log.warning("%s: device lost (%s); retrying until it is back", name, exc)
            said = {_LOST}
            publisher.set_device("disconnected")
        finally:
            with contextlib.suppress(*errors):
                close(device)


_LOST = "lost"


def _kind(exc: BaseException) -> str:
    """What sort of failure ``exc`` is, to say each sort once: its type and errno."""
    return f"{type(exc).__name__}:{getattr(exc, 'errno', None)}"


class DecodeWatch:
    """Says on the console when a device sends bytes but nothing of them decodes
    for :data:`NO_DECODE_S` (a wrong baud rate, most often): a warning naming
    the device, what was rejected meanwhile and ``hint``, again every
    :data:`NO_DECODE_REPEAT_S` while it lasts, and a line when it decodes again.

    The bridge calls :meth:`received` with the size of each read and
    :meth:`decoded` for each thing decoded (a sample, a node's status: anything
    but a rejection), from the thread that reads."""

    def __init__(self, publisher: SitePublisher, device: str, hint: str) -> None:
        self.publisher = publisher
        self.device = device
        self.hint = hint
        self.after_s = NO_DECODE_S
        self.repeat_s = NO_DECODE_REPEAT_S
        self._since: float | None = None  # the first byte since anything decoded
        self._bytes = 0
        self._rejected_before = RejectCounts()
        self._warned_at: float | None = None

    def received(self, n: int) -> None:
        if n <= 0:
            return
        now = time.monotonic()
        if self._since is None:
            self._since, self._bytes = now, 0
            self._rejected_before = RejectCounts(self.publisher.rejected)
        self._bytes += n
        if now - self._since < self.after_s:
            return
        if self._warned_at is not None and now - self._warned_at < self.repeat_s:
            return
        self._warned_at = now
        rejected = RejectCounts(self.publisher.rejected - self._rejected_before)
        log.warning("%s: receiving bytes from %s but nothing valid for %.0f s (%d bytes; "
                    "rejected %s): %s", self.publisher.name, self.device, now - self._since,
                    self._bytes, rejected.summary() or "none", self.hint)  # fmt: skip

    def decoded(self) -> None:
        if self._since is None and self._warned_at is None:
            return
        if self._warned_at is not None:
            log.warning("%s: %s sends valid data again", self.publisher.name, self.device)
        self._since = self._warned_at = None

    def restart(self) -> None:
        """The device was opened again: its bytes are counted afresh (a warning
        given still waits for valid data to be called off)."""
        self._since = None
