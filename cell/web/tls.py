"""The screen's HTTPS certificate: the one configured (`service.web.tls_certificate` and
`tls_key`), or a self-signed one made on first start beside OPC UA's (`screen-cert.pem`,
`screen-key.pem` in the certificate folder; the key readable by its owner only).

A browser warns about a self-signed certificate until it is trusted (docs/security.md says
how, and how to replace or rotate it: delete both files and restart, or configure your own).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
import socket
import ssl
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from cell.atomicfile import write_atomic
from cell.errors import ConfigError

log = logging.getLogger(__name__)

CERT_NAME, KEY_NAME = "screen-cert.pem", "screen-key.pem"
VALID_DAYS = 5 * 365


def server_context(certificate: Path | None, key: Path | None, cert_dir: Path, host: str) -> ssl.SSLContext:
    """A TLS 1.2+ server context from the configured certificate and key, else from the made one."""
    if certificate is None or key is None:
        certificate, key = ensure_self_signed(cert_dir, host)
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.set_alpn_protocols(["http/1.1"])
    try:
        context.load_cert_chain(certificate, key)
    except FileNotFoundError as e:
        raise ConfigError(f"screen HTTPS: {e.filename}: file not found", hint=_HINT) from None
    except (ssl.SSLError, OSError) as e:
        raise ConfigError(
            f"screen HTTPS: cannot use certificate {certificate} with key {key}: {getattr(e, 'reason', None) or e}",
            hint=_HINT,
        ) from None
    return context


_HINT = (
    "service.web.tls_certificate and tls_key must be PEM files that belong together; leave both unset to have one made"
)


def ensure_self_signed(cert_dir: Path, host: str) -> tuple[Path, Path]:
    """The made certificate and key in `cert_dir`, made now if either is missing."""
    cert, key = cert_dir / CERT_NAME, cert_dir / KEY_NAME
    if cert.is_file() and key.is_file():
        return cert, key
    cert_dir.mkdir(parents=True, exist_ok=True)
    private = ec.generate_private_key(ec.SECP256R1())
    names = _names(host)
    now = dt.datetime.now(dt.UTC)
    subject = x509.Name(
        [
            x509.NameAttribute(NameOID.COMMON_NAME, "pick-cell screen"),
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "pick-cell"),
        ]
    )
    built = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(private.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .sign(private, hashes.SHA256())
    )
    key_pem = private.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )

    def write_key(f) -> None:
        os.fchmod(f.fileno(), 0o600)
        f.write(key_pem)

    write_atomic(key, write_key)
    write_atomic(cert, lambda f: f.write(built.public_bytes(serialization.Encoding.PEM)))
    fingerprint = built.fingerprint(hashes.SHA256()).hex(":")
    log.warning("screen HTTPS: made a self-signed certificate %s (SHA-256 %s)", cert, fingerprint)
    return cert, key


def _names(host: str) -> list[x509.GeneralName]:
    """The names the certificate is for: this machine's, loopback's, and the configured host."""
    dns = {socket.gethostname(), "localhost"}
    ips = {ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("::1")}
    try:
        address = ipaddress.ip_address(host.strip("[]"))
        if not address.is_unspecified:
            ips.add(address)
    except ValueError:
        dns.add(host)
    return [x509.DNSName(n) for n in sorted(dns) if n] + [x509.IPAddress(a) for a in sorted(ips, key=str)]


def fingerprint(certificate: Path) -> str:
    """SHA-256 of a PEM certificate, as browsers show it (for the operator to compare)."""
    cert = x509.load_pem_x509_certificate(certificate.read_bytes())
    return cert.fingerprint(hashes.SHA256()).hex(":").upper()
