"""bodynet report: each statistic against inputs whose answer is known
independently, then the whole report from a real processed recording."""

from __future__ import annotations

import json
import math
import threading
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import zenoh

from bodynet.cli.main import main as cli_main
from bodynet.clients import stats
from bodynet.clients.mcap_store import McapSink, read_poses, read_raw, read_truth
from bodynet.clients.recorder import Recorder
from bodynet.clients.report import load_recording
from bodynet.core import keys
from bodynet.core.codecs import pose, smartsuit_can
from bodynet.core.keys import LEFT_ARM, Site, Stream
from bodynet.core.profile import SMARTSUIT_SITES
from bodynet.core.skeleton import build_skeleton
from bodynet.nodes.emulator import BodyEmulator, Realism, Truth, smartsuit_sensors
from bodynet.nodes.motion import ROUTINES, Routine
from bodynet.nodes.services import truth_sink

# -- the pure statistics -------------------------------------------------------


def test_rom_and_repetitions_of_a_sine_of_known_amplitude_and_cycles() -> None:
    t = np.arange(0, 5.0, 0.01)  # 5 cycles at 1 Hz, 100 samples each
    x = 20.0 + 30.0 * np.sin(2 * math.pi * t)
    rom = stats.range_of_motion(x)
    assert rom.minimum == pytest.approx(-10.0, abs=1e-3)
    assert rom.maximum == pytest.approx(50.0, abs=1e-3)
    assert rom.span == pytest.approx(60.0, abs=1e-3)
    peaks = stats.repetitions(x)
    assert len(peaks) == 5
    assert t[peaks] == pytest.approx([0.25, 1.25, 2.25, 3.25, 4.25])


def test_repetitions_ignore_noise_and_small_wobbles() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0, 6.0, 0.01)
    # three 0-90-0 cycles, a 3-degree wobble on top and sensor noise
    x = 45 * (1 - np.cos(2 * math.pi * t / 2)) + 3 * np.sin(2 * math.pi * 7 * t)
    x += rng.normal(0, 0.5, t.size)
    assert len(stats.repetitions(x)) == 3
    still = rng.normal(10.0, 0.5, t.size)  # a still channel: noise only
    assert len(stats.repetitions(still)) == 0


def test_trials_meet_at_the_valleys_between_peaks() -> None:
    t = np.arange(0, 3.0, 0.01)
    x = 45 * (1 - np.cos(2 * math.pi * t))  # 0 at t = 0, 1, 2, (3)
    bounds = stats.trial_bounds(x, stats.repetitions(x))
    assert [(round(t[a], 2), round(t[b], 2)) for a, b in bounds] == [
        (0.0, 1.0),
        (1.0, 2.0),
        (2.0, 2.99),
    ]


def test_rms_error_and_correlation_of_synthetic_signals() -> None:
    t = np.linspace(0, 4, 4000, endpoint=False)  # whole cycles at 1 Hz
    ref = 45 * np.sin(2 * math.pi * t)
    assert stats.rms_error(ref + 2.5, ref) == pytest.approx(2.5)
    # an error that is a sine of amplitude a has RMS a / sqrt(2)
    assert stats.rms_error(ref + 3 * np.sin(2 * math.pi * 5 * t), ref) == pytest.approx(
        3 / math.sqrt(2)
    )
    # a gain and an offset do not change the correlation; a phase shift phi makes it cos(phi)
    assert stats.correlation(2 * ref + 7, ref) == pytest.approx(1.0)
    shifted = 45 * np.sin(2 * math.pi * t + math.pi / 3)
    assert stats.correlation(shifted, ref) == pytest.approx(0.5, abs=1e-9)
    with pytest.raises(stats.StatsError, match="differ in length"):
        stats.rms_error(ref[:-1], ref)


def test_repeatability_range_and_sd_of_trial_means() -> None:
    shape = np.sin(np.linspace(0, math.pi, 101))
    offsets = np.array([1.0, 3.0, 2.0, 6.0])
    trials = shape + offsets[:, None]
    rep = stats.repeatability(trials)
    assert rep.trial_means == pytest.approx(shape.mean() + offsets)
    assert rep.range == pytest.approx(5.0)
    # SD of 1, 3, 2, 6 with n - 1: sqrt(14 / 3)
    assert rep.sd == pytest.approx(math.sqrt(14 / 3))
    with pytest.raises(stats.StatsError, match="two or more trials"):
        stats.repeatability(trials[:1])


