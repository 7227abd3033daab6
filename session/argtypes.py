"""Checked argument types: every command-line value is checked where it enters.

Each type is a callable for argparse's ``type=``: it takes the text the user
typed and returns the value, or raises ``argparse.ArgumentTypeError`` with one
line saying what is wrong (argparse prefixes it with the option's name and
exits 2). Numbers are finite and within what they mean, with the reason in the
message; paths are checked as far as can be without side effects (an input
exists and is a readable file; an output's folder exists and is writable, and
the output is not a folder or a device).

What can only be checked across options (an output that is one of the
inputs) is ``same_file``'s job, called by ``bodynet.session.outputs``.

This module is pure apart from ``os``/``pathlib`` look-ups: no Zenoh, no
python-can, so ``--help`` and argument errors stay fast.

Use::

    p.add_argument("--rate-hz", type=argtypes.RATE_HZ)
    p.add_argument("--seconds", type=argtypes.positive_float(86400, "a day at most"))
    p.add_argument("capture", type=argtypes.input_file)
    p.add_argument("-o", "--output", type=argtypes.output_file)
"""

from __future__ import annotations

import argparse
import errno
import ipaddress
import math
import os
import re
import stat
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

__all__ = [
    "DURATION_S",
    "RATE_HZ",
    "bounded_float",
    "bounded_int",
    "endpoint",
    "existing_dir",
    "free_text",
    "hostname",
    "input_file",
    "input_or_new_file",
    "key_expr",
    "link_path",
    "name_chunk",
    "non_negative_float",
    "number_list",
    "output_dir",
    "output_file",
    "output_file_new_folder",
    "port",
    "port_or_zero",
    "positive_float",
    "positive_int",
    "same_file",
    "time_window",
    "url",
]


def fail(message: str) -> NoReturn:
    """Refuse a value: argparse shows ``argument --opt: <message>`` and exits 2."""
    raise argparse.ArgumentTypeError(message)


def _shown(text: str, limit: int = 400) -> str:
    """``text`` quoted for a message: escapes control and undecodable characters."""
    shown = repr(text)
    return shown if len(shown) <= limit else shown[: limit - 4] + "...'"


# -- numbers -----------------------------------------------------------------


def _float(text: str) -> float:
    try:
        value = float(text.strip())
    except ValueError:
        fail(f"{_shown(text)} is not a number")
    if not math.isfinite(value):
        fail(f"{_shown(text)} is not a finite number")
    return value


def _int(text: str) -> int:
    try:
        return int(text.strip())
    except ValueError:  # also the over-long ones (int's digit limit)
        fail(f"{_shown(text)} is not a whole number")


def bounded_float(
    lo: float, hi: float, why: str = "", *, lo_open: bool = False, hi_open: bool = False
) -> Callable[[str], float]:
    """A finite number in ``[lo, hi]`` (``lo_open``/``hi_open``: the bound itself
    excluded); ``why`` is said when the value is out of range."""
    left, right = "(" if lo_open else "[", ")" if hi_open else "]"
    because = f" ({why})" if why else ""

    def parse(text: str) -> float:
        value = _float(text)
        below = value <= lo if lo_open else value < lo
        above = value >= hi if hi_open else value > hi
        if below or above:
            fail(f"{_shown(text)} is outside {left}{lo:g}, {hi:g}{right}{because}")
        return value

    parse.__name__ = f"number in {left}{lo:g}, {hi:g}{right}"
    return parse


def positive_float(hi: float, why: str = "") -> Callable[[str], float]:
    """A finite number above 0 and at most ``hi``."""
    check = bounded_float(0.0, hi, why, lo_open=True)

    def parse(text: str) -> float:
        value = _float(text)
        if value <= 0:
            fail(f"{_shown(text)} must be above 0")
        return check(text)

    parse.__name__ = "positive number"
    return parse


def non_negative_float(hi: float, why: str = "") -> Callable[[str], float]:
    """A finite number from 0 to ``hi``."""
    check = bounded_float(0.0, hi, why)

    def parse(text: str) -> float:
        value = _float(text)
        if value < 0:
            fail(f"{_shown(text)} must not be negative")
        return check(text)

    parse.__name__ = "non-negative number"
    return parse


def bounded_int(lo: int, hi: int, why: str = "") -> Callable[[str], int]:
    """A whole number from ``lo`` to ``hi``."""
    because = f" ({why})" if why else ""

    def parse(text: str) -> int:
        value = _int(text)
        if not lo <= value <= hi:
            fail(f"{_shown(text)} is outside {lo}..{hi}{because}")
        return value

    parse.__name__ = f"whole number in {lo}..{hi}"
    return parse


def positive_int(hi: int, why: str = "") -> Callable[[str], int]:
    """A whole number from 1 to ``hi``."""
    return bounded_int(1, hi, why)


