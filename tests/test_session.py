"""The Zenoh runtime a bodynet process runs: its threads, seen in /proc."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from zenoh_helpers import free_port

# A router and a client in a fresh process, 200 samples from one to the other,
# then the names of the process's threads (Zenoh names them after its runtimes).
_SCRIPT = """
import json, sys, time
from pathlib import Path
from bodynet.session import open_session, session_config
endpoint = sys.argv[1]
router = open_session(session_config("router", listen=[endpoint]))
client = open_session(session_config("client", connect=[endpoint]))
got = []
sub = router.declare_subscriber("body/**", lambda sample: got.append(sample))
time.sleep(0.5)
for i in range(200):
    client.put("body/arm/left/elbow/raw", b"x")
deadline = time.monotonic() + 10
while len(got) < 200 and time.monotonic() < deadline:
    time.sleep(0.05)
names = sorted(p.read_text().strip() for p in Path("/proc/self/task").glob("*/comm"))
print(json.dumps({"received": len(got), "threads": names}))
client.close()
router.close()
"""


def _run(env_runtime: str | None) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    if env_runtime is not None:
        env["ZENOH_RUNTIME"] = env_runtime
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = subprocess.run([sys.executable, "-c", _SCRIPT, endpoint], env=env,
                         capture_output=True, text=True, timeout=60, check=True)  # fmt: skip
    result: dict[str, object] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_a_session_receives_on_the_app_threads_unless_told_otherwise() -> None:
    lean = _run(None)
    assert lean["received"] == 200
    threads = lean["threads"]
    assert isinstance(threads, list)
    assert "app-0" in threads
    assert not [t for t in threads if t.startswith(("rx-", "acc-"))], threads
    # A user's own ZENOH_RUNTIME stands: two receiving threads of their own.
    theirs = _run("(rx: (worker_threads: 2))")
    assert theirs["received"] == 200
    threads = theirs["threads"]
    assert isinstance(threads, list)
    assert {"rx-0", "rx-1"} <= set(threads), threads


@pytest.mark.parametrize(("name", "value", "said"), [
    ("BODYNET_SUBJECT", "a/b", "environment variable BODYNET_SUBJECT: subject 'a/b'"),
    ("BODYNET_SUBJECT", "body", "environment variable BODYNET_SUBJECT: subject 'body'"),
    ("BODYNET_ZENOH_CONNECT", "nonsense", "environment variable BODYNET_ZENOH_CONNECT: "
                                          "'nonsense' is not a Zenoh endpoint"),
    ("BODYNET_ZENOH_CONNECT", "tcp/999.1.1.1:7447", "environment variable BODYNET_ZENOH_CONNECT:"
                                                    " 'tcp/999.1.1.1:7447': 999.1.1.1 is not an "
                                                    "IPv4 address"),
    ("ZENOH_RUNTIME", "garbage", "Zenoh failed to start: "),
])  # fmt: skip
def test_a_bad_environment_variable_is_one_line_as_a_bad_flag(
    name: str, value: str, said: str
) -> None:
    """The variables every command reads are checked as their flags are: one line, exit 2."""
    env = {**os.environ, name: value, "RUST_BACKTRACE": "0"}
    argv = [str(Path(sys.executable).with_name("bodynet")), "subjects", "--timeout", "1"]
    if name != "BODYNET_ZENOH_CONNECT":
        argv += ["-e", f"tcp/127.0.0.1:{free_port()}", "--connect-timeout", "1"]
    out = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 2, out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith(f"bodynet subjects: {said}"), out.stderr
    assert "Traceback" not in out.stderr
    if name == "ZENOH_RUNTIME":
        assert "ZENOH_RUNTIME='garbage'" in last


@pytest.mark.parametrize(("flag", "text", "said"), [
    ("-c", '{\n  mode: "client",\n  connect: { endpoints: ["tcp/127.0.0.1:1"], },,\n}\n',
     "cannot use Zenoh config {file}, line 3, column 48: expected identifier or string"),
    ("-c", '{ mode: "bogus" }', "cannot use Zenoh config {file}, line 1, column 9: "
                                "unknown variant `bogus`, expected one of `router`"),
    ("--cfg", 'mode:"cl', "--cfg 'mode:\"cl' (column 4 of the value): expected char_literal"),
    ("--cfg", "connect/endpoints:[bad", "--cfg 'connect/endpoints:[bad' (column 2 of the "
                                        "value): expected array, boolean, null, number"),
    ("--cfg", "no/such:1", "--cfg 'no/such:1': unknown key"),
])  # fmt: skip
def test_a_malformed_zenoh_config_is_one_clean_line_naming_where(
    tmp_path: Path, flag: str, text: str, said: str
) -> None:
    """Zenoh's parser error is one line: the file, its line and column, and what the
    parser expected; no literal \\n, Rust wrapping or picture of the line."""
    file = tmp_path / "zenoh.json5"
    file.write_text(text)
    value = str(file) if flag == "-c" else text
    argv = [str(Path(sys.executable).with_name("bodynet")), "subjects", flag, value,
            "--connect-timeout", "1", "--timeout", "1"]  # fmt: skip
    out = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1, out.stderr
    assert out.stderr.startswith(f"bodynet subjects: {said.format(file=file)}"), out.stderr
    for noise in ("\\n", "-->", "^---", "Json5Err", "Message {", ".rs:", "Str("):
        assert noise not in out.stderr


def test_a_client_that_cannot_listen_is_told_so_not_that_no_router_answered(
    router_endpoint: str,
) -> None:
    """`subjects -l` on a port that is taken: the listener is what failed; the router
    (up, on loopback) is not blamed."""
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        argv = [str(Path(sys.executable).with_name("bodynet")), "subjects", "-e", router_endpoint,
                "-l", f"tcp/127.0.0.1:{port}", "--connect-timeout", "5"]  # fmt: skip
        out = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1, out.stderr
    assert out.stderr.startswith("bodynet subjects: cannot open the Zenoh session: "), out.stderr
    assert f"127.0.0.1:{port}" in out.stderr
    assert "Address already in use" in out.stderr
    assert "router" not in out.stderr
