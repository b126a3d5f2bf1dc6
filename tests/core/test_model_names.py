"""The robot API's names mean one thing on every result: a world object's direction of motion is
`course_deg` (a Detection's `heading_deg` is a marker's heading), and `camera_errors` is camera id ->
CameraError on a Snapshot as on a DetectionResult and a Track. The old spellings work for one release,
each with a DeprecationWarning and the same value."""

from __future__ import annotations

import dataclasses
import warnings

import pytest
from shapely.geometry import box

from drvs.core.model import CameraError, Snapshot, WorldObject
from drvs.robot.results import DetectionResult
from drvs.wire.convert import snapshot_from_pb, snapshot_to_pb

LATE = CameraError("DEADLINE_EXCEEDED", "camera c2: no final report in time", "c2")
GONE = CameraError("UNAVAILABLE", "camera c3: gone", "c3")


def moving(course: float | None = 30.0) -> WorldObject:
    return WorldObject(
        1, box(0, 0, 1, 1), (0.0, 0.0, 1.0, 1.0), (0.5, 0.5), (0.87, 0.5), course, marker_heading_deg=-90.0
    )


def test_a_world_objects_direction_of_motion_is_course_deg_and_heading_deg_is_its_deprecated_alias() -> None:
    obj = moving(30.0)
    assert obj.course_deg == 30.0 and obj.marker_heading_deg == -90.0
    with pytest.warns(DeprecationWarning, match=r"WorldObject\.heading_deg is deprecated: use WorldObject\.course_deg"):
        assert obj.heading_deg == 30.0
    with pytest.warns(DeprecationWarning):
        assert moving(None).heading_deg is None


def test_the_old_keyword_still_builds_and_replaces_the_course() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the keyword is accepted quietly: the server's own code passes it
        built = WorldObject(7, box(0, 0, 1, 1), (0.0, 0.0, 1.0, 1.0), (0.5, 0.5), heading_deg=45.0)
        assert built.course_deg == 45.0
        assert dataclasses.replace(built, heading_deg=None).course_deg is None
        assert dataclasses.replace(built, heading_deg=10.0).course_deg == 10.0
        assert dataclasses.replace(built, course_deg=20.0).course_deg == 20.0
    assert built == WorldObject(7, box(0, 0, 1, 1), (0.0, 0.0, 1.0, 1.0), (0.5, 0.5), course_deg=45.0)
    assert "course_deg=45.0" in repr(built) and " heading_deg" not in repr(built)
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(built, "course_deg", 1.0)  # noqa: B010 (frozen: refused)
    assert [f.name for f in dataclasses.fields(WorldObject)][5] == "course_deg"


def test_the_course_crosses_the_wire_in_its_field() -> None:
    snapshot = Snapshot(12.5, (moving(30.0),), {"c2": LATE})
    msg = snapshot_to_pb(snapshot)
    assert msg.objects[0].heading_deg == 30.0 and msg.objects[0].marker_heading_deg == -90.0
    back = snapshot_from_pb(msg)
    assert back.objects[0].course_deg == 30.0 and back.camera_errors == {"c2": LATE}


def test_a_snapshots_camera_errors_are_by_camera_and_missing_cameras_is_their_deprecated_tuple() -> None:
    snapshot = Snapshot(1.0, (), {"c2": LATE, "c3": GONE})
    assert snapshot.camera_errors == {"c2": LATE, "c3": GONE} and not snapshot.all_seen
    with pytest.warns(
        DeprecationWarning, match=r"Snapshot\.missing_cameras is deprecated: use Snapshot\.camera_errors"
    ):
        assert snapshot.missing_cameras == (LATE, GONE)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # unpacking is not deprecated
        time, objects, errors = snapshot
    assert (time, objects, errors) == (1.0, (), (LATE, GONE))
    assert Snapshot(2.0).all_seen and Snapshot(2.0).camera_errors == {}


def test_the_old_snapshot_keyword_still_builds_and_replaces_the_errors() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # accepted quietly for one release, as heading_deg= is
        built = Snapshot(1.0, missing_cameras=(LATE, GONE), request_id="r1")
        assert built.camera_errors == {"c2": LATE, "c3": GONE} and built.request_id == "r1"
        assert built == Snapshot(1.0, camera_errors={"c2": LATE, "c3": GONE}, request_id="r1")
        assert dataclasses.replace(built, missing_cameras=()).camera_errors == {}
        assert dataclasses.replace(built, sequence=3).camera_errors == built.camera_errors
    assert [f.name for f in dataclasses.fields(Snapshot)][:3] == ["time", "objects", "camera_errors"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(built, "time", 2.0)  # noqa: B010 (frozen: refused)


def test_camera_errors_is_the_same_thing_on_a_detection_result() -> None:
    result = DetectionResult("r1", ("c1", "c2"), skipped={"c3": GONE})
    assert set(result.camera_errors) == {"c1", "c2", "c3"} and result.camera_errors["c3"] == GONE
    assert result.missing_cameras == set(result.camera_errors)


def test_a_world_object_holds_each_argument_in_its_field() -> None:
    # Its __init__ writes each field by name: a field added to the class and not to it fails here.
    values = (
        7, box(0, 0, 1, 1), (0.0, 0.0, 1.0, 1.0), (0.5, 0.5), (0.25, -0.5), 30.0, 0.03, ("cam1",), 12.5, 4, -90.0,
        "marker", 0.9, 1.0,
    )  # fmt: skip
    obj = WorldObject(*values)
    assert dataclasses.astuple(obj) == values
    assert dataclasses.replace(obj) == obj and hash(dataclasses.replace(obj)) == hash(obj)
    with pytest.raises(dataclasses.FrozenInstanceError):
        obj.track_id = 8


def test_a_snapshot_holds_each_argument_in_its_field() -> None:
    errors = {"c2": LATE}
    values = (12.5, (moving(),), errors, ("c1",), 3, False, "track-1", (box(0, 0, 1, 1),))
    snapshot = Snapshot(*values)
    assert tuple(getattr(snapshot, f.name) for f in dataclasses.fields(Snapshot)) == values
    assert dataclasses.replace(snapshot) == snapshot
