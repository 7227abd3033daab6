"""Mutual TLS, roles and access control for a bodynet network.

``make_certs(DIR, subjects)`` writes a certificate authority, the router's
certificate and Zenoh config (mutual TLS only, default-deny access control),
and one folder per identity with its certificate, key and a self-contained
Zenoh client config (``-c DIR/node@alice/zenoh.json5``).

An identity is a role, for one subject (``node@alice``, whose keys are
``alice/body/...`` on the wire) or, written without ``@``, for the subjects of
the router: the default subject (plain ``body/...``) when the directory was
made without subjects, otherwise every named subject (``*/body/...``). The
certificate's common name is the identity; the router matches it exactly.

What each role may do is one table, ``GRANTS``, in verbs over bodynet keys;
each verb expands to the Zenoh messages and directions it needs (a publisher
must also be told of matching subscribers, or Zenoh filters its samples at
the writer). Everything not granted is denied.
"""

from __future__ import annotations

import json
import secrets
import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from bodynet.core import keys
from bodynet.core.keys import KeySpaceError
from bodynet.session import certs
from bodynet.session.outputs import OutputError, scratch_folder

PORT = 7447
MANIFEST = "bodynet-certs.json"
ROUTER = "router"
LOCAL_HOSTS = ("localhost", "127.0.0.1")


class SecurityError(Exception):
    """A certificate directory that cannot be made or extended as asked."""


class Role(StrEnum):
    NODE = "node"  # publishes its subject's raw samples, truths, health and liveliness
    GATEWAY = "gateway"  # reads raw samples, writes poses/topology/health, answers queries
    VIEWER = "viewer"  # reads poses, topology and health; asks for the topology
    GAME = "game"  # reads poses and topology; asks for the topology
    RECORDER = "recorder"  # reads every data key (raw, truth, poses), topology and health
    ADMIN = "admin"  # anything, the Zenoh admin space and calibration included


#: Roles that get one identity per subject, and those that also get one for
#: every subject of the router (a clinic's dashboard, a multi-subject gateway).
PER_SUBJECT = (Role.NODE, Role.GATEWAY, Role.VIEWER, Role.GAME, Role.RECORDER)
EVERY_SUBJECT = (Role.GATEWAY, Role.VIEWER, Role.RECORDER, Role.ADMIN)


@dataclass(frozen=True, slots=True, order=True)
class Identity:
    """A role, for one subject (``node@alice``) or for the router's subjects (``viewer``)."""

    role: Role
    subject: str | None = None

    @property
    def name(self) -> str:
        return str(self.role) if self.subject is None else f"{self.role}@{self.subject}"

    def __str__(self) -> str:
        return self.name

    @classmethod
    def parse(cls, name: str) -> Identity:
        role, sep, subject = name.partition("@")
        try:
            return cls(Role(role), keys.subject_name(subject) if sep else None)
        except (ValueError, KeySpaceError):
            raise SecurityError(f"{name!r} is not an identity (ROLE or ROLE@SUBJECT)") from None


def identities(subjects: Sequence[str]) -> list[Identity]:
    """Every identity a directory for ``subjects`` holds (none: the default subject)."""
    if not subjects:
        return [Identity(role) for role in Role]
    per = [Identity(role, s) for s in subjects for role in PER_SUBJECT]
    return per + [Identity(role) for role in EVERY_SUBJECT]


# --- what each role may do -------------------------------------------------------

#: Zenoh messages per verb and direction, seen from the router: ``ingress`` comes
#: from the identity, ``egress`` goes to it.
VERBS: dict[str, dict[str, tuple[str, ...]]] = {
    # put samples; learn of subscribers, else the publisher drops its samples
    "write": {"ingress": ("put", "delete"), "egress": ("declare_subscriber",)},
    # subscribe and receive samples
    "read": {"ingress": ("declare_subscriber",), "egress": ("put", "delete")},
    # hold liveliness tokens
    "token": {"ingress": ("liveliness_token",)},
    # see others' liveliness tokens, now and as they come and go
    "watch": {
        "ingress": ("declare_liveliness_subscriber", "liveliness_query"),
        "egress": ("liveliness_token", "reply"),
    },
    # answer queries
    "serve": {"ingress": ("declare_queryable", "reply"), "egress": ("query",)},
    # ask queries and get the replies
    "ask": {"ingress": ("query",), "egress": ("reply", "declare_queryable")},
}
ALL_MESSAGES = (
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "liveliness_query", "declare_liveliness_subscriber",
)  # fmt: skip

