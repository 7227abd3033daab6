"""What the live benchmarks share: a loopback endpoint and a router on it."""

from __future__ import annotations

import socket

import zenoh

from bodynet.session import open_session, session_config


def free_endpoint() -> str:
    """A Zenoh endpoint on a free loopback port."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def router(endpoint: str) -> zenoh.Session:
    """A Zenoh router listening on ``endpoint`` (scouting off, as every bodynet session)."""
    return open_session(session_config("router", listen=[endpoint]))


def client(endpoint: str) -> zenoh.Session:
    """A client session of the router at ``endpoint``."""
    return open_session(session_config("client", connect=[endpoint]))
