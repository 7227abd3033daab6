"""Command-line wiring of security: ``bodynet certs``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bodynet.core.keys import KeySpaceError, subject_name
from bodynet.session import argtypes


def _subject(text: str) -> str:
    try:
        return subject_name(text)
    except KeySpaceError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _router_path(text: str) -> Path:
    """A path on the router's machine (not checked here), printable."""
    return Path(argtypes.free_text(1000)(text))


def cmd_certs(args: argparse.Namespace) -> int:
    from bodynet.session.certs import CertError
    from bodynet.session.outputs import OutputError
    from bodynet.session.security import Layout, SecurityError, make_certs

    try:
        made = make_certs(args.dir, args.subject, args.host, args.users, args.port,
                          args.router_path, args.days)  # fmt: skip
    except (SecurityError, CertError, KeySpaceError) as exc:
        print(f"bodynet certs: {exc}", file=sys.stderr)
        return 2
    except OutputError as exc:  # it names the file
        print(f"bodynet certs: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"bodynet certs: cannot write {exc.filename or args.dir}: {exc.strerror or exc}",
              file=sys.stderr)  # fmt: skip
        return 2
    layout = Layout(args.dir)
    subjects = ", ".join(made.subjects) or "the default subject (plain body/... keys)"
    print(f"bodynet certs: {args.dir} for {subjects}")
    print(f"  created: {', '.join(made.created) or 'nothing (all there already)'}")
    if made.kept:
        print(f"  kept:    {', '.join(made.kept)}")
    print(f"  router:  bodynet router -c {layout.config('router')}")
    print(f"  clients: -c {layout.root}/<identity>/zenoh.json5, e.g. "
          f"bodynet view -c {layout.root}/viewer{'@' + made.subjects[0] if made.subjects else ''}"
          "/zenoh.json5")  # fmt: skip
    print(f"  keep {layout.ca_key} away from the network; it signs new identities")
    return 0


def add_certs_args(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Create DIR with a certificate authority, the router's certificate and "
        "config (mutual TLS only, default-deny access control) and one folder per identity "
        "(ROLE@SUBJECT, or ROLE for the router's subjects) with its certificate, key and "
        "Zenoh client config. Run again to add subjects; what exists is kept."
    )
    p.add_argument("dir", type=argtypes.output_dir, metavar="DIR",
                   help="where to write (created 0700)")  # fmt: skip
    p.add_argument("--subject", action="append", default=[], metavar="NAME", type=_subject,
                   help="a subject to serve (repeat; default: the default subject)")  # fmt: skip
    p.add_argument("--host", action="append", default=[], metavar="NAME", type=argtypes.hostname,
                   help="a name or address clients dial the router by (repeat; "
                        "localhost and 127.0.0.1 are always in; the first goes into "
                        "client configs)")  # fmt: skip
    p.add_argument("--users", action="store_true",
                   help="also require a user name and password (one per identity)")  # fmt: skip
    p.add_argument("--port", type=argtypes.port, default=7447, help="router port (default 7447)")
    p.add_argument("--router-path", type=_router_path, default=None, metavar="PATH",
                   help="where DIR will be on the router's machine, for the paths in its config "
                        "(default: DIR)")  # fmt: skip
    p.add_argument("--days", type=argtypes.positive_int(36500, "days, a hundred years at most"),
                   default=825, help="validity of the certificates")  # fmt: skip