_RAW = keys.all_raw()
_TRUTH = keys.all_sites(keys.Stream.TRUTH)
_POSES = keys.all_poses()
_BATCHES = keys.all_batches()  # raw samples put together (bridges with --batch-ms)

#: What each role may do: verb -> bodynet key expressions (prefixed with the
#: identity's subject on the wire).
GRANTS: dict[Role, dict[str, tuple[str, ...]]] = {
    Role.NODE: {
        "write": (_RAW, _BATCHES, _TRUTH, keys.all_health()),
        "token": (_RAW,),
    },
    Role.GATEWAY: {
        "read": (_RAW, _BATCHES),
        "watch": (_RAW,),
        "write": (_POSES, keys.TOPOLOGY, keys.health_key("gateway")),
        "serve": (keys.TOPOLOGY, keys.CALIBRATE_TPOSE, keys.CALIBRATE_YAW),
    },
    Role.VIEWER: {
        "read": (_POSES, keys.TOPOLOGY, keys.all_health()),
        "ask": (keys.TOPOLOGY,),
    },
    Role.GAME: {
        "read": (_POSES, keys.TOPOLOGY),
        "ask": (keys.TOPOLOGY,),
    },
    Role.RECORDER: {
        "read": (keys.all_data(), _BATCHES, keys.TOPOLOGY, keys.all_health()),
        "ask": (keys.TOPOLOGY,),
    },
}

#: The admin may do anything anywhere: ``**`` never matches ``@`` chunks, so
#: bodynet's admin keys and Zenoh's admin space are named too.
ADMIN_KEYS = ("**", f"**/{keys.HEALTH}/**", f"**/{keys.TOPOLOGY}",
              f"**/{keys.CALIBRATE_TPOSE}", f"**/{keys.CALIBRATE_YAW}", f"**/{keys.BATCH}/*",
              "@/**")  # fmt: skip


def _prefix(identity: Identity, named_subjects: bool) -> str:
    if identity.subject is not None:
        return keys.subject_prefix(identity.subject)
    return keys.subject_prefix(keys.ANY_SUBJECT) if named_subjects else ""


def acl_rules(identity: Identity, named_subjects: bool) -> list[dict[str, Any]]:
    """The allow rules of one identity, as Zenoh ``access_control`` rules."""
    if identity.role is Role.ADMIN:
        return [
            {"id": f"{identity} all", "permission": "allow", "flows": ["ingress", "egress"],
             "messages": list(ALL_MESSAGES), "key_exprs": list(ADMIN_KEYS)}
        ]  # fmt: skip
    prefix = _prefix(identity, named_subjects)
    rules = []
    for verb, exprs in GRANTS[identity.role].items():
        for flow, messages in VERBS[verb].items():
            rules.append(
                {
                    "id": f"{identity} {verb} {flow}",
                    "permission": "allow",
                    "flows": [flow],
                    "messages": list(messages),
                    "key_exprs": [prefix + e for e in exprs],
                }
            )
    return rules


