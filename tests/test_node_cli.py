"""`bodynet node` processes on a loopback router: branches come and go live."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import pytest
import zenoh
from service_procs import ended
from zenoh_helpers import Collector, Liveliness, raw_collector

from bodynet.core.keys import LEFT_ARM, RIGHT_ARM
from bodynet.core.profile import SMARTSUIT_SITES

BODYNET = Path(sys.executable).with_name("bodynet")


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(timeout=10)


def keys_of(branch: object) -> set[str]:
    return {s.raw_key for s in SMARTSUIT_SITES.values() if s.branch == branch}


def test_branches_hot_plug(
    zsession: zenoh.Session, router_endpoint: str, processes: list[subprocess.Popen[str]]
) -> None:
    live = Liveliness(zsession)
    truth = Collector(zsession, "body/*/*/*/truth", json.loads)
    common = ["--routine", "reach", "--ideal", "-e", router_endpoint]
    left = subprocess.Popen(
        [str(BODYNET), "node", "smartsuit", "--branch", "left-arm", "--via", "slcan", *common],
        text=True,
        stderr=subprocess.PIPE,
    )
    right = subprocess.Popen(
        [
            str(BODYNET),
            "node",
            "smartsuit",
            "--branch",
            "right-arm",
            "--via",
            "concentrator",
            *common,
        ],
        text=True,
        stderr=subprocess.PIPE,
    )
    processes += [left, right]
    both = keys_of(LEFT_ARM) | keys_of(RIGHT_ARM)
    live.wait_for(lambda alive: both <= alive, timeout=30)
    seen = truth.wait_for(lambda s: len({k for k, _ in s}) >= 6)
    assert {"t_ns", "segment", "segment_quat_wxyz", "angles_deg"} <= set(seen[0][1])

    right.send_signal(signal.SIGTERM)  # unplug the right arm: only its nodes go
    assert right.wait(timeout=15) == 0
    alive = live.wait_for(lambda alive: not (keys_of(RIGHT_ARM) & alive))
    assert keys_of(LEFT_ARM) <= alive
    raw = raw_collector(zsession, "body/arm/left/*/raw")
    raw.wait_for(lambda s: len(s) >= 30)  # the left arm never noticed

    left.send_signal(signal.SIGKILL)  # a crash is seen too, by the token vanishing
    live.wait_for(lambda alive: not alive)


def test_emulated_adapter_process_and_bridge_process(
    zsession: zenoh.Session,
    router_endpoint: str,
    tmp_path: Path,
    processes: list[subprocess.Popen[str]],
) -> None:
    """Hardware emulated in one process, bridged by another, as with real hardware."""
    link = tmp_path / "ttyACM-bodynet"
    emulator = subprocess.Popen(
        [
            str(BODYNET),
            "emulate",
            "slcan",
            "--link",
            str(link),
            "--branch",
            "right-arm",
            "--routine",
            "elbow-slow",
            "--truth",
            "-e",
            router_endpoint,
        ],
        text=True,
        stdout=subprocess.PIPE,
    )
    processes.append(emulator)
    assert emulator.stdout is not None
    assert f"emulated slcan on {link}" in emulator.stdout.readline()
    truth = Collector(zsession, "body/arm/right/*/truth", json.loads)
    raw = raw_collector(zsession, "body/arm/right/*/raw")
    bridge = subprocess.Popen(
        [
            str(BODYNET),
            "bridge",
            "can",
            "--interface",
            "slcan",
            "--channel",
            str(link),
            "-e",
            router_endpoint,
        ],
        text=True,
    )
    processes.append(bridge)
    seen = raw.wait_for(lambda s: len({k for k, _ in s}) == 3, timeout=30)
    assert {k for k, _ in seen} == keys_of(RIGHT_ARM)
    truth.wait_for(lambda s: len(s) >= 3)
    for p in (bridge, emulator):
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=15) == 0


def test_subjects_on_one_router_are_listed_and_served_by_one_gateway(
    zsession: zenoh.Session, router_endpoint: str, processes: list[subprocess.Popen[str]]
) -> None:
    """`bodynet node --subject` x2, `bodynet gateway --all-subjects`, `bodynet subjects`."""
    from bodynet.core import keys
    from bodynet.core.codecs import pose

    common = ["--routine", "reach", "--ideal", "-e", router_endpoint]
    for name, branch in (("alice", "left-arm"), ("bob", "right-arm")):
        processes.append(subprocess.Popen(
            [str(BODYNET), "node", "smartsuit", "--branch", branch, "--subject", name, *common],
            text=True, stderr=subprocess.PIPE))  # fmt: skip
    processes.append(subprocess.Popen(
        [str(BODYNET), "gateway", "--all-subjects", "--mode", "client", "-e", router_endpoint],
        text=True, stdout=subprocess.PIPE))  # fmt: skip
    for name in ("alice", "bob"):
        Collector(zsession, f"{name}/{keys.pose_key()}", pose.decode).wait_for(bool, timeout=30)
    listing = subprocess.run(
        [str(BODYNET), "subjects", "-e", router_endpoint],
        capture_output=True, text=True, timeout=60, check=True)  # fmt: skip
    rows = {row["subject"]: row for row in map(json.loads, listing.stdout.splitlines())}
    assert set(rows) == {"alice", "bob"}
    assert rows["alice"]["branches"] == ["left-arm"]
    assert rows["alice"]["gateway"]
    assert rows["bob"]["branches"] == ["right-arm"]
    assert rows["bob"]["nodes"] == 3


def test_a_bad_config_is_a_message_and_sigterm_ends_a_wait_for_the_router(tmp_path: Path) -> None:
    from zenoh_helpers import free_port

    missing = tmp_path / "missing.json5"
    bad = subprocess.run([str(BODYNET), "router", "-c", str(missing)],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2
    assert f"argument -c/--config: cannot read '{missing}': no such file" in bad.stderr
    assert "Traceback" not in bad.stderr
    missing.write_text("{ mode: ")  # there, but not JSON5
    bad = subprocess.run([str(BODYNET), "router", "-c", str(missing)],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2
    assert "cannot use Zenoh config" in bad.stderr
    assert "Traceback" not in bad.stderr
    # a client waits for its router (up to --connect-timeout, 30 s), saying so; SIGTERM ends
    # the wait
    waiting = subprocess.Popen(
        [str(BODYNET), "gateway", "--mode", "client", "-e", f"tcp/127.0.0.1:{free_port()}"],
        stderr=subprocess.PIPE, text=True)  # fmt: skip
    assert waiting.stderr is not None
    first = waiting.stderr.readline()  # said once its signal handlers are in place
    assert "bodynet: waiting for the router at tcp/127.0.0.1:" in first
    waiting.send_signal(signal.SIGTERM)
    assert waiting.wait(timeout=30) == 0
    assert "Traceback" not in waiting.stderr.read()


def _emulate(*args: object) -> subprocess.CompletedProcess[str]:
    """``bodynet emulate ...`` that must end by itself (a refusal); one still
    running after a minute fails the test (subprocess kills it)."""
    return subprocess.run([str(BODYNET), "emulate", *map(str, args)], capture_output=True,
                          text=True, timeout=60, check=False)  # fmt: skip


def test_emulate_never_replaces_a_file_and_says_why_it_cannot_start(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("data\n")
    for device in ("concentrator", "imu-central", "slcan"):
        result = _emulate(device, "--link", victim)
        assert result.returncode == 2, result.stderr
        assert "exists and is not a link to a pseudo-terminal" in result.stderr
        assert victim.read_text() == "data\n"
    for device, link in (("concentrator", "/proc/nope"), ("slcan", "/proc/x")):
        result = _emulate(device, "--link", link)
        assert result.returncode == 2, result.stderr
        assert result.stderr == f"bodynet emulate {device}: cannot make the link {link}: " \
                                "No such file or directory\n"  # fmt: skip
    for bus in ([], ["--interface", "socketcan", "--channel", "bodynet-none0"],
                ["--interface", "socketcand", "--channel", "x"],
                ["--interface", "slcan", "--channel", tmp_path / "ttyNOPE"]):  # fmt: skip
        result = _emulate("can", *bus)
        assert result.returncode == 2, (bus, result.stderr)
        assert result.stderr.startswith("bodynet emulate can: cannot open the CAN bus ("), bus
        assert result.stderr.count("\n") == 1, result.stderr  # one line, no traceback
    result = _emulate("slimevr", "--server", "nohost.invalid:6969")
    assert result.returncode == 2, result.stderr
    assert result.stderr == "bodynet emulate slimevr: cannot find the server nohost.invalid: " \
                            "Name or service not known\n"  # fmt: skip


def test_emulate_replaces_a_stale_link_and_removes_only_its_own(tmp_path: Path) -> None:
    link = tmp_path / "ttyUSB0"
    link.symlink_to("/dev/pts/999999")  # left by an emulator that was killed
    beside = tmp_path / "ttyUSB0.tmp"
    beside.write_text("kept\n")
    first = _until_sigterm("emulate", "imu-central", "--link", link,
                           started=link.exists)  # a live terminal by then  # fmt: skip
    assert f"emulated imu-central on {link} -> /dev/pts/" in first
    assert [p.name for p in tmp_path.iterdir()] == ["ttyUSB0.tmp"]
    assert beside.read_text() == "kept\n"


def test_emulated_trackers_given_a_server_by_name_stop_on_sigterm() -> None:
    from zenoh_helpers import free_port

    first = _until_sigterm("emulate", "slimevr", "--server", f"localhost:{free_port()}")
    assert "emulated slimevr on localhost:" in first


_SIGNAL_IN_WAIT = """
import os, signal, sys
from bodynet.cli.nodes import stop_on_signals
stop = stop_on_signals()
# the signal comes while this thread holds the event's lock, as it does for a
# moment inside stop.wait() (CPython's Event: a Condition over a plain Lock)
with stop._cond:
    os.kill(os.getpid(), signal.SIGTERM)
    for _ in range(1000):  # bytecodes: the handler runs between two of them
        pass