#: A rate of samples, poses or frames: 0.01 Hz to 10 kHz (no body sensor or
#: display runs faster; a higher value is a typo that would make millions of
#: frames, a lower one times past what a clock counts: 1e-300 Hz).
RATE_HZ = bounded_float(0.01, 10_000.0, "a rate in Hz, 0.01 Hz to 10 kHz")
#: A length of time given on the command line: above 0, at most a day.
DURATION_S = positive_float(86_400.0, "seconds, at most a day")


def port(text: str) -> int:
    """A TCP/UDP port, 1..65535."""
    return bounded_int(1, 65535, "a port")(text)


def port_or_zero(text: str) -> int:
    """A port to listen on, 1..65535, or 0 for any free one."""
    return bounded_int(0, 65535, "a port; 0 picks a free one")(text)


def number_list(lo: int, hi: int) -> Callable[[str], tuple[int, ...]]:
    """``"1-3,7"`` -> ``(1, 2, 3, 7)``, every number within ``lo..hi``."""

    def parse(text: str) -> tuple[int, ...]:
        out: list[int] = []
        for part in text.split(","):
            a, dash, b = part.strip().partition("-")
            if not re.fullmatch(r"\d{1,12}", a) or (dash and not re.fullmatch(r"\d{1,12}", b)):
                fail(f"{_shown(text)} is not a list like 1-3,7")
            first, last = int(a), int(b) if dash else int(a)
            if first > last or first < lo or last > hi:
                fail(f"{_shown(text)}: numbers must be within {lo}..{hi}, ranges low-high")
            out.extend(range(first, last + 1))
        return tuple(dict.fromkeys(out))

    parse.__name__ = "number list"
    return parse


def time_window(text: str) -> tuple[float, float]:
    """``START:END`` in seconds, ``0 <= START < END``, both finite."""
    start_s, sep, end_s = text.partition(":")
    if not sep:
        fail(f"{_shown(text)} is not START:END in seconds")
    try:
        start, end = float(start_s), float(end_s)
    except ValueError:
        fail(f"{_shown(text)} is not START:END in seconds")
    if not (math.isfinite(start) and math.isfinite(end)):
        fail(f"{_shown(text)}: START and END must be finite")
    if not 0 <= start < end:
        fail(f"{_shown(text)}: need 0 <= START < END")
    return start, end


# -- files -------------------------------------------------------------------


def _path(text: str) -> Path:
    if not text:
        fail("an empty path")
    if "\0" in text:
        fail(f"{_shown(text)} holds a NUL character")
    try:
        os.stat(text)
    except FileNotFoundError:
        pass
    except OSError as exc:  # a name too long, a loop of links...
        if exc.errno in (errno.ENAMETOOLONG, errno.ELOOP):
            fail(f"{_shown(text)}: {exc.strerror}")
    return Path(text)