def access_control(ids: Iterable[Identity], named_subjects: bool, users: bool) -> dict[str, Any]:
    """A default-deny Zenoh ``access_control`` section for ``ids``.

    Each identity is matched by its certificate's common name and, with
    ``users``, also by its user name (both must match).
    """
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for ident in ids:
        own = acl_rules(ident, named_subjects)
        rules += own
        subject: dict[str, Any] = {"id": ident.name, "cert_common_names": [ident.name]}
        if users:
            subject["usernames"] = [ident.name]
        subjects.append(subject)
        policies.append({"id": ident.name, "rules": [r["id"] for r in own],
                         "subjects": [ident.name]})  # fmt: skip
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# --- Zenoh configs ---------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Layout:
    """Where the files of a certificate directory live."""

    root: Path

    @property
    def ca_cert(self) -> Path:
        return self.root / "ca.pem"

    @property
    def ca_key(self) -> Path:
        return self.root / "ca-key.pem"

    @property
    def manifest(self) -> Path:
        return self.root / MANIFEST

    def folder(self, name: str) -> Path:
        return self.root / name

    def cert(self, name: str) -> Path:
        return self.root / name / "cert.pem"

    def key(self, name: str) -> Path:
        return self.root / name / "key.pem"

    def config(self, name: str) -> Path:
        return self.root / name / ("router.json5" if name == ROUTER else "zenoh.json5")

    @property
    def users(self) -> Path:
        return self.root / ROUTER / "users.txt"


def router_config(
    where: Path,
    subjects: Sequence[str],
    users: bool,
    listen: Sequence[str] = (f"tls/0.0.0.0:{PORT}",),
) -> dict[str, Any]:
    """The router's Zenoh config; ``where`` is the directory as the router will see it."""
    layout = Layout(where)
    tls = {
        "root_ca_certificate": str(layout.ca_cert),
        "listen_certificate": str(layout.cert(ROUTER)),
        "listen_private_key": str(layout.key(ROUTER)),
        "enable_mtls": True,
        "close_link_on_expiration": True,
    }
    transport: dict[str, Any] = {"link": {"protocols": ["tls"], "tls": tls}}
    if users:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(layout.users)}}
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": access_control(identities(subjects), bool(subjects), users),
    }


def client_config(
    pair: certs.KeyPair,
    ca_pem: bytes,
    identity: Identity,
    endpoint: str,
    password: str | None = None,
) -> dict[str, Any]:
    """A self-contained client config: the key material is inline (base64)."""
    import base64

    def b64(data: bytes) -> str:
        return base64.b64encode(data).decode("ascii")

    tls = {
        "root_ca_certificate_base64": b64(ca_pem),
        "connect_certificate_base64": b64(pair.cert_pem()),
        "connect_private_key_base64": b64(pair.key_pem()),
        "enable_mtls": True,
    }
    conf: dict[str, Any] = {
        "mode": "client",
        "connect": {
            "endpoints": [endpoint],
            "timeout_ms": -1,  # wait for the router, as bodynet's plain sessions do
            "retry": {"period_init_ms": 100, "period_max_ms": 500},
        },
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"protocols": ["tls"], "tls": tls}},
    }
    if identity.subject is not None:
        conf["namespace"] = identity.subject
    if password is not None:
        conf["transport"]["auth"] = {"usrpwd": {"user": identity.name, "password": password}}
    return conf


def render(conf: dict[str, Any], header: str) -> str:
    """A config as JSON5 text (JSON with a comment header)."""
    lines = "".join(f"// {line}".rstrip() + "\n" for line in header.strip().splitlines())
    return lines + _dump(conf, 0) + "\n"


def _dump(value: Any, indent: int, width: int = 100) -> str:
    """JSON, each value on one line where it fits in ``width``."""
    flat = json.dumps(value, separators=(", ", ": "))
    if not isinstance(value, dict | list) or indent + len(flat) <= width or not value:
        return flat
    pad = " " * (indent + 2)
    if isinstance(value, dict):
        items = [f"{pad}{json.dumps(k)}: {_dump(v, indent + 2, width)}"
                 for k, v in value.items()]  # fmt: skip
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    items = [pad + _dump(v, indent + 2, width) for v in value]
    return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"


def router_text(where: Path, subjects: Sequence[str], users: bool, port: int = PORT) -> str:
    """The router's config file as ``bodynet certs`` writes it (see ``router_config``)."""
    conf = router_config(where, subjects, users, [f"tls/0.0.0.0:{port}"])
    names = ", ".join(i.name for i in identities(subjects))
    return render(conf, ROUTER_HEADER.format(path=Layout(where).config(ROUTER), names=names))


