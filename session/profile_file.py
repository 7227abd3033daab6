"""Reading and writing a subject's profile as TOML: shared by the gateway, which
writes its calibrations there, and the clients and commands that read it."""

from __future__ import annotations

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
        # an editor's byte order mark (Notepad's "UTF-8 with BOM") is no TOML statement
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))
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
    """Write ``profile`` to ``path`` whole or not at all, readable by the owner
    only (a nameless file until it is whole: a failed or killed run leaves
    nothing beside it); ``OutputError`` (an ``OSError``) names ``path``."""
    from bodynet.session.outputs import atomic_file

    text = HEADER + tomli_w.dumps(profile.to_dict())
    with atomic_file(path) as f:
        f.write(text)
