"""The camera's prefetcher: a filter looked up on one frame is found on the next as soon as it
arrives, on the prefetcher's thread; a filter nobody looked up is never prefetched."""

from __future__ import annotations

import threading

import numpy as np

from drvs.camera.prefetch import Analyses
from drvs.detectors import Frame
from tests.helpers import BIG, GREEN, YELLOW, camera, detector, render


class _Frames:
    """A frame source fed by the test: the newest frame pushed is the latest."""

    description = "test frames"

    def __init__(self, image: np.ndarray) -> None:
        self._image = image
        self._latest: Frame | None = None
        self._lock = threading.Lock()

    def push(self, sequence: int) -> Frame:
        frame = Frame(self._image, float(sequence), sequence)
        with self._lock:
            self._latest = frame
        return frame

    def latest(self) -> Frame | None:
        with self._lock:
            return self._latest


def test_a_filter_looked_up_on_one_frame_is_found_on_the_next_before_anyone_asks() -> None:
    frames = _Frames(render(BIG))
    analyses = Analyses(frames, detector(camera()).blobs, "cam1")  # type: ignore[arg-type]
    analyses.start()
    try:
        first = analyses.for_frame(frames.push(1))
        assert first.cached_blobs(YELLOW) is None and analyses.prefetched == 0
        analyses.want(first, YELLOW)  # a request looked yellow up on frame 1
        second = frames.push(2)
        assert analyses.wait_prefetched(1, timeout_s=10)
        analysis = analyses.for_frame(second)
        assert analysis.cached_blobs(GREEN) is None  # nobody asked for green
        assert sorted(round(d.centroid.x, 1) for d in analysis.cached_blobs(YELLOW) or ()) == [-1.0, 1.5]
        assert analyses.prefetched == 1
        # Nobody looked anything up on frame 2: frame 3 is left alone. A request that comes first
        # on frame 4, looking up green on it, still has yellow found for it: frame 3 asked for it.
        analyses.want(analyses.for_frame(frames.push(3)), YELLOW)
        fourth = analyses.for_frame(frames.push(4))
        analyses.want(fourth, GREEN)
        assert analyses.wait_prefetched(2, timeout_s=10)
        assert fourth.cached_blobs(YELLOW) is not None
    finally:
        analyses.stop()
    assert analyses.prefetched == 2


def test_one_analysis_per_frame_whoever_asks_first() -> None:
    frames = _Frames(render(BIG))
    analyses = Analyses(frames, detector(camera()).blobs, "cam1")  # type: ignore[arg-type]
    frame = frames.push(5)
    assert analyses.for_frame(frame) is analyses.for_frame(frame)
    assert analyses.for_frame(frames.push(6)).frame.sequence == 6
    analyses.stop()  # never started: stopping is harmless