ROUTER_HEADER = """\
bodynet secure router: mutual TLS only, default-deny access control.
Written by `bodynet certs`; regenerate rather than edit (see README, Security).
Run: bodynet router -c {path}
Identities (certificate common names): {names}
"""


# --- the directory -----------------------------------------------------------------


@dataclass
class Made:
    """What ``make_certs`` did."""

    created: list[str] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)
    subjects: list[str] = field(default_factory=list)


def make_certs(
    root: Path,
    subjects: Sequence[str] = (),
    hosts: Sequence[str] = (),
    users: bool = False,
    port: int = PORT,
    router_path: Path | None = None,
    days: int = 825,
) -> Made:
    """Create (or extend) a certificate directory; see the module docstring.

    Anything missing is made, anything present is kept: running again with the
    same arguments changes nothing, and with a new subject adds its identities,
    signed by the same CA. Conflicting arguments raise ``SecurityError``.
    """
    subjects = [keys.subject_name(s) for s in dict.fromkeys(subjects)]
    layout = Layout(root)
    manifest = _read_manifest(layout)
    if manifest is not None:
        hosts = hosts or manifest["hosts"]
        if bool(manifest["subjects"]) != bool(subjects) and subjects:
            raise SecurityError(
                f"{root} was made for the default subject (plain body/... keys); "
                "named subjects need a directory of their own"
            )
        if manifest["users"] != users:
            raise SecurityError(
                f"{root} was made {'with' if manifest['users'] else 'without'} --users; "
                "pass the same again"
            )
        subjects = list(dict.fromkeys([*manifest["subjects"], *subjects]))
        port = port if port != PORT else manifest["port"]
    all_hosts = tuple(dict.fromkeys((*hosts, *LOCAL_HOSTS)))
    for host in all_hosts:
        certs.general_name(host)  # a bad name fails here, before anything is written
    made = Made(subjects=subjects)
    if manifest is not None:
        _fill(layout, root, made, hosts, all_hosts, users, port, router_path, days)
        return made
    # a new directory is made beside its place and renamed into it when whole
    root.parent.mkdir(parents=True, exist_ok=True)
    work = scratch_folder(root)  # 0700; one a killed run left is removed by the next
    try:
        _fill(Layout(work), root, made, hosts, all_hosts, users, port, router_path, days)
        if root.exists():
            root.rmdir()  # empty, as _read_manifest checked
        work.rename(root)
    except OutputError as exc:  # named in the scratch folder: told as where it was going
        shutil.rmtree(work, ignore_errors=True)
        raise OutputError(str(exc).replace(str(work), str(root), 1)) from None
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return made


def _fill(
    layout: Layout,
    root: Path,
    made: Made,
    hosts: Sequence[str],
    all_hosts: tuple[str, ...],
    users: bool,
    port: int,
    router_path: Path | None,
    days: int,
) -> None:
    """Write what is missing into ``layout``, a directory that will be at ``root``."""
    subjects = made.subjects
    ca = _ca(layout, made, days * 4)
    router = _pair(layout, ROUTER, made, lambda: certs.issue(ca, ROUTER, hosts=all_hosts,
                                                             server=True, days=days))  # fmt: skip
    missing = [h for h in all_hosts if h not in certs.cert_hosts(router.cert)]
    if missing:
        raise SecurityError(
            f"{Layout(root).cert(ROUTER)} is not valid for {', '.join(missing)} "
            f"(it names {', '.join(certs.cert_hosts(router.cert))}); remove "
            f"{Layout(root).folder(ROUTER)} and run again to reissue it"
        )
    passwords = _read_users(layout) if users else {}
    ca_pem = ca.cert_pem()
    endpoint = f"tls/{(hosts or LOCAL_HOSTS)[0]}:{port}"
    for ident in identities(subjects):
        pair = _pair(layout, ident.name, made, lambda i=ident: certs.issue(ca, i.name, days=days))
        if users and ident.name not in passwords:
            passwords[ident.name] = secrets.token_urlsafe(18)
        conf = client_config(pair, ca_pem, ident, endpoint, passwords.get(ident.name))
        header = f"bodynet identity {ident}: use with -c {Layout(root).config(ident.name)}"
        certs.write_private(layout.config(ident.name), render(conf, header).encode())
    if users:
        text = "".join(f"{name}:{pw}\n" for name, pw in sorted(passwords.items()))
        certs.write_private(layout.users, text.encode())
    text = router_text(router_path or root.resolve(), subjects, users, port)
    certs.write_private(layout.config(ROUTER), text.encode())
    info = {"subjects": subjects, "hosts": list(hosts), "users": users, "port": port}
    # the manifest last: a directory without one was never finished
    certs.write_private(layout.manifest, (json.dumps(info, indent=2) + "\n").encode())


