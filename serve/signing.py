"""Signed bundles: who made this team, and is it what they made?

A bundle's manifest holds the sha256 of every weights file and its own seal (the sha256 of the
rest of the manifest, config included: `bundle.seal`), so the manifest's bytes stand for the whole
bundle. Signing puts an ed25519 signature of exactly those bytes in `BUNDLE/manifest.sig`; an edge
agent or a server given trusted public keys (`--trust KEY.pub`) loads a bundle only if one of them
verifies it, and refuses an unsigned, tampered or foreign-signed bundle in one line. The private
key never leaves the machine that exports (0600, PEM PKCS#8); the public key is what robots get.

Why ed25519 through `cryptography`: a base dependency already (the secure profile's certificates),
64-byte signatures, microseconds to verify on a robot; nothing is unpickled or executed.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
from pathlib import Path

SIGNATURE = "manifest.sig"  # beside the manifest it signs


class SignatureError(ValueError):
    """The bundle's signature is missing or does not verify; the message is the reason and its fix."""


def new_key(path: Path, force: bool = False) -> tuple[Path, Path]:
    """Write a new ed25519 key pair: `PATH.key` (private, 0600) and `PATH.pub`; returns both paths."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    path = Path(path)
    private, public = path.with_name(path.name + ".key"), path.with_name(path.name + ".pub")
    for p in (private, public):
        if p.exists() and not force:
            raise FileExistsError(f"{p} exists; fix: choose another name or pass --force to replace the key pair")
    path.parent.mkdir(parents=True, exist_ok=True)
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    fd = os.open(private, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(pem)
    os.chmod(private, 0o600)
    public.write_bytes(key.public_key().public_bytes(serialization.Encoding.PEM,
                                                     serialization.PublicFormat.SubjectPublicKeyInfo))
    return private, public


def _private(path: Path):
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    try:
        key = serialization.load_pem_private_key(Path(path).read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as e:
        raise SignatureError(f"--sign {path}: not a readable private key ({e}); fix: make one with "
                             "`hammer keygen NAME` and pass NAME.key") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SignatureError(f"--sign {path}: not an ed25519 key; fix: make one with `hammer keygen NAME`")
    return key


def _public(path: Path):
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    try:
        key = serialization.load_pem_public_key(Path(path).read_bytes())
    except (OSError, ValueError, TypeError) as e:
        raise SignatureError(f"--trust {path}: not a readable public key ({e}); fix: pass the NAME.pub that "
                             "`hammer keygen NAME` wrote") from None
    if not isinstance(key, Ed25519PublicKey):
        raise SignatureError(f"--trust {path}: not an ed25519 public key; fix: pass the NAME.pub of `hammer keygen`")
    return key


def key_id(public_key) -> str:
    """A short name of a public key (the first 16 hex digits of the sha256 of its raw bytes)."""
    from cryptography.hazmat.primitives import serialization

    raw = public_key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:16]


def sign_manifest(manifest: Path, private_key: Path) -> str:
    """Sign a bundle's manifest file (its exact bytes) with `private_key`, into SIGNATURE beside it;
    returns the key id."""
    key = _private(private_key)
    data = Path(manifest).read_bytes()
    kid = key_id(key.public_key())
    Path(manifest).with_name(SIGNATURE).write_text(json.dumps(
        {"algorithm": "ed25519", "key_id": kid, "signature": base64.b64encode(key.sign(data)).decode()}, indent=1))
    return kid


def verify_manifest(manifest: Path, trusted: list[Path] | tuple[Path, ...]) -> str:
    """The key id of the trusted key that signed this bundle manifest; SignatureError otherwise (no
    signature, a malformed one, or one no trusted key verifies: tampered, or signed by another key)."""
    from cryptography.exceptions import InvalidSignature

    manifest = Path(manifest)
    bundle_dir = manifest.parent
    keys = [_public(p) for p in trusted]
    sig_file = manifest.with_name(SIGNATURE)
    if not sig_file.is_file():
        raise SignatureError(f"{bundle_dir}: not signed ({SIGNATURE} missing) and --trust asks for a signed bundle; "
                             "fix: sign it where it was exported (`hammer sign BUNDLE --key NAME.key`)")
    try:
        sig = json.loads(sig_file.read_text())
        signature = base64.b64decode(sig["signature"], validate=True)
        if sig.get("algorithm") != "ed25519" or len(signature) != 64:
            raise ValueError("expected an ed25519 signature of 64 bytes")
    except (ValueError, KeyError, TypeError) as e:
        raise SignatureError(f"{sig_file}: not a bundle signature ({e}); fix: sign the bundle again") from None
    data = manifest.read_bytes()
    for key in keys:
        try:
            key.verify(signature, data)
            return key_id(key)
        except InvalidSignature:
            continue
    raise SignatureError(f"{bundle_dir}: its signature does not verify against the trusted key(s) "
                         f"{', '.join(key_id(k) for k in keys)} (signed by {sig.get('key_id', '?')}): the bundle was "
                         "changed after signing, or signed by another key; fix: copy the bundle again from its "
                         "source, or trust the key that signed it")
