"""Whom a camera node trusts: who may ask it for detections or frames, and where it may send its
reports (and with them its token).

Requests come only from the server it registered with (which presents the secret the node handed
it) or from a holder of the node's own token; frames only from a holder of its token, never from
the server's forward secret. A fused request's reports, which carry the node's token, go only to
a server the node knows: one of its --server addresses, or another port on one of their hosts (a
`drvs-server --workers N` worker takes reports on a port of its own), by name or by the addresses
the names resolve to. Anything else is refused and logged."""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import logging
import socket
from collections.abc import AsyncIterator, Sequence
from typing import TYPE_CHECKING, Any

import grpc
from grpc import aio

from drvs.core.errors import InvalidArgument, PermissionDenied
from drvs.core.net import host_of
from drvs.wire.security import bearer_token

if TYPE_CHECKING:
    from .node import CameraNode

log = logging.getLogger("drvs.camera")

#: What check_caller is asked about for the FrameStream service: these need the token itself.
FRAME_STREAMS = "frame streams"


def presents_secret(node: CameraNode, metadata: list[tuple[str, Any]], *, token_only: bool = False) -> bool:
    """Does a call present what only this node's server knows: the secret the node handed it at
    registration, or the node's own token (`token_only`: the token alone)? Constant time."""
    given = bearer_token(metadata).encode()
    ok = not token_only and hmac.compare_digest(given, node.forward_secret.encode())
    token = node.security.token
    return ok | (bool(token) and hmac.compare_digest(given, token.encode()))


async def check_caller(
    node: CameraNode, context: aio.ServicerContext[Any, Any], what: str, requests: AsyncIterator[Any] | None = None
) -> None:
    """The camera takes requests only from the server it registered with (which presents the
    secret back), not from any host or process that finds its port; frames only with its token."""
    frames = what == FRAME_STREAMS
    if not presents_secret(node, list(context.invocation_metadata() or ()), token_only=frames):
        if requests is not None:
            # Take the first message before refusing a stream (as security._refusal does): an abort
            # racing the caller's first write reaches the caller as INTERNAL, not UNAUTHENTICATED.
            with contextlib.suppress(Exception):
                await asyncio.wait_for(anext(aiter(requests)), 1.0)
        await context.abort(
            grpc.StatusCode.UNAUTHENTICATED,
            f"{what} need this camera's token (the secret it gave its server opens no frames)"
            if frames
            else f"{what} need the secret this camera gave its server, or its token: send them via the server",
        )


def _host(address: str) -> str:
    return host_of(address).strip("[]").lower()


#: Report hosts named (not IP literals) whose resolution a camera remembers; more start afresh.
MAX_NAMES = 256


def _ips(infos: Sequence[Any]) -> set[str]:
    return {str(ipaddress.ip_address(str(info[4][0]).split("%")[0])) for info in infos}


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


class ReportTargets:
    """Where this camera sends a fused request's reports: its servers (`servers`, the --server
    list) and other ports on their hosts, named as given, or by an address a server's name resolved
    to at start (`resolve`), or by another name all of whose addresses are among those (resolved
    when first named: `allowed`). `check` refuses any other report address at once, where it can
    tell without resolving a name."""

    def __init__(self, camera_id: str, servers: Sequence[str]) -> None:
        self.camera_id = camera_id
        self.servers = tuple(servers)
        self.hosts = {_host(s) for s in self.servers}
        #: Other names a report address gave: whether all their addresses are the servers'.
        self._names: dict[str, bool] = {}

    async def resolve(self) -> None:
        """Add the addresses the servers' names resolve to (a name that does not resolve adds none)."""
        loop = asyncio.get_running_loop()
        for host in list(self.hosts):
            with contextlib.suppress(OSError, UnicodeError):
                self.hosts |= _ips(await loop.getaddrinfo(host, None, type=socket.SOCK_STREAM))

    def _verdict(self, address: str) -> bool | None:
        """True: a server's; False: not; None: a name not resolved yet."""
        try:
            host = _host(address)
        except InvalidArgument:
            return False
        if address in self.servers or host in self.hosts:
            return True
        return False if _is_ip(host) else self._names.get(host)

    def _refuse(self, address: str) -> PermissionDenied:
        log.warning(
            "camera %s: refused a fused request whose reports were to go to %s: not a server this camera knows",
            self.camera_id,
            address[:100],
        )
        return PermissionDenied(
            f"report_address: {address[:100]!r} is not one of this camera's servers ({', '.join(self.servers)}) "
            "nor on one's host; the camera sends its reports, and its token, nowhere else"
        )

    def check(self, address: str) -> str:
        """`address` unless it is known not to be a server's (PERMISSION_DENIED, logged); a name not
        resolved yet passes here, and `allowed` decides before anything is sent."""
        if self._verdict(address) is False:
            raise self._refuse(address)
        return address

    async def allowed(self, address: str) -> bool:
        """May reports (and this camera's token) go to `address`? A new name is resolved (off the
        event loop) and allowed when all its addresses are the servers'. A refusal is logged."""
        verdict = self._verdict(address)
        if verdict is None:
            host = _host(address)
            try:
                ips = _ips(await asyncio.get_running_loop().getaddrinfo(host, None, type=socket.SOCK_STREAM))
            except (OSError, UnicodeError):
                ips = set()
            verdict = bool(ips) and ips <= self.hosts
            if len(self._names) >= MAX_NAMES:
                self._names.clear()
            self._names[host] = verdict
        if not verdict:
            self._refuse(address)  # (logged; the caller stops)
        return verdict
