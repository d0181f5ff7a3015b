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
| router.pem/.key    | router         | forwards for its clients (only with ``--router``) |

Every role may subscribe and query. ``ca.pem`` is the trust root every process loads;
``ca.key`` signs the certificates and should not leave the machine that made them.
With ``--users`` a ``users.txt`` of ``role:password`` lines (random passwords) is
written for Zenoh's user/password authentication. Keys are ECDSA P-256 in PKCS#8 PEM,
readable by the owner only. Files are created anew (``O_EXCL``, never through a symbolic
link, mode 0600 for keys); an existing file is replaced only with ``--force``, and a
symbolic link in the way is refused even then.
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
    # A new file with its final mode, so that a key is never readable by others, not even
    # briefly, and is never written through a link planted in the folder (O_EXCL, O_NOFOLLOW).
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    fd = os.open(path, flags, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _clear(out: Path, names: list[str], force: bool) -> None:
    """Refuse links and (without ``force``) existing files among ``names``; remove the rest."""
    links = [n for n in names if (out / n).is_symlink()]
    if links:
        raise ConfigError(f"{out / links[0]}: is a symbolic link; refusing to write a certificate or key through it")
    present = [n for n in names if (out / n).exists()]
    if present and not force:
        raise ConfigError(f"{out}: already holds {present[0]} (pass --force to replace every certificate and key)")
    for n in present:
        if not (out / n).is_file():
            raise ConfigError(f"{out / n}: exists and is not a file")
        (out / n).unlink()


def init_certs(out: Path, renderers: tuple[str, ...] = ("ego",), hosts: tuple[str, ...] = (),
               days: int = 365, users: bool = False, force: bool = False, router: bool = False) -> list[Path]:
    """Write ``ca.pem``/``ca.key`` and a certificate + key per role into ``out``.

    ``renderers``: ego ids, one certificate ``renderer-<id>`` each. ``hosts``: extra DNS
    names or IP addresses the certificates are valid for (``localhost`` and 127.0.0.1
    always are). ``router``: also a ``router`` certificate (only for runs through
    ``sumoco router``: it may forward anything). Returns the files written.
    """
    x509, hashes, serialization, ec, EKU, NameOID = _crypto()
    for r in renderers:
        check_chunk(r, "renderer ego id")
    if days < 1:
        raise ConfigError(f"--days: expected >= 1, got {days}")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    names = [*(r for r in ROLES if r != "router" or router), *(renderer_role(r) for r in renderers)]
    files = ["ca.key", "ca.pem", *(f"{n}.{e}" for n in names for e in ("key", "pem"))]
    _clear(out, files + (["users.txt"] if users else []), force)

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
    router = bool(getattr(args, "router", False))
    files = init_certs(out, renderers=renderers, hosts=tuple(args.host or ()), days=int(args.days),
                       users=bool(args.users), force=bool(args.force), router=router)
    roles = ", ".join([*(r for r in ROLES if r != "router" or router), *(renderer_role(r) for r in renderers)])
    print(f"wrote {len(files)} files to {out}: CA + certificates for {roles}", file=sys.stderr)
    return 0
