"""Atomic outputs: a command's file appears whole, or not at all, and never
over one of its inputs.

Every file a command writes goes through :func:`atomic_path` (a writer that
takes a path: MCAP, C3D, Rerun) or :func:`atomic_file` (a writer that takes an
open file: CSV, BVH, Markdown). Both

- refuse an output that is one of the command's inputs (the same path, or the
  same file by another name: a link), a folder, a device, or an empty name;
- write to a new file in the output's folder that has no name until the
  writer has finished (Linux's ``O_TMPFILE``), then link it over the output,
  so a failed or interrupted run, even one killed by SIGKILL, leaves any
  earlier file of that name as it was and no half file; where a file must
  have a name while it is written, a later run removes the one a killed run
  left (:func:`remove_stale`);
- turn an error while writing (a full disk, a file too large) into
  :class:`OutputError`, whose message names the output, not the input.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
import signal
import stat
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from bodynet.session.argtypes import same_file


class OutputError(OSError):
    """An output that may not or could not be written; the message names it."""


def check_output(output: Path, inputs: Iterable[Path | None] = ()) -> None:
    """``OutputError`` unless ``output`` may be written: not empty, not a folder,
    a device or a read-only file (even for root), and none of ``inputs``."""
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
    if st is not None and (not os.access(output, os.W_OK) or not st.st_mode & 0o222):
        raise OutputError(f"cannot write {output}: it is read-only")
    folder = output.parent
    if not folder.is_dir():
        raise OutputError(f"cannot write {output}: its folder {folder} does not exist")


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc)


@contextlib.contextmanager
def atomic_path(
    output: Path,
    inputs: Iterable[Path | None] = (),
    suffix: str = ".part",
    named: bool = False,
) -> Iterator[Path]:
    """A temporary path beside ``output`` (a new file, the owner's only: this
    is health data) for a writer to fill; it becomes ``output`` when the block
    ends without error, and is removed otherwise.

    The file has no name while it is written (``/proc/self/fd/N`` of an
    ``O_TMPFILE`` file): a run killed even by SIGKILL leaves nothing. A writer
    that must name its file (with ``suffix``: ezc3d adds ".c3d" to any other
    name) gets ``named``: ``.<output name>.<pid>.<random><suffix>``, which a
    later run writing the same output removes once its process is gone.

    An ``OSError`` raised in the block about the temporary file, or by the
    final rename, becomes ``OutputError`` naming ``output``."""
    check_output(output, inputs)
    with terminate_unwinds():
        yield from _atomic(output, suffix, named)


class Interrupted(SystemExit):
    """A SIGTERM while an output is written (or an offline command runs): the
    process ends as on Ctrl-C, unwinding, so nothing half-written is left;
    ``code`` is 128 + the signal's number, as a shell reports a killed process."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum


@contextlib.contextmanager
def terminate_unwinds() -> Iterator[None]:
    """SIGTERM (a ``kill``, a service manager) raises :class:`Interrupted` in
    the block, so that temporary files are removed as on Ctrl-C (only where
    SIGTERM would otherwise kill at once, in the main thread)."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def terminate(signum: int, _frame: object) -> None:
        raise Interrupted(signum)

    signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _atomic(output: Path, suffix: str, named: bool) -> Iterator[Path]:
    pending = PendingOutput(output, suffix, named)
    try:
        try:
            yield pending.path
        except OSError as exc:
            if isinstance(exc, OutputError) or not pending.is_about(exc):
                raise
            raise OutputError(f"cannot write {output}: {_why(exc)}") from None
        pending.commit()
    finally:
        pending.discard()


class PendingOutput:
    """An output being written: ``path``, a new file the owner's only (health
    data), becomes ``output`` on :meth:`commit`; :meth:`discard` (always call
    it) removes it if it was not committed. For a writer whose file stays open
    across calls (a viewer's ``.rrd``); see :func:`atomic_path`."""

    def __init__(self, output: Path, suffix: str = ".part", named: bool = False) -> None:
        remove_stale(output)
        self.output = output
        self._fd = None if named else _anonymous(output)
        if self._fd is not None:
            self.path = Path(f"/proc/self/fd/{self._fd}")
            return
        try:
            fd, name = tempfile.mkstemp(prefix=_stale_prefix(output) + f"{os.getpid()}.",
                                        suffix=suffix, dir=output.parent)  # fmt: skip
        except OSError as exc:
            raise OutputError(f"cannot write {output}: {_why(exc)}") from None
        os.close(fd)
        self.path = Path(name)

    def is_about(self, exc: OSError) -> bool:
        """Is ``exc`` an error of writing this output (not of reading an input)?"""
        if exc.filename is None:
            return exc.errno in _WRITE_ERRNOS
        return str(exc.filename) == str(self.path)

    def commit(self) -> None:
        """The file becomes the output (its data on disk first); ``OutputError``
        naming the output if it cannot."""
        try:
            if self._fd is not None:  # nameless until now: linked under the output's name
                os.fsync(self._fd)
                _link(self._fd, self.output)
            else:
                with open(self.path, "rb+") as f:
                    os.fsync(f.fileno())
                os.replace(self.path, self.output)
        except OSError as exc:
            raise OutputError(f"cannot write {self.output}: {_why(exc)}") from None

    def discard(self) -> None:
        """Remove the file if it was not committed; release it."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        else:
            self.path.unlink(missing_ok=True)


def _anonymous(output: Path) -> int | None:
    """A new file with no name in the output's folder (Linux's ``O_TMPFILE``):
    a process killed while it is written leaves nothing behind. ``None`` where
    the system or its file system has none (then a named temporary file)."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None or not os.path.isdir("/proc/self/fd"):
        return None
    try:
        return os.open(output.parent, flag | os.O_RDWR, 0o600)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT):
            return None  # a file system without it (or a kernel before 3.11)
        raise OutputError(f"cannot write {output}: {_why(exc)}") from None


