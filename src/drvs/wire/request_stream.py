"""Detection requests on long-lived calls, each answered by a reply.

A unary call pays for its headers, trailers and call set-up on every request; on a stream a
request is one message. The robot client sends to the server on DetectStream (`RequestStream`):
replies carry the request_id they answer; a refused request gets a reply with `error` set and
the stream goes on. The server sends to each camera on DetectBatches (`BatchSender`): whatever
waits for the camera when it can write goes as one message, answered by one message.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable

import grpc
from grpc import aio

from drvs.core import errors
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from drvs.wire import _grpc
from drvs.wire.convert import MAX_REGION_BYTES

log = logging.getLogger(__name__)

Reply = detection_pb2.DetectionReply
Request = detection_pb2.DetectionRequest
Requests = detection_pb2.DetectionRequests
Replies = detection_pb2.DetectionReplies
#: A batch is closed once its requests' serialised sizes add up to this (a lone request may be
#: larger, up to the message size limit).
MAX_BATCH_BYTES = 1024 * 1024


class RequestStream:
    """The sending side: `await request(message, timeout_s)` returns the peer's reply or raises the
    DrvsError it stands for. The call is opened on first use and reopened after it ends (a peer that
    restarted), so a request during an outage fails fast with Unavailable and the next one retries.

    It leaves out robot_id, callback_address, filter_def and region when they repeat the previous
    request on the stream (the receiver fills them back in): it edits the messages it is given.

    A fused continuous request is answered more than once: `request(message, timeout_s, consumer)`
    returns its first reply as usual, and hands every later reply carrying a snapshot to `consumer`,
    without waiting, until `release(request_id)`; when the call ends, `consumer` gets the DrvsError
    that ended it (and is released).
    """

    def __init__(
        self,
        stub: detection_pb2_grpc.DetectObjectBoundaryStub,
        peer: str,
        *,
        metadata: tuple[tuple[str, str], ...] = (),
    ) -> None:
        self._stub = stub
        self._metadata = metadata
        self._peer = peer
        self._call: aio.StreamStreamCall[Request, Reply] | None = None
        self._reader: asyncio.Task[None] | None = None
        self._pending: dict[str, asyncio.Future[Reply]] = {}
        # request_id -> (the call it was sent on, who takes its snapshots): fused continuous requests.
        self._consumers: dict[str, tuple[aio.StreamStreamCall[Request, Reply], Consumer]] = {}
        self._write_lock = asyncio.Lock()
        self._sent = StreamContext()
        self._due_cancels: list[str] = []
        self._flusher: asyncio.Task[None] | None = None

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
                if reply.HasField("snapshot"):
                    taker = self._consumers.get(reply.request_id)
                    if taker is not None:
                        _consume(taker[1], reply, self._peer)
                        continue
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
        for request_id, (on, consumer) in list(self._consumers.items()):
            if on is call:
                del self._consumers[request_id]
                _consume(consumer, failure, self._peer)

    async def request(self, message: Request, timeout_s: float, consumer: Consumer | None = None) -> Reply:
        """Send `message` and return its (first) reply; `consumer` takes its later snapshots (see
        the class). A refusal raises its DrvsError and releases the consumer."""
        if not message.request_id:
            raise errors.InvalidArgument("request_id: empty; a streamed request needs its own id")
        if message.request_id in self._pending:
            raise errors.InvalidArgument(f"request_id: {message.request_id!r} is already waiting for a reply")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Reply] = loop.create_future()
        self._pending[message.request_id] = future
        timer = loop.call_later(timeout_s, _expire, future, self._peer, timeout_s)
        restore: Callable[[], None] | None = None
        try:
            async with self._write_lock:
                # A request whose time ran out while it waited for its turn is not sent: the peer
                # would work on a request whose sender has already given up on it.
                if not future.done():
                    if self._due_cancels:
                        await self._write_cancels()
                    call = self._call or self._open()
                    if consumer is not None:  # before the write: a reply cannot come before it
                        self._consumers[message.request_id] = (call, consumer)
                    restore = self._sent.elide(message)
                    try:
                        await call.write(message)
                    except (grpc.RpcError, asyncio.InvalidStateError) as exc:
                        if self._call is call:
                            self._call = None
                        if isinstance(exc, grpc.RpcError):
                            raise _grpc.from_rpc_error(exc, self._peer) from None
                        raise errors.Unavailable(f"{self._peer}: the request stream ended") from None
            reply = await future
        except errors.Unavailable:
            # The stream ended: whoever sends this message again sends it whole, on a new stream.
            if restore is not None:
                restore()
            self.release(message.request_id)
            raise
        except BaseException:
            self.release(message.request_id)
            raise
        finally:
            timer.cancel()
            self._pending.pop(message.request_id, None)
            if future.done() and not future.cancelled():
                future.exception()  # retrieved: a failure nobody awaited is not an error to log
            else:
                future.cancel()
        if reply.HasField("error"):
            self.release(message.request_id)
            raise _grpc.error_from_code(reply.error.code, reply.error.message, reply.error.retry_after_s)
        return reply

    def release(self, request_id: str) -> None:
        """Stop handing `request_id`'s snapshots to its consumer (later ones are dropped)."""
        self._consumers.pop(request_id, None)

    def cancel_soon(self, request_id: str) -> None:
        """Tell the peer to stop the continuous request `request_id`, sent earlier on this stream:
        written before any request sent after this call. Best effort: no reply is awaited, and when
        the stream that carried it has ended there is nothing to tell (the peer forgot its requests)."""
        self._due_cancels.append(request_id)
        if self._flusher is None or self._flusher.done():
            self._flusher = asyncio.get_running_loop().create_task(self.flush_cancels())

    async def flush_cancels(self) -> None:
        """Write the cancels that are due now."""
        async with self._write_lock:
            await self._write_cancels()

    async def _write_cancels(self) -> None:
        due, self._due_cancels = self._due_cancels, []
        call = self._call
        if call is None:
            return
        for request_id in due:
            # Not elided: it carries no repeatable field, so the stream's context stays as it is.
            with contextlib.suppress(grpc.RpcError, asyncio.InvalidStateError):
                await call.write(Request(request_id=request_id, cancel=True))

    async def close(self) -> None:
        if self._flusher is not None:
            await asyncio.gather(self._flusher, return_exceptions=True)
        call, reader = self._call, self._reader
        self._call = None
        if call is not None:
            call.cancel()
        if reader is not None:
            reader.cancel()
            await asyncio.gather(reader, return_exceptions=True)


