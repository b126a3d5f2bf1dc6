"""The paper's colour model: parsing filter_def strings, and masks on real HSV pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from drvs.core.errors import InvalidArgument
from drvs.core.filters import HsvRange, detector_kind, validate_filter_def

YELLOW = "hsv_014110130035225200"
RED = "hsv_170100100010255255"


def hsv_row(*pixels: tuple[int, int, int]) -> NDArray[np.uint8]:
    """A 1-row HSV image (OpenCV ranges) holding the given pixels."""
    return np.array([list(pixels)], dtype=np.uint8)


def test_parse_paper_yellow_gives_exact_bounds() -> None:
    r = HsvRange.parse(YELLOW)
    assert (r.h_lo, r.s_lo, r.v_lo, r.h_hi, r.s_hi, r.v_hi) == (14, 110, 130, 35, 225, 200)
    assert r == HsvRange(14, 110, 130, 35, 225, 200)
    assert not r.wraps


@pytest.mark.parametrize(
    "filter_def",
    [YELLOW, RED, "hsv_000000000179255255", "hsv_000000000000000000", "hsv_040080080080255255"],
)
def test_parse_round_trips_through_to_filter_def(filter_def: str) -> None:
    r = HsvRange.parse(filter_def)
    assert r.to_filter_def() == filter_def
    assert HsvRange.parse(r.to_filter_def()) == r


def test_red_wraps_through_zero() -> None:
    r = HsvRange.parse(RED)
    assert (r.h_lo, r.s_lo, r.v_lo, r.h_hi, r.s_hi, r.v_hi) == (170, 100, 100, 10, 255, 255)
    assert r.wraps


def test_wrapping_mask_includes_both_ends_of_the_hue_circle() -> None:
    r = HsvRange.parse(RED)
    hsv = hsv_row((175, 200, 200), (5, 200, 200), (90, 200, 200))
    mask = r.mask(hsv)
    assert mask.shape == (1, 3)
    assert mask.dtype == np.uint8
    assert mask.tolist() == [[255, 255, 0]]


def test_wrapping_mask_boundaries_are_inclusive() -> None:
    r = HsvRange.parse(RED)
    hues = [169, 170, 179, 0, 10, 11]
    mask = r.mask(hsv_row(*[(h, 200, 200) for h in hues]))
    assert mask.tolist() == [[0, 255, 255, 255, 255, 0]]


def test_wrapping_mask_still_applies_saturation_and_value() -> None:
    r = HsvRange.parse(RED)
    # Hue in range on both sides of 0, but S or V below their lower bounds.
    mask = r.mask(hsv_row((175, 99, 200), (5, 200, 99), (175, 100, 100), (5, 255, 255)))
    assert mask.tolist() == [[0, 0, 255, 255]]


def test_non_wrapping_mask_is_the_closed_box() -> None:
    r = HsvRange.parse(YELLOW)
    pixels = [
        (13, 150, 150),  # hue just below
        (14, 110, 130),  # lower corner
        (35, 225, 200),  # upper corner
        (36, 150, 150),  # hue just above
        (20, 109, 150),  # S just below
        (20, 226, 150),  # S just above
        (20, 150, 129),  # V just below
        (20, 150, 201),  # V just above
        (175, 150, 150),  # red: not yellow
    ]
    assert r.mask(hsv_row(*pixels)).tolist() == [[0, 255, 255, 0, 0, 0, 0, 0, 0]]


@pytest.mark.parametrize("filter_def", [YELLOW, RED, "hsv_040080080080255255"])
def test_centre_colour_passes_its_own_filter(filter_def: str) -> None:
    r = HsvRange.parse(filter_def)
    bgr = np.array([[r.centre_bgr()]], dtype=np.uint8)
    hsv = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV), dtype=np.uint8)
    assert r.mask(hsv).tolist() == [[255]]


def test_centre_hsv_of_wrapping_range_is_on_the_wrap() -> None:
    # Hues 170..179 and 0..10: 20 hues, the middle one is 0.
    assert HsvRange.parse(RED).centre_hsv() == (0, 177, 177)
    assert HsvRange.parse(YELLOW).centre_hsv() == (24, 167, 165)


@pytest.mark.parametrize(
    ("filter_def", "message"),
    [
        ("rgb_014110130035225200", r"filter_def: .*does not start with 'hsv_'"),
        ("HSV_014110130035225200", r"filter_def: .*does not start with 'hsv_'"),
        ("hsv014110130035225200", r"filter_def: .*does not start with 'hsv_'"),
        ("hsv_01411013003522520", r"filter_def: .*18 digits"),
        ("hsv_0141101300352252000", r"filter_def: .*18 digits"),
        ("hsv_", r"filter_def: .*18 digits"),
        ("hsv_01411013003522520x", r"filter_def: .*18 digits"),
        ("hsv_014 110130035225200", r"filter_def: .*18 digits"),
        ("hsv_-14110130035225200", r"filter_def: .*18 digits"),
        ("hsv_014110130035225200\n", r"filter_def: .*18 digits"),
        ("hsv_180110130035225200", r"filter_def: H low = 180 is out of range 0-179"),
        ("hsv_014110130180225200", r"filter_def: H high = 180 is out of range 0-179"),
        ("hsv_014256130035225200", r"filter_def: S low = 256 is out of range 0-255"),
        ("hsv_014110130035999200", r"filter_def: S high = 999 is out of range 0-255"),
        ("hsv_014110256035225255", r"filter_def: V low = 256 is out of range 0-255"),
        ("hsv_014110130035225256", r"filter_def: V high = 256 is out of range 0-255"),
        ("hsv_014230130035225200", r"filter_def: S low 230 > S high 225"),
        ("hsv_014110210035225200", r"filter_def: V low 210 > V high 200"),
        ("", r"filter_def: "),
    ],
)
def test_parse_rejects_malformed_filter_def(filter_def: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        HsvRange.parse(filter_def)


@pytest.mark.parametrize(
    "filter_def",
    [
        "hsv_" + "\u0660" * 18,  # ARABIC-INDIC DIGIT ZERO: a Unicode digit, not an ASCII one
        "hsv_\uff10\uff11\uff14110130035225200",  # FULLWIDTH DIGITs 0 1 4
    ],
)
def test_parse_rejects_non_ascii_digits(filter_def: str) -> None:
    # The contract is six zero-padded 3-digit numbers; a filter_def that is not its own canonical
    # form (to_filter_def) would be a different cache key for the same filter.
    with pytest.raises(InvalidArgument, match=r"filter_def: .*18 digits"):
        HsvRange.parse(filter_def)


def test_validate_filter_def_checks_the_whole_string() -> None:
    assert validate_filter_def(YELLOW) == "hsv"
    with pytest.raises(InvalidArgument, match=r"filter_def: H low = 180"):
        validate_filter_def("hsv_180110130035225200")
    with pytest.raises(InvalidArgument, match=r"filter_def: empty"):
        validate_filter_def("")


def test_detector_kind() -> None:
    assert detector_kind(YELLOW) == "hsv"
    # The kind comes from the detector's own parser, which checks the whole string.
    with pytest.raises(InvalidArgument, match=r"'hsv_x' is not 'hsv_' followed by 18 digits"):
        detector_kind("hsv_x")
    with pytest.raises(InvalidArgument, match=r"filter_def: empty"):
        detector_kind("")
    with pytest.raises(InvalidArgument, match=r"filter_def: unknown object type 'rgb' .*known types: .*hsv"):
        detector_kind("rgb_014110130035225200")
    with pytest.raises(InvalidArgument, match=r"filter_def: 'hsv' does not start with 'hsv_'"):
        detector_kind("hsv")
    with pytest.raises(InvalidArgument, match=r"filter_def: unknown object type 'HSV'"):
        detector_kind("HSV_014110130035225200")
