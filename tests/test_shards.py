"""Several gateways share the subjects: who owns what (pure), and live gateway
processes on hosts of their own (network namespaces) sharing eight subjects,
one killed and its subjects taken over."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from pathlib import Path

import pytest
import zenoh
from service_procs import Services
from test_netns import Hosts, hosts, in_ns, services  # noqa: F401  (fixtures)
from zenoh_helpers import client, free_port

from bodynet.core import keys
from bodynet.core.codecs import pose, raw_sample
from bodynet.core.keys import KeySpaceError
from bodynet.core.messages import Quat, RawSample, Source
from bodynet.gateway.shards import Share, check_id, new_id, owner

SUBJECTS = [f"s{i}" for i in range(8)]
SITES = ("body/trunk/mid/chest/raw", "body/trunk/mid/sacrum/raw")

# one at a time under `make test`'s two processes: links from this namespace take 10.77.n.0/24
pytestmark = pytest.mark.xdist_group("netns")


def test_every_subject_has_one_owner_and_only_a_leaver_s_subjects_move() -> None:
    subjects = [None, *(f"subject-{i}" for i in range(200))]
    members = {"gw-a", "gw-b", "gw-c", "gw-d"}
    owners = {s: owner(members, s) for s in subjects}
    assert set(owners.values()) == members  # everyone gets a share
    assert max(list(owners.values()).count(m) for m in members) < 0.4 * len(subjects)
    assert owners == {s: owner(sorted(members, reverse=True), s) for s in subjects}  # any order
    survivors = members - {"gw-c"}
    for s in subjects:  # gw-c leaves: only its subjects move
        after = owner(survivors, s)
        assert after == owners[s] if owners[s] != "gw-c" else after in survivors
    assert owner(set(), "x") is None


def test_a_share_knows_what_is_its_own_as_members_come_and_go() -> None:
    a = Share("gw-a")
    assert all(a.owns(s) for s in SUBJECTS)  # alone: everything
    assert a.update("gw-b", True)
    assert not a.update("gw-b", True)
    mine = {s for s in SUBJECTS if a.owns(s)}
    assert mine == {s for s in SUBJECTS if owner({"gw-a", "gw-b"}, s) == "gw-a"}
    assert not a.update("gw-a", False)  # never out of its own view
    assert a.update("gw-b", False)
    assert all(a.owns(s) for s in SUBJECTS)
    for bad in ("", "a/b", "*", "@x", "a b"):
        with pytest.raises(KeySpaceError):
            check_id(bad)
    assert check_id(new_id())


class Feed:
    """Raw samples of every subject (two trunk tags each) at 50 Hz, from a thread."""

    def __init__(self, session: zenoh.Session) -> None:
        self.stop = threading.Event()
        self._pubs = [(i, session.declare_publisher(f"{s}/{site}"))
                      for s in SUBJECTS for i, site in enumerate(SITES, 1)]  # fmt: skip
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        seq = 0
        while not self.stop.wait(0.02):
            for node, pub in self._pubs:
                sample = RawSample(Quat(node, (1.0, 0.0, 0.0, 0.0)), seq, time.time_ns(),
                                   Source.IMU_CENTRAL)  # fmt: skip
                pub.put(raw_sample.encode(sample))
            seq += 1

    def close(self) -> None:
        self.stop.set()
        self._thread.join(timeout=5)


class Watch:
    """Which gateway each subject's health comes from, and each subject's pose
    sequence numbers (a subject served twice shows two interleaved sequences)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.served_by: dict[str, list[tuple[float, str]]] = defaultdict(list)
        self.seqs: dict[str, list[tuple[float, int]]] = defaultdict(list)
        self.members: dict[str, list[str]] = {}
        self._subs = [
            session.declare_subscriber(f"*/{keys.health_key('gateway')}", self._on_health),
            session.declare_subscriber(f"*/{keys.pose_key()}", self._on_pose),
        ]

    def _on_health(self, sample: zenoh.Sample) -> None:
        subject = str(sample.key_expr).split("/", 1)[0]
        share = json.loads(sample.payload.to_bytes())["share"]
        with self.lock:
            self.served_by[subject].append((time.monotonic(), share["gateway"]))
            self.members[share["gateway"]] = share["members"]

    def _on_pose(self, sample: zenoh.Sample) -> None:
        subject = str(sample.key_expr).split("/", 1)[0]
        frame = pose.decode(sample.payload.to_bytes())
        with self.lock:
            self.seqs[subject].append((time.monotonic(), frame.seq))

    def wait(self, done: object, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                if done():  # type: ignore[operator]
                    return
            assert time.monotonic() < deadline, f"timed out: {dict(self.served_by)}"
            threading.Event().wait(0.1)

    def owners_since(self, t: float) -> dict[str, set[str]]:
        with self.lock:
            return {s: {g for when, g in seen if when >= t} for s, seen in self.served_by.items()}

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


@pytest.mark.timeout(180)
def test_gateways_on_two_hosts_share_the_subjects_and_take_over_a_dead_one(
    hosts: Hosts,  # noqa: F811
    services: Services,  # noqa: F811
    tmp_path: Path,
) -> None:
    port = free_port()
    router_ns = hosts.add("rt")
    _, router_here = hosts.link(None, router_ns, 1)  # the test process reaches it there
    router = services.start("router", in_ns(router_ns, "router", "-l", f"tcp/0.0.0.0:{port}"))
    router.wait_line("listening", timeout=60)
    gateways = {}
    for n, gid in ((2, "gw-a"), (3, "gw-b")):
        ns = hosts.add(gid)
        router_there, _ = hosts.link(router_ns, ns, n)
        gateways[gid] = services.start(gid, in_ns(
            ns, "gateway", "--mode", "client", "-e", f"tcp/{router_there}:{port}",
            "--all-subjects", "--share", gid, "--profile-dir", str(tmp_path / gid)))  # fmt: skip
    for service in gateways.values():
        service.wait_line("bodynet gateway:", timeout=60)
    session = client(f"tcp/{router_here}:{port}")
    watch, feed = Watch(session), Feed(session)
    try:
        both = {"gw-a", "gw-b"}
        watch.wait(lambda: all(set(m) == both for m in watch.members.values())
                   and set(watch.members) == both)  # fmt: skip
        settled = time.monotonic()
        watch.wait(
            lambda: (
                set(SUBJECTS)
                <= {
                    s
                    for s, seen in watch.served_by.items()
                    if any(w > settled + 1.5 for w, _ in seen)
                }
            )
        )
        owners = watch.owners_since(settled + 1.0)
        expected = {s: owner(both, s) for s in SUBJECTS}
        assert {s: owners[s] for s in SUBJECTS} == {s: {expected[s]} for s in SUBJECTS}
        assert set(expected.values()) == both  # each serves some
        with watch.lock:  # one server a subject: its pose sequence only rises
            for s in SUBJECTS:
                seqs = [q for when, q in watch.seqs[s] if when > settled + 1.0]
                assert seqs, s
                assert seqs == sorted(set(seqs)), s

        gateways["gw-b"].kill()  # SIGKILL: its link closes, its token goes
        killed = time.monotonic()
        moved = [s for s in SUBJECTS if expected[s] == "gw-b"]
        watch.wait(lambda: all(any(w > killed and g == "gw-a" for w, g in watch.served_by[s])
                               for s in moved))  # fmt: skip
        with watch.lock:
            first_pose = max(min(w for w, _ in watch.seqs[s] if w > killed) for s in moved)
        print(
            f"takeover: every subject of the killed gateway posed again "
            f"{first_pose - killed:.3f} s after the kill"
        )
    finally:
        feed.close()
        watch.close()
        session.close()