sys.exit(0 if stop.wait(10) else 3)
"""


def test_sigterm_in_the_middle_of_the_wait_still_stops() -> None:
    """A service's SIGTERM that comes while its main thread is inside
    ``stop.wait()`` (emulate, bridge, node: they print that they run, then
    wait) stops it: the handler sets the event from another thread, not while
    the lock it would need is held by the thread it interrupted (a hang that
    CI met once, ``bodynet emulate slimevr`` never ending on SIGTERM)."""
    done = subprocess.run([sys.executable, "-c", _SIGNAL_IN_WAIT], capture_output=True, check=False,
                          text=True, timeout=30)  # fmt: skip
    assert done.returncode == 0, done.stderr


def _until_sigterm(*args: object, started: Callable[[], bool] = lambda: True) -> str:
    """Run ``bodynet *args`` until its first line, check ``started``, end it with
    SIGTERM: it exits 0 with no traceback. Its first line."""
    proc = subprocess.Popen([str(BODYNET), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONFAULTHANDLER": "1"})  # fmt: skip
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert started(), first
        proc.send_signal(signal.SIGTERM)
        code, err = ended(proc, 30)  # else where each thread was, in the failure
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert code == 0, err
    assert "Traceback" not in err
    return first


@pytest.mark.parametrize("device", ["can --interface serial",
                                    "concentrator --port {tmp}", "concentrator --port {tmp}/f.bin",
                                    "concentrator --port /dev/null"])  # fmt: skip
def test_a_device_that_can_never_open_is_refused_at_once(
    router_endpoint: str, tmp_path: Path, device: str
) -> None:
    """Options that do not suit the interface (serial without a --channel), a folder or
    a file as a serial port: one line, exit 2, instead of retrying for ever as for an
    unplugged device."""
    (tmp_path / "f.bin").write_bytes(b"\x00" * 64)
    argv = [str(BODYNET), "bridge", *device.format(tmp=tmp_path).split(), "-e", router_endpoint]
    bad = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2, bad.stderr
    what = device.partition(" ")[0]
    assert bad.stderr.startswith(f"bodynet bridge {what}: cannot open the device: ")
    assert bad.stderr.count("\n") == 1, bad.stderr  # one line, no traceback
    assert "retrying" not in bad.stderr


def _can_driver_installed(interface: str) -> bool:
    """Whether python-can's ``interface`` finds its vendor library or module here."""
    import ctypes.util
    import importlib.util

    if interface == "neovi":
        return importlib.util.find_spec("ics") is not None
    return (
        ctypes.util.find_library({"kvaser": "canlib", "pcan": "pcanbasic"}[interface]) is not None
    )


