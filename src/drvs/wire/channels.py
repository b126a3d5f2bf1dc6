"""Channels to a list of peers of one role (`--server A,B`, `etcd://A,B`), and the check that a
peer's certificate has the role it is dialled for.

One gRPC channel for several addresses (an `ipv4:` list) has one authority, the whole list, which
no certificate names: under TLS hostname verification fails for every peer. So under TLS each
address gets a channel of its own (its authority its own host), and `ListChannel` sends each call
on one of them: the one in use while it is connected or connecting, else the next that is not
failing (a peer that died is left for the next, as gRPC's pick_first does within one channel).
Without TLS one gRPC channel holds the whole list, as before.

gRPC's Python API shows a client nothing of the peer's certificate, so `check_role` looks with a
TLS handshake of its own (the same CA, the same client certificate) before a robot or a camera
first talks to a server: a certificate of another DRVS role (OU=camera or robot) is refused with
PermissionDenied naming it, before any request or secret is sent.
"""

from __future__ import annotations

import asyncio
import ssl
from collections.abc import Callable, Sequence
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import PermissionDenied
from drvs.core.net import grpc_target, parse_address
from drvs.wire.security import Security, certificate_fields

#: How long the role check waits for a peer's handshake, seconds (a peer that does not answer is
#: left to gRPC, which reports it unreachable).
PROBE_TIMEOUT_S = 3.0


def open_channel(security: Security, addresses: Sequence[str], name: str = "server") -> aio.Channel:
    """A channel to every address (one peer of several answers each call): one gRPC channel, or
    under TLS with several addresses a ListChannel of one channel per address."""
    if len(addresses) > 1 and security.tls:
        return ListChannel([security.channel(a) for a in addresses])
    return security.channel(grpc_target(addresses, name))


_OK = (grpc.ChannelConnectivity.READY, grpc.ChannelConnectivity.IDLE, grpc.ChannelConnectivity.CONNECTING)


class ListChannel(aio.Channel):
    """Several channels as one: each call goes on the channel in use unless it is failing
    (TRANSIENT_FAILURE or shut down), then on the next that is connected, else the next not
    failing. Streams stay on the channel they started on; a broken one is started again by its
    caller, on whichever channel is picked then."""

    def __init__(self, channels: Sequence[aio.Channel]) -> None:
        self._channels = list(channels)
        self._current = 0

    def pick(self) -> int:
        n = len(self._channels)
        states = [self._channels[(self._current + i) % n].get_state(try_to_connect=(i == 0)) for i in range(n)]
        if states[0] in _OK:
            return self._current
        order = sorted(
            range(1, n), key=lambda i: (states[i] != grpc.ChannelConnectivity.READY, states[i] not in _OK, i)
        )
        for i in order:
            if states[i] in _OK:
                self._current = (self._current + i) % n
                return self._current
        self._current = (self._current + 1) % n  # every one failing: try the next, round the list
        return self._current

    def _multi(self, make: Callable[[aio.Channel], Any]) -> Any:
        made = [make(c) for c in self._channels]
        return _Picking(self, made)

    def unary_unary(self, method: str, request_serializer: Any = None, response_deserializer: Any = None,
                    _registered_method: bool | None = False) -> Any:  # fmt: skip
        return self._multi(lambda c: c.unary_unary(method, request_serializer, response_deserializer))

    def unary_stream(self, method: str, request_serializer: Any = None, response_deserializer: Any = None,
                     _registered_method: bool | None = False) -> Any:  # fmt: skip
        return self._multi(lambda c: c.unary_stream(method, request_serializer, response_deserializer))

    def stream_unary(self, method: str, request_serializer: Any = None, response_deserializer: Any = None,
                     _registered_method: bool | None = False) -> Any:  # fmt: skip
        return self._multi(lambda c: c.stream_unary(method, request_serializer, response_deserializer))

    def stream_stream(self, method: str, request_serializer: Any = None, response_deserializer: Any = None,
                      _registered_method: bool | None = False) -> Any:  # fmt: skip
        return self._multi(lambda c: c.stream_stream(method, request_serializer, response_deserializer))

    async def close(self, grace: float | None = None) -> None:
        for channel in self._channels:
            await channel.close(grace)

    async def __aenter__(self) -> ListChannel:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def get_state(self, try_to_connect: bool = False) -> grpc.ChannelConnectivity:
        return self._channels[self._current].get_state(try_to_connect)

    async def wait_for_state_change(self, last_observed_state: grpc.ChannelConnectivity) -> None:
        await self._channels[self._current].wait_for_state_change(last_observed_state)

    async def channel_ready(self) -> None:
        """Until one of the channels is connected."""
        waits = [asyncio.ensure_future(c.channel_ready()) for c in self._channels]
        try:
            done, _ = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            self._current = waits.index(next(iter(done)))
        finally:
            for w in waits:
                w.cancel()


class _Picking:
    """A method on every channel of a ListChannel; a call goes on the one picked then."""

    def __init__(self, owner: ListChannel, made: list[Any]) -> None:
        self._owner = owner
        self._made = made

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._made[self._owner.pick()](*args, **kwargs)


async def peer_certificate(security: Security, address: str) -> tuple[str, str] | None:
    """The (common name, role) of the certificate `address` presents to a TLS handshake checked
    against `security`'s CA and host name, presenting its client certificate; None when the peer
    cannot be reached or the handshake fails (gRPC's own handshake then reports it)."""
    host, port = parse_address(address, "server")
    context = ssl.create_default_context(cadata=security._pem["ca"].decode() if security._pem["ca"] else None)
    if security.tls_cert is not None and security.tls_key is not None:
        context.load_cert_chain(security.tls_cert, security.tls_key)
    context.set_alpn_protocols(["h2"])
    try:
        _, writer = await asyncio.wait_for(
            asyncio.open_connection(host, port, ssl=context, server_hostname=host), PROBE_TIMEOUT_S
        )
    except (OSError, ssl.SSLError, asyncio.TimeoutError):
        return None
    try:
        der = writer.get_extra_info("ssl_object").getpeercert(binary_form=True)
    finally:
        writer.transport.abort()  # no TLS goodbye: a gRPC peer may never answer one
    return certificate_fields(ssl.DER_cert_to_PEM_cert(der).encode()) if der else None


async def check_role(security: Security, addresses: Sequence[str], role: str, what: str) -> None:
    """PermissionDenied when a peer at `addresses` answers under TLS with a certificate made for
    another DRVS role than `role` (a certificate without a DRVS role, from a CA that writes none,
    is left to the CA and host name checks). Nothing without TLS."""
    if not security.tls:
        return
    for address in addresses:
        found = await peer_certificate(security, address)
        if found is None:
            continue
        common_name, peer_role = found
        if peer_role and peer_role != role:
            raise PermissionDenied(
                f"{what} {address}: its certificate {common_name!r} has the role {peer_role} (OU={peer_role}), "
                f"not {role} (OU={role}); refusing to talk to it"
            )