class _Forward:
    """One request on its way through a BatchSender; `done` is called exactly once."""

    __slots__ = ("deadline", "done", "message", "settled", "written_at")

    def __init__(self, message: Request, deadline: float, done: Callable[[Reply | errors.DrvsError], None]) -> None:
        self.message = message
        self.deadline = deadline
        self.done = done
        self.settled = False
        self.written_at: float | None = None  # when its write began (loop time)


class _BatchCall:
    """One DetectBatches call and the requests written on it that have no reply yet, in order."""

    __slots__ = ("call", "reader", "sent")

    def __init__(self, call: aio.StreamStreamCall[Requests, Replies]) -> None:
        self.call = call
        self.sent: deque[_Forward] = deque()
        self.reader: asyncio.Task[None] | None = None


class BatchSender:
    """The server's side of DetectBatches to one camera.

    `submit(message, done)` queues a request and returns at once; `done` is later called exactly
    once with the camera's reply, or with the DrvsError that stands for its refusal, its silence
    past `timeout_s` (DeadlineExceeded), or a broken stream (Unavailable). No task, future or timer
    is made per request: one writer task sends whatever is queued whenever the previous write has
    completed (so batches grow with load and a lone request goes at once), one reader task matches
    the replies to the requests in order, and one timer expires the oldest requests. A request
    whose time ran out while it was queued is not sent. The call is opened on first use and
    reopened after it ends (a camera that restarted).
    """

    def __init__(
        self,
        stub: detection_pb2_grpc.DetectObjectBoundaryStub,
        peer: str,
        *,
        timeout_s: float,
        metadata: tuple[tuple[str, str], ...] = (),
        max_batch_bytes: int = MAX_BATCH_BYTES,
    ) -> None:
        self._stub = stub
        self._peer = peer
        self._timeout_s = timeout_s
        self._metadata = metadata
        self._max_batch_bytes = max_batch_bytes
        self._queue: deque[_Forward] = deque()  # submitted, not yet written
        self._order: deque[_Forward] = deque()  # every unsettled request, oldest (first to expire) first
        self._unsettled = 0
        self._call: _BatchCall | None = None
        self._writer: asyncio.Task[None] | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._closed = False
        #: Messages written and requests they carried, for the curious (benchmarks, tests).
        self.batches_written = 0
        self.requests_written = 0

    @property
    def in_flight(self) -> int:
        """Requests submitted that have no answer yet (queued, or sent and not answered)."""
        return self._unsettled

    def submit(self, message: Request, done: Callable[[Reply | errors.DrvsError], None]) -> None:
        loop = asyncio.get_running_loop()
        forward = _Forward(message, loop.time() + self._timeout_s, done)
        self._unsettled += 1
        if self._closed:
            self._settle(forward, errors.Unavailable(f"{self._peer}: the request stream was closed"))
            return
        self._queue.append(forward)
        self._order.append(forward)
        if self._timer is None:
            self._timer = loop.call_at(forward.deadline, self._expire)
        if self._writer is None:
            self._writer = loop.create_task(self._write())

    def _settle(self, forward: _Forward, result: Reply | errors.DrvsError) -> None:
        if forward.settled:
            return
        forward.settled = True
        self._unsettled -= 1
        try:
            forward.done(result)
        except Exception:
            log.exception("%s: handling the answer to request %s failed", self._peer, forward.message.request_id)
        order = self._order
        while order and order[0].settled:
            order.popleft()

    def _expire(self) -> None:
        self._timer = None
        loop = asyncio.get_running_loop()
        now = loop.time()
        order = self._order
        failure = errors.DeadlineExceeded(f"{self._peer}: no reply within {self._timeout_s:g} s")
        while order and (order[0].settled or order[0].deadline <= now):
            self._settle(order.popleft(), failure)
        state = self._call
        oldest = state.sent[0].written_at if state is not None and state.sent else None
        if state is not None and oldest is not None and oldest + self._timeout_s <= now:
            # The camera has had a whole timeout to read and answer a request written to it, and
            # has not: it is not reading its stream (or cannot keep up). The call is cut off, so
            # neither this process nor gRPC keeps writing to (and buffering for) a peer that does
            # not read; the next request opens a new one.
            log.warning("%s: no reply within %g s; closing its request stream", self._peer, self._timeout_s)
            state.call.cancel()
            self._end(state, failure)
            oldest = None
        self._schedule(oldest)

    def _schedule(self, oldest_written: float | None = None) -> None:
        """Wake for the next deadline, or for the oldest unanswered write's timeout."""
        wake = [self._order[0].deadline] if self._order else []
        if oldest_written is not None:
            wake.append(oldest_written + self._timeout_s)
        if wake and self._timer is None:
            self._timer = asyncio.get_running_loop().call_at(min(wake), self._expire)

    def _open(self) -> _BatchCall:
        state = _BatchCall(self._stub.DetectBatches(metadata=self._metadata or None))
        state.reader = asyncio.get_running_loop().create_task(self._read(state))
        self._call = state
        return state

    def _take(self) -> list[_Forward]:
        """The next batch: queued requests still wanted, up to the byte budget."""
        batch: list[_Forward] = []
        size = 0
        queue = self._queue
        while queue:
            forward = queue[0]
            if forward.settled:
                queue.popleft()
                continue
            size += forward.message.ByteSize()
            if batch and size > self._max_batch_bytes:
                break
            batch.append(queue.popleft())
        return batch

    async def _write(self) -> None:
        try:
            while self._queue:
                batch = self._take()
                if not batch:
                    break
                state = self._call or self._open()
                now = asyncio.get_running_loop().time()
                for forward in batch:
                    forward.written_at = now
                state.sent.extend(batch)
                self.batches_written += 1
                self.requests_written += len(batch)
                try:
                    await state.call.write(Requests(requests=[f.message for f in batch]))
                except (grpc.RpcError, asyncio.InvalidStateError) as exc:
                    failure = (
                        _grpc.from_rpc_error(exc, self._peer)
                        if isinstance(exc, grpc.RpcError)
                        else errors.Unavailable(f"{self._peer}: the request stream ended")
                    )
                    self._end(state, failure)
        finally:
            self._writer = None

    async def _read(self, state: _BatchCall) -> None:
        failure: errors.DrvsError = errors.Unavailable(f"{self._peer}: the request stream ended")
        try:
            async for replies in state.call:
                for reply in replies.replies:
                    if not state.sent or state.sent[0].message.request_id != reply.request_id:
                        # Replies come in the order of the requests; anything else is a broken peer.
                        log.error("%s: reply for %r out of order; closing the stream", self._peer, reply.request_id)
                        state.call.cancel()
                        self._end(state, failure)
                        return
                    forward = state.sent.popleft()
                    if reply.HasField("error"):
                        error = _grpc.error_from_code(reply.error.code, reply.error.message, reply.error.retry_after_s)
                        self._settle(forward, error)
                    else:
                        self._settle(forward, reply)
        except grpc.RpcError as exc:
            failure = _grpc.from_rpc_error(exc, self._peer)
        except asyncio.CancelledError:
            failure = errors.Unavailable(f"{self._peer}: the request stream was closed")
        self._end(state, failure)

    def _end(self, state: _BatchCall, failure: errors.DrvsError) -> None:
        """The call is over: what was sent on it will not be answered."""
        if self._call is state:
            self._call = None
        while state.sent:
            self._settle(state.sent.popleft(), failure)

    async def close(self) -> None:
        self._closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        failure = errors.Unavailable(f"{self._peer}: the request stream was closed")
        while self._queue:
            self._settle(self._queue.popleft(), failure)
        state, writer = self._call, self._writer
        self._call = None
        if writer is not None:
            writer.cancel()
            await asyncio.gather(writer, return_exceptions=True)
        if state is not None:
            state.call.cancel()
            if state.reader is not None:
                state.reader.cancel()
                await asyncio.gather(state.reader, return_exceptions=True)
            self._end(state, failure)


