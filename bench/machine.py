"""The machine a benchmark ran on, written beside its numbers."""

from __future__ import annotations

import os
import platform
from importlib import metadata
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else what platform says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe() -> dict[str, object]:
    """CPU model, cores, OS, Python and the versions of the libraries measured."""

    def version(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "-"

    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "zenoh": version("eclipse-zenoh"),
        "pylsl": version("pylsl"),
        "mcap": version("mcap"),
    }


def line(info: dict[str, object] | None = None) -> str:
    """One line for a table's caption."""
    m = info or describe()
    return (f"{m['cpu']}, {m['cores']} cores, {m['os']}, Python {m['python']}, "
            f"zenoh {m['zenoh']}, pylsl {m['pylsl']}, mcap {m['mcap']}")  # fmt: skip