#: what to do about a damaged manifest: its CA signed certificates that may be in use
_REDO = "; restore it from a copy, or make new certificates in a new directory"


def _read_manifest(layout: Layout) -> dict[str, Any] | None:
    root = layout.root
    if root.exists() and not root.is_dir():
        raise SecurityError(f"{root} exists and is not a directory")
    if not layout.manifest.exists():
        if root.exists() and any(root.iterdir()):
            raise SecurityError(
                f"{root} is not empty and was not made by bodynet certs; choose another directory"
            )
        return None
    try:
        info = json.loads(layout.manifest.read_text())
    except (OSError, ValueError) as exc:
        raise SecurityError(f"cannot read {layout.manifest}: {exc}") from None
    fields = ("subjects", "hosts", "users", "port")
    damaged = f"{layout.manifest} is damaged (not what bodynet certs wrote"
    if not isinstance(info, dict) or (missing := [f for f in fields if f not in info]):
        what = (f"no {', '.join(missing)}" if isinstance(info, dict)
                else f"a JSON {type(info).__name__}, not an object")  # fmt: skip
        raise SecurityError(f"{damaged}: {what}){_REDO}")
    try:
        return {"subjects": list(info["subjects"]), "hosts": list(info["hosts"]),
                "users": bool(info["users"]), "port": int(info["port"])}  # fmt: skip
    except (ValueError, TypeError) as exc:
        raise SecurityError(f"{damaged}: {exc}){_REDO}") from None


def _ca(layout: Layout, made: Made, days: int) -> certs.KeyPair:
    have = layout.ca_cert.exists(), layout.ca_key.exists()
    if all(have):
        made.kept.append("ca")
        return _load(layout.ca_cert, layout.ca_key)
    if any(have):
        raise SecurityError(f"{layout.root} has half a CA ({layout.ca_cert}, {layout.ca_key})")
    if any(layout.root.glob("*/cert.pem")):
        raise SecurityError(f"{layout.root} has certificates but no CA; choose another directory")
    ca = certs.make_ca(days)
    certs.save(ca, layout.ca_cert, layout.ca_key)
    made.created.append("ca")
    return ca


def _pair(layout: Layout, name: str, made: Made, issue: Any) -> certs.KeyPair:
    cert, key = layout.cert(name), layout.key(name)
    if cert.exists() and key.exists():
        made.kept.append(name)
        return _load(cert, key)
    layout.folder(name).mkdir(mode=0o700, exist_ok=True)
    pair: certs.KeyPair = issue()
    certs.save(pair, cert, key)
    made.created.append(name)
    return pair


def _load(cert: Path, key: Path) -> certs.KeyPair:
    try:
        return certs.load(cert, key)
    except certs.CertError as exc:
        raise SecurityError(str(exc)) from None


def _read_users(layout: Layout) -> dict[str, str]:
    if not layout.users.exists():
        return {}
    out = {}
    for line in layout.users.read_text().splitlines():
        name, sep, password = line.partition(":")
        if sep:
            out[name] = password
    return out
