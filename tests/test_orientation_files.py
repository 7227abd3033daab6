"""Orientation files in: OpenSense `.sto` and per-segment quaternion CSV through
`bodynet decode` and `bodynet process`, with their own timestamps."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
from scipy.spatial.transform import Rotation

from bodynet.cli.main import main
from bodynet.clients.mcap_store import read_poses
from bodynet.core.codecs.orientation import OrientationFileError, parse_sto
from bodynet.core.messages import Quat
from bodynet.core.profile import mount
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags
from bodynet.nodes.motion import ROUTINES

BODYNET = Path(sys.executable).with_name("bodynet")


def is_measured(frame: object, dof: str) -> bool:  # core.codecs.pose.is_measured once it lands
    return getattr(frame, "flags", {}).get(dof) in (None, "clamped")


def bodynet(*args: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BODYNET), *map(str, args)], capture_output=True, text=True,
                          timeout=120, check=False)  # fmt: skip


def test_an_sto_export_processed_again_gives_the_same_angles(
    body_mcap: Path, tmp_path: Path
) -> None:
    """`export sto` then `process trial.sto`: every measured angle comes back."""
    sto = tmp_path / "trial.sto"
    assert main(["export", "sto", str(body_mcap), "-o", str(sto)]) == 0
    out = tmp_path / "again.mcap"
    assert main(["process", str(sto), "--tpose-s", "0", "-o", str(out)]) == 0  # format: suffix
    before = dict(read_poses(body_mcap))
    after = dict(read_poses(out))
    assert sorted(after) == sorted(before)  # the file's own times, frame for frame
    compared, close = 0, 0
    for t, frame in before.items():
        again = after[t]
        for segment, (_, q) in frame.segments.items():
            diff = Rotation.from_quat(again.segments[segment][1], scalar_first=True)
            diff = diff * Rotation.from_quat(q, scalar_first=True).inv()
            assert diff.magnitude() < 1e-4, (t, segment)  # the file's 8 decimals
        for name, value in frame.angles_deg.items():
            if is_measured(frame, name):
                # 0.05 deg where the shoulder nears its singular pose (flexion and
                # rotation about one axis), a ten-thousandth elsewhere
                error = abs(again.angles_deg[name] - value)
                assert error < 0.05, (t, name)
                compared += 1
                close += error < 1e-3
    assert compared > 1000
    assert close >= 0.95 * compared


def test_a_quaternion_csv_processed_to_the_true_angles(tmp_path: Path) -> None:
    """Segment orientations (ideal tags mounted square on their segments) as a CSV
    with irregular timestamps; `--map` puts one renamed column on its site."""
    motion = ROUTINES["upper-body"]
    tags = imu_tags()
    body = BodyEmulator(motion, tags, realism=Realism.ideal(), seed=3)
    names = {t.node: mount(t.site).segment for t in tags}
    names[1] = "headband"  # not a default name: mapped below
    header = ["time"] + [f"{names[t.node]}_{c}" for t in tags for c in "wxyz"]
    times = [0.5 + 0.021 * k + 0.004 * (k % 3) for k in range(120)]  # never within a tick
    rows = []
    for t in times:
        readings, _ = body.sample(t)
        quats = {r.node: r.wxyz for r in readings if isinstance(r, Quat)}
        rows.append([repr(t)] + [repr(c) for tag in tags for c in quats[tag.node]])
    csv_file = tmp_path / "trial.csv"
    csv_file.write_text("\n".join(",".join(r) for r in [header, *rows]) + "\n")
    out = tmp_path / "trial.mcap"
    assert main(["process", str(csv_file), "--tpose-s", "0", "--map",
                 "headband=trunk/forehead", "-o", str(out)]) == 0  # fmt: skip
    poses = list(read_poses(out))
    assert [t / 1e9 for t, _ in poses] == pytest.approx(times)
    for t_ns, frame in poses[::10]:
        truth = motion.angles(t_ns / 1e9)
        for name in ("left_shoulder_abduction_deg", "right_elbow_flexion_deg",
                     "neck_rotation_deg", "lumbar_rotation_deg"):  # fmt: skip
            assert frame.angles_deg[name] == pytest.approx(truth.get(name, 0.0), abs=0.01), name
    assert "neck_rotation_deg" not in poses[0][1].flags  # the mapped head column counts


MALFORMED = {
    "missing endheader": ("DataType=Quaternion\nversion=3\ntime\tpelvis_imu\n0\t1,0,0,0\n", 4),
    "bad cell": ("DataType=Quaternion\nendheader\ntime\tpelvis_imu\n0\t1,0,0,0\n"
                 "0.01\t1,0,zero,0\n", 5),
    "non-unit quaternion": ("DataType=Quaternion\nendheader\ntime\tpelvis_imu\n0\t1,0,0,0\n"
                            "0.01\t2,0,0,0\n", 5),
    "unsorted time": ("DataType=Quaternion\nendheader\ntime\tpelvis_imu\n0.02\t1,0,0,0\n"
                      "0.01\t1,0,0,0\n", 5),
    "short row": ("DataType=Quaternion\nendheader\ntime\tpelvis_imu\ttorso_imu\n"
                  "0\t1,0,0,0\n", 4),
    "positions, not quaternions": ("version=3\nDataType=Vec3\nOpenSimVersion=4.6\nendheader\n"
                                   "time\tpelvis_imu\n0\t1,0,0\n", 2),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_a_malformed_sto_is_refused_naming_its_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text, line = MALFORMED[case]
    sto = tmp_path / "bad.sto"
    sto.write_text(text)
    with pytest.raises(OrientationFileError, match=f"^line {line}: "):
        parse_sto(text.splitlines())
    for argv in (["decode", "--format", "sto", str(sto)],
                 ["process", str(sto), "-o", str(tmp_path / "x.mcap")]):  # fmt: skip
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"bad.sto: line {line}: " in err, err
        assert "Traceback" not in err
    assert not (tmp_path / "x.mcap").exists()


def test_a_sto_file_named_csv_is_told_what_it_looks_like(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An OpenSense .sto saved as .csv: read as a CSV it has no quaternion
    columns, and the error says it looks like a .sto and how to read it; a .sto
    named so gets no such hint with its own error."""
    text = "DataType=Quaternion\nversion=3\nendheader\ntime\tpelvis_imu\n0\t1,0,0,0\n"
    misnamed = tmp_path / "trial.csv"
    misnamed.write_text(text)
    assert main(["decode", "--format", "orientation-csv", str(misnamed)]) == 2
    err = capsys.readouterr().err
    assert "no quaternion columns" in err
    assert "it looks like an OpenSense orientation file (--format sto, named .sto)" in err
    bad = tmp_path / "bad.sto"
    bad.write_text(MALFORMED["bad cell"][0])
    assert main(["decode", "--format", "sto", str(bad)]) == 2
    assert "looks like" not in capsys.readouterr().err


