"""The newest frame's analysis, shared by requests and a prefetching thread.

A request costs a detection (colour conversion, threshold, contours, mapping: about a
millisecond) plus a hop to a worker thread and back, unless some earlier request already found
the frame's blobs for its filter. The prefetcher takes the detection off the request path: as
soon as a new frame arrives it finds, on its own thread, the blobs of every filter some request
looked up on the previous frame. A request that follows selects the blobs in its region on the
event loop, in microseconds.

A filter that nobody looked up on the previous frame is not prefetched, so for a filter asked
about rarely prefetching costs at most one extra detection per frame asked about, and for a
filter asked about on every frame (a robot following objects, many robots) it costs nothing extra.
"""

from __future__ import annotations

import logging
import threading

from drvs.detection import Frame, FrameAnalysis, HsvDetector

from .source import FrameSource

log = logging.getLogger(__name__)

#: How often the thread looks for a new frame while some filter is wanted.
POLL_S = 0.002


class Analyses:
    def __init__(self, source: FrameSource, detector: HsvDetector, name: str = "") -> None:
        self._source = source
        self._detector = detector
        self._lock = threading.Lock()
        self._current: FrameAnalysis | None = None
        self._wanted = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"prefetch:{name}", daemon=True)
        self._done = threading.Condition()
        #: Frames whose blobs were found as they arrived, for the curious (tests, benchmarks).
        self.prefetched = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wanted.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)

    def for_frame(self, frame: Frame) -> FrameAnalysis:
        """The one analysis of `frame`, made by whoever asks first (a request or the prefetcher)."""
        with self._lock:
            current = self._current
            if current is None or current.frame.sequence != frame.sequence:
                inherited = frozenset(current.wanted) if current is not None else frozenset()
                current = FrameAnalysis(frame, inherited=inherited)
                self._current = current
            return current

    def want(self, analysis: FrameAnalysis, filter_def: str) -> None:
        """A request looked `filter_def` up on `analysis`: the next frame's blobs are found early."""
        if filter_def not in analysis.wanted:
            analysis.wanted.add(filter_def)
            self._wanted.set()

    def wait_prefetched(self, count: int, timeout_s: float) -> bool:
        """Wait until `count` frames have been prefetched in all; False on timeout."""
        with self._done:
            return self._done.wait_for(lambda: self.prefetched >= count, timeout_s)

    def _run(self) -> None:
        handled = -1
        while not self._stop.is_set():
            frame = self._source.latest()
            if frame is None or frame.sequence == handled:
                current = self._current
                if current is None or not current.wanted:
                    self._wanted.wait()  # nothing to prefetch on the next frame until a request looks
                    self._wanted.clear()
                else:
                    self._stop.wait(POLL_S)
                continue
            handled = frame.sequence
            analysis = self.for_frame(frame)
            if not analysis.inherited:
                continue
            for filter_def in sorted(analysis.inherited):
                try:
                    self._detector.blobs(analysis, filter_def)  # waits if a request is finding them
                except Exception:  # a frame the detector refuses: the request path reports it
                    log.debug("prefetching %s failed", filter_def, exc_info=True)
            with self._done:
                self.prefetched += 1
                self._done.notify_all()
