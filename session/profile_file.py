"""Reading and writing a subject's profile as TOML: shared by the gateway, which
writes its calibrations there, and the clients and commands that read it."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import tomli_w

from bodynet.core.subject import Profile, ProfileError

HEADER = (
    "# bodynet subject profile: edit freely; `bodynet calibrate` rewrites the sections it owns.\n"
)


def load(path: Path) -> Profile:
    """The profile in ``path``; ``ProfileError`` says what is wrong with it."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ProfileError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ProfileError(f"{path}: not a text file (a profile is TOML)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path}: not valid TOML: {exc}") from None
    try:
        return Profile.from_dict(data)
    except ProfileError as exc:
        raise ProfileError(f"{path}: {exc}") from None


def save(profile: Profile, path: Path) -> None:
    """Write ``profile`` to ``path`` atomically, readable by the owner only."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(HEADER + tomli_w.dumps(profile.to_dict()))
    tmp.replace(path)
