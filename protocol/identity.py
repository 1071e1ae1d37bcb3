"""Identities: per run (a CA made for one run, one certificate per role), or kept by a site.

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


def _builder(subject: str, issuer, public_key, days: int = VALID_DAYS):
    from cryptography import x509

    now = datetime.datetime.now(datetime.UTC)
    return (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(issuer)
            .public_key(public_key).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days)))


def make_ca(cn: str, days: int = VALID_DAYS):
    """A fresh self-signed CA: (private key, certificate)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    usage = x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                          key_encipherment=False, data_encipherment=False, key_agreement=False,
                          encipher_only=False, decipher_only=False)
    cert = (_builder(cn, _name(cn), key.public_key(), days)
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


# ---- site identities: a CA made once per site, robot identities issued from it and kept ----------
#
# Per-run identities suit a run that lives and dies on its own. A site's robots outlive every run:
# restarting the fleet must not mean copying new files to each robot. So a site keeps its CA key
# (SITE/ca.key, 0600; it signs each serve's server roles) and each robot's identity once issued.
#
# Revocation without touching the others, with what Zenoh's TLS offers (a `root_ca_certificate`
# file of trust anchors; no revocation list, no OCSP): each robot's certificate is signed by an
# issuer of its own, a one-certificate CA whose key is discarded at once, and the fleet's processes
# trust SITE/trust.pem = the site CA + the issuer of every robot in good standing. Revoking a robot
# drops its issuer from trust.pem: its certificate no longer chains to anything the fleet trusts
# (refused at the TLS handshake), and no other robot's files change. Rotating a robot is revoking
# its old issuer and issuing anew. A robot checks the fleet against the site CA only (its ca.pem).
#
#   SITE/ca.pem, SITE/ca.key        the site CA (the key never leaves the site's machine)
#   SITE/trust.pem                  what the fleet's processes trust (rebuilt on issue / revoke)
#   SITE/robots/<role>/             what a robot copies: ca.pem (the site CA), <role>.pem, <role>.key
#   SITE/robots/<role>/issuer.pem   that robot's own issuer (in trust.pem while it is in good standing)
#   SITE/revoked.json               every revoked or rotated-out identity: role, serial, when, why

SITE_CA_KEY = "ca.key"
SITE_TRUST = "trust.pem"
SITE_ROBOTS = "robots"
SITE_REVOKED = "revoked.json"
SITE_CA_DAYS = 3650  # a site's CA outlives its robots' certificates (VALID_DAYS), which are re-issued


class SiteError(ValueError):
    """A site directory that cannot do what was asked (one line naming the fix)."""


def _load_pem_cert(path: Path):
    from cryptography import x509

    return x509.load_pem_x509_certificate(Path(path).read_bytes())


def site_ca(site: Path):
    """(key, certificate) of the site's CA."""
    from cryptography.hazmat.primitives import serialization

    s = Path(site)
    if not (s / SITE_CA_KEY).is_file() or not (s / CA_FILE).is_file():
        raise SiteError(f"{s} is not a site: no {CA_FILE} / {SITE_CA_KEY} (fix: hammer site init {s})")
    key = serialization.load_pem_private_key((s / SITE_CA_KEY).read_bytes(), password=None)
    return key, _load_pem_cert(s / CA_FILE)


def init_site(site: Path, name: str = "hammer-site-ca") -> Path:
    """Make a site's CA once (SITE/ca.pem, SITE/ca.key 0600, in a 0700 directory). Refuses a
    directory that already is a site: a new CA would cut off every robot issued from the old one."""
    s = Path(site)
    if (s / SITE_CA_KEY).exists():
        raise SiteError(f"{s} already holds a site CA; its robots' identities chain to it (to start over, "
                        f"remove {s} first)")
    s.mkdir(parents=True, exist_ok=True)
    s.chmod(0o700)
    key, cert = make_ca(name, days=SITE_CA_DAYS)
    _write_private(s / SITE_CA_KEY, _pem_key(key))
    _write_private(s / CA_FILE, _pem_cert(cert))
    (s / SITE_ROBOTS).mkdir(mode=0o700, exist_ok=True)
    _write_trust(s)
    return s


def robot_dir(site: Path, role: str) -> Path:
    return Path(site) / SITE_ROBOTS / role


def issue_robot(site: Path, role: str, hosts: tuple[str, ...] = (), rotate: bool = False) -> Identity:
    """Issue `role`'s identity from the site (SITE/robots/<role>/: the three files the robot copies)
    under an issuer of its own. An existing identity is replaced only with `rotate` (the old one is
    revoked: the robot must get the new files)."""
    _check_robot_role(role)
    s = Path(site)
    _, site_cert = site_ca(s)
    d = robot_dir(s, role)
    if (d / f"{role}.pem").is_file():
        if not rotate:
            raise SiteError(f"{role} already has an identity in {d} (fix: --rotate to replace it; the robot then "
                            f"needs the new files)")
        _revoke_files(s, role, "rotated")
    d.mkdir(parents=True, exist_ok=True)
    d.chmod(0o700)
    issuer_key, issuer_cert = make_ca(f"hammer-issuer-{role}-{os.urandom(4).hex()}")
    key, cert = make_role_cert(issuer_key, issuer_cert, role, hosts)
    del issuer_key  # never written: only this one certificate will ever chain to this issuer
    _write_private(d / "issuer.pem", _pem_cert(issuer_cert))
    _write_private(d / CA_FILE, _pem_cert(site_cert))
    _write_private(d / f"{role}.pem", _pem_cert(cert))
    _write_private(d / f"{role}.key", _pem_key(key))
    _write_trust(s)
    return identity_of(d, role)


def revoke_robot(site: Path, role: str) -> dict:
    """Take `role` out of the site: its issuer leaves trust.pem, its files move to
    SITE/robots/revoked/, and the record goes into revoked.json. Other robots are untouched; the fleet
    refuses it from its next start."""
    _check_robot_role(role)
    s = Path(site)
    site_ca(s)
    if not (robot_dir(s, role) / f"{role}.pem").is_file():
        raise SiteError(f"{role} has no identity in {s} to revoke (hammer site list {s})")
    record = _revoke_files(s, role, "revoked")
    _write_trust(s)
    return record


def site_robots(site: Path) -> dict[str, dict]:
    """The site's robots in good standing: role -> serial, not_after."""
    out = {}
    base = Path(site) / SITE_ROBOTS
    for d in sorted(base.iterdir()) if base.is_dir() else ():
        cert_file = d / f"{d.name}.pem"
        if d.name != "revoked" and cert_file.is_file():
            c = _load_pem_cert(cert_file)
            out[d.name] = {"serial": format(c.serial_number, "x"), "not_after": c.not_valid_after_utc.isoformat()}
    return out


def revoked(site: Path) -> list[dict]:
    import json

    f = Path(site) / SITE_REVOKED
    return json.loads(f.read_text()) if f.is_file() else []


def site_run_identities(site: Path, directory: Path, roles: list[str], hosts: tuple[str, ...] = ()) -> None:
    """A secure run's identity directory from a site: the server roles (every role but the robots)
    get certificates signed by the site CA, made anew for the run; each robot role gets its kept
    identity from the site (issued now if it has none: a robot the launcher starts itself), and so
    does the site feed (`site`) where the site issued it one; ca.pem is the site's trust.pem, so the
    run accepts exactly the robots (and site feed) in good standing."""
    import shutil

    s = Path(site)
    site_key, site_cert = site_ca(s)
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    d.chmod(0o700)
    for role in roles:
        # a robot's kept identity (issued now for one the launcher starts itself); the site feed's kept one
        # where the site was issued one (an external site), else made anew like a server role's (the world)
        kept = _is_robot(role) or (role == SITE_FEED and (robot_dir(s, role) / f"{role}.pem").is_file())
        if kept:
            if not (robot_dir(s, role) / f"{role}.pem").is_file():
                issue_robot(s, role, hosts)
            for name in (f"{role}.pem", f"{role}.key"):
                (d / name).unlink(missing_ok=True)
                shutil.copyfile(robot_dir(s, role) / name, d / name)
                (d / name).chmod(0o600)
        else:
            key, cert = make_role_cert(site_key, site_cert, role, hosts)
            ident = identity_of(d, role)
            _write_private(ident.cert, _pem_cert(cert))
            _write_private(ident.key, _pem_key(key))
    _write_private(d / CA_FILE, (s / SITE_TRUST).read_bytes())


def _is_robot(role: str) -> bool:
    return role.startswith("local-") and role[6:].isdigit()


SITE_FEED = "site"  # the site feed's publisher (protocol.access.SITE): kept like a robot's where issued


def _check_robot_role(role: str) -> None:
    if not _is_robot(role) and role != SITE_FEED:
        raise SiteError(f"{role!r}: a site issues robot identities, local-<i> (e.g. local-0), and the site feed's, "
                        "site; the fleet's own roles get theirs from the site CA at every start")


def _write_trust(site: Path) -> None:
    s = Path(site)
    pems = [(s / CA_FILE).read_bytes()]
    base = s / SITE_ROBOTS
    for d in sorted(base.iterdir()) if base.is_dir() else ():
        if d.name != "revoked" and (d / "issuer.pem").is_file():
            pems.append((d / "issuer.pem").read_bytes())
    _write_private(s / SITE_TRUST, b"".join(pems))


def _revoke_files(site: Path, role: str, why: str) -> dict:
    import json
    import shutil

    s = Path(site)
    d = robot_dir(s, role)
    cert = _load_pem_cert(d / f"{role}.pem")
    now = datetime.datetime.now(datetime.UTC)
    record = {"role": role, "serial": format(cert.serial_number, "x"), "at": now.isoformat(timespec="seconds"),
              "why": why}
    gone = s / SITE_ROBOTS / "revoked" / f"{role}-{record['serial'][:12]}"
    gone.parent.mkdir(mode=0o700, exist_ok=True)
    shutil.move(str(d), str(gone))
    records = revoked(s) + [record]
    (s / SITE_REVOKED).write_text(json.dumps(records, indent=1))
    return record
