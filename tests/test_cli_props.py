"""The whole command line against a careless user: every option of the real
parser gets hostile values (and hypothesis-made ones), every offline command
gets unusable files, and nothing may answer with a traceback, accept nonsense,
exit 0 on unusable input, or change an input file.

Kept fast: options are parsed in this process (the real ``build_parser``); the
commands run in this process through ``main`` (an exception escaping it fails
the test as a traceback would); only what needs a process of its own (a closed
stdout, a full disk, the real executable's argv) starts one. A longer fuzzing
run: ``HYPOTHESIS_PROFILE=long``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer

from bodynet.cli.main import build_parser, main
from bodynet.clients.mcap_store import MCAP_MAGIC, read_poses
from bodynet.core.errors import Reason
from bodynet.session import argtypes

BODYNET = Path(sys.executable).with_name("bodynet")
DATA = Path(__file__).parent / "data"
LONG = os.environ.get("HYPOTHESIS_PROFILE") == "long"

# -- every option of the real parser --------------------------------------------------


@dataclass(frozen=True)
class Opt:
    """One option (or positional) of one command."""

    command: tuple[str, ...]
    action: argparse.Action
    parser: argparse.ArgumentParser

    @property
    def name(self) -> str:
        """The option as argparse names it in its errors ("argument NAME: ...")."""
        a = self.action
        if a.option_strings:
            return "/".join(a.option_strings)
        return str(a.metavar if a.metavar not in (None, argparse.SUPPRESS) else a.dest)

    def __repr__(self) -> str:  # hypothesis and pytest ids
        return f"{' '.join(self.command)} {self.name}"


def _walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
          ) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:  # fmt: skip
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _walk(sub, (*path, name))


def _takes_value(action: argparse.Action) -> bool:
    skip = (argparse._HelpAction, argparse._SubParsersAction, argparse._VersionAction)
    return not isinstance(action, skip) and action.nargs != 0


PARSER = build_parser()
OPTIONS = [Opt(path, a, p) for path, p in _walk(PARSER) for a in p._actions if _takes_value(a)]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Things a value may name: a file, a folder, nothing."""
    d = tmp_path_factory.mktemp("cli")
    f = d / "a-file.txt"
    f.write_text("something\n")
    ro = d / "read-only.out"
    ro.write_text("kept\n")
    ro.chmod(0o444)  # refused as an output, by root too
    return {
        "file": f,
        "dir": d,
        "missing": d / "missing" / "nothing.txt",
        "new": d / "new.out",
        "read-only": ro,
    }


def _candidates(files: dict[str, Path]) -> list[str]:
    return ["1", "0.5", "115200", str(files["file"]), str(files["new"]),
            str(files["new"].with_suffix(".md")), "tcp/127.0.0.1:7447",
            "body/**", "left_elbow", "x=left-arm/upperarm", "left-arm/upperarm",
            "aabbccddeeff-0", "aabbccddeeff-0=left-arm/upperarm", "127.0.0.1:6969", "0:1",
            "rerun+http://127.0.0.1:9876/proxy", "sacrum:+z", "socketcan", "x"]  # fmt: skip


def _valid(action: argparse.Action, files: dict[str, Path]) -> str:
    """A value ``action`` accepts."""
    if action.choices:
        return str(next(iter(action.choices)))
    for text in _candidates(files):
        try:
            (action.type or str)(text)  # type: ignore[operator]
        except (argparse.ArgumentTypeError, ValueError, TypeError):
            continue
        return text
    raise AssertionError(f"no valid value found for {action}")


def _required(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in parser._actions if _takes_value(a) and (
        a.required or (not a.option_strings and a.nargs not in ("?", "*")))]  # fmt: skip


def argv(opt: Opt, value: str, files: dict[str, Path]) -> list[str]:
    """The command line giving ``value`` to ``opt``, every other required
    argument a valid value, positionals after ``--`` (a value may start with -)."""
    optionals: list[str] = []
    positionals: list[str] = []
    actions = _required(opt.parser)
    if opt.action not in actions:
        actions.append(opt.action)
    for a in opt.parser._actions:  # positionals in their order
        if a not in actions:
            continue
        text = value if a is opt.action else _valid(a, files)
        if a.option_strings:
            flag = max(a.option_strings, key=len)
            optionals.append(f"{flag}={text}")
        else:
            positionals.append(text)
    return [*opt.command, *optionals, *(["--", *positionals] if positionals else [])]


def _is_number(action: argparse.Action) -> bool:
    """Does the option's type make numbers (or a list of them) of its text?"""
    try:
        value = action.type("1") if callable(action.type) else None
    except (argparse.ArgumentTypeError, ValueError, TypeError):
        return False
    items = value if isinstance(value, (list, tuple)) else [value]
    return bool(items) and all(isinstance(v, (int, float)) for v in items)


