"""`bodynet calibrate ole`: from reference pairs, and live, holding poses on cue."""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import pytest
import zenoh
from zenoh_helpers import raw_collector

from bodynet.core.calibration import ELBOW_SF
from bodynet.core.keys import LEFT_ARM
from bodynet.nodes.can_bridge import CanBridge
from bodynet.nodes.emulator import BodyEmulator, Realism, smartsuit_sensors
from bodynet.nodes.hardware import CanNodes
from bodynet.nodes.motion import Routine
from bodynet.session import profile_file

BODYNET = Path(sys.executable).with_name("bodynet")


def test_from_pairs_reproduces_table_4_1(tmp_path: Path) -> None:
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("angle_deg,counts\n0,0\n30,141\n60,280\n90,391\n120,486\n140,522\n")
    profile = tmp_path / "subject.toml"
    result = subprocess.run([str(BODYNET), "calibrate", "ole", "--joint", "left_elbow",
                             "--from-pairs", str(pairs), "--profile", str(profile)],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 0, result.stderr
    cal = profile_file.load(profile).ole["left_elbow_flexion_deg"]
    assert cal.radius_mm == pytest.approx(26.93, abs=0.05)
    assert cal.sf == pytest.approx(ELBOW_SF, abs=0.003)


@pytest.mark.parametrize(("row", "line", "why"), [
    ("90,abc", 4, "not angle_deg,counts"), ("90,nan", 4, "not angle_deg,counts"),
    ("90", 4, "not angle_deg,counts"), ("90,391,1", 4, "not angle_deg,counts"),
    ("3600,391", 4, "angle 3600 is not within +-360 deg"),
    ("nan,391", 4, "angle nan is not within +-360 deg"),
])  # fmt: skip
def test_a_bad_pairs_row_is_refused_naming_its_line(
    tmp_path: Path, row: str, line: int, why: str
) -> None:
    """A row that is not two finite numbers, or an angle past a turn, is an error
    naming the file and line (exit 2, nothing written), never skipped unsaid."""
    pairs = tmp_path / "pairs.csv"
    pairs.write_text(f"angle_deg,counts\n0,0\n\n{row}\n30,141\n60,280\n120,486\n")
    profile = tmp_path / "subject.toml"
    result = subprocess.run([str(BODYNET), "calibrate", "ole", "--joint", "left_elbow",
                             "--from-pairs", str(pairs), "--profile", str(profile)],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(f"bodynet calibrate ole: {pairs}: line {line}: {why}")
    assert result.stderr.endswith("; nothing written\n"), result.stderr
    assert not profile.exists()


def test_pairs_saved_with_a_byte_order_mark_keep_their_first_row(tmp_path: Path) -> None:
    """Excel's "CSV UTF-8" (a byte order mark first) of rows with no header: the
    first row is a pair like the others, not taken for a header."""
    fits = []
    for name, encoding in (("plain.csv", "utf-8"), ("marked.csv", "utf-8-sig")):
        pairs = tmp_path / name
        pairs.write_text("30,141\n0,0\n60,280\n120,486\n", encoding=encoding)
        profile = tmp_path / f"{name}.toml"
        argv = [str(BODYNET), "calibrate", "ole", "--joint", "left_elbow",
                "--from-pairs", str(pairs), "--profile", str(profile)]  # fmt: skip
        result = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
        assert result.returncode == 0, result.stderr
        fits.append(profile.read_text())
    assert fits[1] == fits[0]


def test_live_calibration_on_cue(
    zsession: zenoh.Session, router_endpoint: str, tmp_path: Path
) -> None:
    held = {"left_elbow_flexion_deg": 0.0}
    routine = Routine("held", "", lambda t: dict(held))
    channel = f"calibrate-{time.monotonic_ns()}"
    stop = threading.Event()
    bridge = CanBridge(zsession, "calibrate-test")
    bridge_thread = threading.Thread(
        target=bridge.run_bus,
        args=(stop,),
        kwargs={"interface": "virtual", "channel": channel},
        daemon=True,
    )
    bridge_thread.start()
    raw = raw_collector(zsession, "body/arm/left/elbow/raw")
    profile = tmp_path / "subject.toml"
    with can.Bus(interface="virtual", channel=channel) as bus:
        nodes = CanNodes(
            bus, BodyEmulator(routine, smartsuit_sensors([LEFT_ARM]), realism=Realism.ideal())
        )
        nodes.start()
        proc = subprocess.Popen([str(BODYNET), "calibrate", "ole", "--joint", "left_elbow",
                                 "--angles", "0,30,60,90,120,140", "--still-s", "0.2",
                                 "--profile", str(profile), "-e", router_endpoint],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
        lines: queue.SimpleQueue[str] = queue.SimpleQueue()
        assert proc.stderr is not None
        assert proc.stdin is not None
        stderr = proc.stderr
        threading.Thread(target=lambda: [lines.put(x) for x in stderr], daemon=True).start()
        cues = 0
        while cues < 6:
            line = lines.get(timeout=30)
            if not line.startswith("Hold left_elbow at "):
                continue
            angle = float(line.split(" at ")[1].split()[0])
            held["left_elbow_flexion_deg"] = angle
            expected = round(
                BodyEmulator(routine, smartsuit_sensors([LEFT_ARM]), realism=Realism.ideal())
                .sample(0.0)[0][1]
                .encoder
            )  # type: ignore[union-attr]
            n = len(raw.seen)

            def held_now(seen: list[Any], n: int = n, expected: int = expected) -> bool:
                return len(seen) > n and seen[-1][1].reading.encoder == expected

            raw.wait_for(held_now)  # the pose is held before the cue is answered
            proc.stdin.write("\n")
            proc.stdin.flush()
            cues += 1
        assert proc.wait(timeout=30) == 0
        nodes.stop()
    stop.set()
    bridge_thread.join(timeout=10)
    bridge.close()
    cal = profile_file.load(profile).ole["left_elbow_flexion_deg"]
    assert cal.radius_mm == pytest.approx(26.93, abs=0.3)
    assert cal.angle_deg(cal.travel_mm(90.0) / 0.1) == pytest.approx(90.0, abs=0.01)
    assert max(cal.sf) == pytest.approx(1.261, abs=0.01)