#: Who takes a fused continuous request's later replies: each reply, then the DrvsError that ended
#: the call. Called on the stream's reader: it must not block.
Consumer = Callable[[Reply | errors.DrvsError], None]


def _consume(consumer: Consumer, item: Reply | errors.DrvsError, peer: str) -> None:
    try:
        consumer(item)
    except Exception:
        log.exception("%s: handing a snapshot over failed", peer)


def _expire(future: asyncio.Future[Reply], peer: str, timeout_s: float) -> None:
    if not future.done():
        future.set_exception(errors.DeadlineExceeded(f"{peer}: no reply within {timeout_s:g} s"))


#: Fields a sender may leave out when they repeat the previous request on the same stream: who
#: asks and where reports go, and, for a robot asking again and again, what and where to look; and
#: the robot's report secret, which it sends once per stream.
REPEATABLE = ("robot_id", "callback_address", "filter_def", "report_secret")
#: What an absent repeatable field is (report_secret is bytes).
_EMPTY: dict[str, str | bytes] = {"robot_id": "", "callback_address": "", "filter_def": "", "report_secret": b""}


class StreamContext:
    """The previous request's repeatable fields and region on one stream. The sender elides what
    repeats; the receiver fills it back in. Both update from every request sent or received,
    whatever its fate, so their views never part."""

    def __init__(self) -> None:
        self.values: dict[str, str | bytes] = dict(_EMPTY)
        self.region: geometry_pb2.Region | None = None

    def elide(self, message: Request) -> Callable[[], None]:
        """Leave out what repeats; returns what puts it back, for sending the message again on
        another stream (a retry after this one ended), whose receiver has seen none of it."""
        elided: list[tuple[str, str | bytes]] = []
        for name in REPEATABLE:
            value = getattr(message, name)
            if value and value == self.values[name]:
                setattr(message, name, _EMPTY[name])
                elided.append((name, value))
            else:
                self.values[name] = value
        region: geometry_pb2.Region | None = None
        if message.HasField("region"):
            if self.region is not None and message.region == self.region:
                region = self.region
                message.ClearField("region")
            else:
                self.region = geometry_pb2.Region()
                self.region.CopyFrom(message.region)

        def restore() -> None:
            for name, value in elided:
                setattr(message, name, value)
            if region is not None:
                message.region.CopyFrom(region)

        return restore

    def fill(self, message: Request) -> None:
        for name in REPEATABLE:
            value = getattr(message, name)
            if value:
                self.values[name] = value
            else:
                setattr(message, name, self.values[name])
        if message.HasField("region"):
            if message.region.ByteSize() > MAX_REGION_BYTES:
                self.region = None  # refused as too large: not kept for the requests that follow
            else:
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
        request_id = message.request_id
        try:
            reply = await answer(message)
        except Exception as exc:
            reply = _refused(request_id, exc, where)
        await asyncio.sleep(0)  # see serve_request_batches
        yield reply