STO_HEAD = "DataType=Quaternion\n{}\nendheader\ntime\tpelvis_imu\n0\t1,0,0,0\n"
CSV_HEAD = "time,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n0,1,0,0,0\n"
#: read as a table, refused by the reader: the header's values, a time no sample holds
UNUSABLE = {
    "start not a number": ("bad.sto", STO_HEAD.format("bodynet_start_ns=abc"), 2),
    "start empty": ("bad.sto", STO_HEAD.format("bodynet_start_ns="), 2),
    "start nan": ("bad.sto", STO_HEAD.format("bodynet_start_ns=nan"), 2),
    "start inf": ("bad.sto", STO_HEAD.format("bodynet_start_ns=inf"), 2),
    "start and time past 64 bits": (
        "bad.sto", STO_HEAD.format("bodynet_start_ns=9223372036000000000") + "1e3\t1,0,0,0\n", 6),
    "rotation nan": ("bad.sto", STO_HEAD.format("sensor_to_opensim_rotations=nan 0 0"), 2),
    "rotation inf": ("bad.sto", STO_HEAD.format("sensor_to_opensim_rotations=0 inf 0"), 2),
    "rotation 1e400": ("bad.sto", STO_HEAD.format("sensor_to_opensim_rotations=0 0 1e400"), 2),
    "rotation in degrees": ("bad.sto", STO_HEAD.format("sensor_to_opensim_rotations=90 0 0"), 2),
    "time 1e300": ("bad.csv", CSV_HEAD + "1e300,1,0,0,0\n", 3),
    "time -1e30": ("bad.csv", "time,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n-1e30,1,0,0,0\n", 2),
    "field past csv's limit": ("bad.csv", CSV_HEAD + '0.1,"' + "1" * 140_000 + '",0,0,0\n', 3),
    "one 1 MB line": ("bad.csv", CSV_HEAD + "9" * 1_000_000 + "\n", 3),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(UNUSABLE))
