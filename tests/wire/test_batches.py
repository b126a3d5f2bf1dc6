"""DetectBatches, the server-to-camera hop: requests waiting for a camera travel together, every
request is answered exactly once, in order, and requests nobody waits for any more are not sent."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any

import grpc
import pytest
from grpc import aio

from drvs.core import errors
from drvs.server import DrvsServer
from drvs.v1 import detection_pb2, detection_pb2_grpc, geometry_pb2
from drvs.wire import _grpc
from drvs.wire.request_stream import BatchSender, refusal
from tests.fakes import serve_camera

Result = detection_pb2.DetectionReply | errors.DrvsError


class _Camera(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """Answers every batch at once (refusing ids that start with "bad"). With `reading` cleared it
    stops reading the stream after its next answer until it is set again; with `answering`
    cleared it takes batches and never answers them."""

    def __init__(self) -> None:
        self.batches: list[list[str]] = []
        self.got_batch = asyncio.Event()
        self.reading = asyncio.Event()
        self.reading.set()
        self.answering = True
        self.calls = 0
        self.ended = asyncio.Event()  # a call ended (by the server, or by the camera's stop)

    async def DetectBatches(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequests],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReplies]:
        self.calls += 1

        def ended(_: aio.ServicerContext[Any, Any]) -> None:
            self.ended.set()

        context.add_done_callback(ended)  # type: ignore[arg-type]  # (the stubs want a grpc.aio private type)
        async for batch in request_iterator:
            self.batches.append([r.request_id for r in batch.requests])
            self.got_batch.set()
            if not self.answering:
                continue
            yield detection_pb2.DetectionReplies(
                replies=[
                    refusal(r.request_id, grpc.StatusCode.INVALID_ARGUMENT, "filter_def: bad")
                    if r.request_id.startswith("bad")
                    else detection_pb2.DetectionReply(request_id=r.request_id, camera_ids=["cam"])
                    for r in batch.requests
                ]
            )
            await self.reading.wait()


class _Results:
    def __init__(self) -> None:
        self.by_id: dict[str, list[Result]] = {}
        self.changed = asyncio.Event()

    def callback(self, request_id: str) -> Callable[[Result], None]:
        def done(result: Result) -> None:
            self.by_id.setdefault(request_id, []).append(result)
            self.changed.set()

        return done

    async def wait_for(self, count: int) -> None:
        while len(self.by_id) < count:
            self.changed.clear()
            await asyncio.wait_for(self.changed.wait(), 10)


@contextlib.asynccontextmanager
async def _sending_to_a_camera(**sender_options: Any) -> AsyncIterator[tuple[_Camera, BatchSender, _Results]]:
    """A _Camera on a free port, a BatchSender to it (timeout_s 10 unless `sender_options` say),
    and the results it gives; the camera's server stops on exit."""
    camera = _Camera()
    server, address = await serve_camera(camera, options=_grpc.SERVER_OPTIONS)
    try:
        async with _grpc.insecure_channel(address) as channel:
            stub = detection_pb2_grpc.DetectObjectBoundaryStub(channel)
            sender_options.setdefault("timeout_s", 10)
            yield camera, BatchSender(stub, "camera", **sender_options), _Results()
    finally:
        await server.stop(None)


def _request(request_id: str, vertices: int = 0) -> detection_pb2.DetectionRequest:
    message = detection_pb2.DetectionRequest(request_id=request_id, robot_id="r", filter_def="hsv_014110130035225200")
    if vertices:
        ring = geometry_pb2.Polygon(points=[geometry_pb2.Point2(x=float(i), y=float(i % 7)) for i in range(vertices)])
        message.region.CopyFrom(geometry_pb2.Region(polygon=ring))
    return message


async def test_requests_waiting_together_travel_in_one_message_and_are_answered_in_order() -> None:
    async with _sending_to_a_camera() as (camera, sender, results):
        ids = [f"a{i}" for i in range(6)] + ["bad1"] + [f"b{i}" for i in range(3)]
        for request_id in ids:  # no await in between: all are waiting when the writer first runs
            sender.submit(_request(request_id), results.callback(request_id))
        assert sender.in_flight == len(ids)
        await results.wait_for(len(ids))
        assert camera.batches == [ids]
        assert (sender.batches_written, sender.requests_written, sender.in_flight) == (1, len(ids), 0)
        for request_id in ids:
            [result] = results.by_id[request_id]
            if request_id == "bad1":
                assert isinstance(result, errors.InvalidArgument) and "filter_def" in str(result)
            else:
                assert isinstance(result, detection_pb2.DetectionReply) and result.request_id == request_id
        # A lone request afterwards goes on its own, on the same call.
        sender.submit(_request("c0"), results.callback("c0"))
        await results.wait_for(len(ids) + 1)
        assert camera.batches[-1] == ["c0"] and sender.batches_written == 2
        await sender.close()