# Shrout & Fleiss (1979), Table 2: six targets rated by four judges, and their
# published ICCs (Table 4): ICC(1,1) .17, ICC(2,1) .29, ICC(3,1) .71,
# ICC(1,4) .44, ICC(2,4) .62, ICC(3,4) .91.
SHROUT_FLEISS = np.array(
    [[9, 2, 5, 8], [6, 1, 3, 2], [8, 4, 6, 8], [7, 1, 2, 6], [10, 5, 6, 9], [6, 2, 4, 7]]
)


def test_icc_matches_shrout_and_fleiss() -> None:
    result = stats.icc(SHROUT_FLEISS.T)  # rows are trials (judges), columns targets
    assert result.form == "ICC(3,1)"
    assert result.value == pytest.approx(0.71, abs=0.005)
    assert result.ci95[0] < result.value < result.ci95[1]
    published = {"ICC(1,1)": 0.17, "ICC(2,1)": 0.29, "ICC(3,1)": 0.71,
                 "ICC(1,k)": 0.44, "ICC(2,k)": 0.62, "ICC(3,k)": 0.91}  # fmt: skip
    for name, value in published.items():
        assert result.forms[name] == pytest.approx(value, abs=0.005), name
    assert stats.icc(SHROUT_FLEISS.T, "ICC2").value == pytest.approx(0.29, abs=0.005)


def test_icc_refuses_too_few_trials_and_a_flat_channel() -> None:
    with pytest.raises(stats.StatsError, match="two or more trials"):
        stats.icc(SHROUT_FLEISS.T[:1])
    with pytest.raises(stats.StatsError, match="does not move"):
        stats.icc(np.full((3, 10), 4.0))


def test_type_a_of_a_known_sample() -> None:
    result = stats.type_a([1.0, 2.0, 3.0, 4.0, 5.0])
    assert result.n == 5
    assert result.mean == pytest.approx(3.0)
    assert result.variance == pytest.approx(2.5)
    assert result.sd == pytest.approx(math.sqrt(2.5))
    assert result.variance_of_mean == pytest.approx(0.5)
    assert result.sd_of_mean == pytest.approx(math.sqrt(0.5))


def test_still_window_finds_the_stretch_that_does_not_move() -> None:
    rng = np.random.default_rng(2)
    t = np.arange(0, 10.0, 0.01)
    x = np.column_stack([40 * np.sin(2 * math.pi * 0.5 * t), 20 * np.cos(2 * math.pi * t)])
    still = (t >= 6.0) & (t < 8.5)
    x[still] = [12.0, -3.0]
    x += rng.normal(0, 0.05, x.shape)
    start, stop = stats.still_window(t, x, 2.0)
    assert t[start] >= 6.0
    assert t[stop - 1] < 8.5
    assert t[stop - 1] - t[start] == pytest.approx(2.0)
    with pytest.raises(stats.StatsError, match="shorter than"):
        stats.still_window(t, x, 20.0)


# -- ground truth in recordings ------------------------------------------------


def test_a_recording_from_before_the_stale_reason_leaves_out_what_rests_on_a_stale_sensor(
    tmp_path: Path,
) -> None:
    """Poses as an older gateway wrote them: the elbow module listed stale in the
    second and third, no dof flagged for it. The elbow and wrist samples of those
    are left out, counted ``stale``; the knee keeps all three."""
    key = keys.raw_key("arm", "left", "elbow")
    path = tmp_path / "old.mcap"
    sink = McapSink(path)
    for i in range(3):
        angles = {"left_elbow_flexion_deg": 10.0 * i, "left_wrist_flexion_deg": 1.0 * i,
                  "left_knee_flexion_deg": 5.0 + i}  # fmt: skip
        t_ns = 1_700_000_000_000_000_000 + i * 10_000_000
        frame = pose.PoseFrame(i, t_ns, angles, {}, {}, {}, stale=[key] if i else [])
        sink.write_pose(keys.pose_key(), frame, t_ns)
    sink.close()
    rec = load_recording(path)
    assert rec.left_out == {"left_elbow_flexion_deg": {"stale": 2},
                            "left_wrist_flexion_deg": {"stale": 2}}  # fmt: skip
    assert rec.angles["left_elbow_flexion_deg"].notna().tolist() == [True, False, False]
    assert rec.angles["left_knee_flexion_deg"].tolist() == [5.0, 6.0, 7.0]


