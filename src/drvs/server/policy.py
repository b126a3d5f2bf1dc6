"""Who may receive reports (by default only the robot that asked), and how much a robot may ask.
Pure logic but for DNS."""

from __future__ import annotations

import asyncio
import ipaddress
import socket
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Iterable

from drvs.core.errors import InvalidArgument, PermissionDenied, ResourceExhausted
from drvs.core.net import format_address, parse_address

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

    def __init__(
        self,
        allowed: Iterable[str] = (),
        allow_any: bool = False,
        resolve: Callable[[str, int], Awaitable[list[IPAddress]]] | None = None,
    ) -> None:
        self.allow_any = allow_any
        self._resolve = resolve or _resolve
        self.allowed = []
        for cidr in allowed:
            try:
                self.allowed.append(ipaddress.ip_network(cidr, strict=False))
            except ValueError:
                raise InvalidArgument(f"--allow-callback: {cidr!r} is not an IP network (e.g. 10.0.0.0/8)") from None

    async def check(self, callback_address: str, peer: IPAddress | None) -> str:
        """The address cameras are to dial: a name is resolved and replaced by an address it resolved
        to, so cameras dial exactly what was checked (a name that resolves again differently later,
        DNS rebinding, changes nothing). Every address a name resolves to must pass, not just one:
        a name that also resolves to a third party is refused. With allow_any, unchanged."""
        if self.allow_any:
            return callback_address
        host, port = parse_address(callback_address, "callback_address")
        try:
            addresses: list[IPAddress] = [ipaddress.ip_address(host)]
        except ValueError:
            addresses = await self._resolve(host, port)
        refused = [a for a in addresses if not self._allowed(a, peer)]
        if refused:
            what = host if str(refused[0]) == host else f"{host} (resolves to {refused[0]})"
            raise PermissionDenied(
                f"callback_address: {what} is not the requesting robot's address ({peer or 'unknown'}); "
                "reports go back only to the robot that asks, or to networks the server allows (--allow-callback)"
            )
        return format_address(str(addresses[0]), port)

    def _allowed(self, address: IPAddress, peer: IPAddress | None) -> bool:
        if peer is not None and _same(address, peer):
            return True
        return any(address in net for net in self.allowed if address.version == net.version)


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
    addresses = list(dict.fromkeys(ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos))
    if not addresses:
        raise InvalidArgument(f"callback_address: host {host!r} does not resolve")
    return addresses


#: Per robot: requests a second (sustained), the burst above it, and continuous requests running at once.
DEFAULT_RATE_HZ = 200.0
DEFAULT_BURST = 400
DEFAULT_MAX_ACTIVE = 32
#: Per robot: bytes a second the server may forward to cameras on its behalf (a request's size
#: times the cameras it goes to), and the burst above it. A robot on a stream repeats a region by
#: leaving it out, so without this a few bytes from it could become a 24 kB region sent to every
#: camera, as often as the rate limit allows.
DEFAULT_FORWARD_BYTES_PER_S = 1024 * 1024
#: Robots whose buckets are kept; the longest idle is dropped past this, so memory stays bounded.
MAX_TRACKED_ROBOTS = 10_000


class RequestLimits:
    """Per robot (its credential, or without credentials its connection): a token bucket on the
    request rate, one on the bytes forwarded to cameras for it, and a cap on continuous requests
    running at once, so no robot can keep every camera busy, amplify its traffic, or starve the
    others."""

    def __init__(
        self,
        rate_hz: float = DEFAULT_RATE_HZ,
        burst: int = DEFAULT_BURST,
        max_active: int = DEFAULT_MAX_ACTIVE,
        clock: Callable[[], float] = time.monotonic,
        forward_bytes_per_s: float = DEFAULT_FORWARD_BYTES_PER_S,
        forward_burst_bytes: float | None = None,
    ) -> None:
        if not (rate_hz > 0 and burst >= 1 and max_active >= 1 and forward_bytes_per_s > 0):
            raise InvalidArgument(
                "request limits: rate_hz > 0, burst >= 1, max_active >= 1 and forward_bytes_per_s > 0"
            )
        self.rate_hz = rate_hz
        self.burst = float(burst)
        self.max_active = max_active
        self.forward_bytes_per_s = float(forward_bytes_per_s)
        self.forward_burst_bytes = float(
            2 * forward_bytes_per_s if forward_burst_bytes is None else forward_burst_bytes
        )
        self._clock = clock
        # robot -> (request tokens, forward byte tokens, last refill); robot -> end times of its
        # running continuous requests
        self._buckets: OrderedDict[str, tuple[float, float, float]] = OrderedDict()
        self._active: dict[str, list[float]] = {}

    def admit(self, robot: str, continuous_s: float, forward_bytes: int = 0) -> float | None:
        """Count one request that will forward `forward_bytes` to cameras, or raise
        ResourceExhausted naming the limit (nothing is counted then). Returns the continuous
        request's slot, for `release`, or None for a single shot."""
        now = self._clock()
        tokens, byte_tokens, last = self._buckets.pop(robot, (self.burst, self.forward_burst_bytes, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate_hz)
        byte_tokens = min(self.forward_burst_bytes, byte_tokens + (now - last) * self.forward_bytes_per_s)
        active = [end for end in self._active.get(robot, ()) if end > now]
        slot: float | None = None
        try:
            if tokens < 1.0:
                raise ResourceExhausted(
                    f"rate: more than {self.rate_hz:g} requests a second (burst {self.burst:g}); slow down"
                )
            if forward_bytes > byte_tokens:
                raise ResourceExhausted(
                    f"forwarded bytes: this request goes to cameras as {forward_bytes} bytes, more than the "
                    f"{int(byte_tokens)} left of {self.forward_bytes_per_s:g} bytes a second "
                    f"(burst {self.forward_burst_bytes:g}); use a smaller region or slow down"
                )
            if continuous_s > 0 and len(active) >= self.max_active:
                raise ResourceExhausted(
                    f"continuous: {len(active)} continuous requests already running (limit {self.max_active}); "
                    "wait for one to end or cancel one"
                )
            tokens -= 1.0
            byte_tokens -= forward_bytes
            if continuous_s > 0:
                slot = now + continuous_s
                active.append(slot)
        finally:
            self._buckets[robot] = (tokens, byte_tokens, now)
            if active:
                self._active[robot] = active
            else:
                self._active.pop(robot, None)
            while len(self._buckets) > MAX_TRACKED_ROBOTS:
                old, _ = self._buckets.popitem(last=False)
                self._active.pop(old, None)
        return slot

    def release(self, robot: str, slot: float | None) -> None:
        """A continuous request ended early (no camera took it): its slot is free again."""
        if slot is None:
            return
        active = self._active.get(robot)
        if active is None:
            return
        try:
            active.remove(slot)
        except ValueError:
            return
        if not active:
            del self._active[robot]

    def active(self, robot: str) -> int:
        """Continuous requests of `robot` still holding a slot."""
        now = self._clock()
        return sum(1 for end in self._active.get(robot, ()) if end > now)
