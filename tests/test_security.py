"""Security: `bodynet certs`, mutual TLS and default-deny access control on real routers.

Every router here is a real Zenoh router on loopback, configured by the file
`bodynet certs` writes (only its listening port is changed); every client
opens with an identity's own config file. "Not delivered" is always shown
against a sample that was: a marker put after the forbidden one, by a sender
with the right, reaches the same subscriber first.
"""

from __future__ import annotations

import json
import queue
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from zenoh_helpers import Collector, free_port

from bodynet.cli.main import main as bodynet_main
from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.session import SessionError, certs, open_session, session_config
from bodynet.session.security import (
    MANIFEST,
    Identity,
    Layout,
    SecurityError,
    identities,
    make_certs,
    router_text,
)

BODYNET = Path(sys.executable).with_name("bodynet")
DEPLOY = Path(__file__).parent.parent / "deploy"
ELBOW = keys.raw_key("arm", "left", "elbow")
REFUSED_MS = 1500  # how long a refused client keeps trying (an accepted one connects at once)


@pytest.fixture(scope="module")
def cert_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sec") / "certs"
    make_certs(root, ["alice", "bob"])
    return root


@pytest.fixture(scope="module")
def users_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sec") / "certs"
    make_certs(root, ["alice"], users=True)
    return root


def start_router(root: Path) -> tuple[zenoh.Session, str]:
    port = free_port()
    conf = session_config("router", listen=[f"tls/127.0.0.1:{port}"],
                          config_file=Layout(root).config("router"))  # fmt: skip
    return open_session(conf), f"tls/localhost:{port}"


@pytest.fixture(scope="module")
def router(cert_dir: Path) -> Iterator[str]:
    session, endpoint = start_router(cert_dir)
    yield endpoint
    session.close()


def connect(
    endpoint: str, config: Path, subject: str | None = None, *entries: str, wait_ms: int = 10_000
) -> zenoh.Session:
    """A client opened with an identity's config file, as `-c FILE -e ENDPOINT` would."""
    conf = session_config("client", [endpoint], config_file=config, subject=subject,
                          entries=[f"connect/timeout_ms:{wait_ms}", *entries])  # fmt: skip
    return open_session(conf)


@pytest.fixture
def open_as(cert_dir: Path, router: str) -> Iterator[Callable[..., zenoh.Session]]:
    sessions: list[zenoh.Session] = []

    def open_identity(name: str, subject: str | None = None) -> zenoh.Session:
        sessions.append(connect(router, Layout(cert_dir).config(name), subject))
        return sessions[-1]

    yield open_identity
    for s in sessions:
        s.close()


def round_trip(session: zenoh.Session) -> None:
    """Return once the router has handled what ``session`` sent before.

    A query travels at the priority of puts, behind them on the same link,
    and the router answers it (a final reply) even where the ACL drops it.
    """
    list(session.get(keys.TOPOLOGY, timeout=5))


def nothing_more(collector: Collector) -> None:
    """After a round trip: nothing arrives for a while either."""
    with pytest.raises(queue.Empty):
        collector.queue.get(timeout=0.5)


def wait_marker(collector: Collector, marker: bytes) -> list[tuple[str, bytes]]:
    return collector.wait_for(lambda seen: any(v == marker for _, v in seen))


def raw_bytes(session: zenoh.Session, key: str) -> Collector:
    return Collector(session, key, lambda b: b)


# --- the certificate directory ------------------------------------------------------


