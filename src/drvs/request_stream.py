"""DetectStream: many detection requests on one long-lived call, each answered by a reply.

A unary call pays for its headers, trailers and call set-up on every request; on the stream a
request is one message. Both hops use it: the robot client to the server, the server to each
camera. Replies carry the request_id they answer; a refused request gets a reply with `error`
set and the stream goes on.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Awaitable, Callable

import grpc
from grpc import aio

from drvs import _grpc, errors
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2

log = logging.getLogger(__name__)

Reply = detection_pb2.DetectionReply
Request = detection_pb2.DetectionRequest


class RequestStream:
    """The sending side: `await request(message, timeout_s)` returns the peer's reply or raises the
    DrvsError it stands for. The call is opened on first use and reopened after it ends (a peer that
    restarted), so a request during an outage fails fast with Unavailable and the next one retries.

    elide_repeats=True leaves out robot_id, callback_address, filter_def and region when they repeat
    the previous request on the stream (the receiver fills them back in); only for senders whose
    messages are their own to edit.
    """

    def __init__(
        self,
        stub: detection_pb2_grpc.DetectObjectBoundaryStub,
        peer: str,
        *,
        elide_repeats: bool,
        metadata: tuple[tuple[str, str], ...] = (),
    ) -> None:
        self._stub = stub
        self._metadata = metadata
        self._peer = peer
        self._elide = elide_repeats
        self._call: aio.StreamStreamCall[Request, Reply] | None = None
        self._reader: asyncio.Task[None] | None = None
        self._pending: dict[str, asyncio.Future[Reply]] = {}
        self._write_lock = asyncio.Lock()
        self._sent = StreamContext()

    @property
    def in_flight(self) -> int:
        """Requests sent or waiting to be sent that have no reply yet."""
        return len(self._pending)

    def _open(self) -> aio.StreamStreamCall[Request, Reply]:
        call: aio.StreamStreamCall[Request, Reply] = self._stub.DetectStream(metadata=self._metadata or None)
        self._call = call
        self._sent = StreamContext()
        self._reader = asyncio.get_running_loop().create_task(self._read(call))
        return call

    async def _read(self, call: aio.StreamStreamCall[Request, Reply]) -> None:
        failure: errors.DrvsError
        try:
            async for reply in call:
                future = self._pending.pop(reply.request_id, None)
                if future is not None and not future.done():
                    future.set_result(reply)
            failure = errors.Unavailable(f"{self._peer}: the request stream ended")
        except grpc.RpcError as exc:
            failure = _grpc.from_rpc_error(exc, self._peer)
        except asyncio.CancelledError:
            failure = errors.Unavailable(f"{self._peer}: the request stream was closed")
        if self._call is call:
            self._call = None
        for future in self._pending.values():
            if not future.done():
                future.set_exception(failure)
        self._pending.clear()

    async def request(self, message: Request, timeout_s: float) -> Reply:
        if not message.request_id:
            raise errors.InvalidArgument("request_id: empty; a streamed request needs its own id")
        if message.request_id in self._pending:
            raise errors.InvalidArgument(f"request_id: {message.request_id!r} is already waiting for a reply")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Reply] = loop.create_future()
        self._pending[message.request_id] = future
        timer = loop.call_later(timeout_s, _expire, future, self._peer, timeout_s)
        try:
            async with self._write_lock:
                # A request whose time ran out while it waited for its turn is not sent: the peer
                # would work on a request whose sender has already given up on it.
                if not future.done():
                    call = self._call or self._open()
                    if self._elide:
                        self._sent.elide(message)
                    try:
                        await call.write(message)
                    except (grpc.RpcError, asyncio.InvalidStateError) as exc:
                        if self._call is call:
                            self._call = None
                        if isinstance(exc, grpc.RpcError):
                            raise _grpc.from_rpc_error(exc, self._peer) from None
                        raise errors.Unavailable(f"{self._peer}: the request stream ended") from None
            reply = await future
        finally:
            timer.cancel()
            self._pending.pop(message.request_id, None)
            if future.done() and not future.cancelled():
                future.exception()  # retrieved: a failure nobody awaited is not an error to log
            else:
                future.cancel()
        if reply.HasField("error"):
            raise _grpc.error_from_code(reply.error.code, reply.error.message)
        return reply

    async def close(self) -> None:
        call, reader = self._call, self._reader
        self._call = None
        if call is not None:
            call.cancel()
        if reader is not None:
            reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)


def _expire(future: asyncio.Future[Reply], peer: str, timeout_s: float) -> None:
    if not future.done():
        future.set_exception(errors.DeadlineExceeded(f"{peer}: no reply within {timeout_s:g} s"))


#: Fields a sender may leave out when they repeat the previous request on the same stream: who
#: asks and where reports go, and, for a robot asking again and again, what and where to look.
REPEATABLE = ("robot_id", "callback_address", "filter_def")


class StreamContext:
    """The previous request's repeatable fields and region on one stream. The sender elides what
    repeats; the receiver fills it back in. Both update from every request sent or received,
    whatever its fate, so their views never part."""

    def __init__(self) -> None:
        self.values = dict.fromkeys(REPEATABLE, "")
        self.region: geometry_pb2.Region | None = None

    def elide(self, message: Request) -> None:
        for name in REPEATABLE:
            value = getattr(message, name)
            if value and value == self.values[name]:
                setattr(message, name, "")
            else:
                self.values[name] = value
        if message.HasField("region"):
            if self.region is not None and message.region == self.region:
                message.ClearField("region")
            else:
                self.region = geometry_pb2.Region()
                self.region.CopyFrom(message.region)

    def fill(self, message: Request) -> None:
        for name in REPEATABLE:
            value = getattr(message, name)
            if value:
                self.values[name] = value
            else:
                setattr(message, name, self.values[name])
        if message.HasField("region"):
            self.region = geometry_pb2.Region()
            self.region.CopyFrom(message.region)
        elif self.region is not None:
            message.region.CopyFrom(self.region)


async def serve_request_stream(
    requests: AsyncIterator[Request], answer: Callable[[Request], Awaitable[Reply]], where: str
) -> AsyncIterator[Reply]:
    """The receiving side: answer each request in order; a DrvsError becomes a reply's error and the
    stream goes on; anything unexpected is logged and answered as INTERNAL."""
    context = StreamContext()
    async for message in requests:
        context.fill(message)
        try:
            yield await answer(message)
        except errors.DrvsError as exc:
            yield refusal(message.request_id, _grpc.status_of(exc), str(exc))
        except Exception:
            log.exception("%s: request %s failed", where, message.request_id)
            yield refusal(message.request_id, grpc.StatusCode.INTERNAL, f"{where}: internal error")


def refusal(request_id: str, code: grpc.StatusCode, text: str) -> Reply:
    return Reply(request_id=request_id, error=detection_pb2.RequestError(code=code.name, message=text))