def test_recorder_keeps_the_ground_truth_emulated_nodes_publish(
    zsession: zenoh.Session, tmp_path: Path
) -> None:
    out = tmp_path / "truth.mcap"
    recorder = Recorder(zsession, out, [keys.all_truth()])
    put = truth_sink(zsession, {2: Site(LEFT_ARM, "elbow")})
    t0 = 1_700_000_000_000_000_000
    try:
        for i in range(20):
            put(2, Truth({"left_elbow_flexion_deg": 4.5 * i}, "left_forearm", (1, 0, 0, 0)),
                t0 + i * 10_000_000)  # fmt: skip
        deadline = time.monotonic() + 20
        while recorder.messages < 20 and time.monotonic() < deadline:
            threading.Event().wait(0.02)
    finally:
        recorder.close()
    got = list(read_truth(out))
    assert [topic for topic, _, _ in got] == [Site(LEFT_ARM, "elbow").key(Stream.TRUTH)] * 20
    assert [t for _, t, _ in got] == [t0 + i * 10_000_000 for i in range(20)]
    assert [a["left_elbow_flexion_deg"] for _, _, a in got] == [4.5 * i for i in range(20)]


# -- the whole report from a real recording ------------------------------------

STILL_S, CYCLES = 2.5, 5
T0 = 1_700_000_000.0


def _routine_angles(t: float) -> dict[str, float]:
    """Still for STILL_S, then the elbow-slow routine (0-90-0 deg at 0.6 Hz)."""
    return ROUTINES["elbow-slow"].angles(max(0.0, t - STILL_S))