#: Replies a request stream holds for a robot that is not reading: past this, answers wait (the
#: next request is not read) and snapshots of continuous fused requests are dropped.
MAX_REPLY_BACKLOG = 256


class ReplyQueue:
    """The replies a request stream is to write, in the order they are ready: each request's answer
    in the order of the requests, and between them replies that come later (a fused single shot's
    answer, a fused continuous request's snapshots), so a slow answer holds back no other.

    `owe()` promises a later reply; `put_later(reply, last=True)` or `settle()` keeps the promise.
    The stream ends once the requests have ended and no promise is open."""

    def __init__(self, max_backlog: int = MAX_REPLY_BACKLOG) -> None:
        self.max_backlog = max_backlog
        self._replies: deque[Reply] = deque()
        self._wake = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()
        self._owed = 0
        self._input_ended = False
        self.closed = False
        #: Later replies dropped because the robot was not reading.
        self.dropped = 0

    def owe(self) -> None:
        self._owed += 1

    def settle(self) -> None:
        """A promised reply will not come (its request was cancelled or ended)."""
        self._owed -= 1
        self._wake.set()

    def put_later(self, reply: Reply, *, last: bool) -> bool:
        """Queue a later reply; `last` keeps its promise. One that is not `last` is dropped (False)
        while the backlog is full; a last one always goes (there are as many as promises)."""
        if last:
            self.settle()
        if self.closed:
            return False
        if not last and len(self._replies) >= self.max_backlog:
            self.dropped += 1
            return False
        self._replies.append(reply)
        self._wake.set()
        return True

    async def put(self, reply: Reply) -> None:
        """Queue a request's answer, waiting while the backlog is full."""
        while len(self._replies) >= self.max_backlog and not self.closed:
            self._room.clear()
            await self._room.wait()
        self._replies.append(reply)
        self._wake.set()

    def input_ended(self) -> None:
        self._input_ended = True
        self._wake.set()

    async def drain(self) -> AsyncIterator[Reply]:
        while not self.closed:
            while self._replies and not self.closed:
                reply = self._replies.popleft()
                if len(self._replies) < self.max_backlog:
                    self._room.set()
                yield reply
            if self._input_ended and self._owed <= 0:
                return
            self._wake.clear()
            await self._wake.wait()

    def close(self) -> None:
        self.closed = True
        self._room.set()