def test_certs_make_a_ca_and_one_owner_only_identity_per_role(cert_dir: Path) -> None:
    layout = Layout(cert_dir)
    ca = x509.load_pem_x509_certificate(layout.ca_cert.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    names = {i.name for i in identities(["alice", "bob"])}
    assert {"node@alice", "viewer@bob", "game@alice", "recorder@bob", "admin"} <= names
    for name in [*names, "router"]:
        cert = x509.load_pem_x509_certificate(layout.cert(name).read_bytes())
        cert.verify_directly_issued_by(ca)  # raises if another CA signed it
        assert certs.common_name(cert) == name
        for path in (layout.key(name), layout.cert(name), layout.config(name)):
            assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
        assert stat.S_IMODE(layout.folder(name).stat().st_mode) == 0o700
    assert stat.S_IMODE(layout.ca_key.stat().st_mode) == 0o600
    router_cert = x509.load_pem_x509_certificate(layout.cert("router").read_bytes())
    assert set(certs.cert_hosts(router_cert)) == {"localhost", "127.0.0.1"}
    node_conf = layout.config("node@alice").read_text()
    assert '"namespace": "alice"' in node_conf
    assert "tls/localhost:7447" in node_conf


def test_certs_again_keeps_everything_and_adds_new_subjects(tmp_path: Path) -> None:
    root = tmp_path / "certs"
    assert bodynet_main(["certs", str(root), "--subject", "alice", "--host", "lab.example"]) == 0
    layout = Layout(root)
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert bodynet_main(["certs", str(root), "--subject", "alice"]) == 0  # same again
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before
    made = make_certs(root, ["carol"])
    assert made.created == ["node@carol", "gateway@carol", "viewer@carol", "game@carol",
                            "recorder@carol"]  # fmt: skip
    assert made.subjects == ["alice", "carol"]
    assert layout.key("node@alice").read_bytes() == before[layout.key("node@alice")]
    assert "carol/body/*/*/*/raw" in layout.config("router").read_text()
    assert "tls/lab.example:7447" in layout.config("node@carol").read_text()  # host remembered


@pytest.mark.parametrize(
    ("setup", "args", "message"),
    [
        (lambda d: (d / "notes.txt").write_text("mine"), [], "not empty"),
        (make_certs, ["--subject", "alice"], "default subject"),
        (lambda d: make_certs(d, ["alice"]), ["--users"], "without --users"),
        (lambda d: make_certs(d, ["alice"]), ["--host", "10.1.2.3"], "not valid for 10.1.2.3"),
        (lambda d: None, ["--subject", "a/b"], "one key chunk"),
        (lambda d: None, ["--host", "bad host"], "neither a host name"),
        (lambda d: (d / MANIFEST).write_text('{"x": 1}'), [],
         "bodynet-certs.json is damaged (not what bodynet certs wrote: no subjects, hosts, "
         "users, port)"),
        (lambda d: (d / MANIFEST).write_text("[]"), [],
         "is damaged (not what bodynet certs wrote: a JSON list, not an object)"),
        (lambda d: (d / MANIFEST).write_text('{"subjects": [], "hosts": [], "users": false, '
                                             '"port": "x"}'), [],
         "is damaged (not what bodynet certs wrote: invalid literal"),
    ],
)  # fmt: skip
def test_certs_refuses_clearly_and_leaves_the_directory_as_it_was(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    setup: Callable[[Path], object],
    args: list[str],
    message: str,
) -> None:
    root = tmp_path / "certs"
    root.mkdir()
    setup(root)
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    try:
        code = bodynet_main(["certs", str(root), *args])
    except SystemExit as exc:  # argparse's refusal of an option, where it enters
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("bodynet certs: ") or "\nbodynet certs: error: argument" in err
    assert message in err
    assert "Traceback" not in err
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before


def test_a_file_certs_cannot_write_is_named_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A config whose place is taken by a folder, and a disk that takes no more
    bytes (`ulimit -f`, the real executable): one line naming the file as it is
    meant to be, never `cannot write DIR: cannot write FILE` nor a scratch folder."""
    root = tmp_path / "certs"
    make_certs(root)
    config = Layout(root).config("viewer")
    config.unlink()
    config.mkdir()
    assert bodynet_main(["certs", str(root)]) == 2
    assert capsys.readouterr().err == f"bodynet certs: cannot write {config}: it is a folder\n"
    new = tmp_path / "new"
    full = subprocess.run(["sh", "-c", 'trap \'\' XFSZ; ulimit -f 0; exec "$0" "$@"', str(BODYNET),
                           "certs", str(new)], capture_output=True, text=True, timeout=60,
                          check=False)  # fmt: skip
    assert full.returncode == 2, full.stderr
    assert full.stderr == f"bodynet certs: cannot write {Layout(new).ca_key}: File too large\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["certs"]


def test_a_new_directory_appears_whole_or_not_at_all(tmp_path: Path) -> None:
    with pytest.raises(OverflowError):  # the CA's end date is past the year 9999
        make_certs(tmp_path / "certs", ["alice"], days=10**6)
    assert list(tmp_path.iterdir()) == []  # no half-made directory, no temporary one


def test_certs_on_a_file_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(SecurityError, match="not a directory"):
        make_certs(tmp_path / "f", ["alice"])


def test_the_documented_router_config_is_what_certs_writes(tmp_path: Path) -> None:
    text = (DEPLOY / "router-secure.json5").read_text()
    assert text == router_text(Path("/etc/bodynet/certs"), ["alice"], users=False)
    make_certs(tmp_path / "certs", ["alice"], router_path=Path("/etc/bodynet/certs"))
    assert Layout(tmp_path / "certs").config("router").read_text() == text
    conf = zenoh.Config.from_file(str(DEPLOY / "router-secure.json5"))  # Zenoh reads it
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]


# --- who may connect ------------------------------------------------------------------


def other_ca_identity(tmp_path: Path, name: str, like: Path) -> Path:
    """``like``'s client config with a certificate of the same name from another CA."""
    other = tmp_path / "other"
    make_certs(other, [Identity.parse(name).subject or "alice"])
    text = Layout(other).config(name).read_text()
    # keep trusting the real router, so only the client's certificate is foreign
    ca_line = next(line for line in like.read_text().splitlines() if "root_ca_certificate" in line)
    lines = [ca_line if "root_ca_certificate" in line else line for line in text.splitlines()]
    path = tmp_path / "foreign.json5"
    path.write_text("\n".join(lines))
    return path


def test_only_clients_with_a_certificate_of_this_ca_connect(
    cert_dir: Path, router: str, tmp_path: Path
) -> None:
    layout = Layout(cert_dir)
    good = connect(router, layout.config("node@alice"))  # the control: this one gets in
    good.close()

    no_cert = tmp_path / "no-cert.json5"
    conf = json.loads(layout.config("node@alice").read_text().split("\n", 1)[1])
    tls = conf["transport"]["link"]["tls"]
    del tls["connect_certificate_base64"], tls["connect_private_key_base64"]
    no_cert.write_text(json.dumps(conf))
    with pytest.raises(SessionError):
        connect(router, no_cert, wait_ms=REFUSED_MS)

    foreign = other_ca_identity(tmp_path, "node@alice", layout.config("node@alice"))
    with pytest.raises(SessionError):
        connect(router, foreign, wait_ms=REFUSED_MS)

    with pytest.raises(SessionError):  # plain TCP to the TLS port
        open_session(session_config("client", [router.replace("tls/", "tcp/")],
                                    entries=[f"connect/timeout_ms:{REFUSED_MS}"]))  # fmt: skip


def test_a_router_config_of_certs_has_no_plain_tcp(cert_dir: Path) -> None:
    conf = session_config("router", listen=[f"tcp/127.0.0.1:{free_port()}"],
                          config_file=Layout(cert_dir).config("router"))  # fmt: skip
    with pytest.raises(SessionError, match=r"(?i)unsupported protocol"):
        open_session(conf)


def test_users_need_their_own_password_too(users_dir: Path, tmp_path: Path) -> None:
    session, endpoint = start_router(users_dir)
    try:
        layout = Layout(users_dir)
        node = connect(endpoint, layout.config("node@alice"))  # the control
        gateway = connect(endpoint, layout.config("gateway@alice"))
        raw = raw_bytes(gateway, keys.all_raw())
        round_trip(gateway)
        node.put(ELBOW, b"with password")
        wait_marker(raw, b"with password")
        node.close()
        gateway.close()

        for password in ("wrong", None):
            entries = ['transport/auth/usrpwd:{user: "node@alice", password: "wrong"}']
            if password is None:
                entries = ["transport/auth/usrpwd:{}"]
            with pytest.raises(SessionError):
                connect(endpoint, layout.config("node@alice"), None, *entries, wait_ms=REFUSED_MS)
        # a valid password of another identity does not go with this certificate
        viewer_pw = layout.users.read_text().split("viewer@alice:")[1].split()[0]
        swapped = f'transport/auth/usrpwd:{{user: "viewer@alice", password: "{viewer_pw}"}}'
        intruder = connect(endpoint, layout.config("node@alice"), None, swapped)
        gateway = connect(endpoint, layout.config("gateway@alice"))
        node = connect(endpoint, layout.config("node@alice"))
        raw = raw_bytes(gateway, keys.all_raw())
        round_trip(gateway)
        intruder.put(ELBOW, b"swapped")
        round_trip(intruder)
        node.put(ELBOW, b"marker")
        seen = wait_marker(raw, b"marker")
        assert b"swapped" not in [v for _, v in seen]
        for s in (intruder, gateway, node):
            s.close()
    finally:
        session.close()


# --- what each role may do --------------------------------------------------------------


def test_a_node_publishes_its_own_subject_and_the_gateway_and_recorder_get_it(
    open_as: Callable[..., zenoh.Session],
) -> None:
    gateway = open_as("gateway@alice")
    recorder = open_as("recorder@alice")
    at_gateway = raw_bytes(gateway, keys.all_raw())
    at_recorder = raw_bytes(recorder, keys.all_data())
    tokens: queue.SimpleQueue[str] = queue.SimpleQueue()
    gateway.liveliness().declare_subscriber(keys.all_raw(), lambda s: tokens.put(str(s.key_expr)))
    round_trip(gateway)
    round_trip(recorder)
    node = open_as("node@alice")
    token = node.liveliness().declare_token(ELBOW)
    publisher = node.declare_publisher(ELBOW)
    round_trip(node)  # the publisher has learnt who listens (else Zenoh drops at the writer)
    for i in range(20):  # a stream, as a node sends, not a single sample
        publisher.put(b"sample %d" % i)
    wait_marker(at_gateway, b"sample 19")
    wait_marker(at_recorder, b"sample 19")
    assert at_gateway.seen[0] == (ELBOW, b"sample 0")  # keys stay inside the namespace
    assert tokens.get(timeout=5) == ELBOW
    token.undeclare()


def test_a_nodes_batches_reach_the_gateway_and_recorder_and_a_viewers_do_not(
    open_as: Callable[..., zenoh.Session],
) -> None:
    """A bridge run with ``--batch-ms`` puts on ``body/@batch/<name>``: the node may,
    the gateway and the recorder read it, a viewer may not put there."""
    batch = keys.batch_key("imu")
    gateway = open_as("gateway@alice")
    recorder = open_as("recorder@alice")
    at_gateway = raw_bytes(gateway, keys.all_batches())
    at_recorder = raw_bytes(recorder, keys.all_batches())
    round_trip(gateway)
    round_trip(recorder)
    viewer = open_as("viewer@alice")
    viewer.put(batch, b"injected")
    round_trip(viewer)  # the router has handled the put
    node = open_as("node@alice")
    publisher = node.declare_publisher(batch)
    round_trip(node)
    publisher.put(b"marker")
    assert [v for _, v in wait_marker(at_gateway, b"marker")] == [b"marker"]
    assert [v for _, v in wait_marker(at_recorder, b"marker")] == [b"marker"]


def test_a_viewer_cannot_inject_raw_samples_nor_read_them(
    open_as: Callable[..., zenoh.Session],
) -> None:
    gateway = open_as("gateway@alice")
    at_gateway = raw_bytes(gateway, keys.all_raw())
    viewer = open_as("viewer@alice")
    other_viewer = open_as("viewer@alice")  # (a session sees its own puts, so another one reads)
    at_viewer = raw_bytes(other_viewer, keys.all_raw())
    round_trip(gateway)
    round_trip(other_viewer)
    node = open_as("node@alice")

    viewer.put(ELBOW, b"injected")
    viewer.declare_publisher(ELBOW).put(b"injected by a publisher")
    round_trip(viewer)  # the router has handled both puts
    node.put(ELBOW, b"marker")
    seen = wait_marker(at_gateway, b"marker")
    assert [v for _, v in seen] == [b"marker"]
    round_trip(other_viewer)  # had the marker been routed to it, it came before this
    nothing_more(at_viewer)


def test_a_node_cannot_read_nor_write_another_subject(
    open_as: Callable[..., zenoh.Session],
) -> None:
    gateway_bob = open_as("gateway@bob")
    at_gateway_bob = raw_bytes(gateway_bob, keys.all_raw())
    spy = open_as("node@alice", "bob")  # alice's node certificate in bob's namespace
    reader = open_as("node@alice", "bob")  # (a session sees its own puts, so another one reads)
    spied = raw_bytes(reader, keys.all_data())
    spied_poses = raw_bytes(reader, keys.pose_key())
    round_trip(reader)
    round_trip(gateway_bob)
    node_bob = open_as("node@bob")

    spy.put(ELBOW, b"forged for bob")
    round_trip(spy)
    node_bob.put(ELBOW, b"bob's own")
    gateway_bob.put(keys.pose_key(), b"bob's pose")
    seen = wait_marker(at_gateway_bob, b"bob's own")
    assert [v for _, v in seen] == [b"bob's own"]
    round_trip(reader)
    nothing_more(spied)
    nothing_more(spied_poses)


def test_viewers_and_games_get_poses_and_topology_only(
    open_as: Callable[..., zenoh.Session],
) -> None:
    gateway = open_as("gateway@alice")
    topology = json.dumps({"branches": {}}).encode()
    gateway.declare_queryable(keys.TOPOLOGY, lambda q: q.reply(keys.TOPOLOGY, topology))
    clinic = open_as("viewer")  # every subject, from outside any namespace
    game = open_as("game@alice")
    game_bob = open_as("game@bob")
    got = {name: raw_bytes(s, keys.all_poses()) for name, s in (("game", game), ("bob", game_bob))}
    got["clinic"] = raw_bytes(clinic, keys.subject_prefix(keys.ANY_SUBJECT) + keys.all_poses())
    clinic_alice = raw_bytes(clinic, keys.subject_prefix("alice") + keys.pose_key())
    game_raw = raw_bytes(game, keys.all_raw())
    for s in (clinic, game, game_bob, gateway):
        round_trip(s)
    node = open_as("node@alice")
    node.put(ELBOW, b"raw")
    gateway.put(keys.pose_key(), b"pose 1")
    gateway.put(keys.pose_key(keys.LEFT_ARM), b"left arm pose")
    wait_marker(got["game"], b"left arm pose")
    wait_marker(clinic_alice, b"pose 1")
    wait_marker(got["clinic"], b"left arm pose")
    assert (keys.pose_key(), b"pose 1") in got["game"].seen

    replies = list(game.get(keys.TOPOLOGY, timeout=5))
    assert [r.ok.payload.to_bytes() for r in replies if r.ok] == [topology]

    game.put(keys.pose_key(), b"a game's fake pose")  # games only read
    round_trip(game)
    gateway.put(keys.pose_key(), b"pose 2")
    seen = wait_marker(got["clinic"], b"pose 2")
    assert b"a game's fake pose" not in [v for _, v in seen]
    round_trip(game)
    round_trip(game_bob)
    nothing_more(game_raw)  # no raw samples
    nothing_more(got["bob"])  # nor another subject's poses


def test_only_the_admin_may_calibrate(open_as: Callable[..., zenoh.Session]) -> None:
    gateway = open_as("gateway@alice")
    asked: queue.SimpleQueue[str] = queue.SimpleQueue()

    def on_query(query: zenoh.Query) -> None:
        asked.put(str(query.selector))
        query.reply(keys.CALIBRATE_TPOSE, b"calibrated")

    gateway.declare_queryable(keys.CALIBRATE_TPOSE, on_query)
    round_trip(gateway)
    viewer = open_as("viewer@alice")
    assert [r for r in viewer.get(keys.CALIBRATE_TPOSE, timeout=3) if r.ok] == []
    admin = open_as("admin", "alice")
    replies = [r.ok.payload.to_bytes() for r in admin.get(keys.CALIBRATE_TPOSE, timeout=5) if r.ok]
    assert replies == [b"calibrated"]
    assert asked.get(timeout=1).startswith(keys.CALIBRATE_TPOSE)
    assert asked.empty()  # the viewer's query never reached the gateway


# --- the real processes, end to end ---------------------------------------------------


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)


