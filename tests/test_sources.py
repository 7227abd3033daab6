"""The source registry: a source added by the registry alone runs live and offline.

The toy source below is registered from this test (no file of bodynet knows
it): a line protocol on a serial port, ``<node> <w> <x> <y> <z>``, with a wire
id no bodynet version has a name for. It gets its ``bridge``, ``decode`` and
``process`` commands from the registry, and a real gateway takes its samples
and counts its sites in health.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import pytest
import zenoh
from zenoh_helpers import Collector, Running, client, raw_collector

from bodynet.cli.main import build_parser, main
from bodynet.clients.mcap_store import read_poses, read_raw
from bodynet.core.errors import DecodeError, Reason, Rejected
from bodynet.core.keys import LEFT_ARM, Site
from bodynet.core.messages import Quat, StreamEvent, Tick, source_name
from bodynet.gateway.service import Gateway
from bodynet.nodes import services, sources
from bodynet.nodes.hardware import PtyPort
from bodynet.nodes.sources.base import Source, Transport
from bodynet.nodes.sources.serial_port import SerialSource

TOY_ID = 0xE7
SITES = {1: Site(LEFT_ARM, "upperarm"), 2: Site(LEFT_ARM, "forearm")}
Q1 = (1.0, 0.0, 0.0, 0.0)
Q2 = (0.5**0.5, 0.0, 0.0, 0.5**0.5)  # a quarter turn about z


class ToyDecoder:
    """``<node> <w> <x> <y> <z>\\n`` lines; a tick starts when the node numbers do."""

    def __init__(self) -> None:
        self._buf = b""
        self._last = 1 << 16
        self._tick = -1

    def feed(self, data: bytes) -> list[StreamEvent]:
        *lines, self._buf = (self._buf + data).split(b"\n")
        out: list[StreamEvent] = []
        for line in lines:
            try:
                node_text, *q = line.split()
                node, (w, x, y, z) = int(node_text), map(float, q)
            except ValueError:
                out.append(Rejected(Reason.GARBAGE, "not a toy line", line[:64]))
                continue
            if node <= self._last:
                self._tick += 1
                out.append(Tick(self._tick))
            self._last = node
            out.append(Quat(node, (w, x, y, z)))
        return out

    def close(self) -> list[StreamEvent]:
        return [Rejected(Reason.TRUNCATED, "cut line")] if self._buf else []


class Toy(SerialSource):
    name = "toy"
    wire_id = TOY_ID
    transport = Transport.SERIAL
    help = "a toy line protocol"
    SITES = SITES
    PERIOD_S = 0.02
    formats: ClassVar = {"toy-lines": "toy lines"}

    def decoder(self) -> ToyDecoder:
        return ToyDecoder()


@pytest.fixture
def toy() -> Iterator[type[Source]]:
    sources.register("toy", Toy)
    yield Toy
    sources.unregister("toy")


def toy_lines(ticks: int) -> bytes:
    def line(node: int, q: tuple[float, ...]) -> str:
        return f"{node} {' '.join(map(repr, q))}\n"

    return "".join(line(1, Q1) + line(2, Q1 if t < 10 else Q2) for t in range(ticks)).encode()


def test_a_source_added_by_the_registry_alone_runs_live(
    toy: type[Source], router_endpoint: str, zsession: zenoh.Session, tmp_path: Path
) -> None:
    port = PtyPort(tmp_path / "toy0", 115200)
    port.plug()
    gateway_session = client(router_endpoint)
    gateway = Gateway(gateway_session)
    health = Collector(zsession, "body/@health/**", json.loads)
    raw = raw_collector(zsession)
    args = build_parser().parse_args(["bridge", "toy", "--port", str(port.link)])
    assert args.func.__name__ == "cmd_bridge"
    assert args.device == "toy"
    served = Running(gateway.run)
    bridged = Running(lambda stop: services.bridge(zsession, stop, "toy", "toy-test", args))
    writing = threading.Event()

    def write() -> None:
        while not writing.wait(0.02):
            port.write(toy_lines(1))

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    try:
        keys = {site.raw_key for site in SITES.values()}
        seen = raw.wait_for(lambda s: {k for k, _ in s} >= keys)
        assert all(sample.source == TOY_ID for _, sample in seen)
        report = health.wait_for(lambda h: any(
            m.get("sources") == {"source-231": 2} for k, m in h if k.endswith("gateway")
        ))  # fmt: skip
        bridge_health = [m for k, m in report if k.endswith("toy-test")][-1]
        assert bridge_health["kind"] == source_name(TOY_ID) == "source-231"
        assert set(bridge_health["nodes"]) == {"1", "2"}
        assert gateway.rejected.get(Reason.BAD_KIND, 0) == 0  # nothing refused for its id
    finally:
        writing.set()
        writer.join()
        bridged.stop()
        served.stop()
        gateway.close()
        gateway_session.close()
        port.unplug()


def test_a_source_added_by_the_registry_alone_runs_offline(
    toy: type[Source], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    capture = tmp_path / "session.toy"
    capture.write_bytes(toy_lines(60) + b"garbage\n")
    assert main(["decode", "--format", "toy-lines", str(capture)]) == 0
    out, err = capsys.readouterr()
    rows = [json.loads(line) for line in out.splitlines()]
    assert len(rows) == 120
    assert rows[-1] == {"node": 2, "key": SITES[2].raw_key, "t_s": 59 * 0.02,
                        "quat_wxyz": list(Q2)}  # fmt: skip
    assert err.strip() == "decoded 120, rejected 1 (garbage: 1)"

    out_mcap = tmp_path / "session.mcap"
    assert main(["process", str(capture), "--format", "toy-lines", "-o", str(out_mcap)]) == 0
    raw = list(read_raw(out_mcap))
    assert len(raw) == 120
    assert {sample.source for _, _, sample in raw} == {TOY_ID}
    poses = list(read_poses(out_mcap))
    assert len(poses) == 60
    # the forearm turned against the upper arm at tick 10: the elbow bends then, not before
    elbow = [frame.rel_deg["left_elbow"] for _, frame in poses]
    assert max(elbow[:10]) == pytest.approx(0.0, abs=1e-3)
    assert min(elbow[10:]) > 1.0


def test_the_registry_says_what_it_lacks() -> None:
    with pytest.raises(sources.UnknownSource, match="no source 'nope'; sources: can"):
        sources.get("nope")
    with pytest.raises(sources.UnknownSource, match="no capture format 'nope'"):
        sources.by_format("nope")
    # every registered name resolves to a class of its name
    for name in sources.names():
        assert sources.get(name).name == name


def test_unknown_wire_ids_decode() -> None:
    from bodynet.core.codecs import raw_sample
    from bodynet.core.messages import RawSample, source_of

    sample = RawSample(Quat(1, Q1), 7, 123, TOY_ID)
    assert raw_sample.decode(raw_sample.encode(sample)) == sample
    assert source_of(source_name(TOY_ID)) == TOY_ID
    with pytest.raises(ValueError, match="no source named"):
        source_of("source-999")
    with pytest.raises(DecodeError):
        raw_sample.decode(b"BN\x02")


def test_offline_processing_loads_no_zenoh(tmp_path: Path, data_dir: Path) -> None:
    """`process` reads a capture through its source and runs the solver without
    the live parts: Zenoh is never imported."""
    import subprocess
    import sys

    code = (
        "import sys\nfrom pathlib import Path\nfrom bodynet.offline.process import process\n"
        f"r = process(Path({str(data_dir / 'imu_central.txt')!r}), 'imu-central', "
        f"Path({str(tmp_path / 'x.mcap')!r}))\n"
        "print(r.ticks > 0, sorted(m for m in sys.modules if m.split('.')[0] == 'zenoh'))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, check=True)  # fmt: skip
    assert done.stdout.split() == ["True", "[]"]