def _link(fd: int, output: Path) -> None:
    """Give the nameless file ``fd`` the name ``output`` (over any file of that
    name: the old file stays whole until the new one replaces it)."""
    src = f"/proc/self/fd/{fd}"
    folder = os.open(output.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        # with a folder's descriptor Python calls linkat(AT_SYMLINK_FOLLOW), which
        # follows the /proc link to the file (a plain link() would not)
        def link(name: str) -> None:
            os.link(src, name, src_dir_fd=folder, dst_dir_fd=folder, follow_symlinks=True)

        try:
            link(output.name)  # no file of that name: done
            return
        except FileExistsError:
            pass
        tmp = f"{_stale_prefix(output)}{os.getpid()}.{secrets.token_hex(4)}.part"
        link(tmp)
        try:
            os.replace(tmp, output.name, src_dir_fd=folder, dst_dir_fd=folder)
        except BaseException:
            os.unlink(tmp, dir_fd=folder)
            raise
    finally:
        os.close(folder)


def _stale_prefix(output: Path) -> str:
    """The start of the name of a temporary file of ``output``, before the
    writing process's id: ``.rec.c3d.<pid>.``."""
    return f".{output.name}."


def remove_stale(output: Path) -> list[Path]:
    """Remove the temporary files of ``output`` (``.<name>.<pid>.*.part*``)
    that a killed run left in its folder (their process is gone), saying so on
    stderr; returns them."""
    prefix = _stale_prefix(output)
    removed = []
    try:
        names = [n for n in os.listdir(output.parent) if n.startswith(prefix) and ".part" in n]
    except OSError:
        return []
    for name in names:
        pid_text = name[len(prefix) :].split(".", 1)[0]
        if not pid_text.isdigit() or _alive(int(pid_text)):
            continue
        stale = output.parent / name
        try:
            if stale.is_dir() and not stale.is_symlink():  # a scratch folder
                shutil.rmtree(stale)
            else:
                stale.unlink()
        except OSError:
            continue
        removed.append(stale)
        print(f"bodynet: removed {stale}, a temporary file of {output.name} left by an "
              f"interrupted run (process {pid_text})", file=sys.stderr)  # fmt: skip
    return removed


def scratch_folder(output: Path) -> Path:
    """A new folder beside ``output`` (the owner's only) for a writer that makes
    several files before they go into place; named as temporary files are
    (``.<name>.<pid>.*.part``), so a later run removes one a killed run left.
    The caller removes it when done."""
    remove_stale(output)
    try:
        return Path(tempfile.mkdtemp(prefix=f"{_stale_prefix(output)}{os.getpid()}.",
                                     suffix=".part", dir=output.parent))  # fmt: skip
    except OSError as exc:
        raise OutputError(f"cannot write {output}: {_why(exc)}") from None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


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
