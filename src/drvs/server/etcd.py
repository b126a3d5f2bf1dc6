"""etcd, the store several DRVS servers share their registry in: a small asyncio client of
etcd's own v3 gRPC API. The server's (drvs-server --registry etcd://...); the tools' launcher starts etcd.

The API's messages and stubs are the generated ones the `aetcd` package ships (`aetcd.rpc`: etcd's
own .proto files, compiled for current grpcio and protobuf, maintained); the channel is ours, so
that it can hold several endpoints (gRPC's own `ipv4:` name resolution with round-robin balancing:
a member that dies is skipped) and TLS, which aetcd's client does not offer. Install with the
`etcd` extra (`pip install 'drvs[etcd]'`).

What DRVS needs of etcd and nothing more: keys under a prefix, leases (a camera's lease is an etcd
lease: it expires on its own when nobody keeps it alive), compare-and-put transactions (who holds
a camera id), and a watch of the prefix from a revision (every server keeps its own index current).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Sequence
from dataclasses import dataclass
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import InvalidArgument, Unavailable
from drvs.core.net import format_address, grpc_target, parse_address

log = logging.getLogger("drvs.server.etcd")
SCHEME = "etcd://"
#: A read failed UNAVAILABLE is sent this many times in all (EtcdClient._call), the first pause
#: READ_BACKOFF_S and doubling.
READ_ATTEMPTS = 3
READ_BACKOFF_S = 0.05
#: How long one call to etcd may take, seconds.
CALL_TIMEOUT_S = 5.0


def _rpc() -> Any:
    try:
        from aetcd import rpc
    except ImportError:
        raise InvalidArgument("registry: an etcd registry needs the etcd extra (pip install 'drvs[etcd]')") from None
    return rpc


@dataclass(frozen=True)
class Endpoints:
    """`etcd://HOST:PORT[,HOST:PORT...]`: the members to talk to."""

    addresses: tuple[tuple[str, int], ...]

    @classmethod
    def parse(cls, text: str, name: str = "registry") -> Endpoints:
        if not text.startswith(SCHEME):
            raise InvalidArgument(f"{name}: {text[:80]!r} is not etcd://HOST:PORT[,HOST:PORT...] (or memory)")
        parts = [p.strip() for p in text[len(SCHEME) :].split(",")]
        if not parts or not all(parts):
            raise InvalidArgument(f"{name}: {text[:80]!r} names an empty etcd endpoint")
        return cls(tuple(parse_address(p, name) for p in parts))

    def target(self) -> str:
        """A gRPC target naming every member (drvs.core.net.grpc_target): an `ipv4:`/`ipv6:` list for
        addresses, or one DNS name (which may resolve to several members)."""
        return grpc_target([format_address(h, p) for h, p in self.addresses], "registry")

    def __str__(self) -> str:
        return SCHEME + ",".join(f"{h}:{p}" for h, p in self.addresses)


@dataclass(frozen=True)
class Event:
    """One change under a watched prefix: a put (value, lease) or a delete (a lease's expiry too)."""

    kind: str  # "put" or "delete"
    key: bytes
    value: bytes
    lease: int
    revision: int


class EtcdClient:
    """Keys, leases, transactions and watches on one etcd cluster. `async with` or start()/close()."""

    def __init__(
        self,
        endpoints: Endpoints,
        *,
        credentials: grpc.ChannelCredentials | None = None,
        token: str = "",
        timeout_s: float = CALL_TIMEOUT_S,
    ) -> None:
        self.endpoints = endpoints
        self._credentials = credentials
        self._metadata = (("token", token),) if token else ()
        self.timeout_s = timeout_s
        self._channel: aio.Channel | None = None
        self._rpc = _rpc()

    async def start(self) -> None:
        options = [("grpc.lb_policy_name", "round_robin"), ("grpc.enable_retries", 1)]
        target = self.endpoints.target()
        if self._credentials is not None and len(self.endpoints.addresses) > 1:
            # One channel per member under TLS: a list's authority is the whole list, which no
            # member's certificate names (drvs.wire.channels).
            from drvs.wire.channels import ListChannel

            self._channel = ListChannel(
                [aio.secure_channel(format_address(h, p), self._credentials, options=options)
                 for h, p in self.endpoints.addresses]
            )  # fmt: skip
        elif self._credentials is not None:
            self._channel = aio.secure_channel(target, self._credentials, options=options)
        else:
            self._channel = aio.insecure_channel(target, options=options)
        rpc = self._rpc
        self.kv = rpc.KVStub(self._channel)
        self.leases = rpc.LeaseStub(self._channel)
        self.watches = rpc.WatchStub(self._channel)
        self.maintenance = rpc.MaintenanceStub(self._channel)

    async def close(self) -> None:
        if self._channel is not None:
            await self._channel.close()
            self._channel = None

    async def __aenter__(self) -> EtcdClient:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _call(self, method: Any, request: Any, what: str, *, repeatable: bool = False) -> Any:
        """One call within timeout_s. A `repeatable` one (a read: etcd answers it alike however
        often it is sent) is sent again when it fails UNAVAILABLE, up to READ_ATTEMPTS times in
        all, READ_BACKOFF_S apart and doubling, within the same timeout: a member killed or cut
        off with the call on its connection fails it so ("Stream removed"), and the next attempt
        goes where the channel picks next. A write is not: it may have been applied (etcd's own
        Go client, clientv3, likewise retries on Unavailable only the calls it marks repeatable)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout_s
        attempt = 1
        while True:
            left = deadline - loop.time()
            try:
                return await method(request, timeout=left, metadata=self._metadata, wait_for_ready=False)
            except aio.AioRpcError as exc:
                pause = READ_BACKOFF_S * 2 ** (attempt - 1)
                again = repeatable and exc.code() == grpc.StatusCode.UNAVAILABLE and attempt < READ_ATTEMPTS
                if not again or deadline - loop.time() <= pause:
                    raise Unavailable(f"etcd {self.endpoints}: {what}: {exc.code().name} {exc.details()}") from None
                log.debug(
                    "etcd %s: %s failed UNAVAILABLE (%s): again in %g s", self.endpoints, what, exc.details(), pause
                )
            await asyncio.sleep(pause)
            attempt += 1

    async def status(self) -> Any:
        """The answering member's status (its version, the cluster's revision); Unavailable if none answers."""
        return await self._call(self.maintenance.Status, self._rpc.StatusRequest(), "status", repeatable=True)

    async def grant(self, ttl_s: float) -> int:
        """A new lease of `ttl_s` seconds (etcd counts whole seconds: rounded up, at least 1); its id."""
        ttl = max(1, int(-(-ttl_s // 1)))
        reply = await self._call(self.leases.LeaseGrant, self._rpc.LeaseGrantRequest(TTL=ttl), "lease grant")
        return int(reply.ID)

    async def keep_alive(self, lease: int) -> float:
        """Renew a lease once; the seconds it has left (0: it had expired, or never was)."""
        rpc = self._rpc
        try:
            call = self.leases.LeaseKeepAlive(metadata=self._metadata, timeout=self.timeout_s)
            await call.write(rpc.LeaseKeepAliveRequest(ID=lease))
            reply = await call.read()
            await call.done_writing()
            call.cancel()
        except aio.AioRpcError as exc:
            raise Unavailable(f"etcd {self.endpoints}: lease keep-alive: {exc.code().name} {exc.details()}") from None
        return float(reply.TTL) if reply is not aio.EOF else 0.0

    async def revoke(self, lease: int) -> None:
        """End a lease now: etcd deletes its keys (a lease already gone is not an error)."""
        try:
            await self._call(self.leases.LeaseRevoke, self._rpc.LeaseRevokeRequest(ID=lease), "lease revoke")
        except Unavailable as exc:
            if "NOT_FOUND" not in str(exc) and "not found" not in str(exc):
                raise

    async def put(self, key: bytes, value: bytes, lease: int = 0) -> int:
        """Set a key (attached to `lease`, 0: none); the store's revision after it."""
        reply = await self._call(self.kv.Put, self._rpc.PutRequest(key=key, value=value, lease=lease), "put")
        return int(reply.header.revision)

    async def get(self, key: bytes) -> tuple[bytes, int] | None:
        """A key's value and its lease, or None."""
        reply = await self._call(self.kv.Range, self._rpc.RangeRequest(key=key), "get", repeatable=True)
        if not reply.kvs:
            return None
        return bytes(reply.kvs[0].value), int(reply.kvs[0].lease)

    async def get_prefix(self, prefix: bytes) -> tuple[list[tuple[bytes, bytes, int]], int]:
        """Every (key, value, lease) under `prefix`, and the revision they were read at."""
        reply = await self._call(
            self.kv.Range,
            self._rpc.RangeRequest(key=prefix, range_end=_prefix_end(prefix)),
            "get prefix",
            repeatable=True,
        )
        return [(bytes(kv.key), bytes(kv.value), int(kv.lease)) for kv in reply.kvs], int(reply.header.revision)

    async def delete(self, key: bytes) -> bool:
        """Delete a key; whether it was there."""
        reply = await self._call(self.kv.DeleteRange, self._rpc.DeleteRangeRequest(key=key), "delete")
        return int(reply.deleted) > 0

    async def put_if(self, key: bytes, value: bytes, lease: int, expected: bytes | None) -> bool:
        """Set `key` only if it holds `expected` now (None: only if it is absent); whether it was set."""
        rpc = self._rpc
        if expected is None:
            compare = rpc.Compare(key=key, result=rpc.Compare.EQUAL, target=rpc.Compare.VERSION, version=0)
        else:
            compare = rpc.Compare(key=key, result=rpc.Compare.EQUAL, target=rpc.Compare.VALUE, value=expected)
        txn = rpc.TxnRequest(
            compare=[compare],
            success=[rpc.RequestOp(request_put=rpc.PutRequest(key=key, value=value, lease=lease))],
        )
        reply = await self._call(self.kv.Txn, txn, "put if")
        return bool(reply.succeeded)

    async def watch_prefix(self, prefix: bytes, start_revision: int) -> AsyncIterator[Event]:
        """Every change under `prefix` from `start_revision` on, in order, until cancelled or the
        stream breaks (Unavailable: the caller reads the prefix again and watches anew)."""
        rpc = self._rpc
        create = rpc.WatchCreateRequest(key=prefix, range_end=_prefix_end(prefix), start_revision=start_revision)
        call = self.watches.Watch(metadata=self._metadata)
        try:
            await call.write(rpc.WatchRequest(create_request=create))
            async for reply in call:
                if reply.canceled:
                    raise Unavailable(f"etcd {self.endpoints}: watch cancelled: {reply.cancel_reason or 'compacted'}")
                for e in reply.events:
                    kind = "delete" if e.type == rpc.Event.DELETE else "put"
                    kv = e.kv
                    yield Event(kind, bytes(kv.key), bytes(kv.value), int(kv.lease), int(kv.mod_revision))
        except aio.AioRpcError as exc:
            raise Unavailable(f"etcd {self.endpoints}: watch: {exc.code().name} {exc.details()}") from None
        finally:
            call.cancel()


def _prefix_end(prefix: bytes) -> bytes:
    """The end of the key range that holds every key starting with `prefix` (etcd's range_end)."""
    end = bytearray(prefix)
    for i in range(len(end) - 1, -1, -1):
        if end[i] < 0xFF:
            end[i] += 1
            return bytes(end[: i + 1])
    return b"\0"


async def wait_ready(
    endpoints: Endpoints, timeout_s: float, credentials: grpc.ChannelCredentials | None = None
) -> None:
    """Until some member answers Status (gRPC waits for a connection), within `timeout_s` seconds;
    Unavailable naming the endpoints otherwise."""
    async with EtcdClient(endpoints, timeout_s=timeout_s, credentials=credentials) as client:
        try:
            await client.maintenance.Status(client._rpc.StatusRequest(), timeout=timeout_s, wait_for_ready=True)
        except aio.AioRpcError as exc:
            raise Unavailable(f"etcd {endpoints}: not ready within {timeout_s:g} s: {exc.code().name}") from None


__all__: Sequence[str] = ("Endpoints", "EtcdClient", "Event", "wait_ready")
