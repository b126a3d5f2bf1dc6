"""Frame sources: a background grabber that always holds the newest frame."""

from __future__ import annotations

import importlib.metadata
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Protocol, cast

import cv2
import numpy as np

from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.frames import NewestFrame
from drvs.detectors import Frame

log = logging.getLogger("drvs.camera.source")


class FrameSource(Protocol):
    """Anything that yields frames: a device, a file, a stream, a simulator."""

    description: str

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def latest(self) -> Frame | None: ...

    async def wait_first_frame(self, timeout_s: float) -> Frame: ...


#: The entry-point group naming a frame source for a URL scheme: a callable (spec, camera_id) ->
#: FrameSource, e.g. [project.entry-points."drvs.frame_sources"] sim = "drvs.sim.source:SimSource".
#: The camera finds the simulator's sim:// source this way without importing the simulator.
SOURCE_ENTRY_POINT_GROUP = "drvs.frame_sources"


def plugin_source(spec: str, camera_id: str) -> FrameSource | None:
    """The frame source an installed package registers for the spec's scheme (sim://...), or None
    for a spec no plug-in claims (OpenCV's: a device, a file, rtsp://...)."""
    scheme, sep, _ = spec.partition("://")
    if not sep:
        return None
    for entry in importlib.metadata.entry_points(group=SOURCE_ENTRY_POINT_GROUP, name=scheme):
        try:
            factory = cast(Callable[[str, str], FrameSource], entry.load())
        except ImportError as exc:
            raise FailedPrecondition(
                f"source {spec}: the {scheme}:// frame source ({entry.value}) cannot load: {exc}"
                + (" (the simulator: pip install 'drvs[sim]')" if scheme == "sim" else "")
            ) from None
        return factory(spec, camera_id)
    return None


def parse_source(spec: str) -> int | str:
    """A device index ("0"), a file or device path (/dev/video0), or a stream URL, as VideoCapture takes them."""
    spec = spec.strip()
    if not spec:
        raise ValueError("source: empty")
    return int(spec) if spec.isdigit() else spec


class VideoSource(NewestFrame):
    """Any OpenCV VideoCapture source, read by a background thread that keeps the newest frame.

    A video file plays at its own frame rate and loops; a device or stream is read as fast as it
    delivers, and reopened with backoff when it drops.
    """

    def __init__(
        self,
        spec: str,
        *,
        loop_file: bool = True,
        reconnect_max_s: float = 5.0,
        resolution: tuple[int, int] | None = None,
        fps: float | None = None,
    ) -> None:
        self.resolution = resolution
        self.fps = fps
        self.source = parse_source(spec)
        self.description = str(spec)
        self.is_file = isinstance(self.source, str) and os.path.isfile(self.source)
        self.loop_file = loop_file
        self.reconnect_max_s = reconnect_max_s
        super().__init__()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: str | None = None
        self._opened_once = False

    def start(self) -> None:
        if isinstance(self.source, str) and "://" not in self.source and not os.path.exists(self.source):
            raise FileNotFoundError(
                f"source: {self.source!r} is neither a device index, an existing file or device path, nor a URL"
            )
        self._thread = threading.Thread(target=self._run, name=f"grabber:{self.description}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _open(self) -> cv2.VideoCapture | None:
        cap = cv2.VideoCapture(self.source)
        if not cap.isOpened():
            cap.release()
            return None
        if not self.is_file:  # a device or stream: ask for the configured mode (it may not grant it)
            if self.resolution is not None:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.resolution[0])
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.resolution[1])
            if self.fps is not None:
                cap.set(cv2.CAP_PROP_FPS, self.fps)
        if self._opened_once:
            log.debug("source %s reopened", self.description)
        else:
            log.info("source %s opened", self.description)
            self._opened_once = True
        return cap

    def _run(self) -> None:
        backoff = 0.2
        while not self._stop.is_set():
            cap = self._open()
            if cap is None:
                self.error = "cannot open source"
                log.warning("source %s: cannot open; retrying in %.1f s", self.description, backoff)
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.reconnect_max_s)
                continue
            backoff = 0.2
            self._read_until_done(cap)
            cap.release()
            if self.is_file and not self.loop_file:
                return

    def _read_until_done(self, cap: cv2.VideoCapture) -> None:
        fps = cap.get(cv2.CAP_PROP_FPS) if self.is_file else 0.0
        period = 1.0 / fps if fps and fps > 0 else (1.0 / 30 if self.is_file else 0.0)
        next_at = time.monotonic()
        while not self._stop.is_set():
            ok, image = cap.read()
            if not ok or image is None:
                if self.is_file:
                    return  # end of file: reopen to loop
                self.error = "source stopped delivering frames"
                log.warning("source %s stopped delivering frames; reconnecting", self.description)
                return
            captured_at, now = time.monotonic(), time.time()
            self._keep(np.asarray(image, dtype=np.uint8), now, captured_at)
            if period:
                next_at += period
                delay = next_at - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_at = time.monotonic()


class PushSource(NewestFrame):
    """Frames that the program itself hands over: a robot's own code, which already has its camera's
    images, pushes each one (`push(image_bgr, capture_time)`) and a camera node serves from the
    newest. Thread-safe: push from any thread."""

    def __init__(self, description: str = "pushed frames") -> None:
        self.description = description
        super().__init__()

    def start(self) -> None:
        """Nothing to open: frames arrive by push."""

    def stop(self) -> None:
        """Nothing to close."""

    def push(self, image: np.ndarray, capture_time: float | None = None) -> Frame:
        """Hand over a BGR image (H x W x 3, uint8) captured at `capture_time` (seconds since the
        Unix epoch; None: now). InvalidArgument for anything that is not such an image."""
        if not (isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3):
            shape = getattr(image, "shape", None)
            raise InvalidArgument(f"image: a BGR image is H x W x 3 uint8, not {type(image).__name__} {shape}")
        if capture_time is not None and not math.isfinite(capture_time):
            raise InvalidArgument(f"capture_time: {capture_time} is not a finite number")
        now = time.time()
        # The frame's age runs on the monotonic clock, from when it was captured.
        captured_at = time.monotonic() - (max(0.0, now - capture_time) if capture_time is not None else 0.0)
        return self._keep(image, now if capture_time is None else capture_time, captured_at)
