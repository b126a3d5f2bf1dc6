"""Who may receive reports: by default only the robot that asked. Pure logic but for DNS."""

from __future__ import annotations

import asyncio
import ipaddress
import socket
from collections.abc import Iterable

from drvs.errors import InvalidArgument, PermissionDenied
from drvs.net import parse_address

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


def peer_ip(peer: str) -> IPAddress | None:
    """The IP of a gRPC peer string ('ipv4:1.2.3.4:5', 'ipv6:[::1]:5'); None for other transports."""
    kind, _, rest = peer.partition(":")
    try:
        if kind == "ipv4":
            return ipaddress.ip_address(rest.rsplit(":", 1)[0])
        if kind == "ipv6":
            return ipaddress.ip_address(rest.rsplit(":", 1)[0].strip("[]").split("%")[0])
    except ValueError:
        return None
    return None


class CallbackPolicy:
    """Reports go to the requesting robot's own address, or to networks the operator allowed, so
    nobody can point every camera at a third party (a traffic amplifier)."""

    def __init__(self, allowed: Iterable[str] = (), allow_any: bool = False) -> None:
        self.allow_any = allow_any
        self.allowed = []
        for cidr in allowed:
            try:
                self.allowed.append(ipaddress.ip_network(cidr, strict=False))
            except ValueError:
                raise InvalidArgument(f"--allow-callback: {cidr!r} is not an IP network (e.g. 10.0.0.0/8)") from None

    async def check(self, callback_address: str, peer: IPAddress | None) -> None:
        if self.allow_any:
            return
        host, port = parse_address(callback_address, "callback_address")
        addresses = await _resolve(host, port)
        if peer is not None and any(_same(a, peer) for a in addresses):
            return
        if any(a in net for a in addresses for net in self.allowed if a.version == net.version):
            return
        raise PermissionDenied(
            f"callback_address: {host} is not the requesting robot's address ({peer or 'unknown'}); "
            "reports go back only to the robot that asks, or to networks the server allows (--allow-callback)"
        )


def _same(a: IPAddress, b: IPAddress) -> bool:
    if a == b:
        return True
    return a.is_loopback and b.is_loopback  # 127.0.0.1 and ::1 are the same host


async def _resolve(host: str, port: int) -> list[IPAddress]:
    try:
        return [ipaddress.ip_address(host)]
    except ValueError:
        pass
    try:
        infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except OSError:
        raise InvalidArgument(f"callback_address: host {host!r} does not resolve") from None
    return [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]
