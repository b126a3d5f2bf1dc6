"""What a streamed request leaves out when it repeats the previous one, and how it comes back."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from drvs.request_stream import StreamContext
from drvs.v1 import detection_pb2, geometry_pb2

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
