"""Bridges run with ``--batch-ms``: their samples go out together on
``body/@batch/<bridge>`` (``core/codecs/raw_batch.py``), and the gateway, the
recorder and the live outputs take them as they take samples on the sites' own
keys. Emulated hardware, real Zenoh sessions, a recording read back with the
mcap library's own reader."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader
from zenoh_helpers import Collector, Running, client, raw_collector, wait_until

from bodynet.clients import live
from bodynet.clients.recorder import DEFAULT_KEYS, Recorder
from bodynet.core import keys
from bodynet.core.codecs import pose, raw_batch, raw_sample
from bodynet.core.errors import DecodeError, Reason
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import OleAccel, Quat, RawSample, Source
from bodynet.core.profile import IMU_SITES, SMARTSUIT_SITES
from bodynet.gateway.service import Gateway
from bodynet.nodes.emulator import Realism
from bodynet.nodes.motion import Routine
from bodynet.nodes.services import EmulationOptions, NodePlan, run_node

HELD = Routine("held", "", lambda t: {"left_elbow_flexion_deg": 60.0})
IMU = tuple(n for n, s in IMU_SITES.items() if s.branch != LEFT_ARM)
ARM_KEYS = {s.raw_key for s in SMARTSUIT_SITES.values() if s.branch == LEFT_ARM}
IMU_KEYS = {IMU_SITES[n].raw_key for n in IMU}


class RawSeen(live.LiveOutput):
    """A live output that keeps the raw samples it is handed, by key."""

    wants_raw = True

    def __init__(self) -> None:
        self.raw: dict[str, list[RawSample]] = {}
        self.lock = threading.Lock()

    def on_pose(self, subject: str, frame: pose.PoseFrame) -> None:
        pass

    def on_raw(self, subject: str, key: str, sample: RawSample) -> None:
        with self.lock:
            self.raw.setdefault(key, []).append(sample)


def test_batching_bridges_feed_the_gateway_the_recorder_and_a_live_output(
    gateway: Gateway, router_endpoint: str, zsession: zenoh.Session, tmp_path: Path
) -> None:
    """A SmartSuit arm on CAN and the IMU central's tags, both batching: nothing on
    the sites' own keys, every site in the poses, the recording holding each
    site's samples on its own key, in order, and a live output handed them."""
    per_site = raw_collector(zsession, keys.all_raw())
    batches = Collector(zsession, keys.all_batches(), raw_batch.decode)
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    recorder = Recorder(zsession, tmp_path / "batched.mcap", DEFAULT_KEYS)
    seen, stop = RawSeen(), threading.Event()
    output = threading.Thread(target=live.run, args=(client(router_endpoint), seen, stop))
    output.start()
    plans = [NodePlan("smartsuit", "can", (LEFT_ARM,)), NodePlan("imu", "imu-central", None, IMU)]
    nodes = Running(partial(run_node, client(router_endpoint), plans=plans,
                            options=EmulationOptions(HELD, Realism.ideal()), name="batch",
                            batch_s=0.005))  # fmt: skip
    everyone = ARM_KEYS | IMU_KEYS
    try:
        poses.wait_for(lambda s: len(s) > 50 and everyone <= set(s[-1][1].sources), timeout=30)
        # thirty samples of every site handed on: the bridges put out that many, and so
        # the recording, subscribed before they started, holds them too
        wait_until(lambda: set(seen.raw) >= everyone
                   and min(len(seen.raw[k]) for k in everyone) >= 30,
                   timeout=30, what="raw samples of every site")  # fmt: skip
    finally:
        nodes.stop()
        stop.set()
        output.join(timeout=10)
        recorder.close()
    assert not per_site.drained()  # the bridges put nothing on the sites' own keys
    assert {key for key, _ in batches.drained()} == {
        keys.batch_key("batch-can-0"),
        keys.batch_key("batch-imu-central-1"),
    }
    assert not recorder.rejected
    by_topic: dict[str, list[int]] = {}
    with (tmp_path / "batched.mcap").open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic.endswith("/raw"):
                by_topic.setdefault(channel.topic, []).append(json.loads(message.data)["seq"])
    assert set(by_topic) == everyone
    for topic, seqs in by_topic.items():  # each site's samples, in their order
        assert len(seqs) > 20, topic
        assert seqs == sorted(seqs), topic
    for key in everyone:  # the live output's are the same samples as the recording's
        assert [s.seq for s in seen.raw[key]][:20] == by_topic[key][:20]


