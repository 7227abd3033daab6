"""Orientation files as other tools write them: the same samples, or a refusal
that says what is wrong and how (never two sensors mixed, never a time unit guessed)."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import pytest

from bodynet.cli.main import main

#: (time s, {column: w, x, y, z}): two sensors turning about z at 100 Hz
SEGMENTS = ("pelvis", "left_thigh")
ROWS = [
    (round(0.01 * k, 2), {s: (math.cos(a), 0.0, 0.0, math.sin(a))
                          for s, a in zip(SEGMENTS, (0.002 * k, 0.1 + 0.003 * k), strict=True)})
    for k in range(50)
]  # fmt: skip


def decode(capsys: pytest.CaptureFixture[str], path: Path, *args: str) -> tuple[int, list, str]:
    """``bodynet decode``'s exit code, samples and stderr."""
    fmt = "sto" if path.suffix == ".sto" else "orientation-csv"
    code = main(["decode", "--format", fmt, *args, str(path)])
    out, err = capsys.readouterr()
    return code, [json.loads(line) for line in out.splitlines()], err


def csv_text(names: dict[str, list[str]], sep: str = ",", time: str = "time", scale: float = 1.0,
             end: str = "", cell: str = "{:.9g}") -> str:  # fmt: skip
    """ROWS as a CSV: ``names`` the four column names per segment, ``scale`` the
    time unit's per second, ``end`` after each line's last cell."""
    header = [time] + [n for s in SEGMENTS for n in names[s]]
    lines = [sep.join(header) + end]
    for t, quats in ROWS:
        cells = [f"{t * scale:g}"] + [cell.format(c) for s in SEGMENTS for c in quats[s]]
        lines.append(sep.join(cells) + end)
    return "\n".join(lines) + "\n"


PLAIN = {s: [f"{s}_{c}" for c in "wxyz"] for s in SEGMENTS}