@pytest.mark.parametrize("interface", ["kvaser", "pcan", "neovi"])
def test_a_can_interface_whose_driver_is_not_installed_is_refused_at_once(
    router_endpoint: str, interface: str
) -> None:
    """kvaser without its canlib (python-can fails with a NameError), pcan without
    pcanbasic (an OSError, once retried for ever), neovi without python-ics (an
    ImportError): one line naming the interface, exit 2; for the bridge and the emulator."""
    if _can_driver_installed(interface):
        pytest.skip(f"{interface}'s driver is installed here")
    argv = [str(BODYNET), "bridge", "can", "--interface", interface, "--channel", "1",
            "-e", router_endpoint]  # fmt: skip
    bad = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr.startswith(f"bodynet bridge can: cannot open the device: python-can's "
                                 f"{interface} interface cannot be used here: its driver or "
                                 "library is not installed ("), bad.stderr  # fmt: skip
    assert bad.stderr.count("\n") == 1, bad.stderr  # one line: no traceback, no log line
    result = _emulate("can", "--interface", interface, "--channel", "1")
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(f"bodynet emulate can: cannot open the CAN bus (interface "
                                    f"{interface}, channel 1): python-can's {interface} "
                                    "interface cannot be used here: its driver or library "
                                    "is not installed ("), result.stderr  # fmt: skip
    assert result.stderr.count("\n") == 1, result.stderr


