"""Colour-blob detection on rendered pixels, mapped back onto the floor and compared with the truth."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from shapely.geometry import Point

from drvs.core.geometry import box_region
from drvs.core.model import Detection
from drvs.detectors import DEFAULT_MIN_AREA_PX, FrameAnalysis
from drvs.detectors import Frame as DetFrame
from drvs.sim.scene import write_video
from tests.helpers import BIG, BLUE, GREEN, IMAGE_SIZE, RED, YELLOW, Disc, camera, detector, render

SIZE = IMAGE_SIZE
CAPTURE_TIME = 1_700_000_123.25

#: About 75 pixels in the image: above the default minimum blob size.
SMALL = Disc(YELLOW, (2.0, 7.0), 0.10)
#: About 10 pixels in the image: below the default minimum blob size.
TINY = Disc(YELLOW, (0.0, 9.0), 0.05)


def analysis_of(image: NDArray[np.uint8]) -> FrameAnalysis:
    return FrameAnalysis(DetFrame(image, CAPTURE_TIME, 7))


def matches(detections: list[Detection], discs: list[Disc]) -> dict[Disc, Detection]:
    """Pair each true disc with the detection whose centroid is nearest; one detection per disc."""
    assert len(detections) == len(discs), [d.centroid for d in detections]
    paired = {}
    for disc in discs:
        paired[disc] = min(detections, key=lambda d: d.centroid.distance(Point(disc.center)))
    assert len({id(d) for d in paired.values()}) == len(discs)
    return paired


def assert_located(det: Detection, disc: Disc, tolerance_m: float = 0.02) -> None:
    error = math.dist((det.centroid.x, det.centroid.y), disc.center)
    assert error < tolerance_m, f"{disc}: centroid off by {error:.4f} m"
    assert abs(det.area_m2 - disc.area) < 0.10 * disc.area, f"{disc}: area {det.area_m2} vs {disc.area}"


def test_discs_are_found_where_they_lie() -> None:
    scene = [*BIG, SMALL]
    det = detector(camera())
    analysis = analysis_of(render(scene))
    for filter_def in (YELLOW, GREEN, RED):
        truth = [d for d in scene if d.filter_def == filter_def]
        found = det.detect(analysis, filter_def)
        for disc, d in matches(found, truth).items():
            assert_located(d, disc)
            assert d.filter_def == filter_def
            assert d.camera_id == "cam1"
            assert d.capture_time == CAPTURE_TIME
            assert 0.0 <= d.score <= 1.0
            assert d.outline.is_valid
            assert d.centroid.equals(d.outline.centroid)
            # Axis-aligned floor bounds of a disc: its centre plus or minus the radius.
            cx, cy = disc.center
            r = disc.radius
            expected_bounds = (cx - r, cy - r, cx + r, cy + r)
            assert max(abs(a - b) for a, b in zip(d.bounds, expected_bounds, strict=True)) < 0.03
            # The pixel box is where the disc projects.
            px = camera().inverse().apply(np.asarray(disc.patch().shape.exterior.coords))
            u0, v0 = px.min(axis=0)
            u1, v1 = px.max(axis=0)
            assert abs(d.pixel_box.x - u0) <= 1.5
            assert abs(d.pixel_box.y - v0) <= 1.5
            assert abs(d.pixel_box.x + d.pixel_box.width - u1) <= 1.5
            assert abs(d.pixel_box.y + d.pixel_box.height - v1) <= 1.5
            # The ground contact is the floor point under the bottom centre of that pixel box: on the
            # disc's nearest row (rows are lines y = const for this camera), and to the side of the
            # disc's nearest point by the perspective skew of an off-axis disc's pixel box.
            contact = camera().apply([[(u0 + u1) / 2.0, v1]])[0]
            assert math.dist((d.ground_contact.x, d.ground_contact.y), contact) < 0.02
            assert abs(d.ground_contact.y - (cy - r)) < 0.02
        # Largest blobs (in pixels) first.
        assert [d.area_px for d in found] == sorted((d.area_px for d in found), reverse=True)


def test_detection_survives_sensor_noise() -> None:
    det = detector(camera())
    analysis = analysis_of(render(BIG, noise_sigma=3.0))
    for filter_def in (YELLOW, GREEN, RED):
        truth = [d for d in BIG if d.filter_def == filter_def]
        for disc, d in matches(det.detect(analysis, filter_def), truth).items():
            assert_located(d, disc)
            assert 0.0 <= d.score <= 1.0


def test_region_filters_detections() -> None:
    det = detector(camera())
    analysis = analysis_of(render(BIG))
    # Left half of the floor in front: the yellow disc at x = -1 only, not the one at x = 1.5.
    left = box_region(-3.0, 2.0, 0.0, 6.0)
    found = det.detect(analysis, YELLOW, left)
    assert len(found) == 1
    assert_located(found[0], BIG[0])
    # A region touching the disc only partly still reports it (its outline meets the region).
    edge = box_region(1.6, 2.0, 3.0, 4.0)
    assert [round(d.centroid.x, 1) for d in det.detect(analysis, YELLOW, edge)] == [1.5]
    # A region away from every disc: nothing.
    assert det.detect(analysis, YELLOW, box_region(3.0, 8.0, 4.0, 9.0)) == []
    # Without a region, both.
    assert len(det.detect(analysis, YELLOW)) == 2


def test_each_filter_finds_only_its_own_colour() -> None:
    det = detector(camera())
    analysis = analysis_of(render(BIG))
    green = det.detect(analysis, GREEN)
    assert len(green) == 1
    assert_located(green[0], BIG[2])
    red = det.detect(analysis, RED)
    assert len(red) == 1
    assert_located(red[0], BIG[3])
    assert det.detect(analysis, BLUE) == []


def test_blobs_below_min_area_are_dropped() -> None:
    analysis = analysis_of(render([*BIG, SMALL, TINY]))
    # SMALL (~75 px) is kept and TINY (~10 px) is dropped at the default 30 px.
    default = detector(camera()).detect(analysis, YELLOW)
    truth = [BIG[0], BIG[1], SMALL]
    for disc, d in matches(default, truth).items():
        assert_located(d, disc, tolerance_m=0.02)
    assert all(d.area_px >= DEFAULT_MIN_AREA_PX for d in default)
    # A stricter minimum drops SMALL too; the big discs (well over 1000 px) remain.
    strict = detector(camera(), min_area_px=200.0).detect(FrameAnalysis(analysis.frame), YELLOW)
    matches(strict, [BIG[0], BIG[1]])
    # A minimum of 1 pixel keeps TINY as well.
    loose = detector(camera(), min_area_px=1.0).detect(FrameAnalysis(analysis.frame), YELLOW)
    matches(loose, [BIG[0], BIG[1], SMALL, TINY])


def test_objects_outside_the_field_of_view_are_not_reported() -> None:
    # Clipped to 4 m from the nearest floor point (y = 1.5): the field of view ends at y = 5.5.
    far = Disc(YELLOW, (0.0, 8.0), 0.3)
    behind = Disc(YELLOW, (0.0, -3.0), 0.3)
    image = render([*BIG, far, behind])
    # The far disc is in the picture ...
    assert len(detector(camera()).detect(analysis_of(image), YELLOW)) == 3
    # ... but beyond the clipped field of view, so that camera does not report it.
    found = detector(camera(), max_range_m=4.0).detect(analysis_of(image), YELLOW)
    for disc, d in matches(found, [BIG[0], BIG[1]]).items():
        assert_located(d, disc)
    # Red at (-2, 7) is also beyond 5.5 m.
    assert detector(camera(), max_range_m=4.0).detect(analysis_of(image), RED) == []


def test_results_are_cached_per_filter_in_the_frame_analysis() -> None:
    det = detector(camera())
    analysis = analysis_of(render(BIG))
    first = det.blobs(analysis, YELLOW)
    second = det.blobs(analysis, YELLOW)
    assert isinstance(first, tuple)
    assert first is second
    assert det.blobs(analysis, GREEN) is det.blobs(analysis, GREEN)
    assert det.blobs(analysis, GREEN) is not first
    # detect() hands out the same Detection objects from the cache.
    listed = det.detect(analysis, YELLOW)
    assert all(a is b for a, b in zip(listed, first, strict=True))
    # The HSV conversion is done once per frame.
    assert analysis.hsv() is analysis.hsv()
    # A new frame is a new analysis.
    assert det.blobs(analysis_of(analysis.frame.image), YELLOW) is not first


def test_cached_blobs_are_there_only_once_found_and_select_like_detect() -> None:
    det = detector(camera())
    analysis = analysis_of(render(BIG))
    assert analysis.cached_blobs(YELLOW) is None
    everything = det.detect(analysis, YELLOW)
    cached = analysis.cached_blobs(YELLOW)
    assert cached is not None and list(cached) == everything and analysis.cached_blobs(GREEN) is None
    for region in (box_region(-10, 0, 0, 20), box_region(0, 0, 10, 20), None):
        assert det.select(cached, region) == det.detect(analysis, YELLOW, region)


def test_frame_of_the_wrong_size_is_refused() -> None:
    det = detector(camera())
    small = np.zeros((240, 320, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"frame size \(320, 240\) differs"):
        det.detect(analysis_of(small), YELLOW)


def test_detection_through_a_video_file(tmp_path: Path) -> None:
    image = render(BIG, noise_sigma=2.0)
    path = write_video(tmp_path / "floor.avi", [image, image])
    capture = cv2.VideoCapture(str(path))
    try:
        ok, frame = capture.read()
    finally:
        capture.release()
    assert ok
    decoded = np.asarray(frame, dtype=np.uint8)
    assert decoded.shape == (480, 640, 3)
    # MJPG is lossy: the pixels changed, but not by much.
    assert not np.array_equal(decoded, image)
    assert float(np.mean(np.abs(decoded.astype(np.int16) - image.astype(np.int16)))) < 5.0
    det = detector(camera())
    analysis = analysis_of(decoded)
    for filter_def in (YELLOW, GREEN, RED):
        truth = [d for d in BIG if d.filter_def == filter_def]
        for disc, d in matches(det.detect(analysis, filter_def), truth).items():
            assert_located(d, disc, tolerance_m=0.03)
            assert 0.0 <= d.score <= 1.0
