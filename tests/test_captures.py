"""Golden captures through the real `bodynet decode` command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import can
import pytest

from bodynet.core.errors import Reason
from bodynet.nodes.captures import CaptureStats, can_log_messages, read_capture

BODYNET = Path(sys.executable).with_name("bodynet")
CAPTURES = [
    ("can-log", "smartsuit_arm.log"),
    ("concentrator", "concentrator.cap"),
    ("imu-central", "imu_central.txt"),
]


def run_decode(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(BODYNET), "decode", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.parametrize(("fmt", "name"), CAPTURES)
def test_decode_matches_what_the_capture_writer_injected(
    fmt: str, name: str, data_dir: Path
) -> None:
    manifest = json.loads((data_dir / f"{name}.manifest.json").read_text())
    stats = CaptureStats()
    samples = list(read_capture(data_dir / name, fmt, stats))
    assert len(samples) == stats.decoded == manifest.pop("decoded")
    assert stats.no_new_data == manifest.pop("no_new_data", 0)
    assert stats.sensor_absent == manifest.pop("sensor_absent", 0)
    assert stats.foreign == manifest.pop("foreign", {})  # other devices' frames: not rejected
    assert {str(k): v for k, v in stats.rejected.items()} == manifest


@pytest.mark.parametrize(("fmt", "name"), CAPTURES)
def test_decode_command_output_is_golden(fmt: str, name: str, data_dir: Path) -> None:
    result = run_decode("--format", fmt, data_dir / name)
    assert result.returncode == 0, result.stderr
    assert result.stdout == (data_dir / f"{name}.expected.jsonl").read_text()
    summary = result.stderr.strip().splitlines()
    assert len(summary) == 1
    assert summary[0].startswith(f"decoded {len(result.stdout.splitlines())}, rejected ")


def test_decode_fields(data_dir: Path) -> None:
    result = run_decode("--format", "imu-central", "--rate-hz", "10", data_dir / "imu_central.txt")
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert set(rows[0]) == {"node", "key", "t_s", "quat_wxyz"}
    assert rows[0]["key"] == "body/trunk/mid/forehead/raw"
    # one tick = each sensor's line once; t_s = tick index / rate
    ticks = sorted({r["t_s"] for r in rows})
    assert ticks[:3] == [0.0, 0.1, 0.2]
    result = run_decode("--format", "concentrator", data_dir / "concentrator.cap")
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert set(rows[0]) == {"node", "key", "t_s", "encoder", "accel"}
    assert [r["t_s"] for r in rows[:3]] == [0.0, 0.022, 0.044]  # reply index x 22 ms
    assert result.stderr.startswith("decoded 123, rejected 5 (")


def test_can_log_keeps_capture_time_and_survives_garbled_lines(tmp_path: Path) -> None:
    log = tmp_path / "x.log"
    log.write_text(
        "(12.500000) can0 0006FFFF#0100020003000400\n"
        "(12.5 can0 nonsense\n"
        "(12.510000) can0 000AFFFF#0500060007000800\n"
    )
    result = run_decode("--format", "can-log", log)
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert rows == [
        {
            "node": 1,
            "key": "body/arm/left/shoulder/raw",
            "t_s": 12.5,
            "encoder": 1,
            "accel": [2, 3, 4],
        },
        {
            "node": 2,
            "key": "body/arm/left/elbow/raw",
            "t_s": 12.51,
            "encoder": 5,
            "accel": [6, 7, 8],
        },
    ]
    assert result.stderr.strip() == (
        f"decoded 2, rejected 1 ({Reason.GARBAGE}: 1); skipped garbled line 2"
    )


def test_a_can_log_time_no_sample_holds_costs_only_its_line(tmp_path: Path) -> None:
    """python-can reads "(nan)", "(inf)" and "(1e300)" as a line's time: each such
    line is counted with its number and skipped (decode, and process, whose
    recording holds 64-bit ns), the frames around it kept."""
    log = tmp_path / "x.log"
    log.write_text(
        "(12.500000) can0 0006FFFF#0100020003000400\n"
        "(nan) can0 000AFFFF#0500060007000800\n"
        "(inf) can0 000AFFFF#0500060007000800\n"
        "(1e300) can0 000AFFFF#0500060007000800\n"
        "(-1e30) can0 000AFFFF#0500060007000800\n"
        "(12.510000) can0 000AFFFF#0500060007000800\n"
    )
    told = (f"decoded 2, rejected 4 ({Reason.NOT_FINITE}: 2, {Reason.OUT_OF_RANGE}: 2); "
            "skipped garbled line 2, line 3, line 4, line 5")  # fmt: skip
    result = run_decode("--format", "can-log", log)
    assert result.returncode == 0, result.stderr
    assert [json.loads(line)["t_s"] for line in result.stdout.splitlines()] == [12.5, 12.51]
    assert result.stderr.strip() == told
    out = tmp_path / "x.mcap"
    result = subprocess.run([str(BODYNET), "process", "--format", "can-log", str(log),
                             "-o", str(out)], capture_output=True, text=True, timeout=60,
                            check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert result.stderr.strip().endswith(told), result.stderr
    assert out.exists()


def test_can_log_in_other_python_can_formats(tmp_path: Path, data_dir: Path) -> None:
    """An .asc and a .blf written by python-can decode to the same samples."""
    messages = list(can_log_messages(data_dir / "smartsuit_arm.log", CaptureStats()))
    expected = [
        {k: v for k, v in json.loads(line).items() if k != "t_s"}
        for line in (data_dir / "smartsuit_arm.log.expected.jsonl").read_text().splitlines()
    ]
    for suffix in (".asc", ".blf"):
        path = tmp_path / f"capture{suffix}"
        with can.Logger(path) as logger:
            for msg in messages:
                logger.on_message_received(msg)
        result = run_decode("--format", "can-log", path)
        rows = [json.loads(line) for line in result.stdout.splitlines()]
        assert [{k: v for k, v in r.items() if k != "t_s"} for r in rows] == expected, suffix


def test_missing_file_is_a_clear_error(tmp_path: Path) -> None:
    result = run_decode("--format", "imu-central", tmp_path / "absent.txt")
    assert result.returncode == 2
    assert "cannot read" in result.stderr
    assert "Traceback" not in result.stderr


def _arm_frames(data_dir: Path) -> list[can.Message]:
    return [m for m in can_log_messages(data_dir / "smartsuit_arm.log", CaptureStats())
            if not m.is_error_frame and not m.is_remote_frame]  # fmt: skip


def test_a_relative_asc_log_reads_as_its_absolute_twin(tmp_path: Path, data_dir: Path) -> None:
    """Vector's `timestamps relative` (each frame's time since the one before; python-can's
    reader gives them as they are): the same samples at the same times as the
    absolute log python-can's writer makes of the frames, and as many ticks."""
    absolute, relative = tmp_path / "abs.asc", tmp_path / "rel.asc"
    with can.ASCWriter(absolute) as writer:
        for msg in _arm_frames(data_dir):
            writer.on_message_received(msg)
    lines, last = [], 0.0
    for line in absolute.read_text().splitlines():
        head = line.split(maxsplit=1)
        try:
            t = float(head[0])
        except (ValueError, IndexError):
            lines.append(line.replace("timestamps absolute", "timestamps relative"))
            continue
        lines.append(f"{t - last:.6f} {head[1]}")
        last = t
    relative.write_text("\n".join(lines) + "\n")
    assert "timestamps relative" in relative.read_text()
    decoded = [run_decode("--format", "can-log", path) for path in (absolute, relative)]
    assert [d.returncode for d in decoded] == [0, 0], decoded[1].stderr
    samples = [[json.loads(line) for line in d.stdout.splitlines()] for d in decoded]
    assert len(samples[0]) == 400
    assert [s["t_s"] for s in samples[1]] == pytest.approx([s["t_s"] for s in samples[0]])
    assert [{**s, "t_s": 0} for s in samples[1]] == [{**s, "t_s": 0} for s in samples[0]]
    told = []
    for path in (absolute, relative):
        argv = [str(BODYNET), "process", str(path), "-o", f"{path}.mcap"]
        result = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
        assert result.returncode == 0, result.stderr
        told.append(result.stderr.split(" ticks")[0].split("\n")[-1])
    assert told[1] == told[0] == "100"