def test_a_hostile_batch_is_counted_entry_by_entry_and_its_good_samples_taken(
    gateway: Gateway, router_endpoint: str, zsession: zenoh.Session
) -> None:
    """One entry on a topology's key, one cut short after a good one: the good
    sample goes into the pose, the others are counted, and the gateway goes on."""
    site = IMU_SITES[2]
    good = raw_sample.encode(RawSample(Quat(2, (1.0, 0.0, 0.0, 0.0)), 0, 1, Source.IMU_CENTRAL))
    hostile = raw_batch.encode([(keys.TOPOLOGY, good), (site.raw_key, good), (site.raw_key, good)])
    poses = Collector(zsession, keys.pose_key(), pose.decode)
    node = client(router_endpoint)
    try:
        wait_matching_batches(node)
        node.put(keys.batch_key("hostile"), hostile[:-3])
        poses.wait_for(lambda s: bool(s) and site.raw_key in s[-1][1].sources)
        wait_until(lambda: gateway.rejected[Reason.TRUNCATED] == 1, what="the cut entry counted")
        assert gateway.rejected[Reason.UNKNOWN_NODE] == 1  # the topology's key
        node.put(keys.batch_key("hostile"), b"BN" + hostile)  # not a batch at all
        wait_until(lambda: gateway.rejected[Reason.BAD_MAGIC] == 1, what="the bad batch counted")
        assert gateway.samples == 1
    finally:
        node.close()


def test_a_batch_on_a_known_key_is_judged_entry_by_entry_as_the_codec_does(
    gateway: Gateway, router_endpoint: str, zsession: zenoh.Session
) -> None:
    """From a bridge's second batch on, its key's batches go through the compiled
    intake (``kernels.take_batch``), which takes plain quaternion messages and
    leaves the rest to Python: a batch mixing good samples, an entry on a
    topology's key, a quaternion with extra bytes, one that is not unit, a
    SmartSuit module's sample and a site seen for the first time is taken and
    counted as the codec judges each entry, in order (the site's latest is its
    last good sample); a batch that is not well formed is counted as
    ``raw_batch.decode`` counts it, its readable entries taken."""
    a, b, c = IMU_SITES[2], IMU_SITES[3], IMU_SITES[4]
    module = next(iter(SMARTSUIT_SITES.items()))

    def quat(node: int, seq: int, wxyz: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0),
             extra: bytes = b"") -> bytes:  # fmt: skip
        return raw_sample.encode(RawSample(Quat(node, wxyz, extra), seq, 1_000 + seq,
                                           Source.IMU_CENTRAL))  # fmt: skip

    node = client(router_endpoint)
    key = keys.batch_key("mixed")
    body = gateway._bodies[None]
    try:
        wait_matching_batches(node)
        node.put(key, raw_batch.encode([(a.raw_key, quat(2, 1)), (b.raw_key, quat(3, 1))]))
        wait_until(lambda: gateway.samples == 2, what="the first batch")
        assert key in gateway._batch_bodies  # the next go through the compiled intake
        turned = (0.0, 1.0, 0.0, 0.0)
        mixed = [(a.raw_key, quat(2, 2)), (keys.TOPOLOGY, quat(2, 3)),
                 (b.raw_key, quat(3, 2, turned, b"\x01")), (a.raw_key, quat(2, 4, (2.0, 0, 0, 0))),
                 (module[1].raw_key, raw_sample.encode(RawSample(
                     OleAccel(module[0], 50, (0, 0, 1024)), 1, 1_001, Source.CAN))),
                 (c.raw_key, quat(4, 1, turned)), (a.raw_key, quat(2, 5, turned))]  # fmt: skip
        node.put(key, raw_batch.encode(mixed))
        wait_until(lambda: gateway.samples == 7, what="the mixed batch's good samples")
        assert gateway.rejected[Reason.UNKNOWN_NODE] == 1  # the topology's key
        with pytest.raises(DecodeError) as not_unit:
            raw_sample.decode(quat(2, 4, (2.0, 0, 0, 0)))
        assert gateway.rejected[not_unit.value.reason] == 1
        with gateway._lock:
            latest = {site: body.latest[site].sample for site in (a, b, c, module[1])}
        assert latest[a] == raw_sample.decode(quat(2, 5, turned))  # the last, not the refused
        assert latest[b].reading.extra == b"\x01"  # type: ignore[union-attr]
        assert latest[c].reading.wxyz == turned  # type: ignore[union-attr]
        assert latest[module[1]].reading.encoder == 50  # type: ignore[union-attr]
        node.put(key, raw_batch.encode([(a.raw_key, quat(2, 6)), (c.raw_key, quat(4, 2))])[:-3])
        wait_until(lambda: gateway.rejected[Reason.TRUNCATED] == 1, what="the cut batch counted")
        assert gateway.samples == 8  # its first entry taken
    finally:
        node.close()


def wait_matching_batches(session: zenoh.Session) -> None:
    publisher = session.declare_publisher(keys.batch_key("hostile"))
    try:
        wait_until(lambda: publisher.matching_status.matching, what="the gateway's subscriber")
    finally:
        publisher.undeclare()


