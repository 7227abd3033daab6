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


# The rooms and the arrows between them: which role folder may import which.
# Data flows nodes -> Zenoh -> gateway -> Zenoh -> clients; what two rooms share
# lives below both (core, kinematics, session). Offline processing runs sources,
# the gateway's solver and a sink in one process, so it sits above all three;
# cli and bench sit above everything.
ROOMS = ("core", "kinematics", "session", "nodes", "gateway", "clients", "offline", "cli",
         "bench")  # fmt: skip
MAY_IMPORT: dict[str, set[str]] = {
    "core": {"core"},
    "kinematics": {"core", "kinematics"},
    "session": {"core", "session"},
    "nodes": {"core", "session", "kinematics", "nodes"},
    "gateway": {"core", "kinematics", "session", "gateway"},
    "clients": {"core", "session", "kinematics", "clients"},
    "offline": {"core", "session", "kinematics", "nodes", "gateway", "clients", "offline"},
    "cli": set(ROOMS),
    "bench": set(ROOMS),
}
# Arrows that still point the wrong way, each (file, imported module) with the
# engineer whose change removes it. Remove the line when the arrow is gone; the
# test fails on an exception that no longer happens, so the list only shrinks.
KNOWN_EXCEPTIONS: dict[tuple[str, str], str] = {}


def _our_imports(path: Path) -> list[str]:
    """Every ``bodynet.*`` module a file imports, at the top or inside functions."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("bodynet.")]
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.level:  # relative: within its own room
                continue
            if node.module == "bodynet":
                found += [f"bodynet.{a.name}" for a in node.names]
            elif node.module.startswith("bodynet."):
                found.append(node.module)
    return found


def _wrong_arrows() -> dict[tuple[str, str], str]:
    wrong = {}
    for room in ROOMS:
        for path in sorted((ROOT / room).rglob("*.py")):
            for module in _our_imports(path):
                target = module.split(".")[1]
                if target in ROOMS and target not in MAY_IMPORT[room]:
                    wrong[(str(path.relative_to(ROOT)), module)] = f"{room} -> {target}"
    return wrong


def test_every_import_between_rooms_points_down() -> None:
    wrong = _wrong_arrows()
    new = {k: v for k, v in wrong.items() if k not in KNOWN_EXCEPTIONS}
    assert not new, "imports against the layering (see MAY_IMPORT):\n" + "\n".join(
        f"{path} imports {module} ({arrow})" for (path, module), arrow in sorted(new.items())
    )
    gone = set(KNOWN_EXCEPTIONS) - set(wrong)
    assert not gone, f"these known exceptions are gone: remove them from the list: {sorted(gone)}"


def test_the_layering_check_sees_a_wrong_arrow(tmp_path: Path) -> None:
    """The check above can fail: an upward import, even inside a function, is found."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from bodynet.gateway import service\n"
                     "    import bodynet.cli.main\n")  # fmt: skip
    assert _our_imports(probe) == ["bodynet.gateway", "bodynet.cli.main"]
