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

from drvs.errors import InvalidArgument, PermissionDenied
from drvs.net import host_of
from drvs.security import bearer_token

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


class ReportTargets:
    """Where this camera sends a fused request's reports: its servers (`servers`, the --server
    list) and other ports on their hosts, named as given or by an address a name resolved to at
    start (`resolve`). `check` refuses any other report address."""

    def __init__(self, camera_id: str, servers: Sequence[str]) -> None:
        self.camera_id = camera_id
        self.servers = tuple(servers)
        self.hosts = {_host(s) for s in self.servers}

    async def resolve(self) -> None:
        """Add the addresses the servers' names resolve to (a name that does not resolve adds none)."""
        loop = asyncio.get_running_loop()
        for host in list(self.hosts):
            with contextlib.suppress(OSError, UnicodeError):
                infos = await loop.getaddrinfo(host, None, type=socket.SOCK_STREAM)
                self.hosts |= {str(ipaddress.ip_address(str(info[4][0]).split("%")[0])) for info in infos}

    def check(self, address: str) -> str:
        """`address` if reports (and this camera's token) may go there; PERMISSION_DENIED, logged, if not."""
        try:
            host = _host(address)
        except InvalidArgument:
            host = ""
        if address in self.servers or host in self.hosts:
            return address
        log.warning(
            "camera %s: refused a fused request whose reports were to go to %s: not a server this camera knows",
            self.camera_id,
            address[:100],
        )
        raise PermissionDenied(
            f"report_address: {address[:100]!r} is not one of this camera's servers ({', '.join(self.servers)}) "
            "nor on one's host; the camera sends its reports, and its token, nowhere else"
        )