def _kind(path: Path) -> str:
    """ "dir", "file", "other" (a device, a pipe...), or "none" (nothing there)."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return "none"
    return "dir" if stat.S_ISDIR(mode) else "file" if stat.S_ISREG(mode) else "other"


def _why_not_readable(path: Path) -> str | None:
    try:
        st = path.stat()
    except FileNotFoundError:
        return "no such file"
    except NotADirectoryError:
        return "a part of the path is not a folder"
    except PermissionError:
        return "permission denied"
    except OSError as exc:
        return exc.strerror or str(exc)
    if stat.S_ISDIR(st.st_mode):
        return "a folder, not a file"
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):  # /dev/zero: no end to read
        return "a device, not a file"
    if not os.access(path, os.R_OK):
        return "not readable (permission denied)"
    return None


def input_file(text: str) -> Path:
    """A file that exists and can be read (not a folder or a device; a pipe,
    ``<(...)``, is one)."""
    path = _path(text)
    why = _why_not_readable(path)
    if why:
        fail(f"cannot read {_shown(text)}: {why}")
    return path


def existing_dir(text: str) -> Path:
    """A folder that exists."""
    path = _path(text)
    kind = _kind(path)
    if kind != "dir":
        fail(f"{_shown(text)} is not a folder" + ("" if kind != "none" else " (no such path)"))
    return path


def _writable_folder(path: Path, text: str) -> None:
    parent = path.parent if str(path.parent) else Path(".")
    kind = _kind(parent)
    if kind not in ("dir", "none"):
        fail(f"cannot write {_shown(text)}: {_shown(str(parent))} is a file, not a folder")
    if kind != "dir":
        fail(f"cannot write {_shown(text)}: its folder {_shown(str(parent))} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        fail(f"cannot write {_shown(text)}: its folder is not writable")


def output_file(text: str) -> Path:
    """Where a file will be written: not a folder or a device, in a writable folder.

    An existing regular file is allowed (it is replaced atomically on success,
    see ``bodynet.session.outputs``); whether it is one of the command's inputs
    is checked there."""
    path = _output(text)
    _writable_folder(path, text)
    return path


def output_file_new_folder(text: str) -> Path:
    """As :func:`output_file`, but the folder may not exist yet (the command
    makes it); an existing part of the path must be a writable folder."""
    path = _output(text)
    folder = path.parent
    while str(folder) not in ("", ".", "/") and _kind(folder) == "none":
        folder = folder.parent
    if _kind(folder) != "dir":
        fail(f"cannot write {_shown(text)}: {_shown(str(folder))} is not a folder")
    if not os.access(folder, os.W_OK | os.X_OK):
        fail(f"cannot write {_shown(text)}: {_shown(str(folder))} is not writable")
    return path


def _output(text: str) -> Path:
    path = _path(text)
    if text.endswith(os.sep):
        fail(f"{_shown(text)} names a folder; give a file name")
    try:
        st = path.stat()
    except FileNotFoundError:
        pass
    except OSError as exc:
        fail(f"cannot write {_shown(text)}: {exc.strerror or exc}")
    else:
        if stat.S_ISDIR(st.st_mode):
            fail(f"{_shown(text)} is a folder; give a file name")
        if not stat.S_ISREG(st.st_mode):
            fail(f"{_shown(text)} is not a regular file (a device or pipe); refusing to write it")
        if not os.access(path, os.W_OK) or not st.st_mode & 0o222:  # root too: made read-only
            fail(f"cannot write {_shown(text)}: it is read-only")
    return path


#: Where Linux's pseudo-terminals are (``os.ttyname`` of one).
PTY_FOLDER = "/dev/pts/"


def is_pty_link(path: Path) -> bool:
    """Is ``path`` a symbolic link to a pseudo-terminal (one an emulator made,
    perhaps left by one that was killed: its terminal may be gone)?"""
    try:
        return os.readlink(path).startswith(PTY_FOLDER)
    except OSError:  # nothing there, or not a link
        return False


def link_path(text: str) -> Path:
    """Where a link to a pseudo-terminal will be made: nothing there yet, or
    such a link (an emulator's, which is replaced); in a writable folder."""
    path = _path(text)
    if _kind(path) == "dir" and not os.path.islink(path):
        fail(f"{_shown(text)} is a folder; give a file name")
    if os.path.lexists(path) and not is_pty_link(path):
        fail(f"{_shown(text)} exists and is not a link to a pseudo-terminal; "
             "refusing to replace it: give a new name")  # fmt: skip
    _writable_folder(path, text)
    return path


def input_or_new_file(text: str) -> Path:
    """A file that is read if it exists and written otherwise (a profile that
    calibration creates): a readable file, or a new name in a writable folder."""
    path = _path(text)
    if _kind(path) != "none" or os.path.islink(path):
        input_file(text)
        if _kind(path) != "file":  # it is replaced when written: a regular file only
            fail(f"{_shown(text)} is not a regular file (a pipe?); refusing to write it")
        return path
    _writable_folder(path, text)
    return path


def output_dir(text: str) -> Path:
    """A folder to write into: an existing folder, or a new one whose parent exists."""
    path = _path(text)
    if _kind(path) != "none":
        if _kind(path) != "dir":
            fail(f"{_shown(text)} exists and is not a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            fail(f"cannot write into {_shown(text)}: permission denied")
        return path
    _writable_folder(path, text)
    return path


def same_file(a: Path, b: Path) -> bool:
    """Are ``a`` and ``b`` the same file: the same path, or the same inode
    (a hard or symbolic link)? A path that does not exist is the same as
    another only by name."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


# -- network and names -------------------------------------------------------

_LOCATOR_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe",
                      "serial", "vsock")  # fmt: skip
_HOST = r"(?:\[[0-9A-Fa-f:.]+(?:%[\w.-]+)?\]|[A-Za-z0-9](?:[A-Za-z0-9.-]{0,252})?)"
_ENDPOINT = re.compile(rf"(?P<proto>[a-z][a-z0-9-]*)/(?P<addr>{_HOST}):(?P<port>\d{{1,5}})"
                       r"(?:\?[^#\s]*)?(?:#[^\s]*)?")  # fmt: skip


def endpoint(text: str) -> str:
    """A Zenoh endpoint, ``proto/address:port`` (e.g. ``tcp/127.0.0.1:7447``,
    ``tls/[::1]:7447``), with Zenoh's optional ``?config`` and ``#metadata``;
    socket-file protocols take a path (``unixsock-stream//tmp/zenoh.sock``)."""
    proto, sep, rest = text.partition("/")
    if not sep or not rest:
        fail(f"{_shown(text)} is not a Zenoh endpoint like tcp/127.0.0.1:7447")
    if proto not in _LOCATOR_PROTOCOLS:
        fail(f"{_shown(text)}: unknown protocol {proto!r} "
             f"(Zenoh's: {', '.join(_LOCATOR_PROTOCOLS)})")  # fmt: skip
    if proto in ("unixsock-stream", "unixpipe", "serial"):
        if any(c.isspace() or not c.isprintable() for c in rest):
            fail(f"{_shown(text)}: the path holds spaces or control characters")
        return text
    if proto == "vsock":
        return text
    m = _ENDPOINT.fullmatch(text)
    if m is None:
        fail(f"{_shown(text)} is not a Zenoh endpoint like {proto}/127.0.0.1:7447")
    if int(m["port"]) > 65535:
        fail(f"{_shown(text)}: port {m['port']} is above 65535")
    addr = m["addr"]
    if re.fullmatch(r"[\d.]+", addr):  # numbers and dots: an IPv4 address, or a typo of one
        try:
            ipaddress.IPv4Address(addr)
        except ValueError:
            fail(f"{_shown(text)}: {addr} is not an IPv4 address (four numbers 0-255)")
    return text


_KEY_CHUNK = re.compile(r"\*\*|[^/*$?#\s]*(?:\$\*[^/*$?#\s]*)*|\*")


def key_expr(text: str) -> str:
    """A Zenoh key expression: ``/``-separated non-empty chunks, ``*`` and ``**``
    as whole chunks (or ``$*`` inside one), no ``?``, ``#`` or spaces, no
    leading, trailing or doubled ``/``, in Zenoh's canonical form (``*/**``, not
    ``**/*``). These are Zenoh's ``KeyExpr`` rules, checked without loading
    Zenoh; white space, which Zenoh allows, is refused here as a typo."""
    if not text:
        fail("an empty key expression")
    if text.startswith("/") or text.endswith("/") or "//" in text:
        fail(f"{_shown(text)}: a key expression has no empty chunk (no leading, "
             "trailing or doubled '/')")  # fmt: skip
    previous = ""
    for chunk in text.split("/"):
        if not chunk.isprintable() or not _KEY_CHUNK.fullmatch(chunk):
            fail(f"{_shown(text)}: chunk {_shown(chunk)} is not valid (use * or ** as "
                 "whole chunks; no ?, # or spaces)")  # fmt: skip
        if chunk == "$*" or "$*$*" in chunk:
            fail(
                f"{_shown(text)}: write {_shown(chunk)} as {_shown(chunk.replace('$*$*', '$*'))}"
                if chunk != "$*"
                else f"{_shown(text)}: a chunk that is only $* is written *"
            )
        if previous == "**" and chunk in ("*", "**"):
            fail(
                f"{_shown(text)}: write {previous}/{chunk} as "
                f"{'*/**' if chunk == '*' else '**'} (Zenoh's canonical form)"
            )
        previous = chunk
    return text


def name_chunk(text: str) -> str:
    """A name that is one key chunk: letters, digits, ``-``, ``_`` and ``.``."""
    if not re.fullmatch(r"[A-Za-z0-9_.-]{1,100}", text):
        fail(f"{_shown(text)}: use 1-100 letters, digits, '-', '_' or '.'")
    return text


def hostname(text: str) -> str:
    """A DNS name (ASCII letters, digits, '-', '.') or an IP address."""
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        pass
    labels = text.rstrip(".").split(".")
    ok = (0 < len(text) <= 253 and all(
        re.fullmatch(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?", label) for label in labels
    ))  # fmt: skip
    if not ok:
        fail(f"{_shown(text)} is neither a host name (ASCII letters, digits, '-' and '.') "
             "nor an IP address; write an international name in its xn-- form")  # fmt: skip
    return text


def url(*schemes: str) -> Callable[[str], str]:
    """A URL of one of ``schemes`` with a host, e.g. ``rerun+http://127.0.0.1:9876/proxy``."""

    def parse(text: str) -> str:
        m = re.fullmatch(r"(?P<scheme>[a-z][a-z0-9+.-]*)://(?P<host>[^/\s?#]+)(?P<rest>\S*)", text)
        if m is None or (schemes and m["scheme"] not in schemes):
            want = " or ".join(f"{s}://HOST..." for s in schemes) or "SCHEME://HOST..."
            fail(f"{_shown(text)} is not a URL like {want}")
        return text

    parse.__name__ = "url"
    return parse


def free_text(limit: int = 200) -> Callable[[str], str]:
    """Any printable text up to ``limit`` characters, not empty."""

    def parse(text: str) -> str:
        if not text.strip():
            fail("empty text")
        if len(text) > limit:
            fail(f"longer than {limit} characters")
        if not text.isprintable():
            fail(f"{_shown(text)} holds control or undecodable characters")
        return text

    parse.__name__ = "text"
    return parse