def test_secure_body_network_end_to_end(
    cert_dir: Path, processes: list[subprocess.Popen[str]]
) -> None:
    """`bodynet router`, `node` and `gateway` as processes, each with its own identity."""
    layout = Layout(cert_dir)
    port = free_port()
    endpoint = f"tls/localhost:{port}"

    def run(*args: str) -> None:
        processes.append(
            subprocess.Popen([str(BODYNET), *args], text=True, stderr=subprocess.DEVNULL)
        )

    run("router", "-c", str(layout.config("router")), "-l", f"tls/127.0.0.1:{port}")
    run("gateway", "--mode", "client", "-c", str(layout.config("gateway@alice")), "-e", endpoint,
        "--profile", str(cert_dir.parent / "alice.toml"))  # fmt: skip
    run("node", "imu", "--sensors", "1-15", "--routine", "tpose", "--ideal",
        "-c", str(layout.config("node@alice")), "-e", endpoint)  # fmt: skip
    viewer = connect(endpoint, layout.config("viewer@alice"), wait_ms=-1)  # the router starts
    try:
        poses = Collector(viewer, keys.pose_key(), pose.decode)
        seen = poses.wait_for(lambda s: bool(s) and len(s[-1][1].sources) == 15, timeout=60)
        assert all(k.startswith("body/") for k in seen[-1][1].sources)
        deadline = time.monotonic() + 10
        replies: list[zenoh.Reply] = []
        while not replies and time.monotonic() < deadline:
            replies = [r for r in viewer.get(keys.TOPOLOGY, timeout=2) if r.ok]
        assert replies, "the viewer could not query the topology"
    finally:
        viewer.close()
    assert all(p.poll() is None for p in processes)  # nothing fell over
