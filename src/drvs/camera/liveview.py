"""What a camera shows live (`drvs-camera --foxglove HOST:PORT`, pip install 'drvs[live]'): its own
frames, JPEG-compressed, with the detections it made lately drawn on them, in a Foxglove live view.

One topic:

  /camera/<camera_id>/image    foxglove.CompressedImage    format "jpeg", frame_id "camera/<camera_id>"

Frames are sent only while some client subscribes to that topic, and at most `fps` a second
(`--foxglove-fps`: default 5, drvs.camera.config.DEFAULT_FOXGLOVE_FPS; at most 30). While nobody
subscribes, the view's loop wakes at that rate only to ask the live view whether anyone does: it
reads no frame, encodes nothing and sends nothing. A frame is sent once: when the source has no
newer one, nothing is sent either.

Detections: each request the node serves leaves its newest detections here (one dictionary
assignment on the request path: `show`); the view draws those of every request answered in the
last DETECTIONS_SHOWN_S seconds on the newest frame, as boxes in BOX_BGR with their label, so a
moving object's box may lag it by the detection's age. Drawing and encoding run on the view's own
thread, never on the event loop that serves requests.

Counted in `frames_published`, `frames_skipped_unwatched` and `frames_skipped_unchanged`, and in
Prometheus as drvs_liveview_frames_total{outcome="published|unwatched|unchanged"} and
drvs_liveview_bytes_total.

The view has no access control of its own: anyone who reaches its port sees the camera's images.
PORT alone listens on 127.0.0.1; listen elsewhere only on a network you trust."""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import time
from collections.abc import Iterable, Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.core.errors import InvalidArgument
from drvs.core.filters import object_type
from drvs.core.imaging import encode_jpeg
from drvs.core.model import Detection
from drvs.core.net import is_loopback_host
from drvs.live.liveview import LiveHub, require
from drvs.wire import metrics
from drvs.wire._cli import format_number

from .source import FrameSource

log = logging.getLogger("drvs.camera.liveview")

MAX_FPS = 30.0
JPEG_QUALITY = 80
#: A request's detections are drawn for this long after the node made them.
DETECTIONS_SHOWN_S = 1.0
#: The boxes' colour (BGR: magenta, rare in a building) and line width in pixels.
BOX_BGR = (255, 0, 255)
BOX_THICKNESS = 2
#: At most this many boxes are drawn on one frame (the most recent requests' first).
MAX_BOXES = 256

PUBLISHED = metrics.LIVEVIEW_FRAMES.labels("published")
UNWATCHED = metrics.LIVEVIEW_FRAMES.labels("unwatched")
UNCHANGED = metrics.LIVEVIEW_FRAMES.labels("unchanged")


