"""drvs-certs: a development CA and per-role certificates, so TLS is on in minutes.

    drvs-certs --out certs                       # ca.pem, server.pem/-key.pem, camera.pem/…, robot.pem/…
    drvs-certs --out certs --camera lobby --camera hall-1   # camera-lobby.pem, camera-hall-1.pem (+ keys)
    drvs-certs --out certs --host cams.lan --host 10.0.0.7 --role camera-3

Every certificate names localhost, 127.0.0.1 and ::1 plus each --host, and serves both as a server
certificate (its own listener: every role listens) and as a client certificate (mutual TLS). It
says its role in its subject's organizational unit (OU=server, camera or robot): under mutual TLS
the server lets only camera certificates register cameras. Its common name is the server's name
for the caller, so give each camera its own (--camera NAME): cameras that share one certificate
share one identity, and may take over each other's ids. For development and tests: keep
ca-key.pem private, and use your organisation's CA in production.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
import sys
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from drvs.errors import InvalidArgument
from drvs.model import check_id
from drvs.security import ROLES

DEFAULT_ROLES = ("server", "camera", "robot")
DEFAULT_DAYS = 365


def _name(common_name: str, role: str | None = None) -> x509.Name:
    unit = [x509.NameAttribute(NameOID.ORGANIZATIONAL_UNIT_NAME, role)] if role else []
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "DRVS development"),
            *unit,
            x509.NameAttribute(NameOID.COMMON_NAME, common_name),
        ]
    )


def role_of(name: str) -> str:
    """`camera` -> camera, `camera-3` -> camera: a certificate's role is its name or its prefix."""
    role = name.split("-", 1)[0]
    if role not in ROLES:
        raise InvalidArgument(f"role: {name!r} must be {', '.join(ROLES)}, or one of them followed by -NAME")
    return role


def _write(path: Path, data: bytes, private: bool) -> None:
    path.write_bytes(data)
    if private:
        os.chmod(path, 0o600)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


_CA_USAGE = x509.KeyUsage(
    digital_signature=True,
    key_cert_sign=True,
    crl_sign=True,
    content_commitment=False,
    key_encipherment=False,
    data_encipherment=False,
    key_agreement=False,
    encipher_only=False,
    decipher_only=False,
)


def make_ca(out: Path, days: int) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """Load ca.pem/ca-key.pem from `out`, or make them."""
    cert_path, key_path = out / "ca.pem", out / "ca-key.pem"
    if cert_path.exists() and key_path.exists():
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise InvalidArgument(f"{key_path}: not an EC key made by drvs-certs")
        return cert, key
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name("DRVS development CA"))
        .issuer_name(_name("DRVS development CA"))
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_CA_USAGE, critical=True)
        .sign(key, hashes.SHA256())
    )
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), private=False)
    _write(key_path, _key_pem(key), private=True)
    return cert, key


def _san(hosts: list[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for host in dict.fromkeys(["localhost", "127.0.0.1", "::1", *hosts]):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    return x509.SubjectAlternativeName(names)


def make_certificate(
    out: Path,
    role: str,
    hosts: list[str],
    ca: x509.Certificate,
    ca_key: ec.EllipticCurvePrivateKey,
    days: int,
    common_name: str | None = None,
) -> tuple[Path, Path]:
    """`role`.pem and `role`-key.pem; the role is `role` or its prefix (camera-3: camera), the
    common name `common_name` (default: `role`)."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name or role, role_of(role)))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_san(hosts), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    cert_path, key_path = out / f"{role}.pem", out / f"{role}-key.pem"
    _write(cert_path, cert.public_bytes(serialization.Encoding.PEM), private=False)
    _write(key_path, _key_pem(key), private=True)
    return cert_path, key_path


def make_all(
    out: Path,
    roles: list[str],
    hosts: list[str],
    days: int = DEFAULT_DAYS,
    *,
    cameras: list[str] | tuple[str, ...] = (),
    robots: list[str] | tuple[str, ...] = (),
) -> dict[str, tuple[Path, Path]]:
    """The CA (kept if `out` has one) and one certificate per role, and one per named camera and
    robot (file camera-NAME.pem, common name NAME); returns file stem -> (cert, key)."""
    for role in roles:
        check_id(role, "role")
        role_of(role)
    for name in (*cameras, *robots):
        check_id(name, "name")
    for host in hosts:
        if not host or any(c.isspace() for c in host):
            raise InvalidArgument(f"host: {host!r} is not a host name or IP address")
    if not 1 <= days <= 3650:
        raise InvalidArgument(f"days: {days} must be from 1 to 3650")
    out.mkdir(parents=True, exist_ok=True)
    ca, ca_key = make_ca(out, days)
    made = {role: make_certificate(out, role, hosts, ca, ca_key, days) for role in roles}
    for role, names in (("camera", cameras), ("robot", robots)):
        for name in names:
            made[f"{role}-{name}"] = make_certificate(out, f"{role}-{name}", hosts, ca, ca_key, days, name)
    return made


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="drvs-certs", description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="folder for the files (an existing CA there is reused)")
    p.add_argument(
        "--role",
        action="append",
        default=[],
        help="certificate to make: server, camera, robot, or one of them followed by -NAME (repeatable; default: "
        "server camera robot, unless --camera or --robot is given)",
    )
    p.add_argument(
        "--camera", action="append", default=[], metavar="NAME", help="a camera certificate of its own (repeatable)"
    )
    p.add_argument(
        "--robot", action="append", default=[], metavar="NAME", help="a robot certificate of its own (repeatable)"
    )
    p.add_argument("--host", action="append", default=[], help="another name or IP the certificates answer for")
    p.add_argument("--days", type=int, default=DEFAULT_DAYS, help="validity (default %(default)s)")
    args = p.parse_args(argv)
    try:
        roles = args.role or ([] if args.camera or args.robot else list(DEFAULT_ROLES))
        made = make_all(args.out, roles, args.host, args.days, cameras=args.camera, robots=args.robot)
    except (InvalidArgument, OSError) as exc:
        print(f"drvs-certs: {exc}", file=sys.stderr)
        return 2
    print(f"CA: {args.out / 'ca.pem'} (key {args.out / 'ca-key.pem'}: keep it private)")
    for role, (cert, key) in made.items():
        print(f"{role}: --tls-cert {cert} --tls-key {key} --tls-ca {args.out / 'ca.pem'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
