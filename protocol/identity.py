"""Per-run identities: a certificate authority made for one run and one certificate per role.

Zenoh's mutual TLS admits a process only if its certificate chains to the run's CA, and its
access rules (protocol.access) name a role by the certificate's common name (CN = role name), so
holding `local-1.key` is what makes a process local-1. The CA's private key signs the role
certificates and is then thrown away: nobody can mint a new identity for the run afterwards, and
a copied run directory holds no key that admits more than the roles it was given.

Layout (directory mode 0700, every file 0600, so other users of the host cannot read the keys):

  RUN/identity/ca.pem            the run's CA certificate (every role needs it)
  RUN/identity/<role>.pem        the role's certificate (CN = role)
  RUN/identity/<role>.key        the role's private key

A remote role needs exactly three files: ca.pem, <role>.pem and <role>.key (docs/security.md).
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path

IDENTITY_DIR = "identity"
CA_FILE = "ca.pem"
VALID_DAYS = 365


@dataclass(frozen=True)
class Identity:
    """Where one role's TLS material lives."""

    role: str
    ca: Path
    cert: Path
    key: Path

    def missing(self) -> list[Path]:
        return [p for p in (self.ca, self.cert, self.key) if not p.is_file()]


def identity_dir(run_dir: Path) -> Path:
    return Path(run_dir) / IDENTITY_DIR


def identity_of(directory: Path, role: str) -> Identity:
    d = Path(directory)
    return Identity(role, d / CA_FILE, d / f"{role}.pem", d / f"{role}.key")


def _write_private(path: Path, data: bytes) -> None:
    """Create `path` readable by its owner only, before any byte is written."""
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _name(cn: str):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _builder(subject: str, issuer, public_key):
    from cryptography import x509

    now = datetime.datetime.now(datetime.UTC)
    return (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer)
            .public_key(public_key).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=VALID_DAYS)))


def make_ca(cn: str):
    """A fresh self-signed CA: (private key, certificate)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    usage = x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False,
                          encipher_only=False, decipher_only=False)
    cert = (_builder(cn, _name(cn), key.public_key())
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(usage, critical=True)
            .sign(key, hashes.SHA256()))
    return key, cert


def make_role_cert(ca_key, ca_cert, role: str, hosts: tuple[str, ...] = ()):
    """A certificate for `role` (CN = role) signed by the CA, good for both ends of a TLS link
    (every role listens and connects). SANs: localhost, 127.0.0.1 and `hosts`."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = ec.generate_private_key(ec.SECP256R1())
    names: list[x509.GeneralName] = []
    for h in ("localhost", "127.0.0.1", *hosts):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    cert = (_builder(role, ca_cert.subject, key.public_key())
            .add_extension(x509.SubjectAlternativeName(names), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    return key, cert


def _pem_cert(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


def _pem_key(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def create_identities(directory: Path, roles: list[str], ca_name: str = "hammer-run-ca",
                      hosts: tuple[str, ...] = ()) -> dict[str, Identity]:
    """Write a new CA and one certificate + key per role into `directory` (mode 0700, files 0600);
    the CA key is not kept. Any earlier identities there are replaced."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    d.chmod(0o700)
    ca_key, ca_cert = make_ca(ca_name)
    _write_private(d / CA_FILE, _pem_cert(ca_cert))
    out = {}
    for role in roles:
        key, cert = make_role_cert(ca_key, ca_cert, role, hosts)
        ident = identity_of(d, role)
        _write_private(ident.cert, _pem_cert(cert))
        _write_private(ident.key, _pem_key(key))
        out[role] = ident
    return out


def has_identities(directory: Path, roles: list[str]) -> bool:
    return all(not identity_of(directory, r).missing() for r in roles)