def test_an_unusable_header_or_time_is_refused_naming_its_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """What the table holds but no sample can (a start or rotation that is no
    number, a time past a raw sample's 64-bit ns): one line naming the file's
    line, exit 2, nothing written, and no NaN or Infinity printed as JSON."""
    name, text, line = UNUSABLE[case]
    path = tmp_path / name
    path.write_text(text)
    fmt = "sto" if name.endswith(".sto") else "orientation-csv"
    for argv in (["decode", "--format", fmt, str(path)],
                 ["process", "--format", fmt, str(path), "-o", str(tmp_path / "x.mcap")],
                 ["calibrate", "tpose", "--from", str(path), "--format", fmt,
                  "--profile", str(tmp_path / "p.toml")]):  # fmt: skip
        assert main(argv) == 2, argv
        out, err = capsys.readouterr()
        assert err.count(f"{name}: line {line}: ") == 1, (argv, err)
        assert err.count("\n") == 1, (argv, err)
        assert "NaN" not in out
        assert "Infinity" not in out
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_a_malformed_file_through_the_real_command_shows_no_traceback(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("time,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n0,1,0,0,0\n0.01,1,0,0,nan5\n")
    result = bodynet("process", bad, "-o", tmp_path / "x.mcap")
    assert result.returncode == 2
    assert "bad.csv: line 3: pelvis: not four numbers" in result.stderr
    assert "Traceback" not in result.stderr


def test_our_sto_reader_agrees_with_opensims(body_mcap: Path, tmp_path: Path) -> None:
    """The same file through OpenSim's own TimeSeriesTableQuaternion and through
    ours: the same labels, times and quaternions."""
    osim = pytest.importorskip("opensim")
    sto = tmp_path / "trial.sto"
    assert bodynet("export", "sto", body_mcap, "-o", sto).returncode == 0
    ours = parse_sto(sto.read_text().splitlines())
    table = osim.TimeSeriesTableQuaternion(str(sto))
    assert list(table.getColumnLabels()) == ours.columns
    assert [table.getIndependentColumn()[i] for i in range(table.getNumRows())] == pytest.approx(
        [t for _, t, _ in ours.rows]
    )
    flat = table.flatten()  # OpenSim's own split of each quaternion: <label>_1.._4 = w, x, y, z
    labels = list(flat.getColumnLabels())
    for c, label in enumerate(ours.columns):
        parts = [flat.getDependentColumnAtIndex(labels.index(f"{label}_{k}")) for k in range(1, 5)]
        for r, (_, _, quats) in enumerate(ours.rows):
            theirs = [float(part[r]) for part in parts]
            if c in quats:
                diff = (
                    Rotation.from_quat(theirs, scalar_first=True)
                    * Rotation.from_quat(quats[c], scalar_first=True).inv()
                )
                assert diff.magnitude() < 1e-6, (label, r)
            else:
                assert all(math.isnan(v) for v in theirs), (label, r)


def test_calibrated_from_another_file_of_the_session(tmp_path: Path) -> None:
    """Tags at random mounts: a static T-pose file and a trial file that starts
    moving at once. `--calibration static.csv` takes the T-pose from the first;
    without it the trial's own start (no T-pose) gives wrong angles, and asked
    for (`--tpose-s 1`) is refused."""
    from bodynet.core.skeleton import TPOSE
    from bodynet.nodes.motion import Routine

    upper = ROUTINES["upper-body"].angles
    motion = Routine("session", "", lambda t: dict(TPOSE) if t < 1.0 else upper(t))
    tags = imu_tags()
    body = BodyEmulator(motion, tags, realism=Realism(0.0, 0.0, 0.0, 0.0, 0.0, True), seed=5)
    header = ["time"] + [f"{mount(t.site).segment}_{c}" for t in tags for c in "wxyz"]

    def write(path: Path, times: list[float]) -> None:
        rows = [header]
        for t in times:
            quats = {r.node: r.wxyz for r in body.sample(t)[0] if isinstance(r, Quat)}
            rows.append([repr(t)] + [repr(c) for tag in tags for c in quats[tag.node]])
        path.write_text("\n".join(",".join(r) for r in rows) + "\n")

    write(tmp_path / "static.csv", [0.02 * k for k in range(50)])
    write(tmp_path / "trial.csv", [1.5 + 0.02 * k for k in range(100)])
    static = ["--calibration", str(tmp_path / "static.csv")]
    trial = ["process", str(tmp_path / "trial.csv")]
    assert main([*trial, "--tpose-s", "1", "-o", str(tmp_path / "refused.mcap")]) == 1
    assert not (tmp_path / "refused.mcap").exists()
    for calibration, close in ((["--tpose-s", "1", *static], True), ([], False)):
        out = tmp_path / f"trial{len(calibration)}.mcap"
        assert main([*trial, *calibration, "-o", str(out)]) == 0
        errors = [
            abs(frame.angles_deg[name] - motion.angles(t_ns / 1e9).get(name, 0.0))
            for t_ns, frame in read_poses(out)
            for name in ("left_shoulder_abduction_deg", "right_elbow_flexion_deg")
        ]
        assert (max(errors) < 0.01) is close, max(errors)


def test_a_csv_saved_with_a_byte_order_mark_reads_as_without(tmp_path: Path) -> None:
    """Excel's "CSV UTF-8" starts the file with a byte order mark: the same rows,
    not "no time column"."""
    text = "time,pelvis_w,pelvis_x,pelvis_y,pelvis_z\n0.0,1,0,0,0\n0.01,0,1,0,0\n"
    plain, marked = tmp_path / "plain.csv", tmp_path / "marked.csv"
    plain.write_text(text, encoding="utf-8")
    marked.write_text(text, encoding="utf-8-sig")
    assert marked.read_bytes().startswith(b"\xef\xbb\xbf")
    decoded = [bodynet("decode", "--format", "orientation-csv", path) for path in (plain, marked)]
    assert [d.returncode for d in decoded] == [0, 0], decoded[1].stderr
    assert decoded[1].stdout == decoded[0].stdout
    assert decoded[0].stdout.count("\n") >= 2