def parse(args: list[str]) -> tuple[int | None, str]:
    """(None, "") if the real parser accepts ``args``, else its exit code and stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            PARSER.parse_args(args)
        except SystemExit as exc:
            return int(exc.code or 0), err.getvalue()
    return None, err.getvalue()


def _hostile(files: dict[str, Path]) -> list[str]:
    return ["nan", "NaN", "inf", "-inf", "1e309", "-1", "0", "-0", "1e-300", "9" * 5000,
            "", " ", "\udcff\udcfe", "é", "😀", "x" * 10_000, "a//b", "tcp/", "1:2:3", "-",
            "--", "/dev/full", str(files["dir"]), str(files["missing"]), "1,2,,3",
            "$*", str(files["read-only"])]  # fmt: skip


def test_the_parser_has_every_command_and_each_parses_with_valid_values(
    files: dict[str, Path],
) -> None:
    commands = {o.command for o in OPTIONS}
    assert {("decode",), ("process",), ("export", "csv"), ("record",), ("replay",),
            ("report",), ("view",), ("certs",), ("game",)} <= commands  # fmt: skip
    assert len(OPTIONS) > 200
    for opt in OPTIONS:
        code, err = parse(argv(opt, _valid(opt.action, files), files))
        assert code is None, (opt, err)


#: Options where an empty value means "none", and what it means.
EMPTY_MEANS_NONE = {
    ("game", "--patient"): "no patient id (the default)",
    ("gateway", "--share"): "an id made of the host, the pid and a random part",
}

#: Options checked by their command instead, before it does anything, and why.
CHECKED_BY_THE_COMMAND = {
    ("game", "--results"): "a folder made by the game; told before any wait",
}


def test_no_option_takes_unchecked_text_numbers_or_paths() -> None:
    """Each option is checked where it enters: a checked type or a fixed choice."""
    for opt in OPTIONS:
        kind = opt.action.type
        if opt.action.choices or (*opt.command, opt.name) in CHECKED_BY_THE_COMMAND:
            continue
        assert kind not in (float, int, str, Path), f"{opt}: a bare {kind}"
        assert kind is not None, f"{opt}: free text, unchecked"


@pytest.mark.parametrize("opt", OPTIONS, ids=repr)
def test_hostile_values_parse_or_are_refused_naming_the_option(
    opt: Opt, files: dict[str, Path]
) -> None:
    accepted: set[str] = set()
    for value in _hostile(files):
        code, err = parse(argv(opt, value, files))
        if code is None:
            accepted.add(value)
            continue
        assert code == 2, (opt, value, err)
        lines = [line for line in err.splitlines() if "error:" in line]
        assert len(lines) == 1, (opt, value, err)  # one clear line
        assert f"argument {opt.name}:" in lines[0], (opt, value, err)
    if (*opt.command, opt.name) in CHECKED_BY_THE_COMMAND:
        return
    if (*opt.command, opt.name) not in EMPTY_MEANS_NONE:
        assert "" not in accepted, f"{opt} accepts an empty value"
    numbers = {"nan", "NaN", "inf", "-inf", "1e309", "9" * 5000}
    if _is_number(opt.action):  # a number: finite and bounded
        assert not accepted & numbers, f"{opt} accepts {accepted & numbers}"
    if opt.action.type in (argtypes.input_file, argtypes.input_or_new_file):
        assert not {str(files["dir"]), "/dev/full"} & accepted, opt  # /dev/zero: no end
    if opt.action.type is argtypes.input_file:
        assert str(files["missing"]) not in accepted, opt
    if opt.action.type in (argtypes.output_file, argtypes.output_file_new_folder):
        assert not {str(files["dir"]), "/dev/full", str(files["read-only"])} & accepted, opt


@settings(max_examples=2000 if LONG else 150)
@given(opt=st.sampled_from(OPTIONS), text=st.text(max_size=40))
def test_any_text_parses_or_is_refused_naming_the_option(opt: Opt, text: str) -> None:
    fixed = {"file": DATA / "smartsuit_arm.log", "dir": DATA, "missing": DATA / "nope",
             "new": Path("/tmp/bodynet-props-new.out")}  # fmt: skip
    code, err = parse(argv(opt, text, fixed))
    if code is not None:
        assert code == 2, (opt, text, err)
        assert f"argument {opt.name}:" in err, (opt, text, err)


# -- through the real executable: real argv bytes, exit codes, no traceback ------------


def run(*args: str | bytes | Path, timeout: float = 60, **kw: object
        ) -> subprocess.CompletedProcess[str]:  # fmt: skip
    return subprocess.run([str(BODYNET), *map(os.fsencode, args)], capture_output=True,
                          text=True, timeout=timeout, check=False, **kw)  # type: ignore[call-overload]  # fmt: skip


def test_the_real_executable_refuses_nonsense_in_one_line(tmp_path: Path) -> None:
    log = DATA / "smartsuit_arm.log"
    for args, told in (
        (["decode", "--format", "can-log", "--rate-hz", "nan", log], "argument --rate-hz"),
        (["process", log, "--tick-hz", "0", "-o", tmp_path / "x.mcap"], "argument --tick-hz"),
        (["process", b"/tmp/\xff\xfe-missing.log", "-o", tmp_path / "x.mcap"], "argument input"),
        (["export", "csv", log, "-o", ""], "argument -o/--output: an empty path"),
        (["record", "--rotate-s", "1e-9", "-o", tmp_path / "r.mcap"], "argument --rotate-s"),
        (["certs", "--host", "é.example", tmp_path / "c"], "argument --host"),
        (["replay", "-e", "garbage", log], "argument -e/--connect"),
        (
            [
                "process",
                DATA / "imu_central.txt",
                "--format",
                "imu-central",
                "--rate-hz",
                "1e-300",
                "-o",
                tmp_path / "x.mcap",
            ],
            "argument --rate-hz",
        ),  # its times overflowed
    ):
        result = run(*args)
        assert result.returncode == 2, (args, result.stderr)
        assert told in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.stderr
    assert list(tmp_path.iterdir()) == []
    pairs = tmp_path / "wild.csv"  # counts of 1e300: numpy's overflow warning came out too
    pairs.write_text("0,0\n30,1e300\n60,-1e300\n")
    result = run("calibrate", "ole", "--joint", "left_elbow", "--from-pairs", pairs,
                 "--profile", tmp_path / "p.toml")  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("bodynet calibrate ole: no usable calibration"), result.stderr
    assert result.stderr.count("\n") == 1, result.stderr


def test_no_option_is_taken_as_an_abbreviation_of_another(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`calibrate ole --from` (the option of `calibrate tpose`) is not `--from-pairs`,
    `process --out` not `--output`: refused, nothing read or written as another option's."""
    pairs, profile, out = tmp_path / "pairs.csv", tmp_path / "p.toml", tmp_path / "x.mcap"
    pairs.write_text("0,0\n30,100\n60,200\n")
    for args, told in (
        (["calibrate", "ole", "--joint", "left_elbow", "--from", pairs, "--profile", profile],
         "unrecognized arguments: --from"),
        (["process", DATA / "imu_central.txt", "--format", "imu-central", "--out", out],
         "required: -o/--output"),
    ):  # fmt: skip
        with pytest.raises(SystemExit) as exited:
            main([str(a) for a in args])
        assert exited.value.code == 2
        assert told in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pairs.csv"]
    for command, parser in _walk(build_parser()):  # every command, those to come too
        assert not parser.allow_abbrev, command


def test_a_client_without_its_router_says_so_and_gives_up(tmp_path: Path) -> None:
    from zenoh_helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    result = run("subjects", "-e", endpoint, "--connect-timeout", "1")
    assert result.returncode != 0
    assert f"waiting for the router at {endpoint}" in result.stderr
    assert f"no router answered at {endpoint}" in result.stderr
    assert "Traceback" not in result.stderr
    # a config's mode stands: the gateway's identity config is a client's (not the
    # gateway's default router, which would add a TCP listener the TLS-only config refuses)
    from bodynet.session.security import make_certs

    make_certs(tmp_path / "certs", [], port=free_port())
    conf = tmp_path / "certs" / "gateway" / "zenoh.json5"
    result = run("gateway", "-c", conf, "--connect-timeout", "1")
    assert result.returncode == 2, result.stderr
    assert "waiting for the router at tls/localhost:" in result.stderr
    assert "Unsupported protocol" not in result.stderr


# -- the commands with unusable files ---------------------------------------------------


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else ""


def cli(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str]:
    """``bodynet ...`` in this process: its exit code and stderr."""
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's refusal
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


@pytest.fixture(scope="module")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Good and bad inputs: captures, recordings (whole, cut, a corrupt chunk),
    files of another kind, profiles and reference CSVs."""

    from bodynet.core.codecs import pose

    d = tmp_path_factory.mktemp("corpus")
    c: dict[str, Path] = {}
    for name in ("smartsuit_arm.log", "imu_central.txt", "concentrator.cap"):
        c[name] = d / name
        c[name].write_bytes((DATA / name).read_bytes())
    c["empty"] = d / "empty.log"
    c["empty"].write_bytes(b"")
    c["random"] = d / "random.bin"
    c["random"].write_bytes(random.Random(0).randbytes(3000))
    c["recording"] = d / "arm.mcap"
    assert main(["process", str(c["smartsuit_arm.log"]), "-o", str(c["recording"])]) == 0
    # the body's poses in small chunks, one of them corrupt, and the file cut short
    chunked = d / "chunked.mcap"
    with chunked.open("wb") as out:
        writer = Writer(out, chunk_size=2048, compression=CompressionType.ZSTD)
        writer.start()
        schema = writer.register_schema("bodynet.PoseFrame", "jsonschema", b"{}")
        channel = writer.register_channel("body/pose", "json", schema)
        for t, frame in read_poses(c["recording"]):
            writer.add_message(channel, t, pose.encode(frame), t)
        writer.finish()
    c["chunked"] = chunked
    c["numbered"] = _as_recorded(c["recording"], d / "numbered.mcap")
    data = bytearray(chunked.read_bytes())
    chunks = _chunk_offsets(bytes(data))
    assert len(chunks) > 10
    middle = chunks[len(chunks) // 2]
    data[middle + 80 : middle + 120] = b"\xaa" * 40
    c["corrupt"] = d / "corrupt.mcap"
    c["corrupt"].write_bytes(bytes(data))
    c["cut"] = d / "cut.mcap"
    c["cut"].write_bytes(chunked.read_bytes()[: chunks[-3] + 100])
    c["profile-bytes"] = d / "bytes.toml"
    c["profile-bytes"].write_bytes(b"\xff\xfe\x00" + random.Random(1).randbytes(200))
    c["profile-list"] = d / "list.toml"
    c["profile-list"].write_text("version = 1\nole = [1, 2]\n")
    c["profile-nan"] = d / "nan.toml"
    c["profile-nan"].write_text("version = 1\n[ole.left_elbow_flexion_deg]\nradius_mm = nan\n")
    c["pairs-bad"] = d / "pairs.csv"
    c["pairs-bad"].write_text("angle,counts\n0,nan\n30,inf\nabc,def\n")
    c["pairs-wild"] = d / "wild.csv"
    c["pairs-wild"].write_text("0,0\n30,1e300\n60,-1e300\n")
    c["ref-header"] = d / "ref-header.csv"
    c["ref-header"].write_text("t_s,left_elbow_flexion_deg\n")
    c["ref-ragged"] = d / "ref-ragged.csv"
    lines = ["t_s,left_elbow_flexion_deg"] + [f"{1700000000 + i * 0.01:.2f},{i % 90}"
                                              for i in range(100)]  # fmt: skip
    lines[40] += ",extra"
    lines[60] = "abc,3"
    c["ref-ragged"].write_text("\n".join(lines) + "\n")
    return c


def _as_recorded(src: Path, dst: Path) -> Path:
    """``src``'s poses as bodynet's recorder writes them (numbered, with their
    transforms), in small chunks."""
    from bodynet.clients.mcap_store import McapSink
    from bodynet.core import keys

    sink = McapSink(dst, chunk_size=4096)
    for t, frame in read_poses(src):
        sink.write_pose(keys.pose_key(), frame, t)
    sink.close()
    return dst


def _chunk_offsets(data: bytes) -> list[int]:
    offsets, pos = [], 8
    while pos + 9 <= len(data) and data[pos] != 0x02:  # up to the footer
        if data[pos] == 0x06:
            offsets.append(pos)
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    return offsets


@contextlib.contextmanager
def unchanged(*paths: Path) -> Iterator[None]:
    """Every path's content (or absence) is the same after the block."""
    before = {p: sha(p) for p in paths}
    yield
    assert {p: sha(p) for p in paths} == before


