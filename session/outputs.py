"""Atomic outputs: a command's file appears whole, or not at all, and never
over one of its inputs.

Every file a command writes goes through :func:`atomic_path` (a writer that
takes a path: MCAP, C3D, Rerun) or :func:`atomic_file` (a writer that takes an
open file: CSV, BVH, Markdown). Both

- refuse an output that is one of the command's inputs (the same path, or the
  same file by another name: a link), a folder, a device, or an empty name;
- write to a temporary file in the output's folder and rename it over the
  output only when the writer has finished, so a failed or interrupted run
  leaves any earlier file of that name as it was and no half file;
- turn an error while writing (a full disk, a file too large) into
  :class:`OutputError`, whose message names the output, not the input.
"""

from __future__ import annotations

import contextlib
import os
import signal
import stat
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from bodynet.session.argtypes import same_file


class OutputError(OSError):
    """An output that may not or could not be written; the message names it."""


def check_output(output: Path, inputs: Iterable[Path | None] = ()) -> None:
    """``OutputError`` unless ``output`` may be written: not empty, not a folder
    or a device, and none of ``inputs``."""
    if not str(output) or str(output) == ".":
        raise OutputError("an empty output name")
    try:
        st = output.stat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise OutputError(f"cannot write {output}: {exc.strerror or exc}") from None
    if st is not None and stat.S_ISDIR(st.st_mode):
        raise OutputError(f"cannot write {output}: it is a folder")
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise OutputError(f"refusing to write {output}: it is not a regular file (a device?)")
    for source in inputs:
        if source is not None and same_file(output, source):
            what = "" if str(source) == str(output) else f" ({source}, by another name)"
            raise OutputError(f"refusing to write {output}: it is an input of this "
                              f"command{what}; choose another output")  # fmt: skip
    folder = output.parent
    if not folder.is_dir():
        raise OutputError(f"cannot write {output}: its folder {folder} does not exist")


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc)


@contextlib.contextmanager
def atomic_path(
    output: Path, inputs: Iterable[Path | None] = (), suffix: str = ".part"
) -> Iterator[Path]:
    """A temporary path beside ``output`` (a new file, the owner's only: this
    is health data) for a writer to fill; renamed over ``output`` when the
    block ends without error, removed otherwise.

    An ``OSError`` raised in the block about the temporary file, or by the
    final rename, becomes ``OutputError`` naming ``output``."""
    check_output(output, inputs)
    with _terminate_unwinds():
        yield from _atomic(output, suffix)


@contextlib.contextmanager
def _terminate_unwinds() -> Iterator[None]:
    """SIGTERM (a ``kill``, a service manager) ends the process through
    ``SystemExit`` while an output is being written, so that the temporary file
    is removed as on Ctrl-C (only where SIGTERM would otherwise kill at once)."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def terminate(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _atomic(output: Path, suffix: str) -> Iterator[Path]:
    try:
        fd, name = tempfile.mkstemp(prefix=f".{output.name}.", suffix=suffix, dir=output.parent)
    except OSError as exc:
        raise OutputError(f"cannot write {output}: {_why(exc)}") from None
    os.close(fd)
    tmp = Path(name)
    try:
        try:
            yield tmp
        except OSError as exc:
            if isinstance(exc, OutputError) or exc.filename not in (name, str(tmp), None):
                raise
            if exc.filename is None and exc.errno not in _WRITE_ERRNOS:
                raise
            raise OutputError(f"cannot write {output}: {_why(exc)}") from None
        try:
            with open(tmp, "rb+") as f:  # the data on disk before the name points to it
                os.fsync(f.fileno())
            os.replace(tmp, output)
        except OSError as exc:
            raise OutputError(f"cannot write {output}: {_why(exc)}") from None
    finally:
        tmp.unlink(missing_ok=True)


#: Errors that come from writing, whatever file the library names.
_WRITE_ERRNOS = {28, 27, 122, 30}  # ENOSPC, EFBIG, EDQUOT, EROFS


class _Guarded:
    """A file whose write errors are the output's (see :func:`atomic_file`)."""

    def __init__(self, f: IO[Any], output: Path) -> None:
        self._f = f
        self._output = output

    def _fail(self, exc: OSError) -> OutputError:
        return OutputError(f"cannot write {self._output}: {_why(exc)}")

    def write(self, data: Any) -> int:
        try:
            return self._f.write(data)
        except OSError as exc:
            raise self._fail(exc) from None

    def writelines(self, lines: Iterable[Any]) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        try:
            self._f.flush()
        except OSError as exc:
            raise self._fail(exc) from None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


@contextlib.contextmanager
def atomic_file(
    output: Path, inputs: Iterable[Path | None] = (), mode: str = "w", **open_args: Any
) -> Iterator[IO[Any]]:
    """An open file (``mode`` "w" or "wb") beside ``output``, renamed over it
    when the block ends without error (see :func:`atomic_path`). A write error
    (a full disk) raises ``OutputError`` naming ``output``."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_file writes, mode 'w' or 'wb', not {mode!r}")
    if mode == "w":
        open_args.setdefault("encoding", "utf-8")
    with atomic_path(output, inputs) as tmp:
        f = open(tmp, mode, **open_args)  # noqa: SIM115 (closed below, errors checked)
        guarded = _Guarded(f, output)
        try:
            yield guarded  # type: ignore[misc]
            guarded.flush()
        finally:
            try:
                f.close()
            except OSError as exc:
                raise guarded._fail(exc) from None