def shifted(msg: can.Message, back_s: float) -> can.Message:
    return can.Message(
        timestamp=msg.timestamp - back_s,
        arbitration_id=msg.arbitration_id,
        data=msg.data,
        is_extended_id=msg.is_extended_id,
    )


def test_a_can_log_whose_clock_steps_back_is_refused_naming_the_line(
    tmp_path: Path, data_dir: Path
) -> None:
    """A candump log whose times go back an hour halfway and stay back: refused with
    the line (not half the ticks); one frame's time out of order is only itself."""
    frames = _arm_frames(data_dir)
    half = len(frames) // 2
    log = tmp_path / "step.log"
    with can.CanutilsLogWriter(log) as writer:
        for i, msg in enumerate(frames):
            writer.on_message_received(shifted(msg, 3600.0 if i >= half else 0.0))
    result = run_decode("--format", "can-log", log)
    assert result.returncode == 2
    assert result.stderr.startswith(f"bodynet decode: {log}: line {half + 1}: time "), result.stderr
    assert "goes back" in result.stderr
    assert result.stderr.count("\n") == 1
    out = tmp_path / "x.mcap"
    result = subprocess.run([str(BODYNET), "process", str(log), "-o", str(out)],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2
    assert f"{log}: line {half + 1}: " in result.stderr
    assert "Traceback" not in result.stderr
    assert not out.exists()
    one = tmp_path / "one.log"  # only one frame an hour back: it costs itself
    with can.CanutilsLogWriter(one) as writer:
        for i, msg in enumerate(frames):
            writer.on_message_received(shifted(msg, 3600.0 if i == half else 0.0))
    stats = CaptureStats()
    kept = list(can_log_messages(one, stats))
    assert len(kept) == len(frames) - 1
    assert stats.bad_places == [f"line {half + 1}"]
    assert stats.rejected[Reason.OUT_OF_ORDER] == 1


def test_candump_screen_output_is_told_to_record_with_l(tmp_path: Path, data_dir: Path) -> None:
    """`candump can0` prints frames for the eye, not a log: said, with how to record one."""
    screen = tmp_path / "screen.log"
    screen.write_text("".join(
        f"  can0  {m.arbitration_id:08X}   [{m.dlc}]  {' '.join(f'{b:02X}' for b in m.data)}\n"
        for m in _arm_frames(data_dir)))  # fmt: skip
    result = run_decode("--format", "can-log", screen)
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1] == (
        f"bodynet decode: no can-log samples in {screen}; it looks like candump's screen "
        "output, not a log: record with `candump -l` (or `candump -L`)"
    )
