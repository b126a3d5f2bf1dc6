"""drvs-certs: a development CA and per-role certificates, so TLS is on in minutes.

    drvs-certs --out certs                       # ca.pem, server.pem/-key.pem, camera.pem/…, robot.pem/…
    drvs-certs --out certs --camera lobby --camera hall-1   # camera-lobby.pem, camera-hall-1.pem (+ keys)
    drvs-certs --out certs --host cams.lan --host 10.0.0.7 --role camera-3
    drvs-certs --out certs --server-host drvs.lan --camera-host cams.lan   # names per role
    drvs-certs --out certs --etcd --etcd-host 10.0.0.5   # etcd.pem (its members), etcd-root.pem (CN root)

Every certificate names localhost, 127.0.0.1 and ::1 plus each --host; a server's also each
--server-host, a camera's each --camera-host (a robot's names none of them, so it cannot pass for a
server or a camera at those names). Each serves both as a server
certificate (its own listener: every role listens) and as a client certificate (mutual TLS). It
says its role in its subject's organizational unit (OU=server, camera or robot): under mutual TLS
the server lets only camera certificates register cameras. Its common name is the server's name
for the caller, so give each camera its own (--camera NAME): cameras that share one certificate
share one identity, and may take over each other's ids. For development and tests: keep
ca-key.pem private, and use your organisation's CA in production.

For etcd (drvs.server.etcd_auth): etcd takes a client certificate's common name as its user. A server
certificate's common name (server, server-NAME) is that server's etcd user; etcd-root.pem's is
root. So that no camera or robot certificate can name one of those users, --camera and --robot
names may not be root, etcd, server or server-….
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

from drvs.core._files import folder_problem
from drvs.core.errors import InvalidArgument
from drvs.core.model import check_id
from drvs.wire.security import ROLES

DEFAULT_ROLES = ("server", "camera", "robot")
DEFAULT_DAYS = 365
#: Common names a camera's or robot's certificate may not take: etcd users (drvs.server.etcd_auth).
RESERVED_NAMES = ("root", "etcd", "server")


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
    *,
    unit: str | None = "",
) -> tuple[Path, Path]:
    """`role`.pem and `role`-key.pem; the role is `role` or its prefix (camera-3: camera), the
    common name `common_name` (default: `role`). `unit` None: no DRVS role (etcd's certificates)."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name or role, role_of(role) if unit == "" else unit))
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
    role_hosts: dict[str, list[str]] | None = None,
    etcd_hosts: list[str] | None = None,
) -> dict[str, tuple[Path, Path]]:
    """The CA (kept if `out` has one) and one certificate per role, and one per named camera and
    robot (file camera-NAME.pem, common name NAME); returns file stem -> (cert, key).
    `role_hosts`: more names for one role's certificates only (server: the servers' names).
    `etcd_hosts` (not None): also etcd.pem for etcd's members (these names) and etcd-root.pem."""
    role_hosts = role_hosts or {}
    for role in roles:
        check_id(role, "role")
        role_of(role)
    for name in (*cameras, *robots):
        check_id(name, "name")
        if name in RESERVED_NAMES or name.startswith("server-"):
            raise InvalidArgument(
                f"name: {name!r} is an etcd user's name (root, etcd, server, server-…); a camera or robot "
                "certificate may not carry it"
            )
    for host in [*hosts, *(etcd_hosts or []), *(h for v in role_hosts.values() for h in v)]:
        if not host or any(c.isspace() for c in host):
            raise InvalidArgument(f"host: {host!r} is not a host name or IP address")
    if not 1 <= days <= 3650:
        raise InvalidArgument(f"days: {days} must be from 1 to 3650")
    out.mkdir(parents=True, exist_ok=True)
    ca, ca_key = make_ca(out, days)
    made = {
        role: make_certificate(out, role, hosts + role_hosts.get(role_of(role), []), ca, ca_key, days) for role in roles
    }
    for role, names in (("camera", cameras), ("robot", robots)):
        for name in names:
            named = hosts + role_hosts.get(role, [])
            made[f"{role}-{name}"] = make_certificate(out, f"{role}-{name}", named, ca, ca_key, days, name)
    if etcd_hosts is not None:
        made["etcd"] = make_certificate(out, "etcd", etcd_hosts, ca, ca_key, days, unit=None)
        made["etcd-root"] = make_certificate(out, "etcd-root", [], ca, ca_key, days, "root", unit=None)
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
    p.add_argument("--host", action="append", default=[], help="another name or IP every certificate answers for")
    for role in ("server", "camera", "robot"):
        p.add_argument(
            f"--{role}-host", action="append", default=[], metavar="HOST",
            help=f"another name or IP only the {role} certificates answer for (repeatable)",
        )  # fmt: skip
    p.add_argument(
        "--etcd", action="store_true", help="also etcd.pem (etcd's members) and etcd-root.pem (etcd's root user)"
    )
    p.add_argument("--etcd-host", action="append", default=[], metavar="HOST", help="a name or IP of etcd's members")
    p.add_argument("--days", type=int, default=DEFAULT_DAYS, help="validity (default %(default)s)")
    args = p.parse_args(argv)
    try:
        if (problem := folder_problem(args.out)) is not None:
            raise InvalidArgument(f"--out {args.out}: {problem}")
        roles = args.role or ([] if args.camera or args.robot or args.etcd else list(DEFAULT_ROLES))
        role_hosts = {"server": args.server_host, "camera": args.camera_host, "robot": args.robot_host}
        etcd_hosts = args.etcd_host if args.etcd or args.etcd_host else None
        made = make_all(
            args.out, roles, args.host, args.days, cameras=args.camera, robots=args.robot,
            role_hosts=role_hosts, etcd_hosts=etcd_hosts,
        )  # fmt: skip
    except (InvalidArgument, OSError) as exc:
        print(f"drvs-certs: {exc}", file=sys.stderr)
        return 2
    print(f"CA: {args.out / 'ca.pem'} (key {args.out / 'ca-key.pem'}: keep it private)")
    ca = args.out / "ca.pem"
    for role, (cert, key) in made.items():
        if role == "etcd":
            print(f"etcd (each member): --cert-file {cert} --key-file {key} --trusted-ca-file {ca} --client-cert-auth")
        elif role == "etcd-root":
            print(f"etcd's root (python -m drvs.server.etcd_auth): --cert {cert} --key {key} --ca {ca}")
        else:
            print(f"{role}: --tls-cert {cert} --tls-key {key} --tls-ca {ca}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