@pytest.fixture(scope="module")
def arm_recording(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A left arm's CAN capture from the emulator (noisy sensors), processed
    offline by `bodynet process`; beside it the routine's true angles as a CSV,
    and a copy of the recording with that truth recorded as emulated nodes publish it."""
    folder = tmp_path_factory.mktemp("report")
    body = BodyEmulator(Routine("still-then-elbow", "", _routine_angles),
                        smartsuit_sensors([LEFT_ARM]), realism=Realism(), seed=3)  # fmt: skip
    arm_channels = [n for n in build_skeleton().angle_names() if n.startswith("left_")][:7]
    lines, rows, truths = [], [], []
    for tick in range(int((STILL_S + CYCLES / 0.6 + 0.3) * 100)):
        t = tick * 0.01
        readings, truth = body.sample(t)
        for r in readings:
            f = smartsuit_can.encode_reading(r)
            lines.append(f"({T0 + t + r.node * 1e-4:.6f}) vcan0 "
                         f"{f.arbitration_id:08X}#{f.data.hex().upper()}")  # fmt: skip
        angles = _routine_angles(t)
        rows.append([T0 + t, *(angles.get(c, 0.0) for c in arm_channels)])
        truths.append((t, truth))
    capture = folder / "arm.log"
    capture.write_text("\n".join(lines) + "\n")
    # a second session of the same movement (other sensor noise), processed the same way
    again = BodyEmulator(Routine("still-then-elbow", "", _routine_angles),
                         smartsuit_sensors([LEFT_ARM]), realism=Realism(), seed=4)  # fmt: skip
    lines2 = []
    for tick in range(int((STILL_S + CYCLES / 0.6 + 0.3) * 100)):
        t = tick * 0.01
        for r in again.sample(t)[0]:
            f = smartsuit_can.encode_reading(r)
            lines2.append(f"({T0 + t + r.node * 1e-4:.6f}) vcan0 "
                          f"{f.arbitration_id:08X}#{f.data.hex().upper()}")  # fmt: skip
    (folder / "arm2.log").write_text("\n".join(lines2) + "\n")
    second = folder / "arm2.mcap"
    assert cli_main(["process", str(folder / "arm2.log"), "-o", str(second)]) == 0
    reference = folder / "truth.csv"
    pd.DataFrame(rows, columns=["t_s", *arm_channels]).to_csv(reference, index=False)
    recording = folder / "arm.mcap"
    assert cli_main(["process", str(capture), "-o", str(recording)]) == 0
    # the same poses, plus ground truth on the truth keys, as `bodynet record` keeps them
    with_truth = folder / "arm-truth.mcap"
    sink = McapSink(with_truth)
    for log_time, frame in read_poses(recording):
        sink.write_pose(keys.pose_key(), frame, log_time)
    for t, truth in truths:
        t_ns = round((T0 + t) * 1e9)
        for tr, (_, site) in zip(truth, sorted(SMARTSUIT_SITES.items())[:3], strict=False):
            msg = {"t_ns": t_ns, "segment": tr.segment, "segment_quat_wxyz": tr.segment_quat_wxyz,
                   "angles_deg": dict(tr.angles_deg)}  # fmt: skip
            sink.write_truth(site.key(Stream.TRUTH), json.dumps(msg).encode(), t_ns)
    sink.close()
    return {"recording": recording, "reference": reference, "with_truth": with_truth,
            "second": second}  # fmt: skip


def _first_table_after(text: str, heading: str) -> pd.DataFrame:
    section = text.split(heading, 1)[1]
    block: list[str] = []
    for ln in section.splitlines():
        if ln.startswith("|"):
            block.append(ln)
        elif block:
            break
    cells = [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in block]
    return pd.DataFrame(cells[2:], columns=cells[0]).set_index(cells[0][0])


def _html_tables(text: str) -> list[pd.DataFrame]:
    """The tables of an HTML report, read back with the standard library's parser."""

    class Tables(HTMLParser):
        def __init__(self) -> None:
            super().__init__()
            self.tables: list[list[list[str]]] = []
            self.cell: list[str] | None = None

        def handle_starttag(self, tag: str, attrs: object) -> None:
            if tag == "table":
                self.tables.append([])
            elif tag == "tr":
                self.tables[-1].append([])
            elif tag in ("td", "th"):
                self.cell = []

        def handle_endtag(self, tag: str) -> None:
            if tag in ("td", "th") and self.cell is not None:
                self.tables[-1][-1].append("".join(self.cell).strip())
                self.cell = None

        def handle_data(self, data: str) -> None:
            if self.cell is not None:
                self.cell.append(data)

    parser = Tables()
    parser.feed(text)
    return [pd.DataFrame(t[1:], columns=t[0]).set_index(t[0][0]) for t in parser.tables]


def test_report_of_a_processed_recording_against_a_csv_reference(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "session" / "report.md"
    code = cli_main(["report", str(arm_recording["recording"]), "--reference",
                     str(arm_recording["reference"]), "-o", str(out)])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    text = out.read_text()
    for png in ("report-angles.png", "report-reference.png", "report-trials.png"):
        assert f"]({png})" in text
        assert (out.parent / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in out.parent.iterdir()) == sorted(
        ["report.md", "report-angles.png", "report-reference.png", "report-trials.png"]
    )

    rom = _first_table_after(text, "## Range of motion")
    elbow = rom.loc["left_elbow_flexion_deg"]
    assert float(elbow["min (deg)"]) == pytest.approx(0.0, abs=1.0)
    assert float(elbow["max (deg)"]) == pytest.approx(90.0, abs=1.0)
    assert int(elbow["repetitions"]) == CYCLES

    acc = _first_table_after(text, "## Accuracy")
    assert float(acc.loc["left_elbow_flexion_deg", "RMS error (deg)"]) < 1.0
    assert float(acc.loc["left_elbow_flexion_deg", "correlation r"]) > 0.999

    assert f"the {CYCLES} repetitions of left_elbow_flexion_deg" in text
    rep = _first_table_after(text, "## Repeatability")
    assert int(rep.loc["left_elbow_flexion_deg", "trials"]) == CYCLES
    assert float(rep.loc["left_elbow_flexion_deg", "range (deg)"]) < 2.0
    icc = _first_table_after(text, "Intra-class correlation")
    assert float(icc.loc["left_elbow_flexion_deg", "ICC(3,1)"]) > 0.99

    ua = _first_table_after(text, "## Type A")
    assert "(auto: the 2 s in which the angles moved least)" in text
    window = text.split("Still window ", 1)[1].split(" s", 1)[0]
    _, end = (float(v) for v in window.split("-"))
    assert end <= STILL_S + 0.05
    assert int(ua.loc["left_elbow_flexion_deg", "n"]) > 150
    assert float(ua.loc["left_elbow_flexion_deg", "best estimate q̄ (deg)"]) == pytest.approx(
        0.0, abs=0.5
    )


def test_report_uses_the_recorded_ground_truth_and_writes_html(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "report.html"
    code = cli_main(["report", str(arm_recording["with_truth"]), "-o", str(out),
                     "--still", "0.5:2.0"])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    text = out.read_text()
    assert text.startswith("<!doctype html>")
    assert f"Reference: ground truth in {arm_recording['with_truth']}" in text
    tables = _html_tables(text)
    acc = next(t for t in tables if "RMS error (deg)" in t.columns)
    assert float(acc.loc["left_elbow_flexion_deg", "RMS error (deg)"]) < 1.0
    assert float(acc.loc["left_elbow_flexion_deg", "correlation r"]) > 0.999
    ua = next(t for t in tables if "s(q̄) (deg)" in t.columns)
    assert int(ua.loc["left_elbow_flexion_deg", "n"]) == 151  # 0.50 .. 2.00 s at 100 Hz
    assert "Still window 0.50-2.00 s" in text


def test_several_recordings_are_trials(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r.md"
    recs = [str(arm_recording["recording"]), str(arm_recording["second"])]
    assert cli_main(["report", *recs, "-o", str(out)]) == 0, capsys.readouterr().err
    text = out.read_text()
    assert "each of the 2 recordings is one trial" in text
    assert text.count("| left_elbow_flexion_deg ") >= 4  # ROM of each, repeatability, ICC
    rep = _first_table_after(text, "## Repeatability")
    assert int(rep.loc["left_elbow_flexion_deg", "trials"]) == 2
    # the same movement twice, other sensor noise: the elbow's two trials agree
    assert float(rep.loc["left_elbow_flexion_deg", "range (deg)"]) < 1.0
    icc = _first_table_after(text, "Intra-class correlation")
    assert float(icc.loc["left_elbow_flexion_deg", "ICC(3,1)"]) > 0.99


def test_several_recordings_say_which_is_which_and_the_plots_are_named(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two recordings: each trial is named by its file, and the sections of the
    first recording only (its angles, the accuracy) say so; the plots of `-o rp.md`
    are rp-<plot>.png beside it, each named on stderr."""
    first, second = arm_recording["recording"], arm_recording["second"]
    out = tmp_path / "rp.md"
    for reference in ([], ["--reference", str(arm_recording["reference"])]):
        assert cli_main(["report", str(first), str(second), *reference, "-o", str(out)]) == 0
        text = out.read_text()
        assert f"one trial (trial 1: {first}, trial 2: {second})" in text
        assert f"Joint angles over time of the first recording, {first}:" in text
        if reference:
            assert f"interpolated at the first recording's ({first}; the others are not " \
                   "compared)" in text  # fmt: skip
            plots = ["rp-angles.png", "rp-reference.png", "rp-trials.png"]
        else:
            assert f"no reference: {first} (the first recording) holds no ground truth" in text
            plots = ["rp-angles.png", "rp-trials.png"]
        err = capsys.readouterr().err
        assert err == f"bodynet report: {out} ({len(plots)} plots beside it: {', '.join(plots)})\n"
        assert all((tmp_path / png).is_file() for png in plots)


# -- bad input -----------------------------------------------------------------


def test_a_reference_saved_with_a_byte_order_mark_is_read_as_without(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Excel's "CSV UTF-8" of the reference (a byte order mark first): the same
    report, not "a reference CSV needs a t_s column"."""
    marked = tmp_path / "truth-excel.csv"
    marked.write_bytes(b"\xef\xbb\xbf" + arm_recording["reference"].read_bytes())
    texts = []
    for name, reference in (("plain", arm_recording["reference"]), ("marked", marked)):
        out = tmp_path / name / "report.md"
        code = cli_main(["report", str(arm_recording["recording"]), "--reference",
                         str(reference), "-o", str(out)])  # fmt: skip
        assert code == 0, capsys.readouterr().err
        texts.append(out.read_text().replace(str(reference), "REF"))
    assert texts[1] == texts[0]


def _fails_cleanly(argv: list[str], capsys: pytest.CaptureFixture[str], folder: Path,
                   message: str) -> None:  # fmt: skip
    before = set(folder.iterdir())
    try:
        code = cli_main(argv)
    except SystemExit as exc:  # argparse's refusal of an argument, where it enters
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert message in err
    assert "Traceback" not in err
    assert set(folder.iterdir()) == before  # nothing half-written


def test_bad_input_exits_2_with_a_message_and_writes_nothing(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = str(tmp_path / "r.md")
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(arm_recording["recording"].read_bytes()[:5000])
    _fails_cleanly(["report", str(truncated), "-o", out], capsys, tmp_path,
                   "not a complete MCAP file")  # fmt: skip
    foreign = tmp_path / "foreign.mcap"
    foreign.write_text("t_s,angle\n0,1\n")
    _fails_cleanly(["report", str(foreign), "-o", out], capsys, tmp_path,
                   "not an MCAP recording")  # fmt: skip
    raw_only = tmp_path / "raw-only.mcap"
    sink = McapSink(raw_only)
    for topic, log_time, sample in read_raw(arm_recording["recording"]):
        sink.write_raw(topic, sample, log_time)
    sink.close()
    _fails_cleanly(["report", str(raw_only), "-o", out], capsys, tmp_path, "0 poses")
    # the still part alone: no repetitions, so no trials for ICC
    _fails_cleanly(["report", str(arm_recording["recording"]), "--joint",
                    "left_shoulder_flexion_deg", "-o", out], capsys, tmp_path,
                   "too few trials for repeatability and ICC")  # fmt: skip
    no_time = tmp_path / "goniometer.csv"
    no_time.write_text("sample,left_elbow_flexion_deg\n0,1\n")
    _fails_cleanly(["report", str(arm_recording["recording"]), "--reference",
                    str(no_time), "-o", out], capsys, tmp_path,
                   "a reference CSV needs a t_s column")  # fmt: skip
    _fails_cleanly(["report", str(arm_recording["recording"]), "--still", "5:5.001",
                    "--no-trials", "-o", out], capsys, tmp_path,
                   "the still window holds")  # fmt: skip
    _fails_cleanly(["report", str(tmp_path / "missing.mcap"), "-o", out], capsys, tmp_path,
                   "missing.mcap")  # fmt: skip
    # a window past the recording's end was clipped, an unknown joint ignored: refused
    _fails_cleanly(["report", str(arm_recording["recording"]), "--still", "0:100",
                    "--no-trials", "-o", out], capsys, tmp_path,
                   "the still window 0-100 s (--still) is not within the recording")  # fmt: skip
    for trials in ([], ["--no-trials"]):
        _fails_cleanly(["report", str(arm_recording["recording"]), str(arm_recording["second"]),
                        "--joint", "nosuch", *trials, "-o", out], capsys, tmp_path,
                       "no measured joint angle 'nosuch' (--joint)")  # fmt: skip


def test_a_reference_cell_that_is_not_a_number_is_named_by_its_line(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A reference whose angle cell is ``abc`` (line 4): that cell is taken as
    missing and named with its line, on stderr and in the report; an empty or
    ``nan`` cell is missing and not named; the other rows and cells are kept."""
    lines = arm_recording["reference"].read_text().splitlines()
    header = lines[0].split(",")
    col = next(i for i, h in enumerate(header) if h.endswith("_deg"))

    def with_cell(line: list[str], value: str) -> str:
        return ",".join(value if i == col else c for i, c in enumerate(line))

    lines[3] = with_cell(lines[3].split(","), "abc")
    lines[5] = with_cell(lines[5].split(","), "nan")
    lines[6] = with_cell(lines[6].split(","), "")
    bad = tmp_path / "goniometer.csv"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "r.md"
    code = cli_main(["report", str(arm_recording["recording"]), "--reference", str(bad),
                     "--no-trials", "-o", str(out)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    said = f"line 4: {header[col]} 'abc' is not a number, taken as missing"
    assert f"{bad}: {said}" in err
    assert said in out.read_text()
    assert "line 6" not in err
    assert "line 7" not in err
    acc = _first_table_after(out.read_text(), "## Accuracy")
    assert float(acc.loc["left_elbow_flexion_deg", "RMS error (deg)"]) < 1.0


def test_the_plots_beside_a_report_are_checked_as_the_report_is(
    arm_recording: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A plot never goes over an input (a recording named like it) or a folder
    or a read-only file; the message names the plot, and nothing is written."""
    recording = tmp_path / "rq-angles.png"
    recording.write_bytes(arm_recording["recording"].read_bytes())
    _fails_cleanly(["report", str(recording), "-o", str(tmp_path / "rq.md")], capsys, tmp_path,
                   f"bodynet report: refusing to write {recording}: it is an input")  # fmt: skip
    assert recording.read_bytes() == arm_recording["recording"].read_bytes()
    angles = tmp_path / "rp-angles.png"
    angles.mkdir()
    _fails_cleanly(["report", str(recording), "-o", str(tmp_path / "rp.md")], capsys, tmp_path,
                   f"bodynet report: cannot write {angles}: it is a folder")  # fmt: skip
    trials = tmp_path / "ro-trials.png"
    trials.write_bytes(b"an earlier plot")
    trials.chmod(0o444)
    _fails_cleanly(["report", str(recording), "-o", str(tmp_path / "ro.md")], capsys, tmp_path,
                   f"bodynet report: cannot write {trials}: it is read-only")  # fmt: skip
    assert trials.read_bytes() == b"an earlier plot"
