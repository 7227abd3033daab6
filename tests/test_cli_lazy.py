"""The CLI imports a command's module only when that command runs.

``bodynet --help`` and an argument error of any command are answered without
loading Zenoh, Pinocchio, Rerun, pandas or matplotlib (each costs up to
seconds at start-up). Each case runs in a fresh interpreter and reads its
``sys.modules``."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from bodynet.cli.main import COMMANDS, build_parser, resolve

HEAVY = ("zenoh", "pinocchio", "rerun", "pandas", "matplotlib")

PROBE = """
import json, sys
from bodynet.cli.main import main
try:
    code = main(json.loads(sys.argv[1]))
except SystemExit as exc:
    code = exc.code
loaded = sorted({m.split(".")[0] for m in sys.modules} & set(json.loads(sys.argv[2])))
print(json.dumps({"code": code, "loaded": loaded}), file=sys.stderr)
"""


def probe(argv: list[str], heavy: tuple[str, ...] = HEAVY) -> dict[str, object]:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(argv), json.dumps(heavy)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    result: dict[str, object] = json.loads(done.stderr.strip().splitlines()[-1])
    result["out"] = done.stdout
    return result


def test_help_lists_every_command_and_loads_nothing_heavy() -> None:
    result = probe(["--help"])
    assert result["code"] == 0
    assert result["loaded"] == []
    for name in COMMANDS:
        assert f"    {name}" in str(result["out"])


@pytest.mark.parametrize("command", list(COMMANDS))
def test_an_argument_error_loads_nothing_heavy(command: str) -> None:
    result = probe([command, "--no-such-option"])
    assert result["code"] == 2
    assert result["loaded"] == []


def test_the_probe_sees_a_heavy_import() -> None:
    """The check above can fail: a command that runs does load Zenoh."""
    result = probe(["router", "--cfg", "mode:{"], heavy=("zenoh",))
    assert result["code"] == 2  # the session refuses the entry's JSON5, once Zenoh is loaded
    assert result["loaded"] == ["zenoh"]


def test_every_command_runs_a_function_or_gives_its_subcommands_one() -> None:
    def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
        actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        return dict(actions[0].choices) if actions else {}

    for name, sub in subcommands(build_parser()).items():
        if COMMANDS[name].run:
            assert callable(resolve(COMMANDS[name].run))
            continue
        leaves = subcommands(sub)
        assert leaves, f"{name} has neither a run function nor sub-commands"
        for leaf in leaves.values():
            assert callable(leaf.get_default("func")), f"{name}: a sub-command without func"


def test_bench_without_its_extra_says_what_to_install() -> None:
    """psutil comes with the `bench` extra only; without it `bodynet bench` says so."""
    code = (
        "import sys; sys.modules['psutil'] = None\n"  # as if it were not installed
        "from bodynet.cli.main import main; sys.exit(main(['bench', '--only', 'decode']))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "psutil is missing: install the bench extra" in done.stderr
    assert "Traceback" not in done.stderr