def test_unusable_captures_are_errors_naming_what_they_look_like(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.mcap"
    with unchanged(*corpus.values()):
        for name, fmt, told in (
            ("imu_central.txt", "can-log", "IMU central capture (--format imu-central)"),
            ("smartsuit_arm.log", "imu-central", "candump CAN log (--format can-log"),
            ("smartsuit_arm.log", "concentrator", "candump CAN log"),
            ("recording", "concentrator", "an MCAP recording"),
            ("empty", "can-log", "no can-log samples"),
            ("random", "imu-central", "no imu-central samples"),
        ):
            code, err = cli(capsys, "decode", "--format", fmt, corpus[name])
            assert code == 2, (name, err)
            assert told in err, (name, err)
            code, err = cli(capsys, "process", corpus[name], "--format", fmt, "-o", out)
            assert code == 2, (name, err)
            assert told in err, (name, err)
            assert not out.exists()  # no empty recording
        head = tmp_path / "head.asc"  # a log of the asked format with no frame: no hint
        head.write_text("date Thu Dec 03 21:18:51.770 2026\nbase hex  timestamps absolute\n")
        code, err = cli(capsys, "decode", "--format", "can-log", head)
        assert code == 2
        assert err.splitlines()[-1] == f"bodynet decode: no can-log samples in {head}", err
        head.unlink()
        code, err = cli(capsys, "process", corpus["smartsuit_arm.log"], "--tpose-s", "100",
                        "-o", out)  # fmt: skip
        assert code == 2
        assert "--tpose-s 100 is longer than the capture" in err
        code, err = cli(capsys, "process", corpus["empty"], "--format", "can-log", "--tpose-s",
                        "2", "-o", out)  # fmt: skip
        assert code == 2
        assert "no can-log samples" in err, err  # what is wrong, not a window past its end
        for profile in ("profile-bytes", "profile-list", "profile-nan"):
            code, err = cli(capsys, "process", corpus["smartsuit_arm.log"], "--profile",
                            corpus[profile], "-o", out)  # fmt: skip
            assert code == 2, (profile, err)
            assert str(corpus[profile]) in err
            if profile == "profile-list":  # said by name, not as Python's AttributeError
                assert "ole must be a table ([ole]), not list [1, 2]" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", ["csv", "bvh", "c3d"])
def test_damaged_recordings_are_named_with_the_offset_and_salvage(
    kind: str, corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / f"out.{kind}"
    with unchanged(*corpus.values()):
        for name in ("corrupt", "cut", "random", "empty", "smartsuit_arm.log"):
            code, err = cli(capsys, "export", kind, "-q", corpus[name], "-o", out)
            assert code == 2, (name, err)
            assert err.startswith("bodynet export: "), err
            assert str(corpus[name]) in err
        code, err = cli(capsys, "export", kind, "-q", corpus["corrupt"], "-o", out)
        assert "(in the chunk at byte" in err
        assert f"bodynet record --salvage {corpus['corrupt']}" in err
    assert list(tmp_path.iterdir()) == []


def test_report_view_and_replay_name_a_damaged_recording(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with unchanged(*corpus.values()):
        for args in (["report", corpus["corrupt"], "-o", tmp_path / "r.md"],
                     ["view", corpus["corrupt"], "--viewer", "none", "--save", tmp_path / "v.rrd"],
                     ["replay", corpus["cut"], "-e", "tcp/127.0.0.1:1"]):  # fmt: skip
            code, err = cli(capsys, *args)  # replay: the file is told before any router wait
            assert code == 2, (args, err)
            assert "record --salvage" in err, (args, err)
            assert "waiting for the router" not in err
        for args, told in (  # no recording, and nothing to replay: told before any router wait
            (["replay", corpus["smartsuit_arm.log"]], "not an MCAP recording"),
            (["replay", corpus["chunked"]], "nothing to replay: "),  # poses only
            (["replay", corpus["recording"], "--keys", "nothing/**"], "on these keys"),
        ):
            code, err = cli(capsys, *args, "-e", "tcp/127.0.0.1:1")
            assert code == 2, (args, err)
            assert told in err, (args, err)
            assert "waiting for the router" not in err
    assert list(tmp_path.iterdir()) == []


def test_salvage_skips_a_corrupt_chunk_and_keeps_the_chunks_after_it(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    whole = sum(1 for _ in read_poses(corpus["chunked"]))
    last_t = max(t for t, _ in read_poses(corpus["chunked"]))
    out = tmp_path / "saved.mcap"
    with unchanged(corpus["corrupt"]):
        code, err = cli(capsys, "record", "--salvage", corpus["corrupt"], "-o", out)
    assert code == 0, err
    kept = list(read_poses(out))
    lost = whole - len(kept)
    assert 0 < lost < whole // 10  # one chunk's worth, not everything after it
    assert max(t for t, _ in kept) == last_t  # the chunks after the bad one are there
    assert f"lost {lost} message{'' if lost == 1 else 's'}: byte" in err, err
    code, err = cli(capsys, "record", "--salvage", corpus["cut"], "-o", out)
    assert code == 0
    assert "the file ends inside this record" in err
    code, err = cli(capsys, "record", "--salvage", corpus["random"], "-o", tmp_path / "r.mcap")
    assert code == 2
    assert "not an MCAP recording" in err
    assert not (tmp_path / "r.mcap").exists()


def _garbled(src: Path, dst: Path, keep_summary: bool, index_too: bool = False) -> int:
    """``src`` with the framing of a chunk in its middle garbled (its opcode and
    length overwritten; with ``index_too`` its records' end and its message
    indexes as well), cut before its summary unless ``keep_summary``; the
    garbled chunk's offset."""
    data = bytearray(src.read_bytes())
    chunks = _chunk_offsets(bytes(data))
    at = chunks[len(chunks) // 2]
    data[at : at + 9] = b"\xee" * 9
    if index_too:  # from inside the chunk's records to the next chunk
        nxt = chunks[len(chunks) // 2 + 1]
        data[at + 200 : nxt] = b"\xee" * (nxt - at - 200)
    dst.write_bytes(bytes(data if keep_summary else data[: chunks[-1]]))
    return at


def _headline(err: str) -> tuple[int, int | None]:
    """The bounds salvage told of the messages it lost: (low, high or None)."""
    if "lost an unknown number of messages:" in err:
        return 0, None
    m = re.search(r"lost (at least )?(\d+)(?: to (\d+))? messages?:", err)
    assert m is not None, err
    low = int(m[2])
    return low, None if m[1] else int(m[3] or low)


def test_salvage_counts_what_garbled_framing_cost_where_it_can_be_known(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Garbled framing hides where records begin: a chunk the file's summary
    indexes is read by its index (nothing lost); what cannot be read is counted
    from the summary (exact), else from the message sequence numbers around it
    (bodynet's recorder numbers them), else told unknown and why; a cut chunk
    is bounded by its size."""
    from bodynet.clients.mcap_store import count_messages

    out = tmp_path / "saved.mcap"
    total = {name: count_messages(corpus[name]) for name in ("chunked", "numbered")}
    for name, keep_summary, index_too, told in (
        ("chunked", True, False, "nothing lost"),  # read by the summary's index
        ("numbered", True, False, "nothing lost"),
        ("chunked", True, True, "message"),  # the summary's count: exact
        ("numbered", True, True, "message"),
        ("numbered", False, False, "at least"),  # no summary: the sequence numbers
        ("chunked", False, False, "an unknown number of messages: its "),  # neither
    ):
        bad = tmp_path / f"{name}-{keep_summary}-{index_too}.mcap"
        at = _garbled(corpus[name], bad, keep_summary, index_too)
        with unchanged(bad):
            code, err = cli(capsys, "record", "--salvage", bad, "-o", out)
        assert code == 0, err
        kept = count_messages(out)
        assert told in err, err
        if told == "nothing lost":
            assert kept == total[name], err
            continue
        low, high = _headline(err)
        assert f"byte {at} to " in err, err  # where the unreadable part starts and ends
        if keep_summary:
            assert (low, high) == (total[name] - kept,) * 2, err  # exact
            assert "at least" not in err, err
            assert "unknown" not in err, err
        elif told == "at least":
            assert f"(at least {low} message" in err, err
            assert low >= 1
        else:
            assert "the file has no summary to count it by, nor message sequence numbers" in err
            assert (low, high) == (0, None), err  # not "at least 0"
        # a file without sequence numbers whose loss they would have counted says so
        uncounted = f"bodynet record: {bad}: its messages carry no sequence numbers"
        assert (uncounted in err) == (told.startswith("an unknown")), err
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(corpus["numbered"].read_bytes()[: _chunk_offsets(
        corpus["numbered"].read_bytes())[-1] + 200])  # fmt: skip
    code, err = cli(capsys, "record", "--salvage", cut, "-o", out)
    assert code == 0, err
    low, high = _headline(err)  # what came after the cut: unknowable from the file
    assert high is None, err
    assert low <= total["numbered"] - count_messages(out), err
    assert re.search(r"\(at most \d+ messages; the file ends inside this record; whatever "
                     r"came after it is not in the file\)", err), err  # fmt: skip


@pytest.mark.parametrize("record", ["header", "message index"])
def test_salvage_tells_what_a_garbled_record_length_swallowed(
    corpus: dict[str, Path], tmp_path: Path, record: str
) -> None:
    """A header or message index record (any whose fields carry their lengths)
    whose length is garbled (longer than its fields) would swallow the records
    after it: salvage takes it for garbled framing and reads on from the next
    chunk (found by the property test below: the header's length overwritten
    with ``00 0a``, one message told lost, two were; a message index's with
    ``00 06``, which swallowed the chunk after it untold)."""
    from bodynet.clients.mcap_store import count_messages, salvage_report

    whole = corpus["numbered"].read_bytes()
    total = count_messages(corpus["numbered"])
    damaged = bytearray(whole)
    if record == "header":
        at = 8
    else:  # the message index after the third chunk
        third = _chunk_offsets(whole)[2]
        at = third + 9 + int.from_bytes(whole[third + 1 : third + 9], "little")
        assert whole[at] == 0x07
    damaged[at + 1 : at + 3] = b"\x00\n"  # the record's length: 2,560 more
    bad, out = tmp_path / "bad.mcap", tmp_path / "out.mcap"
    bad.write_bytes(bytes(damaged))
    saved = salvage_report(bad, out)
    lost = total - count_messages(out)
    low, high = _headline(saved.summary())
    assert low <= lost, saved.summary()
    assert high is None or lost <= high, saved.summary()
    assert f"byte {at} to " in saved.summary()  # the garbled part starts at the record
    assert lost == 0, saved.summary()  # reading went on at the next chunk: nothing lost


@pytest.mark.parametrize(
    "junk",
    [b"\x02", b"\x05", b"\x05\x00\x0f", b"\x03\x00\n"],
    ids=["a footer", "a message", "a message with a longer length", "a schema likewise"],
)
def test_salvage_counts_what_a_record_garbled_into_another_cost(
    corpus: dict[str, Path], tmp_path: Path, junk: bytes
) -> None:
    """The header's opcode garbled into another record's: a footer where the
    file does not end is garbled framing (it ended reading, 150 messages lost
    and none told); a message record outside a chunk on a channel the file
    does not define is garbled framing too (a "message" made of the header was
    kept as an orphan, one message told lost, and its length swallowed the
    chunks after it); a record that does not read is counted as garbled framing
    is (its opcode or its length may be what is garbled: a "schema" whose length
    swallowed two chunks counted none). Found by the property test below."""
    from bodynet.clients.mcap_store import count_messages, salvage_report

    damaged = bytearray(corpus["numbered"].read_bytes())
    damaged[8 : 8 + len(junk)] = junk
    bad, out = tmp_path / "bad.mcap", tmp_path / "out.mcap"
    bad.write_bytes(bytes(damaged))
    saved = salvage_report(bad, out)
    lost = count_messages(corpus["numbered"]) - count_messages(out)
    assert _headline(saved.summary()) == (lost, lost), saved.summary()  # exact: the summary's


def test_salvage_counts_a_bad_chunk_once_after_garbled_framing(
    corpus: dict[str, Path], tmp_path: Path
) -> None:
    """Garbled framing (a message index's length) just before a chunk that does
    not read (its records damaged): the chunk is counted once, from its own
    message indexes, and the garbled bytes, which held no message, count none
    (the summary's count gave the chunk to both: two lost told, one was; found
    by fuzzing salvage)."""
    from bodynet.clients.mcap_store import count_messages, salvage_report

    whole = corpus["numbered"].read_bytes()
    damaged = bytearray(whole)
    chunks = _chunk_offsets(whole)
    k = len(chunks) // 2
    index = chunks[k] + 9 + int.from_bytes(whole[chunks[k] + 1 : chunks[k] + 9], "little")
    assert whole[index] == 0x07  # the chunk's first message index
    damaged[index + 1 : index + 3] = b"\x00\n"  # its length: 2,560 more
    damaged[chunks[k + 1] + 9 + 44 + 20] ^= 0xFF  # in the next chunk's compressed records
    bad, out = tmp_path / "bad.mcap", tmp_path / "out.mcap"
    bad.write_bytes(bytes(damaged))
    saved = salvage_report(bad, out)
    lost = count_messages(corpus["numbered"]) - count_messages(out)
    assert lost > 0
    assert "a chunk that does not read" in saved.summary()
    assert _headline(saved.summary()) == (lost, lost), saved.summary()


@pytest.mark.parametrize("garbled", ["the summary's index", "the chunk's own, no summary"])
def test_salvage_reads_a_chunk_by_the_length_its_fields_fill(
    corpus: dict[str, Path], tmp_path: Path, garbled: str
) -> None:
    """A chunk's length is said twice, by its record and by the summary's chunk
    index; whichever is garbled, salvage reads the chunk by the one its fields
    fill, or by its fields where the file has no summary (found by the property
    test: a chunk index's length garbled upward sent the walker past the chunks
    after it, 51 messages lost and 3 told)."""
    from bodynet.clients.mcap_store import count_messages, salvage_report

    damaged = bytearray(corpus["numbered"].read_bytes())
    chunks = _chunk_offsets(bytes(damaged))
    target = chunks[len(chunks) // 2]
    if garbled == "the summary's index":
        pos = chunks[-1]
        while damaged[pos] != 0x02:  # to the footer, through the summary's records
            opcode, length = damaged[pos], int.from_bytes(damaged[pos + 1 : pos + 9], "little")
            offset = int.from_bytes(damaged[pos + 25 : pos + 33], "little")
            if opcode == 0x08 and offset == target:  # the ChunkIndex of the target
                damaged[pos + 34] ^= 0xE0  # its chunk_length, second byte: far longer
                break
            pos += 9 + length
        assert damaged[pos] == 0x08
    else:
        damaged[target + 2] ^= 0x7F  # the chunk record's own length: far longer
        footer = len(damaged) - len(MCAP_MAGIC) - 29
        damaged[footer + 9 : footer + 17] = (2 * len(damaged)).to_bytes(8, "little")
    bad, out = tmp_path / "bad.mcap", tmp_path / "out.mcap"
    bad.write_bytes(bytes(damaged))
    saved = salvage_report(bad, out)
    assert count_messages(out) == count_messages(corpus["numbered"]), saved.summary()
    assert saved.summary() == "nothing lost"


def test_salvage_counts_no_message_for_a_channel_record_that_does_not_read(
    corpus: dict[str, Path], tmp_path: Path
) -> None:
    """A channel record that does not read (its topic garbled, here the copy in
    the file's summary) holds no message: salvage tells the bad record and loses
    nothing, rather than one message it never lost."""
    from bodynet.clients.mcap_store import count_messages, salvage_report

    damaged = bytearray(corpus["numbered"].read_bytes())
    pos, data_ended, channel = 8, False, None
    while pos + 9 <= len(damaged):
        opcode, length = damaged[pos], int.from_bytes(damaged[pos + 1 : pos + 9], "little")
        data_ended |= opcode == 0x0F  # DataEnd: the summary section follows
        if data_ended and opcode == 0x04:  # a Channel record
            channel = pos
            break
        pos += 9 + length
    assert channel is not None
    damaged[channel + 9 + 8] = 0xFF  # the topic's first byte: not UTF-8
    bad, out = tmp_path / "bad.mcap", tmp_path / "out.mcap"
    bad.write_bytes(bytes(damaged))
    saved = salvage_report(bad, out)
    assert count_messages(out) == count_messages(corpus["numbered"])
    assert "a bad record" in saved.summary()
    assert _headline(saved.summary())[0] == 0, saved.summary()


def test_salvage_reads_the_start_of_a_chunk_the_file_ends_inside(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A big chunk (zstd blocks of 128 KiB) cut short: the messages of its whole
    blocks are kept, in order, and the rest is bounded by the chunk's size."""
    from bodynet.clients.mcap_store import McapSink, count_messages, read_raw

    whole = tmp_path / "big.mcap"
    sink = McapSink(whole, chunk_size=4 << 20, max_chunk_s=1e9)  # one chunk
    raw = list(read_raw(corpus["recording"]))
    for i in range(3000):
        topic, _, sample = raw[i % len(raw)]
        sink.write_raw(topic, sample, 10**9 + i * 10**6)
    sink.close()
    data = whole.read_bytes()
    (chunk,) = _chunk_offsets(data)
    cut = tmp_path / "cut.mcap"
    length = int.from_bytes(data[chunk + 1 : chunk + 9], "little")
    cut.write_bytes(data[: chunk + length * 9 // 10])
    out = tmp_path / "saved.mcap"
    code, err = cli(capsys, "record", "--salvage", cut, "-o", out)
    assert code == 0, err
    kept = [t for _, t, _ in read_raw(out)]
    assert 0 < len(kept) < 3000
    assert kept == [10**9 + i * 10**6 for i in range(len(kept))]  # the first ones, in order
    assert f"the file ends inside this chunk (its first {len(kept)} messages read)" in err
    assert count_messages(out) == len(kept)


@settings(max_examples=200 if LONG else 25, deadline=None)
@given(data=st.data())
def test_salvage_of_any_damage_tells_bounds_that_hold(
    data: st.DataObject, corpus: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> None:
    """Any bytes of a recording overwritten (or the file cut): salvage keeps what
    reads, and the count of what it lost that it tells (exact, a range or a lower
    bound) holds against the truth."""
    from bodynet.clients.mcap_store import StoreError, count_messages, salvage_report

    name = data.draw(st.sampled_from(["numbered", "chunked"]), label="file")
    whole = corpus[name].read_bytes()
    total = count_messages(corpus[name])
    damaged = bytearray(whole)
    at = data.draw(st.integers(len(MCAP_MAGIC), len(whole) - 1), label="at")
    if data.draw(st.booleans(), label="cut"):
        damaged = damaged[:at]
    else:
        junk = data.draw(st.binary(min_size=1, max_size=64), label="junk")
        damaged[at : at + len(junk)] = junk
    d = tmp_path_factory.mktemp("salvage")
    bad, out = d / "bad.mcap", d / "out.mcap"
    bad.write_bytes(bytes(damaged))
    try:
        saved = salvage_report(bad, out)
    except StoreError:
        assert not out.exists()
        return
    lost = total - count_messages(out)
    assert saved.messages == total - lost
    text = saved.summary()
    if lost and text == "nothing lost":
        raise AssertionError(f"{lost} lost, nothing told")
    if text != "nothing lost":
        low, high = _headline(text)
        assert low <= lost, text
        assert high is None or lost <= high, text


def test_no_output_overwrites_an_input(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    capture = tmp_path / "arm.log"
    capture.write_bytes(corpus["smartsuit_arm.log"].read_bytes())
    rec = tmp_path / "arm.mcap"
    rec.write_bytes(corpus["recording"].read_bytes())
    (tmp_path / "link.mcap").hardlink_to(rec)
    (tmp_path / "link.md").hardlink_to(rec)  # a report's name, the recording's file
    (tmp_path / "sym.log").symlink_to(capture)
    with unchanged(capture, rec):
        for args in (
            ["process", capture, "-o", capture],
            ["process", capture, "-o", tmp_path / "sym.log"],
            ["export", "csv", rec, "-o", rec],
            ["export", "bvh", rec, "-o", tmp_path / "link.mcap"],
            ["view", rec, "--viewer", "none", "--save", rec],
            ["record", "--salvage", rec, "-o", tmp_path / "link.mcap"],
            ["report", rec, "-o", tmp_path / "link.md"],
        ):
            code, err = cli(capsys, *args)
            assert code == 2, (args, err)
            assert "it is an input of this command" in err, (args, err)


def test_calibrate_and_report_keep_good_rows_and_refuse_bad_files(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    profile = tmp_path / "p.toml"
    with unchanged(*corpus.values()):
        for pairs in ("pairs-bad", "pairs-wild", "random"):
            code, err = cli(capsys, "calibrate", "ole", "--joint", "left_elbow", "--from-pairs",
                            corpus[pairs], "--profile", profile)  # fmt: skip
            assert code == 2, (pairs, err)
            assert not profile.exists()
        code, err = cli(capsys, "calibrate", "ole", "--joint", "left_elbow", "--from-pairs",
                        corpus["pairs-bad"], "--profile", corpus["profile-list"])  # fmt: skip
        assert code == 2
        assert err == (
            f"bodynet calibrate ole: {corpus['profile-list']}: ole must be a table "
            "([ole]), not list [1, 2]; nothing written\n"
        )  # the profile, not the pairs
        out = tmp_path / "r.md"
        code, err = cli(capsys, "report", corpus["recording"], "--reference",
                        corpus["ref-header"], "-o", out, "--no-trials",
                        "--still", "0.1:0.6")  # fmt: skip
        assert code == 2
        assert "no usable row" in err
        code, err = cli(capsys, "report", corpus["recording"], "-o", tmp_path / "rep")
        assert code == 2  # a report named without its format
        assert "rep' is neither .md nor .html: the report is Markdown (rep.md)" in err
        code, err = cli(capsys, "report", corpus["recording"], "--reference",
                        corpus["ref-ragged"], "-o", out, "--no-trials",
                        "--still", "0.1:0.6")  # fmt: skip
        assert code == 0, err
        assert "line 41 left out: 3 fields, the header has 2" in err
        assert "line 61 left out: t_s 'abc' is not a finite number" in err
        assert "2 rows left out" in out.read_text()


#: Where each python-can text format writes a frame's CAN id.
CAN_ID = {".log": r"\s([0-9A-F]{8})#", ".asc": r"\s([0-9A-F]+x)\s",
          ".trc": r"DT\s+\d+\s+([0-9A-F]+)\s", ".csv": r",0x([0-9a-f]+),"}  # fmt: skip


@pytest.mark.parametrize("suffix", [".log", ".asc", ".trc", ".csv", ".blf"])
def test_a_garbled_can_log_line_costs_only_itself(
    suffix: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from bodynet.nodes.captures import CaptureStats, can_log_messages

    good = [m for m in can_log_messages(DATA / "smartsuit_arm.log", CaptureStats())
            if not m.is_error_frame and not m.is_remote_frame]  # fmt: skip
    log = tmp_path / f"arm{suffix}"
    if suffix == ".blf":  # a binary log: small containers, one garbled
        with can.BLFWriter(log, max_container_size=512) as w:
            for m in good:
                w.on_message_received(m)
        data = bytearray(log.read_bytes())
        objects = [i for i in range(len(data)) if data[i : i + 4] == b"LOBJ"]
        data[objects[5] + 40 : objects[5] + 60] = b"\xff" * 20
        log.write_bytes(bytes(data))
    else:
        with can.Logger(log) as w:
            for m in good:
                w.on_message_received(m)
        lines = log.read_text().splitlines(keepends=True)
        bad = len(lines) // 2  # a frame's line: its CAN id garbled (a Z among hex digits)
        m = re.search(CAN_ID[suffix], lines[bad])
        assert m is not None, lines[bad]
        lines[bad] = lines[bad][: m.start(1) + 1] + "Z" + lines[bad][m.start(1) + 2 :]
        log.write_text("".join(lines))
    stats = CaptureStats()
    kept = list(can_log_messages(log, stats))
    if suffix == ".blf":
        assert len(good) - 20 < len(kept) < len(good)  # one container's frames, not the rest
        assert stats.bad_places
        assert stats.bad_places[0].startswith("byte ")
    else:
        assert len(kept) == len(good) - 1
        assert stats.bad_places == [f"line {bad + 1}"]
    code, err = cli(capsys, "decode", "--format", "can-log", log)
    assert code == 0
    assert "skipped garbled " + stats.bad_places[0] in err


def _frames_log(suffix: str, path: Path) -> tuple[list[can.Message], list[str]]:
    """A log of the arm capture's frames in a python-can text format: the frames and
    the file's lines."""
    from bodynet.nodes.captures import CaptureStats, can_log_messages

    good = [m for m in can_log_messages(DATA / "smartsuit_arm.log", CaptureStats())
            if not m.is_error_frame and not m.is_remote_frame][:40]  # fmt: skip
    with can.Logger(path) as w:
        for m in good:
            w.on_message_received(m)
    return good, path.read_text().splitlines(keepends=True)


def _frame_key(m: can.Message) -> tuple[int, bytes]:
    return m.arbitration_id, bytes(m.data)


@settings(max_examples=400 if LONG else 60, deadline=None)
@given(suffix=st.sampled_from([".log", ".asc", ".trc", ".csv"]), data=st.data())
def test_any_garbled_can_log_line_is_counted_or_kept_and_costs_only_itself(
    suffix: str, data: st.DataObject, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """python-can's .asc and .trc readers pass over a line that does not look like a
    frame without a word: any damage to one frame line (a character changed, added,
    removed, the line cut) leaves every other frame, and the damaged line is a frame
    or counted by its number (never taken for one of the format's own lines)."""
    from bodynet.nodes.captures import CaptureStats, can_log_messages

    log = tmp_path_factory.mktemp("garbled") / f"arm{suffix}"
    good, lines = _frames_log(suffix, log)
    ids = {f"{m.arbitration_id:X}" for m in good}
    frame_lines = [i for i, line in enumerate(lines)
                   if any(x in line.upper() for x in ids)]  # fmt: skip
    assert len(frame_lines) == len(good)
    at = data.draw(st.sampled_from(frame_lines[1:-1] or frame_lines), label="line")
    text = lines[at].rstrip("\n")
    i = data.draw(st.integers(0, len(text)), label="where")
    how = data.draw(st.sampled_from(["change", "insert", "delete", "cut"]), label="how")
    line_ends = "\r\n\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"  # what splitlines splits at
    char = data.draw(st.characters(exclude_categories=("Cs",), exclude_characters=line_ends),
                     label="char")  # fmt: skip
    damaged = {"change": text[:i] + char + text[i + 1 :], "insert": text[:i] + char + text[i:],
               "delete": text[:i] + text[i + 1 :], "cut": text[:i]}[how]  # fmt: skip
    lines[at] = damaged + "\n"
    log.write_text("".join(lines), encoding="utf-8")
    stats = CaptureStats()
    kept = [_frame_key(m) for m in can_log_messages(log, stats)]
    others = [_frame_key(m) for m in good]
    # the damaged line's own frame, if it still reads as one, is somewhere in kept
    assert len(kept) in (len(good) - 1, len(good)), (damaged, stats.summary())
    missing = list(others)
    for k in kept:
        if k in missing:
            missing.remove(k)
    assert len(missing) <= 1, (damaged, stats.summary())  # only the damaged line's frame
    if len(kept) == len(good) - 1:  # the damaged line gave no frame: it is counted
        places = [f"line {at + 1}"]
        if stats.rejected.get(Reason.OUT_OF_ORDER):
            # a frame whose time now breaks the order with one neighbour's: which of
            # the two is out, the times alone cannot tell; one of them is counted
            j = frame_lines.index(at)
            places += [f"line {frame_lines[k] + 1}" for k in (j - 1, j + 1)
                       if 0 <= k < len(frame_lines)]  # fmt: skip
        assert len(stats.bad_places) == 1, (damaged, stats.summary())
        assert stats.bad_places[0] in places, (damaged, stats.summary())
    else:
        assert stats.bad_places == [], (damaged, stats.summary())


def test_an_asc_log_s_events_pass_and_its_garbled_frames_are_told(tmp_path: Path) -> None:
    """A Vector .asc log with no "internal events logged" line (python-can's reader
    drops the first frame after such a header), bus events that are not frames, and
    frame lines garbled past python-can's recognition (silently skipped by it): an
    event of no known kind, a frame line without its channel, an empty line among
    frames are counted; empty lines after the last frame are not."""
    from bodynet.nodes.captures import CaptureStats, can_log_messages

    frame = " 0.0{}0000 1  6FF0{}x          Rx   d 8 00 01 02 03 04 05 06 07\n"
    log = tmp_path / "vector.asc"
    log.write_text("date Thu Dec 03 21:18:51.770 2026\nbase hex  timestamps absolute\n"
                   + frame.format(0, 1) + frame.format(1, 2)
                   + " 0.020000 1 Statistic: D 0 R 0 XD 0 XR 0 E 0 O 0 B 0.00%\n"
                   + " 0.020000 CAN 1 Status:chip status error active\n"
                   + " 0.030000 SV: 2 0 1 ::a::b = 3\n"
                   + frame.format(4, 3).replace("Rx", "Rq")  # line 8
                   + frame.format(5, 4).replace("0.050000", "0.05Z000")  # line 9
                   + frame.format(6, 5).replace(" 1  ", " I  ")  # line 10
                   + " 0.060000 1  J1939TP FEE3p  6  0  0  -  Rx  d 9 00 01 02 03 04 05 06 07 08\n"
                   + " 0.060000 log trigger event\n 0.060000 EnvSpeed := 12\n"
                   + " 0.060000 Odd event 1 2 3\n"  # line 14
                   + frame.format(6, 5).replace(" 1  6", "   A")  # line 15: no channel
                   + "\n"  # line 16
                   + frame.format(7, 6) + "\n\nEnd TriggerBlock\n")  # fmt: skip
    assert len(list(can.ASCReader(str(log)))) == 2  # python-can's own reader alone
    stats = CaptureStats()
    kept = [m.arbitration_id for m in can_log_messages(log, stats)]
    assert kept == [0x6FF01, 0x6FF02, 0x6FF06]
    assert stats.bad_places == ["line 8", "line 9", "line 10", "line 14", "line 15", "line 16"]
    assert "skipped garbled line 8, line 9, line 10, line 14, line 15, line 16" in stats.summary()


def test_a_trc_log_s_records_pass_and_frames_made_into_them_are_told(tmp_path: Path) -> None:
    """PCAN's status, error and event records pass; a frame line made into a comment
    or a status record by one character, among frames, is counted."""
    from bodynet.nodes.captures import CaptureStats, can_log_messages

    log = tmp_path / "pcan.trc"
    with can.Logger(log) as w:
        for i in range(6):
            w.on_message_received(can.Message(arbitration_id=0x6FF01 + i, data=bytes(8),
                                              timestamp=1 + i / 100))  # fmt: skip
    lines = log.read_text().splitlines(keepends=True)
    first = next(i for i, line in enumerate(lines) if " DT " in line)
    lines[first + 1] = ";" + lines[first + 1][1:]  # a frame commented out
    lines[first + 2] = lines[first + 2].replace(" DT ", " ST ")  # a frame made a status
    lines[first + 3 : first + 3] = [
        "      9        25.000 ST  1          Rx -       00 00 00 08\n",
        "     10        26.000 ER  1          Rx -       04 00 02 00 00\n",
        "     11        27.000 EV  1 User-defined event text\n",
        "; a comment among frames\n",
    ]  # fmt: skip
    log.write_text("".join(lines))
    stats = CaptureStats()
    kept = [m.arbitration_id for m in can_log_messages(log, stats)]
    assert kept == [0x6FF01, 0x6FF04, 0x6FF05, 0x6FF06]
    assert stats.bad_places == [f"line {first + 2}", f"line {first + 3}"]


# -- full disks and closed descriptors (a process of their own) -------------------------


#: Run a command as if its file system filled at 20-40 kB (``ulimit -f`` counts
#: 512- or 1024-byte blocks); SIGXFSZ ignored, so a write past it fails with
#: EFBIG instead of killing the process.
SMALL_DISK = ["sh", "-c", 'trap \'\' XFSZ; ulimit -f 40; exec "$0" "$@"', str(BODYNET)]


def test_a_full_disk_names_the_output_and_leaves_no_half_file(
    corpus: dict[str, Path], tmp_path: Path
) -> None:
    whole = tmp_path / "whole" / "big.csv"  # the export's size, on a disk with room
    whole.parent.mkdir()
    assert main(["export", "csv", "-q", str(corpus["recording"]), "-o", str(whole)]) == 0
    blocks = whole.stat().st_size // 2 // 512  # sh's ulimit -f counts 512-byte blocks
    shutil.rmtree(whole.parent)
    out = tmp_path / "big.csv"
    out.write_text("an earlier export\n")
    with unchanged(corpus["recording"], out):
        limited = ["sh", "-c", f'trap \'\' XFSZ; ulimit -f {blocks}; exec "$0" "$@"']
        result = subprocess.run([*limited, str(BODYNET), "export", "csv", "-q",
                                 str(corpus["recording"]), "-o", str(out)],
                                capture_output=True, text=True, timeout=60,
                                check=False)  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert f"bodynet export: cannot write {out}: File too large" in result.stderr
    assert "Traceback" not in result.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["big.csv"]  # no temporary file left


def test_a_profile_that_cannot_be_written_is_told_and_left_as_it_was(tmp_path: Path) -> None:
    """calibrate's profile is written as every output is: on a file system that
    takes no more bytes, one line naming it, the earlier profile whole and
    nothing beside it (a ``.tmp`` file was left here once)."""
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("0,1000\n30,1500\n60,2000\n90,2500\n")
    profile = tmp_path / "p.toml"
    profile.write_text("version = 1\n")
    before = profile.read_bytes()
    result = subprocess.run(["sh", "-c", 'trap \'\' XFSZ; ulimit -f 0; exec "$0" "$@"',
                             str(BODYNET), "calibrate", "ole", "--joint", "left_elbow",
                             "--from-pairs", str(pairs), "--profile", str(profile)],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert result.stderr == f"bodynet calibrate ole: cannot write {profile}: File too large\n"
    assert profile.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "pairs.csv"]


def test_a_full_or_closed_stdout_is_an_error(corpus: dict[str, Path], tmp_path: Path) -> None:
    capture = corpus["smartsuit_arm.log"]
    with open("/dev/full", "w") as full:
        result = subprocess.run([str(BODYNET), "decode", "--format", "can-log", str(capture)],
                                stdout=full, stderr=subprocess.PIPE, text=True, timeout=60,
                                check=False)  # fmt: skip
    assert result.returncode == 1
    assert "cannot write the samples to stdout: No space left on device" in result.stderr
    assert "Traceback" not in result.stderr
    assert "Exception ignored" not in result.stderr
    with open("/dev/full", "w") as full:  # any command whose report goes to stdout
        result = subprocess.run([str(BODYNET), "certs", str(tmp_path / "certs")],
                                stdout=full, stderr=subprocess.PIPE, text=True, timeout=60,
                                check=False)  # fmt: skip
    assert result.returncode == 1
    assert result.stderr == "bodynet certs: cannot write its output: No space left on device\n"
    closed = subprocess.run(f"'{BODYNET}' decode --format can-log '{capture}' >&-", shell=True,
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert closed.returncode == 2
    assert "stdout is closed" in closed.stderr
    assert "Traceback" not in closed.stderr
    assert sha(capture) == sha(DATA / "smartsuit_arm.log")


def test_a_terminated_write_leaves_the_earlier_file_and_no_half_file(tmp_path: Path) -> None:
    from bodynet.session.outputs import atomic_file

    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    out = tmp_path / "out.csv"
    out.write_text("an earlier export\n")
    with pytest.raises(SystemExit) as ended, atomic_file(out) as f:  # noqa: PT012
        f.write("half a row,")
        os.kill(os.getpid(), signal.SIGTERM)  # a kill while writing
        f.write("never written\n")
    assert ended.value.code == 128 + signal.SIGTERM
    assert out.read_text() == "an earlier export\n"
    assert list(tmp_path.iterdir()) == [out]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # as it was


@settings(max_examples=5000 if LONG else 500)
@given(text=st.text(alphabet="ab/*$?#@-", min_size=1, max_size=12))
def test_key_expressions_are_checked_as_zenoh_checks_them(text: str) -> None:
    """``argtypes.key_expr`` (no Zenoh loaded) agrees with Zenoh's own ``KeyExpr``."""
    import zenoh

    try:
        zenoh.KeyExpr(text)
        zenoh_takes = True
    except zenoh.ZError:
        zenoh_takes = False
    try:
        argtypes.key_expr(text)
        we_take = True
    except argparse.ArgumentTypeError:
        we_take = False
    assert we_take == zenoh_takes, text


def test_a_recording_onto_a_full_disk_stops_and_says_so(
    tmp_path: Path, router_endpoint: str
) -> None:
    from zenoh_helpers import client

    out = tmp_path / "r.mcap"
    recorder = subprocess.Popen([*SMALL_DISK, "record", "body/@health/**", "-o", str(out),
                                 "-e", router_endpoint], stderr=subprocess.PIPE,
                                text=True)  # fmt: skip
    session = client(router_endpoint)
    try:
        publisher = session.declare_publisher("body/@health/filler")
        t_ns = 1
        while recorder.poll() is None and t_ns < 100_000:  # until the disk is full
            t_ns += 1
            publisher.put(json.dumps({"source": "filler", "t_ns": t_ns, "pad": "x" * 2000}))
            with contextlib.suppress(subprocess.TimeoutExpired):
                recorder.wait(timeout=0.01)
        code = recorder.wait(timeout=60)
    finally:
        session.close()
        if recorder.poll() is None:
            recorder.kill()
    told = recorder.stderr.read() if recorder.stderr else ""
    assert code == 1, told
    assert f"bodynet record: cannot write {out}: File too large" in told
    assert f"bodynet record --salvage {out}" in told
    assert "Traceback" not in told


def test_an_export_of_mostly_repeated_frames_is_refused(
    corpus: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two poses an hour apart at 1 kHz would be 3.6 million frames of two poses."""
    from bodynet.core.codecs import pose

    sparse = tmp_path / "sparse.mcap"
    frames = [frame for _, frame in read_poses(corpus["recording"])][:2]
    with sparse.open("wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema("bodynet.PoseFrame", "jsonschema", b"{}")
        channel = writer.register_channel("body/pose", "json", schema)
        for t, frame in zip((10**9, 3601 * 10**9), frames, strict=True):
            writer.add_message(channel, t, pose.encode(frame), t)
        writer.finish()
    out = tmp_path / "x.c3d"
    code, err = cli(capsys, "export", "c3d", "-q", sparse, "--rate-hz", "1000", "-o", out)
    assert code == 2
    assert "choose a lower rate" in err
    assert not out.exists()


# -- an export killed or interrupted mid-write (real processes, real signals) ----------


def _writing(pid: int, folder: Path) -> bool:
    """Has process ``pid`` a temporary file of its output open in ``folder``: a
    nameless one (``O_TMPFILE``, shown as ``folder/#inode (deleted)``) or a
    named ``.part`` one?"""
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return False
    for fd in fds:
        with contextlib.suppress(OSError):
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
            if link.startswith(f"{folder}/#") or (link.startswith(f"{folder}/.")
                                                   and ".part" in link):  # fmt: skip
                return True
    return False


def _stopped(pid: int) -> bool:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0] in ("T", "t")


@contextlib.contextmanager
def _sigint_not_ignored() -> Iterator[None]:
    """A child started in the block takes SIGINT as from a terminal's Ctrl-C, even
    where this run was started in the background (a shell's background job has
    SIGINT ignored, and its children inherit that; a handled signal is reset to
    the default on exec)."""
    ignored = signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    if ignored:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _stop_mid_write(args: list[str], folder: Path, attempts: int = 5) -> subprocess.Popen[str]:
    """``bodynet ARGS`` started and stopped (SIGSTOP) while it writes its output
    in ``folder`` (its temporary file open, not yet in place); started again
    if it finished before it could be caught."""
    before = {p: p.read_bytes() for p in folder.iterdir()}
    for _ in range(attempts):
        with _sigint_not_ignored():
            proc = subprocess.Popen([str(BODYNET), *args], stderr=subprocess.PIPE, text=True)
        while proc.poll() is None:
            if not _writing(proc.pid, folder):
                with contextlib.suppress(subprocess.TimeoutExpired):  # a breath, not a spin
                    proc.wait(timeout=0.001)
                continue
            os.kill(proc.pid, signal.SIGSTOP)
            while proc.poll() is None and not _stopped(proc.pid):
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=0.001)
            in_place = all(p.read_bytes() == data for p, data in before.items())
            if proc.poll() is None and _writing(proc.pid, folder) and in_place:
                return proc  # stopped mid-write (not after the output took its place)
            os.kill(proc.pid, signal.SIGCONT)
        proc.communicate(timeout=60)
        for p in folder.iterdir():  # it finished: the folder as before, and again
            if p not in before:
                p.unlink()
        for p, data in before.items():
            p.write_bytes(data)
    raise AssertionError(f"never caught writing in {attempts} runs: {args}")


@pytest.fixture
def export_dir(corpus: dict[str, Path], tmp_path: Path) -> Path:
    """A folder with a recording and an earlier export of it."""
    (tmp_path / "arm.mcap").write_bytes(corpus["recording"].read_bytes())
    (tmp_path / "earlier.bvh").write_text("an earlier export\n")
    return tmp_path


@pytest.mark.parametrize("kind", ["bvh", "c3d", "report"])
def test_an_export_killed_mid_write_leaves_nothing(kind: str, export_dir: Path) -> None:
    """SIGKILL cannot be caught: the file being written has no name until it is
    whole (O_TMPFILE), so nothing is left; C3D's writer must name its file, and
    a report makes its plots in a folder of its own, so the next run removes
    what the killed run left, and says so."""
    rec = export_dir / "arm.mcap"
    if kind == "report":
        out = export_dir / "earlier.md"
        args = ["report", str(rec), "-o", str(out), "--no-trials", "--still", "0.1:0.6"]
    else:
        out = export_dir / f"earlier.{kind}"
        args = ["export", kind, "-q", str(rec), "--rate-hz", "1000", "-o", str(out)]
    out.write_text("an earlier export\n")
    before = sorted(p.name for p in export_dir.iterdir())
    with unchanged(rec, out):
        proc = _stop_mid_write(args, export_dir)
        proc.kill()
        assert proc.wait(timeout=60) == -signal.SIGKILL
        proc.communicate()
    left = sorted(p.name for p in export_dir.iterdir())
    from bodynet.session.outputs import PendingOutput

    probe = PendingOutput(export_dir / "probe")
    nameless = str(probe.path).startswith("/proc/self/fd/")  # O_TMPFILE here (else named)
    probe.discard()
    if kind == "bvh" and nameless:
        assert left == before
        return
    stale = [n for n in left if n not in before]
    assert len(stale) == 1, left
    assert stale[0].startswith(f".{out.name}.{proc.pid}.")
    result = run(*args)
    assert result.returncode == 0, result.stderr
    told = f"bodynet: removed {export_dir / stale[0]}, a temporary file of {out.name} left by"
    assert told in result.stderr
    assert not (export_dir / stale[0]).exists()
    assert not [n for n in os.listdir(export_dir) if n.startswith(".")]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_an_export_interrupted_mid_write_says_so_and_leaves_nothing(
    signum: int, export_dir: Path
) -> None:
    rec, out = export_dir / "arm.mcap", export_dir / "earlier.bvh"
    before = sorted(p.name for p in export_dir.iterdir())
    with unchanged(rec, out):
        proc = _stop_mid_write(["export", "bvh", "-q", str(rec), "--rate-hz", "400", "-o",
                                str(out)], export_dir)  # fmt: skip
        os.kill(proc.pid, signum)
        os.kill(proc.pid, signal.SIGCONT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum, err
    name = signal.Signals(signum).name
    assert err == (f"bodynet export: interrupted by {name}: stopped; no output file is left "
                   "half-written\n")  # fmt: skip
    assert sorted(p.name for p in export_dir.iterdir()) == before


# -- every export onto a file system that fills (a real tmpfs, in a mount namespace) --

#: Run in a mount namespace of its own: a tmpfs of the size given on the folder
#: given, then each command line (JSON; "OUT" is its output in that folder) in
#: one process, after an earlier small file of the output's name; prints what
#: each answered and left.
FULL_DISK = r"""
import contextlib, io, json, os, subprocess, sys
folder, size, cases = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", folder],
               check=True)
from bodynet.cli.main import main
results = []
for out_name, args in cases:
    out = os.path.join(folder, out_name)
    with open(out, "w") as f:
        f.write("earlier\n")
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main([out if a == "OUT" else a for a in args])
    with open(out) as f:
        kept = f.read()
    results.append({"out": out, "code": code, "err": err.getvalue(),
                    "left": sorted(os.listdir(folder)), "kept": kept})
    for name in os.listdir(folder):
        os.unlink(os.path.join(folder, name))
print(json.dumps(results))
"""


def _onto_a_full_disk(size: str, cases: list[tuple[str, list[str]]], folder: Path
                      ) -> list[dict[str, Any]]:  # fmt: skip
    """Each case's command run with its output on a tmpfs of ``size`` that fills."""
    prefix = _in_mount_namespace()
    folder.mkdir()
    result = subprocess.run([*prefix, sys.executable, "-c", FULL_DISK, str(folder), size,
                             json.dumps(cases)], capture_output=True, text=True, timeout=300,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    answers: list[dict[str, Any]] = json.loads(result.stdout.splitlines()[-1])
    return answers


def _told_the_disk_is_full(answer: dict[str, Any], command: str) -> None:
    assert answer["code"] in (1, 2), answer
    assert answer["err"].startswith(f"bodynet {command}: cannot write {answer['out']}"), answer
    assert "No space left on device" in answer["err"] or "a full disk" in answer["err"], answer
    assert "Traceback" not in answer["err"], answer
    assert answer["left"] == [Path(answer["out"]).name], answer  # no half file beside it
    assert answer["kept"] == "earlier\n", answer  # the earlier file whole


def _in_mount_namespace() -> list[str]:
    """The command prefix that runs a process in a new mount namespace where it
    may mount, or skip the test if this machine lets none be made."""
    import shutil

    unshare = shutil.which("unshare")
    if unshare is None:
        pytest.skip("no unshare (util-linux) to make a mount namespace")
    prefix = [unshare, "--mount"] if os.geteuid() == 0 else [
        unshare, "--user", "--map-root-user", "--mount"]  # fmt: skip
    probe = subprocess.run([*prefix, "true"], capture_output=True, text=True, check=False)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a mount namespace here: {probe.stderr.strip()}")
    return prefix


def test_every_export_onto_a_full_disk_names_the_output_and_leaves_nothing(
    corpus: dict[str, Path], tmp_path: Path
) -> None:
    from bodynet.clients.exports import WRITERS

    rec = str(corpus["recording"])
    with unchanged(corpus["recording"]):
        answers = _onto_a_full_disk("8k", [(f"out.{kind}", ["export", kind, "-q", rec, "-o",
                                                             "OUT"]) for kind in WRITERS],
                                    tmp_path / "disk")  # fmt: skip
    assert len(answers) == len(WRITERS)
    for answer in answers:
        _told_the_disk_is_full(answer, "export")


def test_every_other_file_output_onto_a_full_disk_names_it_and_leaves_nothing(
    corpus: dict[str, Path], tmp_path: Path
) -> None:
    """process, salvage, report and a saved view (64 KiB: Rerun's own writer
    hangs for ever when the disk fills while it opens the file)."""
    inputs = [corpus[n] for n in ("smartsuit_arm.log", "recording", "numbered")]
    log, rec, numbered = map(str, inputs)
    with unchanged(*inputs):
        answers = _onto_a_full_disk("8k", [
            ("p.mcap", ["process", log, "-o", "OUT"]),
            ("s.mcap", ["record", "--salvage", numbered, "-o", "OUT"]),
            ("r.md", ["report", rec, "-o", "OUT", "--no-trials", "--still", "0.1:0.6"]),
        ], tmp_path / "disk")  # fmt: skip
        answers += _onto_a_full_disk(
            "64k",
            [("v.rrd", ["view", rec, "--viewer", "none", "--save", "OUT"])],
            tmp_path / "disk2",
        )
    for answer, command in zip(answers, ["process", "record", "report", "view"], strict=True):
        _told_the_disk_is_full(answer, command)