async def test_a_camera_that_stops_reading_is_cut_off_and_queued_requests_that_expired_are_never_sent() -> None:
    async with _sending_to_a_camera(timeout_s=0.5, max_batch_bytes=64 * 1024) as (camera, sender, results):
        camera.reading.clear()  # takes the first batch, then stops reading: the stream backs up
        # About 20 kB each: far more than the HTTP/2 windows hold, so writes stop completing.
        ids = [f"big{i}" for i in range(200)]
        messages = [_request(request_id, vertices=1000) for request_id in ids]
        for request_id, message in zip(ids, messages, strict=True):
            sender.submit(message, results.callback(request_id))
        await results.wait_for(len(ids))
        first = camera.batches[0]
        assert all(isinstance(results.by_id[i][0], detection_pb2.DetectionReply) for i in first)
        expired = ids[len(first) :]
        assert all(isinstance(results.by_id[i][0], errors.DeadlineExceeded) for i in expired)
        assert sender.in_flight == 0
        written = sender.requests_written
        assert len(first) < written < len(ids), "some requests were still queued when they expired"
        # What was written and never answered cut the stream off: the camera's call is ended.
        await asyncio.wait_for(camera.ended.wait(), 10)
        camera.reading.set()
        # The next request opens a new stream and is answered as usual; the camera never read
        # the rest of the old one.
        sender.submit(_request("after"), results.callback("after"))
        await results.wait_for(len(ids) + 1)
        [after] = results.by_id["after"]
        assert isinstance(after, detection_pb2.DetectionReply) and after.request_id == "after"
        assert [request_id for batch in camera.batches for request_id in batch] == [*first, "after"]
        assert camera.calls == 2
        assert all(len(rs) == 1 for rs in results.by_id.values())  # nobody answered twice
        await sender.close()


async def test_a_camera_that_goes_away_fails_what_it_had_and_the_next_request_reconnects() -> None:
    camera = _Camera()
    server, address = await serve_camera(camera, options=_grpc.SERVER_OPTIONS)
    port = int(address.rsplit(":", 1)[1])
    async with _grpc.insecure_channel(address) as channel:
        sender = BatchSender(detection_pb2_grpc.DetectObjectBoundaryStub(channel), "camera", timeout_s=10)
        results = _Results()
        sender.submit(_request("first"), results.callback("first"))
        await results.wait_for(1)
        camera.answering = False  # the next batch is taken but not answered before the camera stops
        camera.got_batch.clear()
        sender.submit(_request("lost"), results.callback("lost"))
        await asyncio.wait_for(camera.got_batch.wait(), 10)
        await server.stop(None)
        await results.wait_for(2)
        [lost] = results.by_id["lost"]
        assert isinstance(lost, errors.Unavailable)
        # The camera comes back on the same port: the next request opens a new call.
        camera2 = _Camera()
        server2, address2 = await serve_camera(camera2, f"127.0.0.1:{port}")
        assert address2 == address
        try:
            await asyncio.wait_for(channel.channel_ready(), 20)
            sender.submit(_request("again"), results.callback("again"))
            await results.wait_for(3)
            [again] = results.by_id["again"]
            assert isinstance(again, detection_pb2.DetectionReply) and camera2.batches == [["again"]]
            await sender.close()
        finally:
            await server2.stop(None)


async def test_after_close_requests_fail_at_once() -> None:
    async with _sending_to_a_camera() as (_, sender, results):
        await sender.close()
        sender.submit(_request("x"), results.callback("x"))
        [result] = results.by_id["x"]
        assert isinstance(result, errors.Unavailable) and sender.in_flight == 0


async def test_the_server_does_not_serve_the_camera_hop() -> None:
    async with DrvsServer("127.0.0.1:0") as server, aio.insecure_channel(server.address) as channel:
        call = detection_pb2_grpc.DetectObjectBoundaryStub(channel).DetectBatches()
        with pytest.raises(aio.AioRpcError) as err:
            # The server may end the call before this write completes: then the write raises.
            await call.write(detection_pb2.DetectionRequests(requests=[_request("x")]))
            async for _ in call:
                pass
        assert err.value.code() == grpc.StatusCode.UNIMPLEMENTED and "DetectStream" in (err.value.details() or "")
