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
Heavy detectors (people, models) are never prefetched: at about 100 ms a frame, finding objects
in frames nobody may look at again would take a core.

Detectors that keep a model of the scene (foreground's background model) see new frames on a
second thread from the first request that asks for them: every frame while robots ask, and at most
IDLE_OBSERVE_HZ frames a second after nobody has for IDLE_AFTER_S, so a model stays warm without
taking CPU (and the GIL) from the requests the camera serves. A camera nobody asks for foreground
never runs the model: on two cores, feeding it every frame made other robots' colour answers on
the same camera tens of milliseconds late (tests/behaviour/test_faults.py).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence

from drvs.detectors import Detector, Frame, FrameAnalysis

from .source import FrameSource

log = logging.getLogger(__name__)

#: How often the thread looks for a new frame while some filter is wanted.
POLL_S = 0.002
#: An observing detector nobody has asked for this long sees at most IDLE_OBSERVE_HZ frames a second.
IDLE_AFTER_S = 30.0
IDLE_OBSERVE_HZ = 2.0
#: How often the observing thread looks for a new frame while an observer is due one.
OBSERVE_POLL_S = 0.01


class Analyses:
    def __init__(
        self,
        source: FrameSource,
        prefetch: Callable[[FrameAnalysis, str], None],
        name: str = "",
        *,
        observers: Sequence[Detector] = (),
    ) -> None:
        self._source = source
        self._prefetch = prefetch
        self._observers = tuple(observers)
        # Monotonic times each observer was last asked for by a request, and last fed a frame.
        self._asked: dict[int, float] = {}
        self._fed: dict[int, float] = {}
        self._first_ask = threading.Event()
        self._observer_thread = (
            threading.Thread(target=self._observe, name=f"observe:{name}", daemon=True) if self._observers else None
        )
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
        if self._observer_thread is not None:
            self._observer_thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wanted.set()
        self._first_ask.set()
        for thread in (self._thread, self._observer_thread):
            if thread is not None and thread.is_alive():
                thread.join(timeout=5)

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

    def asked(self, detector: Detector) -> None:
        """A request asked an observing detector: it sees every frame for IDLE_AFTER_S from now."""
        self._asked[id(detector)] = time.monotonic()
        self._first_ask.set()

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
                    self._prefetch(analysis, filter_def)  # waits if a request is finding them
                except Exception:  # a frame the detector refuses: the request path reports it
                    log.debug("prefetching %s failed", filter_def, exc_info=True)
            with self._done:
                self.prefetched += 1
                self._done.notify_all()

    def _observe(self) -> None:
        """Hand new frames to the detectors that model the scene, in order, on this thread. While
        they are idle the thread sleeps until the next frame is due to them rather than polling:
        a thread waking every few milliseconds takes the GIL from the event loop serving requests."""
        handled = -1
        self._first_ask.wait()  # nobody has asked for a model yet: it costs nothing
        while not self._stop.is_set():
            now = time.monotonic()
            due = [d for d in self._observers if self._due(d, now)]
            if not due:
                self._stop.wait(min(self._wait_s(d, now) for d in self._observers))
                continue
            frame = self._source.latest()
            if frame is None or frame.sequence == handled:
                self._stop.wait(OBSERVE_POLL_S)
                continue
            handled = frame.sequence
            for detector in due:
                self._fed[id(detector)] = now
                try:
                    detector.observe(frame)
                except Exception:  # one bad frame must not end the camera's scene model
                    log.warning("%s: observing frame %d failed", type(detector).__name__, frame.sequence, exc_info=True)

    def _idle(self, detector: Detector, now: float) -> bool:
        return now - self._asked.get(id(detector), -math.inf) > IDLE_AFTER_S

    def _wait_s(self, detector: Detector, now: float) -> float:
        """Seconds until `detector` is due a frame (0 when it is due now)."""
        if id(detector) not in self._asked:
            return IDLE_AFTER_S  # never asked: look again later
        if not self._idle(detector, now):
            return 0.0
        return max(0.0, self._fed.get(id(detector), -math.inf) + 1.0 / IDLE_OBSERVE_HZ - now)

    def _due(self, detector: Detector, now: float) -> bool:
        return self._wait_s(detector, now) == 0.0
