"""The part of every role's lifecycle that is the same: a grpc.aio server bound to an address,
with health checking and reflection, started and stopped gracefully."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, TypeVar

from grpc import aio
from grpc_health.v1 import health_pb2

from drvs.core.net import format_address, host_of
from drvs.wire import _grpc
from drvs.wire.health import add_health_and_reflection, mark_serving
from drvs.wire.security import Security

_L = TypeVar("_L", bound="Lifecycle")


class Lifecycle:
    """`async with` for every role object: start() on entry, stop() on exit."""

    async def start(self) -> None:
        raise NotImplementedError

    async def stop(self, grace: float = 2.0) -> None:
        raise NotImplementedError

    async def __aenter__(self: _L) -> _L:
        await self.start()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()


class Endpoint:
    """Binds `listen` (port 0 picks a free port), serves what `add_servicers` adds; stop() is idempotent."""

    def __init__(
        self,
        listen: str,
        service_names: Sequence[str],
        add_servicers: Callable[[aio.Server], None],
        *,
        security: Security | None = None,
        interceptors: Sequence[aio.ServerInterceptor] = (),
        options: Sequence[tuple[str, Any]] = (),
        also_listen: Sequence[str] = (),
    ) -> None:
        self.listen = listen
        #: More addresses the same services are served on (port 0: any free port), and their ports.
        self.also_listen = tuple(also_listen)
        self.also_ports: list[int] = []
        self._options = tuple(options)
        self.security = security or Security()
        self._interceptors = tuple(interceptors)
        self.service_names = tuple(service_names)
        self._add_servicers = add_servicers
        self.port = 0
        self._server: aio.Server | None = None
        self._health: Any = None
        self._stopped = False

    @property
    def address(self) -> str:
        """The bound address: the listen host with the real port."""
        return format_address(host_of(self.listen), self.port)

    @property
    def started(self) -> bool:
        return self._server is not None

    async def start(self) -> None:
        server = _grpc.new_server(self._interceptors, self._options)
        self._add_servicers(server)
        self._health = add_health_and_reflection(server, self.service_names)
        self.port = self.security.bind(server, self.listen)
        self.also_ports = [self.security.bind(server, address) for address in self.also_listen]
        await server.start()
        self._server = server
        await mark_serving(self._health, self.service_names)

    async def set_serving(self, serving: bool) -> None:
        """What the health service answers for every service of this endpoint."""
        status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", *self.service_names):
            await self._health.set(name, status)

    async def set_service_serving(self, name: str, serving: bool) -> None:
        """What the health service answers for one service (the whole process's "" unchanged)."""
        if self._health is not None and not self._stopped:
            status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
            await self._health.set(name, status)

    async def stop(self, grace: float) -> None:
        """Report NOT_SERVING first, so health checkers stop sending, then let calls finish."""
        if self._server is None or self._stopped:
            return
        self._stopped = True
        await self._health.enter_graceful_shutdown()
        await self._server.stop(grace)

    async def wait_for_termination(self) -> None:
        assert self._server is not None
        await self._server.wait_for_termination()
