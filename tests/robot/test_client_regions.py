"""The robot client keeps the regions it is asked about built and encoded, and detections build
their shapely points only when asked."""

from __future__ import annotations

import pytest
from shapely.geometry import Point, box

from drvs.core.errors import InvalidArgument
from drvs.core.model import Detection, PixelBox
from drvs.robot.regions import _Regions
from drvs.wire.convert import region_from_pb, region_to_pb


def test_same_region_values_are_built_and_encoded_once() -> None:
    regions = _Regions()
    first = regions.get((0, 0, 2, 1))
    assert regions.get((0.0, 0.0, 2.0, 1.0))[0] is first[0]  # equal values: the same polygon
    assert regions.get([0, 0, 2, 1])[1] is first[1]
    assert first[1] == region_to_pb(box(0, 0, 2, 1))
    points = [[0, 0], [2, 0], [1, 1]]
    poly, encoded = regions.get(points)
    assert regions.get([(0, 0), (2, 0), (1, 1)])[0] is poly
    assert region_from_pb(encoded).equals(poly)
    assert regions.get((0, 0, 3, 1))[0].bounds == (0, 0, 3, 1)


def test_polygons_are_kept_by_identity() -> None:
    regions = _Regions()
    a, b = box(0, 0, 1, 1), box(0, 0, 2, 2)
    assert regions.get(a)[0].equals(a)
    assert regions.get(b)[0].equals(b)  # a different object, never confused with a
    assert regions.get(a)[0].equals(a)


def test_bad_regions_raise_every_time_and_are_not_kept() -> None:
    regions = _Regions()
    for _ in range(2):
        with pytest.raises(InvalidArgument, match="region"):
            regions.get((0, 0, 0, 1))  # zero area
    assert len(regions._cache) == 0


def test_the_cache_is_bounded() -> None:
    regions = _Regions(size=4)
    for i in range(10):
        regions.get((0, 0, 1 + i, 1))
    assert len(regions._cache) == 4
    assert list(regions._cache)[-1] == (0, 0, 10, 1)


def test_detection_points_are_built_when_asked_for() -> None:
    d = Detection(
        outline=box(0, 0, 1, 1),
        bounds=(0, 0, 1, 1),
        centroid_xy=(0.5, 0.5),
        ground_contact_xy=(0.5, 0.0),
        pixel_box=PixelBox(1, 2, 3, 4),
        area_m2=1.0,
        area_px=12.0,
        score=1.0,
        filter_def="hsv_014110130035225200",
    )
    assert "centroid" not in vars(d)
    assert d.centroid.equals(Point(0.5, 0.5)) and d.ground_contact.equals(Point(0.5, 0.0))
    assert d.centroid is d.centroid  # built once
