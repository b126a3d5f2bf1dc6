"""The newest frame a frame source produced, for a camera node to read: what every source (a
device, a file, a stream, frames a program pushes, the simulator's renderer) shares. In the core:
camera sources and the simulator's plug-in source stand on it alike."""

from __future__ import annotations

import asyncio
import threading

import numpy as np

from drvs.core.errors import FailedPrecondition
from drvs.detectors.base import Frame


class NewestFrame:
    """The newest frame a source produced, kept for the node to read: the part every source shares.

    A source's producer (a grabber thread, a renderer, a program's own `push`) calls `_keep`; the
    node reads `latest()` and, at start, awaits `wait_first_frame`. `lock` is a Lock, or a Condition
    when the source also waits on it for its own state.
    """

    description: str
    error: str | None = None

    def __init__(self, lock: threading.Lock | threading.Condition | None = None) -> None:
        self._lock = lock if lock is not None else threading.Lock()
        self._latest: Frame | None = None
        self._first = threading.Event()
        self._sequence = 0

    def _keep(self, image: np.ndarray, capture_time: float, captured_at: float) -> Frame:
        """Keep `image` as the newest frame, numbered after the last one; return it."""
        with self._lock:
            self._sequence += 1
            frame = Frame(image=image, capture_time=capture_time, sequence=self._sequence, captured_at=captured_at)
            self._latest = frame
        self._first.set()
        return frame

    def latest(self) -> Frame | None:
        """The newest frame, or None before the first."""
        with self._lock:
            return self._latest

    async def wait_first_frame(self, timeout_s: float) -> Frame:
        """The first frame, waiting up to `timeout_s` seconds; FailedPrecondition naming the source
        (and its last error) when none came."""
        if not await asyncio.to_thread(self._first.wait, timeout_s):
            raise FailedPrecondition(
                f"source {self.description!r}: no frame within {timeout_s:g} s"
                + (f" ({self.error})" if self.error else "")
            )
        frame = self.latest()
        assert frame is not None
        return frame
