"""X.509 material for mutual TLS between bodynet processes and their router.

One private certificate authority signs every certificate. The router's
certificate names the hosts clients dial (rustls checks the subject
alternative names, never the common name); each client's certificate carries
its identity as the common name (``node@alice``), which the router's access
control matches exactly. Keys are ECDSA P-256 in PKCS#8 PEM, which rustls
reads. Every file is written owner-only and whole (a temporary file renamed
into place), so a failed run never leaves a half-written key behind.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CA_NAME = "bodynet CA"


class CertError(Exception):
    """Certificate material that cannot be made or read."""


@dataclass(frozen=True, slots=True)
class KeyPair:
    """A private key and the certificate that binds it to a name."""

    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate

    @property
    def common_name(self) -> str:
        return common_name(self.cert)

    def key_pem(self) -> bytes:
        return self.key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )

    def cert_pem(self) -> bytes:
        return self.cert.public_bytes(serialization.Encoding.PEM)


def common_name(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


def _now() -> dt.datetime:
    # a minute of slack for clocks that differ a little between hosts
    return dt.datetime.now(dt.UTC) - dt.timedelta(minutes=1)


def _key_usage(signs_certificates: bool) -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=True,
        key_cert_sign=signs_certificates,
        crl_sign=signs_certificates,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        encipher_only=False,
        decipher_only=False,
    )


def make_ca(days: int = 3650, name: str = CA_NAME) -> KeyPair:
    """A self-signed certificate authority that may sign end certificates only."""
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    public = key.public_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(_now())
        .not_valid_after(_now() + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(signs_certificates=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .sign(key, hashes.SHA256())
    )
    return KeyPair(key, cert)


def issue(
    ca: KeyPair,
    name: str,
    *,
    hosts: tuple[str, ...] = (),
    server: bool = False,
    days: int = 825,
) -> KeyPair:
    """A certificate for ``name`` signed by ``ca``.

    ``server`` certificates (the router's) carry ``hosts`` as DNS names or IP
    addresses, which clients check against the endpoint they dial. Every
    certificate may authenticate a client, so a router can also join another.
    """
    key = ec.generate_private_key(ec.SECP256R1())
    public = key.public_key()
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if server:
        usages.insert(0, ExtendedKeyUsageOID.SERVER_AUTH)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca.cert.subject)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(_now())
        .not_valid_after(_now() + dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(signs_certificates=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()),
            critical=False,
        )
    )
    if server:
        if not hosts:
            raise CertError("a server certificate needs at least one host name or address")
        builder = builder.add_extension(
            x509.SubjectAlternativeName([general_name(h) for h in hosts]), critical=False
        )
    return KeyPair(key, builder.sign(ca.key, hashes.SHA256()))


def general_name(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        pass
    if not host or any(not (c.isalnum() or c in "-.") for c in host):
        raise CertError(f"{host!r} is neither a host name nor an IP address")
    return x509.DNSName(host)


def cert_hosts(cert: x509.Certificate) -> tuple[str, ...]:
    """The DNS names and IP addresses a certificate is valid for."""
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return ()
    ips = [str(ip) for ip in san.get_values_for_type(x509.IPAddress)]
    return (*san.get_values_for_type(x509.DNSName), *ips)


def write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` readable by the owner only, whole or not at all
    (a nameless file until it is whole: a killed run leaves nothing); ``OutputError``
    naming ``path`` if it cannot be written."""
    from bodynet.session.outputs import atomic_path

    with atomic_path(path) as pending:  # created 0600
        pending.write_bytes(data)


def save(pair: KeyPair, cert_path: Path, key_path: Path) -> None:
    """Write a key pair as two owner-only PEM files."""
    write_private(key_path, pair.key_pem())
    write_private(cert_path, pair.cert_pem())


def load(cert_path: Path, key_path: Path) -> KeyPair:
    """Read a key pair written by ``save``; ``CertError`` if unreadable or mismatched."""
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise CertError(f"cannot read {cert_path} / {key_path}: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{key_path} is not an EC private key")
    if key.public_key().public_numbers() != cert.public_key().public_numbers():  # type: ignore[union-attr]
        raise CertError(f"{key_path} does not belong to {cert_path}")
    return KeyPair(key, cert)
