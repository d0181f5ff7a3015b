"""``sumoco certs init DIR``: a certificate authority and one certificate per role.

The secure profile (``configs/secure.toml``) runs Zenoh over TLS with mutual
authentication; the access-control policy (``runtime.transport.access_control``)
tells roles apart by the common name (CN) of the certificate a peer presents:

| file               | CN             | may put                                |
|--------------------|----------------|----------------------------------------|
| sumo.pem/.key      | sumo           | steps, static data, status, sumo token |
| physics.pem/.key   | physics        | physics states, acks, physics tokens   |
| renderer-<id>.pem  | renderer-<id>  | ego poses on ``ego/<id>`` only         |
| viewer.pem/.key    | viewer         | nothing (subscribe and query only)     |
| gateway.pem/.key   | gateway        | ego poses for any id (WebSocket relay) |

Every role may subscribe and query. ``ca.pem`` is the trust root every process loads;
``ca.key`` signs the certificates and should not leave the machine that made them.
With ``--users`` a ``users.txt`` of ``role:password`` lines (random passwords) is
written for Zenoh's user/password authentication. Keys are ECDSA P-256 in PKCS#8 PEM,
readable by the owner only.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
import secrets
import sys
from pathlib import Path

from protocol.errors import ConfigError
from protocol.keys import check_chunk
from runtime.transport import ROLES, renderer_role

log = logging.getLogger(__name__)

CA_NAME = "sumoco run CA"


def _crypto():
    # Imported on use: a bare install has no `cryptography` (the CLI names the extra).
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    return x509, hashes, serialization, ec, ExtendedKeyUsageOID, NameOID


def _write(path: Path, data: bytes, private: bool = False) -> None:
    # Create with the final mode so a key is never readable by others, not even briefly.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def init_certs(out: Path, renderers: tuple[str, ...] = ("ego",), hosts: tuple[str, ...] = (),
               days: int = 365, users: bool = False, force: bool = False) -> list[Path]:
    """Write ``ca.pem``/``ca.key`` and a certificate + key per role into ``out``.

    ``renderers``: ego ids, one certificate ``renderer-<id>`` each. ``hosts``: extra DNS
    names or IP addresses the certificates are valid for (``localhost`` and 127.0.0.1
    always are). Returns the files written.
    """
    x509, hashes, serialization, ec, EKU, NameOID = _crypto()
    for r in renderers:
        check_chunk(r, "renderer ego id")
    if days < 1:
        raise ConfigError(f"--days: expected >= 1, got {days}")
    out.mkdir(parents=True, exist_ok=True)
    if (out / "ca.pem").exists() and not force:
        raise ConfigError(f"{out}: already holds ca.pem (pass --force to replace every certificate)")

    now = dt.datetime.now(dt.timezone.utc)
    not_before, not_after = now - dt.timedelta(minutes=5), now + dt.timedelta(days=days)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, CA_NAME)])
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number()).not_valid_before(not_before).not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    pkcs8 = serialization.PrivateFormat.PKCS8
    nokey = serialization.NoEncryption()
    written = []
    _write(out / "ca.key", ca_key.private_bytes(pem, pkcs8, nokey), private=True)
    _write(out / "ca.pem", ca_cert.public_bytes(pem))
    written += [out / "ca.key", out / "ca.pem"]

    sans: list = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    names = [*ROLES, *(renderer_role(r) for r in renderers)]
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(not_before).not_valid_after(not_after)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            # Peers both listen and connect, so every certificate is a server and a client one.
            .add_extension(x509.ExtendedKeyUsage([EKU.SERVER_AUTH, EKU.CLIENT_AUTH]), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                           critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        _write(out / f"{name}.key", key.private_bytes(pem, pkcs8, nokey), private=True)
        _write(out / f"{name}.pem", cert.public_bytes(pem))
        written += [out / f"{name}.key", out / f"{name}.pem"]
    if users:
        lines = "".join(f"{n}:{secrets.token_urlsafe(18)}\n" for n in names)
        _write(out / "users.txt", lines.encode(), private=True)
        written.append(out / "users.txt")
    return written


def cli_main(args) -> int:
    if args.action != "init":  # pragma: no cover - argparse enforces the choices
        raise ConfigError(f"sumoco certs: unknown action {args.action!r}")
    out = Path(args.dir)
    renderers = tuple(args.renderer or ("ego",))
    files = init_certs(out, renderers=renderers, hosts=tuple(args.host or ()), days=int(args.days),
                       users=bool(args.users), force=bool(args.force))
    roles = ", ".join([*ROLES, *(renderer_role(r) for r in renderers)])
    print(f"wrote {len(files)} files to {out}: CA + certificates for {roles}", file=sys.stderr)
    return 0