def _taker(
    gw: Gateway, node: zenoh.Session, keys_: list[str]
) -> Callable[[list[tuple[str, bytes]]], int]:
    """For a gateway with no worker: ``take(sent)`` puts ``sent`` (key, payload)
    from ``node``, then takes it in one take, as one round would, and says how
    many samples it took."""
    pubs = {k: node.declare_publisher(k) for k in keys_}
    wait_until(lambda: all(p.matching_status.matching for p in pubs.values()),
               what="the gateway's subscribers")  # fmt: skip

    def take(sent: list[tuple[str, bytes]]) -> int:
        for key, payload in sent:
            pubs[key].put(payload)
        time.sleep(1.0)  # on loopback: all in the gateway's queues long before
        return gw._take_pending(time.monotonic())[0]

    return take


def test_only_a_sites_own_messages_take_what_waits_before_them(
    router_endpoint: str, tmp_path: Path
) -> None:
    """Plain quaternion messages wait for one compiled call at the end of a take
    (``_Body.defer``); another message of the same site first takes them, so the
    site's latest is the last it sent. Another site's message (a SmartSuit
    module's among tags) leaves them waiting: the round's tags still take one
    call, not one per module sample."""
    a, b = IMU_SITES[2], IMU_SITES[3]
    module_node, module = next(iter(SMARTSUIT_SITES.items()))

    def quat(node: int, seq: int, extra: bytes = b"") -> bytes:
        return raw_sample.encode(RawSample(Quat(node, (1.0, 0.0, 0.0, 0.0), extra), seq,
                                           1_000 + seq, Source.IMU_CENTRAL))  # fmt: skip

    def ole(seq: int) -> bytes:
        return raw_sample.encode(RawSample(OleAccel(module_node, seq, (0, 0, 1024)), seq,
                                           1_000 + seq, Source.CAN))  # fmt: skip

    session, node = client(router_endpoint), client(router_endpoint)
    gw = Gateway(session, profile_path=tmp_path / "subject.toml")  # taking by hand: no worker
    flushes: list[int] = []
    take_deferred = gw._take_deferred
    gw._take_deferred = lambda *args: flushes.append(1) or take_deferred(*args)  # type: ignore[method-assign]
    try:
        take = _taker(gw, node, [s.raw_key for s in (a, b, module)])

        first = [(a.raw_key, quat(2, 1)), (b.raw_key, quat(3, 1)), (module.raw_key, ole(1))]
        assert take(first) == 3  # each site's first sample: its route made
        flushes.clear()
        sent = [(a.raw_key, quat(2, 2)), (b.raw_key, quat(3, 2)), (module.raw_key, ole(2)),
                (b.raw_key, quat(3, 3)), (module.raw_key, ole(3)),
                (a.raw_key, quat(2, 3, b"\x01"))]  # fmt: skip
        assert take(sent) == 6
        body = gw._bodies[None]
        latest = {site: body.latest[site].sample for site in (a, b, module)}
        assert latest[a] == raw_sample.decode(quat(2, 3, b"\x01"))  # not the plain one before
        assert latest[b].seq == 3
        assert latest[module].reading.encoder == 3  # type: ignore[union-attr]
        assert len(flushes) == 1  # before a's own message; the modules' took none
    finally:
        gw.close()
        node.close()
        session.close()


def test_a_bridges_first_batch_comes_after_the_samples_taken_before_it(
    router_endpoint: str, tmp_path: Path
) -> None:
    """A site's samples that came on its own key before a bridge's first batch
    (its key not yet known to the gateway) are taken before the batch's: the
    site's latest is the batch's, the last it sent, not the older one."""
    a, b = IMU_SITES[2], IMU_SITES[3]

    def quat(node: int, seq: int) -> bytes:
        return raw_sample.encode(RawSample(Quat(node, (1.0, 0.0, 0.0, 0.0)), seq, 1_000 + seq,
                                           Source.IMU_CENTRAL))  # fmt: skip

    session, node = client(router_endpoint), client(router_endpoint)
    gw = Gateway(session, profile_path=tmp_path / "subject.toml")  # taking by hand: no worker
    try:
        batch = keys.batch_key("first")
        take = _taker(gw, node, [a.raw_key, b.raw_key, batch])

        assert take([(a.raw_key, quat(2, 1)), (b.raw_key, quat(3, 1))]) == 2  # routes made
        entries = raw_batch.encode([(a.raw_key, quat(2, 3)), (b.raw_key, quat(3, 3))])
        assert take([(a.raw_key, quat(2, 2)), (batch, entries)]) == 2
        body = gw._bodies[None]
        assert body.latest[a].sample.seq == 3
        assert body.latest[b].sample.seq == 3
        assert batch in gw._batch_bodies  # its next batches: the compiled intake
    finally:
        gw.close()
        node.close()
        session.close()
