"""What the robot client's handles share: a delivery (Subscription, Track) woken when something
arrives and closed on leaving `async with`; and an opening (Connecting, Subscribing, Tracking),
opened by awaiting it or entering it."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Generator, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import grpc
from grpc import aio

from drvs.core.errors import Unavailable
from drvs.wire import _grpc

if TYPE_CHECKING:
    from drvs.robot.client import DrvsClient

T = TypeVar("T")


class _Delivery:
    """What Subscription and Track share: a waiter woken when something arrives or the delivery
    ends, and `async with` closing it on leaving the block."""

    _wakeup: asyncio.Future[None] | None

    def close(self) -> None:
        raise NotImplementedError

    def _wake(self) -> None:
        if self._wakeup is not None and not self._wakeup.done():
            self._wakeup.set_result(None)

    async def __aenter__(self: _D) -> _D:
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


_D = TypeVar("_D", bound=_Delivery)


class _Opening(Generic[T]):
    """Something opened by awaiting it (`x = await opening`) or by entering it as an async context
    manager (`async with opening as x:`), which closes it on leaving the block."""

    def __init__(self) -> None:
        self._opened: T | None = None

    async def _open(self) -> T:
        raise NotImplementedError

    async def _close(self, opened: T) -> None:
        raise NotImplementedError

    async def _opening(self) -> T:
        self._opened = await self._open()
        return self._opened

    def __await__(self) -> Generator[Any, None, T]:
        return self._opening().__await__()

    async def __aenter__(self) -> T:
        return await self._opening()

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._opened is not None:
            await self._close(self._opened)


_Sent = TypeVar("_Sent", bound=_Delivery)


class _Sending(_Opening[_Sent]):
    """A request opened by sending it (`send`), closed by closing what it opened."""

    def __init__(self, send: Callable[[], Awaitable[_Sent]]) -> None:
        super().__init__()
        self._send = send

    async def _open(self) -> _Sent:
        return await self._send()

    async def _close(self, opened: _Sent) -> None:
        opened.close()


class Connecting(_Opening["DrvsClient"]):
    """What DrvsClient.connect returns: `await` it for a started client whose server answered, or
    use it as an async context manager (`async with DrvsClient.connect(...) as drvs:`), which closes
    the client on leaving the block. A server that does not answer raises Unavailable naming it."""

    def __init__(self, client: DrvsClient, connect_timeout_s: float) -> None:
        super().__init__()
        self.client = client
        self._timeout_s = connect_timeout_s

    async def _open(self) -> DrvsClient:
        try:
            await self.client.start()
            await self.client.check_server(self._timeout_s)
        except BaseException:
            await self.client.close()
            raise
        return self.client

    async def _close(self, opened: DrvsClient) -> None:
        await opened.close()


def health_check(
    channel: aio.Channel, metadata: Sequence[tuple[str, str]] | None, server: str, timeout_s: float
) -> Callable[[], Awaitable[None]]:
    """One attempt to ask the server's gRPC health service whether it serves (DrvsClient.check_server):
    Unavailable naming `server` when it is not there, not serving, or silent for `timeout_s` seconds."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    stub = health_pb2_grpc.HealthStub(channel)

    async def check() -> None:
        try:
            reply = await stub.Check(health_pb2.HealthCheckRequest(), timeout=timeout_s, metadata=metadata)
        except grpc.RpcError as exc:
            code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNKNOWN
            if code == grpc.StatusCode.UNIMPLEMENTED:
                return  # a server without a health service: it answered, so it is there
            if code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                details = exc.details() if hasattr(exc, "details") else ""
                raise Unavailable(
                    f"server {server}: not reachable within {timeout_s:g} s ({code.name}: {details})"
                ) from None
            raise _grpc.from_rpc_error(exc, f"server {server}") from None
        if reply.status != health_pb2.HealthCheckResponse.SERVING:
            status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
            raise Unavailable(f"server {server}: its health service says {status}")

    return check