@pytest.fixture
def plain(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> list:
    path = tmp_path / "plain.csv"
    path.write_text(csv_text(PLAIN))
    code, samples, err = decode(capsys, path)
    assert code == 0, err
    assert len(samples) == 2 * len(ROWS)
    return samples


def test_two_columns_on_one_site_are_refused_not_mixed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`pelvis` and `pelvis_imu` (both on the sacrum by the default map), or a
    `--map` onto a taken site: refused naming both; `COLUMN=` leaves one out."""
    both = {"pelvis": PLAIN["pelvis"], "left_thigh": [f"pelvis_imu_{c}" for c in "wxyz"]}
    path = tmp_path / "both.csv"
    path.write_text(csv_text(both))
    code, samples, err = decode(capsys, path)
    assert (code, samples) == (2, [])
    assert err == (
        f"bodynet decode: {path}: line 1: columns pelvis and pelvis_imu are both "
        "on trunk/sacrum (use --map COLUMN=SITE, or COLUMN= to leave one out)\n"
    )
    code, samples, err = decode(capsys, path, "--map", "pelvis_imu=")
    assert code == 0, err
    assert {s["key"] for s in samples} == {"body/trunk/mid/sacrum/raw"}
    assert [s["quat_wxyz"][3] for s in samples] == pytest.approx(
        [q["pelvis"][3] for _, q in ROWS]
    )  # the pelvis column's, not the other's
    sto = tmp_path / "trial.sto"
    sto.write_text("DataType=Quaternion\nendheader\ntime\tpelvis_imu\ttorso_imu\n"
                   "0\t1,0,0,0\t0,1,0,0\n0.01\t1,0,0,0\t0,1,0,0\n")  # fmt: skip
    code, samples, err = decode(capsys, sto, "--map", "torso_imu=trunk/sacrum")
    assert (code, samples) == (2, [])
    assert f"{sto}: line 3: columns pelvis_imu and torso_imu are both on trunk/sacrum" in err
    out = tmp_path / "x.mcap"
    assert main(["process", str(sto), "--map", "torso_imu=trunk/sacrum", "-o", str(out)]) == 2
    assert not out.exists()


def test_a_map_of_a_column_the_file_lacks_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "plain.csv"
    path.write_text(csv_text(PLAIN))
    code, samples, err = decode(capsys, path, "--map", "head_band=trunk/forehead")
    assert (code, samples) == (2, [])
    assert err == (f"bodynet decode: {path}: line 1: --map head_band: no such column "
                   "(the file's: pelvis, left_thigh)\n")  # fmt: skip


@pytest.mark.parametrize(("time", "scale", "args"), [
    ("timestamp_ms", 1e3, ()), ("time_us", 1e6, ()), ("Time (ns)", 1e9, ()),
    ("timestamp", 1e3, ("--time-unit", "ms")), ("t_s", 1.0, ()),
])  # fmt: skip
def test_a_time_column_s_unit_from_its_name_or_the_option(
    time: str, scale: float, args: tuple[str, ...], plain: list, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    path = tmp_path / "units.csv"
    path.write_text(csv_text(PLAIN, time=time, scale=scale))
    code, samples, err = decode(capsys, path, *args)
    assert code == 0, err
    assert [s["t_s"] for s in samples] == pytest.approx([s["t_s"] for s in plain])


def test_milliseconds_are_not_read_as_seconds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A `timestamp` column in ms (0, 10, 20...) would be a recording 1000 times too
    slow: refused with how to say the unit; a contradicting option refused too."""
    path = tmp_path / "ms.csv"
    path.write_text(csv_text(PLAIN, time="timestamp", scale=1e3))
    code, samples, err = decode(capsys, path)
    assert (code, samples) == (2, [])
    assert err.startswith(f"bodynet decode: {path}: line 1: the times step by 10 (median)")
    assert "timestamp_ms" in err
    assert "--time-unit" in err
    out = tmp_path / "x.mcap"
    assert main(["process", str(path), "-o", str(out)]) == 2
    assert not out.exists()
    path.write_text(csv_text(PLAIN, time="timestamp_ms", scale=1e3))
    code, _, err = decode(capsys, path, "--time-unit", "s")
    assert code == 2
    assert "line 1: the time column 'timestamp_ms' is in ms, not s (--time-unit)" in err


def _utf16(path: Path, text: str) -> None:
    path.write_bytes(text.encode("utf-16"))  # with its byte order mark, as Excel's "Unicode text"


SHAPES = {
    "semicolons": lambda p: p.write_text(csv_text(PLAIN, sep=";")),
    "tabs": lambda p: p.write_text(csv_text(PLAIN, sep="\t")),
    "utf-16 tabs": lambda p: _utf16(p, csv_text(PLAIN, sep="\t")),
    "a separator ending each line": lambda p: p.write_text(csv_text(PLAIN, end=",")),
    "_qw names": lambda p: p.write_text(
        csv_text({s: [f"{s}_q{c}" for c in "wxyz"] for s in SEGMENTS})),
    "upper-case names": lambda p: p.write_text(
        csv_text({s: [f"{s}_{c.upper()}" for c in "wxyz"] for s in SEGMENTS})),
}  # fmt: skip


@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_a_csv_written_another_way_gives_the_same_samples(
    shape: str, plain: list, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "shape.csv"
    SHAPES[shape](path)
    code, samples, err = decode(capsys, path)
    assert code == 0, err
    assert samples == plain


def _with_columns(path: Path, names: list[str], cells: list[str]) -> Path:
    """The plain CSV with columns ``names`` added, ``cells`` in every row."""
    lines = csv_text(PLAIN).splitlines()
    path.write_text("".join(f"{line},{','.join(names if i == 0 else cells)}\n"
                            for i, line in enumerate(lines)))  # fmt: skip
    return path


def test_other_sensor_columns_are_left_out_and_told(
    plain: list, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Accelerations (`pelvis_acc_x`..), `FreeAcc_X`.., `gyr_x`, a counter: x/y/z with no
    w are not a quaternion: left out, and said."""
    extra = ["pelvis_acc_x", "pelvis_acc_y", "pelvis_acc_z", "FreeAcc_X", "gyr_x", "counter"]
    path = _with_columns(tmp_path / "acc.csv", extra, ["0.5"] * len(extra))
    code, samples, err = decode(capsys, path)
    assert code == 0, err
    assert samples == plain
    assert "left out 6 columns that are not quaternions (pelvis_acc_x, pelvis_acc_y, " in err


def test_quaternion_columns_with_no_site_are_named(
    plain: list, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Quaternion columns whose names map to no site (OpenSim's body names,
    ``femur_r`` and ``calcn_l``): left out and counted as before, and now named,
    with the option that takes them (they were only counted)."""
    extra = [f"{n}_{c}" for n in ("femur_r", "calcn_l") for c in "wxyz"]
    path = _with_columns(tmp_path / "opensim-names.csv", extra, ["1", "0", "0", "0"] * 2)
    code, samples, err = decode(capsys, path)
    assert code == 0, err
    assert samples == plain
    assert "left out 2 quaternion columns with no site (femur_r, calcn_l): --map" in err


def test_a_dropped_sample_s_empty_cells_are_no_sample_and_counted(
    plain: list, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = csv_text(PLAIN).splitlines()
    cells = lines[11].split(",")
    lines[11] = ",".join(cells[:5] + [""] * 4)  # the thigh's sample at 0.1 s dropped
    cells = lines[21].split(",")
    lines[21] = ",".join(cells[:1] + ["nan"] * 4 + cells[5:])  # and the pelvis's at 0.2 s
    path = tmp_path / "dropped.csv"
    path.write_text("\n".join(lines) + "\n")
    code, samples, err = decode(capsys, path)
    assert code == 0, err
    assert samples == [plain[i] for i in range(len(plain)) if i not in (21, 40)]
    assert "not samples: empty or NaN cells 2" in err
    lines[31] = ",".join([*lines[31].split(",")[:5], "", "", "", "0"])
    path.write_text("\n".join(lines) + "\n")
    code, _, err = decode(capsys, path)
    assert code == 2
    assert "line 32: left_thigh: not four numbers: ',,,0'" in err


def test_a_movella_dot_export_one_sensor_per_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Metadata lines, then PacketCounter,SampleTimeFine (us, wrapping at 2^32),
    Quat_W.., FreeAcc_X..: its one sensor on the site --map names; without one,
    told how."""
    start = 2**32 - 200_000  # the counter wraps 0.2 s in
    lines = ["Movella DOT Export", "Device Tag:,left shank", "Firmware Version:,2.6.0", "",
             "PacketCounter,SampleTimeFine,Quat_W,Quat_X,Quat_Y,Quat_Z,"
             "FreeAcc_X,FreeAcc_Y,FreeAcc_Z,Status"]  # fmt: skip
    for k, (_, quats) in enumerate(ROWS):
        stamp = (start + 10_000 * k) % 2**32
        lines.append(f"{k},{stamp}," + ",".join(f"{c:.9g}" for c in quats["pelvis"]) +
                     ",0.01,0.02,0.03,0")  # fmt: skip
    path = tmp_path / "dot_left_shank.csv"
    path.write_text("\n".join(lines) + "\n")
    code, samples, err = decode(capsys, path)
    assert (code, samples) == (2, [])
    assert f"{path}: line 5: no column is on a site (Quat)" in err
    assert "--map Quat=SITE" in err
    code, samples, err = decode(capsys, path, "--map", "Quat=left-leg/shank")
    assert code == 0, err
    assert {s["key"] for s in samples} == {"body/leg/left/shank/raw"}
    times = [s["t_s"] for s in samples]
    assert [b - a for a, b in itertools.pairwise(times)] == pytest.approx(
        [0.01] * (len(ROWS) - 1))  # fmt: skip
    assert times[0] == pytest.approx(start / 1e6)


STO = "DataType=Quaternion\nendheader\n"


def test_an_sto_with_a_tab_ending_each_line_reads_as_opensim_reads_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rows = "".join(f"{t}\t" + "\t".join(",".join(f"{c:.9g}" for c in q[s]) for s in SEGMENTS)
                   + "\n" for t, q in ROWS)  # fmt: skip
    labels = "time\tpelvis_imu\tfemur_l_imu"
    clean, tabbed = tmp_path / "clean.sto", tmp_path / "tabbed.sto"
    clean.write_text(STO + labels + "\n" + rows)
    tabbed.write_text(STO + labels + "\t\n" + rows.replace("\n", "\t\n"))
    code, samples, err = decode(capsys, clean)
    assert code == 0, err
    assert decode(capsys, tabbed)[:2] == (0, samples)
    utf16 = tmp_path / "utf16.sto"
    _utf16(utf16, clean.read_text())
    assert decode(capsys, utf16)[:2] == (0, samples)
    try:
        import opensim
    except ImportError:
        return
    table = opensim.TimeSeriesTableQuaternion(str(tabbed))
    assert (table.getNumRows(), table.getNumColumns()) == (len(ROWS), 2)


TOLD = {
    "sto by commas": ("x.sto", STO + "time,pelvis_imu_w,pelvis_imu_x\n0,1,0\n", 3,
                      "the column labels are separated by commas: a .sto file separates "
                      "columns with tabs"),
    "sto by spaces": ("x.sto", STO + "time pelvis_imu\n0 1,0,0,0\n", 3,
                      "the column labels are separated by spaces"),
    "sto of four columns": ("x.sto", STO + "time\tpelvis_imu_w\tpelvis_imu_x\tpelvis_imu_y"
                            "\tpelvis_imu_z\n0\t1\t0\t0\t0\n", 3,
                            "four columns per quaternion (pelvis_imu_w..): a .sto cell holds "
                            "the whole quaternion, w,x,y,z, under one label (pelvis_imu)"),
    "decimal commas": ("x.csv", "time;pelvis_w;pelvis_x;pelvis_y;pelvis_z\n0,01;1;0;0;0\n", 2,
                       "time '0,01' is not a number (a decimal comma? numbers are read "
                       "with '.')"),
    "decimal commas in a quaternion": (
        "x.csv", "time;pelvis_w;pelvis_x;pelvis_y;pelvis_z\n0.01;0,5;0;0;0\n", 2,
        "pelvis: not four numbers: '0,5,0,0,0' (a decimal comma? numbers are read with '.')"),
    "one component in two columns": (
        "x.csv", "time,pelvis_w,pelvis_x,pelvis_y,pelvis_z,pelvis_qw\n0,1,0,0,0,1\n", 1,
        "pelvis: two columns of its w: 'pelvis_w' and 'pelvis_qw'"),
    "utf-16 without its mark": ("x.csv", "time,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n", 1,
                                "NUL characters: UTF-16 text? (save it as UTF-8)"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(TOLD))
def test_a_file_written_another_way_is_told_how(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    name, text, line, told = TOLD[case]
    path = tmp_path / name
    if case.startswith("utf-16"):
        path.write_bytes(text.encode("utf-16-le"))
    else:
        path.write_text(text)
    code, samples, err = decode(capsys, path)
    assert (code, samples) == (2, [])
    assert err == f"bodynet decode: {path}: line {line}: {told}" + err.split(told, 1)[1]
    assert err.count("\n") == 1


def test_a_quaternion_that_is_no_number_gets_no_decimal_comma_hint(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The cells are joined with commas in the message: that comma is no hint
    of a decimal comma (every bad quaternion got one)."""
    path = tmp_path / "x.csv"
    path.write_text("time,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n0,abc,0,0,0\n")
    code, samples, err = decode(capsys, path)
    assert (code, samples) == (2, [])
    assert err == f"bodynet decode: {path}: line 2: pelvis: not four numbers: 'abc,0,0,0'\n"


def test_a_metadata_line_with_a_cell_t_is_not_the_header(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An exporter's metadata line ``t,5`` (a cell named as a time column) before
    the header: the header is the line with quaternion columns too."""
    path = tmp_path / "x.csv"
    path.write_text("t,5\n" + csv_text(PLAIN))
    code, samples, err = decode(capsys, path)
    assert code == 0, err
    assert len(samples) == 2 * len(ROWS)
