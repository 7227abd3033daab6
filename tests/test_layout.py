"""The project's shape: a pure core, and one `bodynet` namespace once installed."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parents[1]
IO_LIBRARIES = {"zenoh", "can", "serial", "rerun", "mcap", "pinocchio", "socket", "asyncio",
                "select", "selectors", "subprocess", "threading", "time", "os", "io"}  # fmt: skip


def test_core_source_imports_no_io_library() -> None:
    for path in (ROOT / "core").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in IO_LIBRARIES, f"{path}: imports {name}"


def test_importing_core_loads_no_io_library() -> None:
    code = (
        "import sys, pkgutil, importlib, bodynet.core as c\n"
        "for m in pkgutil.walk_packages(c.__path__, 'bodynet.core.'):\n"
        "    importlib.import_module(m.name)\n"
        "print(' '.join(sorted(sys.modules)))"
    )
    loaded = set(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                check=True).stdout.split())  # fmt: skip
    assert "bodynet.core.codecs.imu_matrix" in loaded
    for banned in ("zenoh", "can", "serial", "rerun", "mcap", "pinocchio", "socket", "asyncio"):
        assert banned not in loaded


def test_installed_names_are_unambiguous(tmp_path: Path) -> None:
    """Outside the checkout, the roles import as bodynet.*, never as bare names."""
    code = (
        "import importlib.util as u\n"
        "roles = ('gateway', 'nodes', 'clients', 'core')\n"
        "print([u.find_spec(n) is None for n in roles],"
        " [u.find_spec('bodynet.' + n) is not None for n in roles])"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, check=True).stdout.strip()  # fmt: skip
    assert out == "[True, True, True, True] [True, True, True, True]"
