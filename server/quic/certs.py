"""Self-signed certificates that browsers accept for WebTransport.

Chromium pins a certificate by `serverCertificateHashes` only when it is ECDSA
P-256 (RSA is refused) and its total validity (notAfter - notBefore) is at most
14 days; 13 days including 5 minutes of backdating is what was checked to work.
"""

from __future__ import annotations

import atexit
import base64
import datetime
import hashlib
import ipaddress
import os
import shutil
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

VALIDITY = datetime.timedelta(days=13)
BACKDATE = datetime.timedelta(minutes=5)
DEFAULT_NAMES = ("localhost", "127.0.0.1", "::1")


@dataclass(frozen=True)
class CertBundle:
    """A certificate and its key, as PEM bytes and as files aioquic can load."""

    cert_pem: bytes
    key_pem: bytes
    cert_path: Path
    key_path: Path
    sha256_hex: str
    """Lowercase hex SHA-256 of the certificate DER (serverCertificateHashes)."""
    spki_sha256_b64: str
    """Base64 SHA-256 of the SubjectPublicKeyInfo DER (--ignore-certificate-errors-spki-list)."""


def _general_name(name: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def _bundle(
    cert: x509.Certificate, cert_pem: bytes, key_pem: bytes, cert_path: Path, key_path: Path
) -> CertBundle:
    der = cert.public_bytes(serialization.Encoding.DER)
    spki = cert.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    return CertBundle(
        cert_pem=cert_pem,
        key_pem=key_pem,
        cert_path=cert_path,
        key_path=key_path,
        sha256_hex=hashlib.sha256(der).hexdigest(),
        spki_sha256_b64=base64.b64encode(hashlib.sha256(spki).digest()).decode("ascii"),
    )


def generate_cert(
    extra_names: Iterable[str] = (),
    directory: str | os.PathLike[str] | None = None,
    now: datetime.datetime | None = None,
) -> CertBundle:
    """Make a fresh ECDSA P-256 self-signed certificate and write it as PEM files.

    `directory` defaults to a new private temporary directory (the key is secret:
    files are created mode 0600). Names that parse as IP addresses become IP SANs.
    """
    names = list(dict.fromkeys([*DEFAULT_NAMES, *extra_names]))
    key = ec.generate_private_key(ec.SECP256R1())
    start = (now or datetime.datetime.now(datetime.UTC)) - BACKDATE
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "upcast")])
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        # Total validity counts the backdating: Chromium's 14-day cap applies to it.
        .not_valid_after(start + VALIDITY)
        .add_extension(
            x509.SubjectAlternativeName([_general_name(n) for n in names]), critical=False
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_pem = cert.public_bytes(serialization.Encoding.PEM)
    key_pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    if directory is None:
        folder = Path(tempfile.mkdtemp("-upcast-cert"))
        # A private key in /tmp must not outlive the process that made it.
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
    else:
        folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    cert_path = folder / "cert.pem"
    key_path = folder / "key.pem"
    cert_path.write_bytes(cert_pem)
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(key_pem)
    return _bundle(cert, cert_pem, key_pem, cert_path, key_path)


def load_cert(cert_path: str | os.PathLike[str], key_path: str | os.PathLike[str]) -> CertBundle:
    """Load an existing PEM certificate (first one in the file) and key."""
    cert_pem = Path(cert_path).read_bytes()
    key_pem = Path(key_path).read_bytes()
    cert = x509.load_pem_x509_certificate(cert_pem)
    # Fail early on a key that does not parse rather than at the first handshake.
    serialization.load_pem_private_key(key_pem, password=None)
    return _bundle(cert, cert_pem, key_pem, Path(cert_path), Path(key_path))


def der_sha256_hex(der: bytes) -> str:
    """Hex SHA-256 of a certificate DER, the form /certificate.sha256 serves."""
    return hashlib.sha256(der).hexdigest()