async def serve_request_stream_queued(
    requests: AsyncIterator[Request],
    answer: Callable[[Request, ReplyQueue], Awaitable[Reply | None]],
    where: str,
    out: ReplyQueue | None = None,
) -> AsyncIterator[Reply]:
    """`serve_request_stream` with an output queue: `answer(message, out)` may return None after
    promising a later reply (`out.owe()`), which it then puts on `out` when it is ready. Requests
    are read and answered in order, a DrvsError becomes a reply's error and the stream goes on."""
    out = out or ReplyQueue()
    failure: list[BaseException] = []

    async def read() -> None:
        context = StreamContext()
        try:
            async for message in requests:
                context.fill(message)
                request_id = message.request_id
                try:
                    reply = await answer(message, out)
                except Exception as exc:
                    reply = _refused(request_id, exc, where)
                if reply is not None:
                    await out.put(reply)
        except Exception as exc:  # the call broke: it ends here too
            failure.append(exc)
            out.close()
            out._wake.set()
        finally:
            out.input_ended()

    reader = asyncio.get_running_loop().create_task(read())
    try:
        async for reply in out.drain():
            yield reply
        if failure:
            raise failure[0]
    finally:
        out.close()
        reader.cancel()
        await asyncio.gather(reader, return_exceptions=True)


async def serve_request_batches(
    batches: AsyncIterator[Requests], answer: Callable[[Request], Reply], where: str
) -> AsyncIterator[Replies]:
    """The receiving side of DetectBatches: one Replies per Requests, one reply per request in
    order; a DrvsError becomes that request's error and the others go on."""
    async for batch in batches:
        replies = Replies()
        for message in batch.requests:
            request_id = message.request_id
            try:
                reply = answer(message)
            except Exception as exc:
                reply = _refused(request_id, exc, where)
            replies.replies.append(reply)
        # One turn of the loop before the acknowledgement is written: the work the requests just
        # started (the server's forwards, a camera's detections and reports) starts its writes
        # first. Those are on the way to the robot's first report; the acknowledgement is not.
        await asyncio.sleep(0)
        yield replies


def _refused(request_id: str, exc: Exception, where: str) -> Reply:
    """The reply to the request `request_id` (as it came: an answer may rename the message it
    forwards, as the server does a fused request's for its cameras) whose answer raised: a
    DrvsError is the peer's to read; anything unexpected is logged here and answered as INTERNAL."""
    if isinstance(exc, errors.DrvsError):
        reply = refusal(request_id, _grpc.status_of(exc), str(exc))
        if isinstance(exc, errors.ResourceExhausted) and exc.retry_after_s > 0:
            reply.error.retry_after_s = exc.retry_after_s
        return reply
    log.error("%s: request %s failed", where, request_id, exc_info=exc)
    return refusal(request_id, grpc.StatusCode.INTERNAL, f"{where}: internal error")


def refusal(request_id: str, code: grpc.StatusCode, text: str) -> Reply:
    return Reply(request_id=request_id, error=detection_pb2.RequestError(code=code.name, message=text))
