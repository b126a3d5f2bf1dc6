"""host:port addresses as DRVS passes them around."""

from __future__ import annotations

import functools
import ipaddress
import re
import socket
from collections.abc import Sequence

from drvs.core.errors import InvalidArgument, expect_str

_HOST_RE = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)


def parse_address(address: str, name: str = "address", *, allow_port_zero: bool = False) -> tuple[str, int]:
    """HOST:PORT (a name, IPv4, or [IPv6]) as (host, port); InvalidArgument names `name` otherwise."""
    if isinstance(address, str) and len(address) <= 300:
        return _parse_address_cached(address, name, allow_port_zero)  # a stream repeats its addresses
    return _parse_address(address, name, allow_port_zero=allow_port_zero)


@functools.lru_cache(maxsize=4096)
def _parse_address_cached(address: str, name: str, allow_port_zero: bool) -> tuple[str, int]:
    return _parse_address(address, name, allow_port_zero=allow_port_zero)


def _parse_address(address: str, name: str = "address", *, allow_port_zero: bool = False) -> tuple[str, int]:
    """Split 'host:port' or '[v6]:port'; InvalidArgument names the field when it is malformed."""
    if not isinstance(address, str) or not address:
        raise InvalidArgument(f"{name}: empty; expected host:port")
    if address.startswith("["):
        end = address.find("]")
        if end < 0 or address[end + 1 : end + 2] != ":":
            raise InvalidArgument(f"{name}: {address[:80]!r} is not [ipv6]:port")
        host, port_text = address[1:end], address[end + 2 :]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise InvalidArgument(f"{name}: {host[:80]!r} is not an IPv6 address") from None
    else:
        host, sep, port_text = address.rpartition(":")
        if not sep or not host:
            raise InvalidArgument(f"{name}: {address[:80]!r} is not host:port")
        if not _HOST_RE.fullmatch(host):
            raise InvalidArgument(f"{name}: {host[:80]!r} is not a valid host name or IPv4 address")
    if not (port_text.isascii() and port_text.isdigit()):
        raise InvalidArgument(f"{name}: port {port_text[:20]!r} is not a number")
    port = int(port_text)
    if not (0 if allow_port_zero else 1) <= port <= 65535:
        raise InvalidArgument(f"{name}: port {port} is out of range")
    return host, port


def format_address(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def local_ip_towards(peers: str | Sequence[str]) -> str:
    """The local IP this host would use to reach `peers` (no packet is sent): one HOST:PORT, a
    list of them ("a:1,b:2", or a sequence: several servers), or a DNS name. With several, the
    first that has a route and resolves decides (a dead server still has one; a name nobody
    resolves does not); with none, 127.0.0.1."""
    addresses = parse_address_list(peers, "server") if isinstance(peers, str) else list(peers)
    for address in addresses:
        ip = _route_towards(*parse_address(address))
        if ip is not None:
            return ip
    return "127.0.0.1"


def _route_towards(host: str, port: int) -> str | None:
    """The local IP of the route to host:port, or None when there is none (or the name resolves to nothing)."""
    if host in ("localhost",) or host.startswith("127."):
        return "127.0.0.1"
    if host == "::1":
        return "::1"
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.connect((host, port))
            return str(s.getsockname()[0])
    except OSError:
        return None


def host_of(listen: str) -> str:
    """The host part of a listen address (port 0 allowed)."""
    return parse_address(listen, "listen", allow_port_zero=True)[0]


def dialable_address(listen: str, port: int, peer: str | Sequence[str]) -> str:
    """What others should dial for a listener bound to `listen` on `port`: a wildcard host
    (0.0.0.0, ::) becomes the local IP this host uses to reach `peer` (one or several: see
    local_ip_towards)."""
    host = host_of(listen)
    if host in ("0.0.0.0", "::"):
        host = local_ip_towards(peer)
    return format_address(host, port)


def is_loopback_host(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and localhost: a listener only this machine can reach."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_address_list(text: str, name: str) -> list[str]:
    """`HOST:PORT[,HOST:PORT...]`: several peers of one role (servers, etcd members), each checked
    as parse_address does; InvalidArgument naming `name`."""
    expect_str(text, name, "such as 'host:50051'")  # code's Python, before anything splits it
    parts = [p.strip() for p in text.split(",")]
    if not all(parts):
        raise InvalidArgument(f"{name}: {text[:80]!r} has an empty address in its list")
    for part in parts:
        parse_address(part, name)
    return parts


def grpc_target(addresses: Sequence[str], name: str = "server") -> str:
    """One gRPC target naming every address: the address itself when there is one, an `ipv4:` /
    `ipv6:` list for several IP addresses (gRPC's own resolver: its load-balancing policy picks
    among them and moves on from one that fails)."""
    if len(addresses) == 1:
        return addresses[0]
    hosts = [parse_address(a, name) for a in addresses]
    versions: set[int] = set()
    for host, _ in hosts:
        try:
            versions.add(ipaddress.ip_address(host).version)
        except ValueError:
            versions.add(0)
    if versions == {4}:
        return "ipv4:" + ",".join(addresses)
    if versions == {6}:
        return "ipv6:" + ",".join(format_address(h, p) for h, p in hosts)
    raise InvalidArgument(
        f"{name}: several addresses must all be IPv4 or all IPv6 addresses (or give one DNS name that "
        "resolves to every peer)"
    )
