"""What a streamed request leaves out when it repeats the previous one, and how it comes back."""

from __future__ import annotations

import asyncio
import functools
from collections.abc import AsyncIterator

from hypothesis import given
from hypothesis import strategies as st

from drvs.core.errors import InvalidArgument
from drvs.v1 import detection_pb2, geometry_pb2
from drvs.wire.request_stream import ReplyQueue, StreamContext, serve_request_stream_queued

FILTERS = ["hsv_014110130035225200", "hsv_040080080080255255"]
Box = tuple[float, float, float, float]


def message(
    i: int, robot: str, callback: str, filter_def: str, box: tuple[float, float, float, float]
) -> detection_pb2.DetectionRequest:
    x0, y0, x1, y1 = box
    return detection_pb2.DetectionRequest(
        request_id=f"r{i}",
        robot_id=robot,
        filter_def=filter_def,
        callback_address=callback,
        region=geometry_pb2.Region(box=geometry_pb2.Box(x_lower=x0, y_lower=y0, x_upper=x1, y_upper=y1)),
    )


requests = st.lists(
    st.tuples(
        st.sampled_from(["turtle", "rover"]),
        st.sampled_from(["10.0.0.5:7000", "10.0.0.5:7001"]),
        st.sampled_from(FILTERS),
        st.sampled_from([(0.0, 0.0, 1.0, 1.0), (-6.0, 0.0, 26.0, 10.0)]),
    ),
    min_size=1,
    max_size=30,
)


@given(requests)
def test_elided_requests_come_back_whole(
    sequence: list[tuple[str, str, str, tuple[float, float, float, float]]],
) -> None:
    sender, receiver = StreamContext(), StreamContext()
    for i, fields in enumerate(sequence):
        original = message(i, *fields)
        wire = detection_pb2.DetectionRequest()
        wire.CopyFrom(original)
        sender.elide(wire)
        received = detection_pb2.DetectionRequest.FromString(wire.SerializeToString())
        receiver.fill(received)
        assert received == original


@given(requests)
def test_an_elided_request_restored_goes_whole_on_a_new_stream(
    sequence: list[tuple[str, str, str, tuple[float, float, float, float]]],
) -> None:
    """A request whose stream ended is sent again on a new one, whose receiver has seen nothing:
    restored, it carries every field again (a retry once sent a region-less request)."""
    sender = StreamContext()
    for i, fields in enumerate(sequence):
        original = message(i, *fields)
        wire = detection_pb2.DetectionRequest()
        wire.CopyFrom(original)
        restore = sender.elide(wire)
        restore()
        assert wire == original
        fresh = StreamContext()
        received = detection_pb2.DetectionRequest.FromString(wire.SerializeToString())
        fresh.fill(received)
        assert received == original


def test_a_repeated_request_is_little_more_than_its_id() -> None:
    sender = StreamContext()
    first = message(1, "turtle", "10.0.0.5:7000", FILTERS[0], (-6.0, 0.0, 26.0, 10.0))
    sender.elide(first)
    again = message(2, "turtle", "10.0.0.5:7000", FILTERS[0], (-6.0, 0.0, 26.0, 10.0))
    sender.elide(again)
    assert again.ByteSize() == len("r2") + 2 < first.ByteSize() / 10


async def _requests(*messages: detection_pb2.DetectionRequest) -> AsyncIterator[detection_pb2.DetectionRequest]:
    for message in messages:
        yield message


async def test_the_queued_stream_sends_later_replies_between_the_answers_in_order() -> None:
    """serve_request_stream_queued: an answer that promises a later reply holds back none after it;
    a refused request is answered with its error and the stream goes on; the stream ends once the
    requests have and every promise is kept."""
    out = ReplyQueue()
    held: list[str] = []

    async def answer(message: detection_pb2.DetectionRequest, queue: ReplyQueue) -> detection_pb2.DetectionReply | None:
        if message.request_id == "bad":
            raise InvalidArgument("filter_def: bad")
        if message.request_id.startswith("later"):
            queue.owe()
            held.append(message.request_id)
            return None
        if message.request_id == "b":  # the promises are kept once b is answered
            for request_id in held:
                asyncio.get_running_loop().call_soon(
                    functools.partial(out.put_later, detection_pb2.DetectionReply(request_id=request_id), last=True)
                )
        return detection_pb2.DetectionReply(request_id=message.request_id)

    messages = [detection_pb2.DetectionRequest(request_id=i) for i in ("later-1", "a", "bad", "later-2", "b")]
    replies = [r async for r in serve_request_stream_queued(_requests(*messages), answer, "here", out)]
    assert [r.request_id for r in replies] == ["a", "bad", "b", "later-1", "later-2"]
    assert replies[1].error.code == "INVALID_ARGUMENT" and replies[1].error.message == "filter_def: bad"


async def test_a_reply_queue_drops_snapshots_for_a_robot_that_does_not_read_but_never_a_last_one() -> None:
    out = ReplyQueue(max_backlog=2)
    out.owe()
    sent = [out.put_later(detection_pb2.DetectionReply(request_id=str(i)), last=False) for i in range(4)]
    assert sent == [True, True, False, False] and out.dropped == 2
    assert out.put_later(detection_pb2.DetectionReply(request_id="last"), last=True)
    out.input_ended()
    assert [r.request_id async for r in out.drain()] == ["0", "1", "last"]