@pytest.mark.parametrize("command", ["bridge", "emulate"])
def test_an_unknown_can_interface_is_refused_by_its_option(command: str) -> None:
    """Not a python-can interface: refused while reading the options, with the known ones."""
    bad = subprocess.run([str(BODYNET), command, "can", "--interface", "kvasr"],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr.splitlines()[-1] == (
        f"bodynet {command} can: error: argument --interface: 'kvasr' is not a python-can "
        "interface (python-can's: " + ", ".join(sorted(can.VALID_INTERFACES)) + ")"
    )
    assert "Traceback" not in bad.stderr


@pytest.mark.parametrize(("system", "selection", "said"), [
    ("imu", ["--sensors", "13-15", "--branch", "left-arm"],
     "--sensors 13,14,15 with --branch left-arm matches no imu sensor"),
    ("slimevr", ["--sensors", "16-20"], "--sensors 16,17,18,19,20 matches no slimevr sensor"),
    # the SmartSuit's sensors go by branch: --sensors was passed over, the whole suit run
    ("smartsuit", ["--sensors", "99"], "--sensors picks IMU tags (node imu, node slimevr)"),
    ("body", ["--sensors", "3"], "--sensors picks IMU tags"),
])  # fmt: skip
def test_a_selection_of_no_sensor_is_refused_at_once(
    system: str, selection: list[str], said: str
) -> None:
    from zenoh_helpers import free_port

    argv = [str(BODYNET), "node", system, *selection, "-e", f"tcp/127.0.0.1:{free_port()}"]
    bad = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2, bad.stderr
    assert bad.stderr.startswith(f"bodynet node {system}: {said}")
    assert "Traceback" not in bad.stderr


def test_a_replay_says_what_it_replayed_and_a_log_of_no_frame_is_an_error(
    router_endpoint: str, tmp_path: Path
) -> None:
    (tmp_path / "rand.bin").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "text.log").write_text("hello\nworld\n")
    (tmp_path / "empty.log").write_text("")
    for name in ("rand.bin", "text.log", "empty.log"):
        argv = [str(BODYNET), "bridge", "can", "--replay", str(tmp_path / name)]
        bad = subprocess.run([*argv, "-e", router_endpoint],
                             capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
        assert bad.returncode == 2, bad.stderr
        assert bad.stderr.startswith(f"bodynet bridge can: no CAN frame in {tmp_path / name}")
        assert "Traceback" not in bad.stderr
    mixed = tmp_path / "mixed.log"
    mixed.write_text("(0.0) vcan0 123#00\nGARBLED\n")
    ok = subprocess.run(
        [str(BODYNET), "bridge", "can", "--replay", str(mixed), "-e", router_endpoint],
        capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    assert f"1 frames replayed from {mixed}; skipped 1 (garbage: 1) at line 2" in ok.stderr


def test_a_bridge_with_batch_ms_puts_its_samples_together_on_its_batch_key(
    router_endpoint: str, zsession: zenoh.Session, data_dir: Path
) -> None:
    """``bodynet bridge can --replay ... --batch-ms 5``: every sample of the log
    comes in batches on ``body/@batch/<name>``, none on the sites' own keys; a
    window out of range is refused by its option."""
    from bodynet.core import keys
    from bodynet.core.codecs import raw_batch

    per_site = raw_collector(zsession, keys.all_raw())
    batches = Collector(zsession, keys.all_batches(), raw_batch.decode)
    log = data_dir / "smartsuit_arm.log"
    argv = [str(BODYNET), "bridge", "can", "--replay", str(log), "--name", "arm"]
    ok = subprocess.run([*argv, "--batch-ms", "5", "-e", router_endpoint],
                        capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    decoded = json.loads((data_dir / "smartsuit_arm.log.manifest.json").read_text())["decoded"]
    got = batches.wait_for(lambda s: sum(len(e) for _, e in s) >= decoded)
    assert {key for key, _ in got} == {keys.batch_key("arm")}
    assert sum(len(e) for _, e in got) == decoded  # every sample, once
    assert len(got) < decoded / 2  # together: the nodes' frames of a cycle in one batch
    assert not per_site.drained()
    bad = subprocess.run([*argv, "--batch-ms", "500", "-e", router_endpoint],
                         capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert bad.returncode == 2
    assert "argument --batch-ms: '500' is outside [0, 10] (ms)" in bad.stderr
    assert "Traceback" not in bad.stderr
