"""drvs.ros2.cdr, the bridge's hand-made CDR, against rosbags: for every topic the bytes equal
rosbags' serialize_cdr of the messages drvs.ros2.convert builds from the same snapshot, over
snapshot after snapshot of varied objects (none, one, twenty, long, flat and degenerate outlines,
repeated corners, holes, unicode ids and types, stopping and ended tracks), and rosbags reads them
back to the same bytes."""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from typing import Any

import pytest
from shapely.geometry import Point, Polygon, box

from drvs.core.model import CameraError, Snapshot, WorldObject
from drvs.ros2.cdr import cdr_string, snapshot_payloads
from drvs.ros2.convert import MarkerState, Style, output_topics, snapshot_messages
from drvs.ros2.types import to_cdr, typestore


def world_object(
    track_id: int, outline: Polygon, rng: random.Random, *, label: str = "", moving: bool = True
) -> WorldObject:
    centre = outline.centroid if not outline.is_empty else Point(rng.uniform(-5, 5), rng.uniform(-5, 5))
    bounds = (
        outline.bounds if not outline.is_empty else (centre.x - 0.3, centre.y - 0.2, centre.x + 0.3, centre.y + 0.2)
    )
    return WorldObject(
        track_id=track_id,
        outline=outline,
        bounds=bounds,
        centroid_xy=(centre.x, centre.y),
        velocity_xy=(rng.uniform(-2, 2), rng.uniform(-2, 2)) if moving else (0.0, 0.0),
        uncertainty_m=rng.uniform(0.0, 0.3),
        camera_ids=("cam1",),
        label=label,
        score=rng.random(),
    )


def outlines(rng: random.Random) -> Iterator[Polygon]:
    """Outlines of every kind the encoder must get right, over and over."""
    while True:
        x, y = rng.uniform(-20, 20), rng.uniform(-20, 20)
        yield Point(x, y).buffer(rng.uniform(0.1, 0.6), quad_segs=rng.choice([1, 4, 16, 64]))  # up to 256 corners
        yield box(x, y, x + rng.uniform(0.01, 3), y + rng.uniform(0.01, 3))
        yield Polygon()  # outlines left out: the bounds stand in
        yield box(x, y, x + 2, y + 2).difference(box(x + 0.5, y + 0.5, x + 1.5, y + 1.5))  # a hole
        yield Polygon([(x, y), (x + 7.3, y + 0.1), (x + 0.2, y + 5.9)])  # long edges: many cloud points
        yield Polygon([(x, y), (x + 1, y), (x + 2, y)])  # flat: no area, its ring still drawn
        yield Polygon([(x, y), (x, y), (x + 0.3, y), (x + 0.3, y + 0.3)])  # a repeated corner


LABELS = ["", "person", "Fußgänger", "🤖 robot", "a" * 37]


def snapshots(rng: random.Random) -> Iterator[Snapshot]:
    """Snapshots of 0, 1, 20 and some objects; tracks come, stop, end and come back."""
    shapes = outlines(rng)
    for n, count in enumerate([0, 1, 20, 3, 20, 0, 1, 7, 20, 2]):
        ids = rng.sample(range(1, 40), count) if count != 20 else list(range(1, 21))
        objects = tuple(
            world_object(i, next(shapes), rng, label=rng.choice(LABELS), moving=rng.random() < 0.6) for i in ids
        )
        errors = {"cam9": CameraError("UNAVAILABLE", "camera cam9: gone", "cam9")} if n % 3 == 0 else {}
        uncovered = (box(0, 0, 1, 2),) if n % 4 == 1 else ()
        yield Snapshot(
            time=1_700_000_000.0 + n * 0.1 + rng.random() * 1e-3,
            objects=objects,
            camera_errors=errors,
            camera_ids=("cam1", "cam2"),
            request_id=rng.choice(["req", "ré-q✓"]),
            uncovered=uncovered,
        )


@pytest.mark.parametrize(
    ("style", "suffix", "seed"),
    [
        (Style(heights={"person": 1.8}), "", 1),
        (Style(frame_id="карта", heights={"🤖 robot": 0.4}, cloud_step_m=0.1, filter_def="people"), "/rq-1", 2),
        (Style(frame_id="", default_height_m=2.5, cloud_step_m=0.013), "", 3),
    ],
)
def test_every_topic_is_byte_for_byte_what_rosbags_serializes(style: Style, suffix: str, seed: int) -> None:
    rng = random.Random(seed)
    reference, encoded = MarkerState(suffix), MarkerState(suffix)
    store = typestore()
    kinds = output_topics("/drvs")
    seen: set[str] = set()
    for snapshot in snapshots(rng):
        at = snapshot.time + rng.choice([0.0, 1e-9, 0.4999999999])
        expected = [(t, to_cdr(m)) for t, m in snapshot_messages(snapshot, style, reference, at, "/drvs")]
        got = [(t, bytes(p)) for t, p in snapshot_payloads(snapshot, style, encoded, at, "/drvs")]
        assert [t for t, _ in got] == [t for t, _ in expected]
        for (topic, want), (_, payload) in zip(expected, got, strict=True):
            assert payload == want, f"{topic}, {len(snapshot.objects)} objects"
            assert bytes(store.serialize_cdr(store.deserialize_cdr(payload, kinds[topic]), kinds[topic])) == payload
            seen.add(topic)
        assert encoded.shown == reference.shown
    assert seen == set(kinds)


def test_markers_of_ended_tracks_are_deleted_in_the_same_bytes() -> None:
    rng = random.Random(7)
    style, reference, encoded = Style(), MarkerState(), MarkerState()
    shapes = outlines(rng)
    first = Snapshot(1.0, tuple(world_object(i, next(shapes), rng) for i in (1, 2, 3)), {}, ("cam1",), 0, False, "r")
    stopped = world_object(2, next(shapes), rng, moving=False)
    second = Snapshot(2.0, (stopped,), {}, ("cam1",), 1, False, "r")  # 1 and 3 ended, 2 stopped
    for snapshot in (first, second, second):
        (want,) = [
            to_cdr(m)
            for t, m in snapshot_messages(snapshot, style, reference, snapshot.time, "/d")
            if t == "/d/markers"
        ]
        (got,) = [
            bytes(p) for t, p in snapshot_payloads(snapshot, style, encoded, snapshot.time, "/d") if t == "/d/markers"
        ]
        assert got == want
    deleted: Any = typestore().deserialize_cdr(want, "visualization_msgs/msg/MarkerArray")
    assert [m.action for m in deleted.markers] == [0, 0]  # the third time nothing is left to delete


def test_strings_are_their_utf8_with_a_nul_after_their_length() -> None:
    assert cdr_string("") == b"\x01\x00\x00\x00\x00"
    assert cdr_string("ü") == b"\x03\x00\x00\x00\xc3\xbc\x00"
    assert math.isclose(len(cdr_string("🤖")), 4 + 4 + 1)


def test_only_the_topics_asked_for_are_made_and_the_markers_follow_all_the_same() -> None:
    rng = random.Random(5)
    style, reference, encoded = Style(), MarkerState(), MarkerState()
    for snapshot in snapshots(rng):
        want = {t: to_cdr(m) for t, m in snapshot_messages(snapshot, style, reference, snapshot.time, "/d")}
        asked = set(rng.sample(sorted(want), rng.randint(0, len(want))))
        got = dict(snapshot_payloads(snapshot, style, encoded, snapshot.time, "/d", topics=asked))
        assert set(got) == asked and all(bytes(p) == want[t] for t, p in got.items())
        assert encoded.shown == reference.shown