def check_fps(fps: float, name: str = "--foxglove-fps") -> float:
    """`fps` when it is a number above 0 and at most MAX_FPS; InvalidArgument naming `name` otherwise."""
    if isinstance(fps, bool) or not isinstance(fps, (int, float)):
        raise InvalidArgument(f"{name}: {fps!r} is not a number")
    if not (math.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise InvalidArgument(
            f"{name}: {format_number(fps)} must be a number above 0 and at most {format_number(MAX_FPS)} "
            "(frames a second)"
        )
    return float(fps)


def topic(camera_id: str) -> str:
    return f"/camera/{camera_id}/image"


def frame_id(camera_id: str) -> str:
    return f"camera/{camera_id}"


def label(d: Detection) -> str:
    """What a box is labelled with: a model's or person's class, a marker's id, else the filter."""
    if d.label:
        return d.label
    if d.marker_id is not None:
        return f"{object_type(d.filter_def).kind} {d.marker_id}"
    return d.filter_def


def draw_detections(image: NDArray[np.uint8], detections: Iterable[Detection]) -> NDArray[np.uint8]:
    """A copy of `image` with each detection's pixel box and label drawn (`image` is left as it is:
    the node's requests read the same frame)."""
    out = image.copy()
    height, width = out.shape[:2]
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.45
    for d in detections:
        b = d.pixel_box
        x0, y0 = int(b.x), int(b.y)
        x1, y1 = int(b.x + b.width), int(b.y + b.height)
        cv2.rectangle(out, (x0, y0), (x1, y1), BOX_BGR, BOX_THICKNESS)
        text = label(d)[:40]
        (tw, th), base = cv2.getTextSize(text, font, scale, 1)
        # Above the box when there is room, else inside its top edge; kept within the image.
        tx = min(max(x0, 0), max(0, width - tw - 2))
        ty = y0 - 4 if y0 - th - base - 4 >= 0 else min(y0 + th + 4, height - base)
        cv2.rectangle(out, (tx, ty - th - 2), (tx + tw + 2, ty + base), (0, 0, 0), cv2.FILLED)
        cv2.putText(out, text, (tx + 1, ty), font, scale, BOX_BGR, 1, cv2.LINE_AA)
    return out


def encode(image: NDArray[np.uint8], detections: Sequence[Detection], quality: int = JPEG_QUALITY) -> bytes:
    """The frame as JPEG, `detections` drawn on it."""
    return encode_jpeg(draw_detections(image, detections) if detections else image, quality)


class CameraLiveView:
    """A Foxglove live view of one camera on `listen` (host, port; port 0 picks a free one): see the
    module docstring. `start()` on the node's event loop, `await stop()`; `show()` from it."""

    def __init__(
        self,
        camera_id: str,
        source: FrameSource,
        listen: tuple[str, int],
        *,
        fps: float,
        quality: int = JPEG_QUALITY,
    ) -> None:
        require("--foxglove")
        from foxglove.channels import CompressedImageChannel

        self.camera_id = camera_id
        self.source = source
        self.listen = listen
        self.fps = check_fps(fps)
        self.quality = quality
        self.topic = topic(camera_id)
        self.frame_id = frame_id(camera_id)
        #: request id -> (time.monotonic() when the node answered it, its detections); see `show`.
        self.recent: dict[str, tuple[float, Sequence[Detection]]] = {}
        self.frames_published = 0
        self.frames_skipped_unwatched = 0
        self.frames_skipped_unchanged = 0
        self.bytes_published = 0
        self.hub = LiveHub(f"drvs-camera {camera_id}", listen=listen, warn=False)
        self.channel = CompressedImageChannel(self.topic, context=self.hub.context)
        self._pool = concurrent.futures.ThreadPoolExecutor(1, f"liveview:{camera_id}")
        self._task: asyncio.Task[None] | None = None

    @property
    def url(self) -> str:
        return str(self.hub.url)

    @property
    def port(self) -> int:
        return self.hub.port

    def watched(self) -> bool:
        """Whether some client subscribes to the camera's image now."""
        return bool(self.channel.has_sinks())

    def show(self, request_id: str, detections: Sequence[Detection]) -> None:
        """A request's newest detections (the node calls this as it answers; on the event loop)."""
        self.recent[request_id] = (time.monotonic(), detections)

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"liveview:{self.camera_id}")
        host = self.listen[0]
        log.info(
            "camera %s: live view on %s (open it in Foxglove: %s, at most %g frames a second, only while watched)",
            self.camera_id,
            self.url,
            self.topic,
            self.fps,
        )
        if not is_loopback_host(host):
            log.warning(
                "camera %s: the live view listens on %s: anyone who reaches it sees this camera's images "
                "(it has no access control; keep it on loopback or a network you trust)",
                self.camera_id,
                host,
            )

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None
        self._pool.shutdown(wait=False, cancel_futures=True)
        await asyncio.to_thread(self.hub.close)

    def forget(self, now: float) -> None:
        """Forget the detections older than DETECTIONS_SHOWN_S."""
        for request_id in [r for r, (at, _) in self.recent.items() if now - at > DETECTIONS_SHOWN_S]:
            del self.recent[request_id]

    def drawn(self, now: float) -> list[Detection]:
        """The detections to draw now: the newest requests' first, the same box of several requests once."""
        self.forget(now)
        seen: set[tuple[Any, ...]] = set()
        out: list[Detection] = []
        for _at, detections in sorted(self.recent.values(), key=lambda item: -item[0]):
            for d in detections:
                key = (d.pixel_box, label(d))
                if key not in seen and len(out) < MAX_BOXES:
                    seen.add(key)
                    out.append(d)
        return out

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.fps
        last_sequence = -1
        while True:
            turn = loop.time()
            try:
                last_sequence = await self._turn(last_sequence)
            except Exception:  # one frame that cannot be drawn or sent must not end the view
                log.warning("camera %s: live view: a frame failed", self.camera_id, exc_info=True)
            # The next turn a whole period after this one began: never more than `fps` a second. Old
            # detections are forgotten meanwhile, also when turns are far apart.
            while (left := turn + period - loop.time()) > 0:
                await asyncio.sleep(min(left, DETECTIONS_SHOWN_S))
                self.forget(time.monotonic())

    async def _turn(self, last_sequence: int) -> int:
        """One turn: publish the newest frame if someone watches and it is new. The sequence sent."""
        from foxglove.messages import CompressedImage, Timestamp

        if not self.watched():
            self.frames_skipped_unwatched += 1
            UNWATCHED.inc()
            return -1  # whoever subscribes next gets the newest frame at once
        frame = self.source.latest()
        if frame is None or frame.sequence == last_sequence:
            self.frames_skipped_unchanged += 1
            UNCHANGED.inc()
            return last_sequence
        detections = self.drawn(time.monotonic())
        data = await asyncio.get_running_loop().run_in_executor(
            self._pool, encode, frame.image, detections, self.quality
        )
        self.channel.log(
            CompressedImage(
                timestamp=Timestamp.from_epoch_secs(frame.capture_time),
                frame_id=self.frame_id,
                data=data,
                format="jpeg",
            )
        )
        self.frames_published += 1
        self.bytes_published += len(data)
        PUBLISHED.inc()
        metrics.LIVEVIEW_BYTES.inc(len(data))
        return frame.sequence
