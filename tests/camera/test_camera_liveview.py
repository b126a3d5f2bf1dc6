"""A camera's own live view (`drvs-camera --foxglove [HOST:]PORT --foxglove-fps N`): its frames as
JPEG with its latest detections drawn, on /camera/<id>/image, sent only while a client subscribes
and at most N a second. Real drvs-server and drvs-camera processes on recorded footage, a robot
asking through the server, and a client that speaks the Foxglove WebSocket protocol as the Foxglove
app does; what the camera encoded is read from its Prometheus metrics."""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import socket
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from numpy.typing import NDArray

from drvs.camera import CameraNode, PushSource
from drvs.camera.cli import main as camera_main
from drvs.camera.liveview import CameraLiveView
from drvs.core.errors import FailedPrecondition
from drvs.core.geometry import Homography
from drvs.core.model import PixelBox
from drvs.live.foxglove_client import Channel, FoxgloveClient, Message
from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import LIVE_READY, ManagedProcess, start_server
from tests.fakes import start_recorded_camera
from tests.helpers import CAM1_REGION, IMAGE_SIZE, YELLOW, metrics_at_least, metrics_port, scrape, wait_until

TOPIC = "/camera/cam1/image"
PUBLISHED = 'drvs_liveview_frames_total{outcome="published"}'
UNWATCHED = 'drvs_liveview_frames_total{outcome="unwatched"}'
BYTES = "drvs_liveview_bytes_total"


@dataclass
class Camera:
    proc: ManagedProcess
    server: str
    url: str
    metrics: int


@contextlib.asynccontextmanager
async def live_camera(rec: RecordedCamera, *args: str) -> AsyncIterator[Camera]:
    """A server, and camera cam1 on its footage with a live view on a free port (`args`: more
    drvs-camera flags) and metrics; both reaped."""
    server, address = await start_server()
    try:
        proc = await start_recorded_camera("cam1", rec, address, "--foxglove", "0", "--metrics-port", "0", *args)
        try:
            url = (await proc.wait_for_line(LIVE_READY, timeout=10)).group(1)
            await proc.wait_for_line(r"metrics on http://", timeout=10)
            yield Camera(proc, address, url, metrics_port(proc))
        finally:
            await proc.stop()
    finally:
        await server.stop()


def decoder(channel: Channel) -> Any:
    """Decode a channel's messages with the schema it advertised, as Foxglove does."""
    schema = Schema(id=1, name=channel.schema_name, encoding=channel.schema_encoding, data=channel.schema)
    decode = DecoderFactory().decoder_for(channel.encoding, schema)
    assert decode is not None, channel
    return decode


def picture(decode: Any, message: Message) -> tuple[Any, NDArray[np.uint8]]:
    """The CompressedImage message and its image, decoded as a viewer does."""
    msg = decode(message.data)
    assert msg.format == "jpeg" and msg.frame_id == "camera/cam1", (msg.format, msg.frame_id)
    image = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None, "not a JPEG"
    return msg, np.asarray(image, dtype=np.uint8)


def box_drawn(image: NDArray[np.uint8], box: PixelBox) -> float:
    """The share of the box's outline (top, bottom, left and right edges, a pixel either side)
    that is in the boxes' colour (magenta), after JPEG."""
    b = image.astype(np.int16)
    magenta = (b[..., 0] > 170) & (b[..., 2] > 170) & (b[..., 1] < 110)
    x0, y0, x1, y1 = box.x, box.y, box.x + box.width, box.y + box.height
    edges = [
        magenta[max(y0 - 1, 0) : y0 + 2, x0:x1].any(axis=0),
        magenta[max(y1 - 1, 0) : y1 + 2, x0:x1].any(axis=0),
        magenta[y0:y1, max(x0 - 1, 0) : x0 + 2].any(axis=1),
        magenta[y0:y1, max(x1 - 1, 0) : x1 + 2].any(axis=1),
    ]
    return float(np.concatenate(edges).mean())


async def test_the_camera_sends_frames_only_while_watched_with_its_detections_drawn(
    recorded: dict[str, RecordedCamera],
) -> None:
    rec = recorded["cam1"]
    capture = cv2.VideoCapture(str(rec.video))
    ok, source_frame = capture.read()
    capture.release()
    assert ok
    async with live_camera(rec, "--foxglove-fps", "10") as cam:
        client = await FoxgloveClient.connect(cam.url)
        try:
            channel = (await client.wait_for_topics([TOPIC]))[TOPIC]
            assert channel.schema_name == "foxglove.CompressedImage"
            decode = decoder(channel)

            # (a) Connected, not subscribed: the view's turns pass, and not one frame is encoded or sent.
            values = await metrics_at_least(cam.metrics, UNWATCHED, 5)
            assert values.get(PUBLISHED, 0.0) == 0.0 and values.get(BYTES, 0.0) == 0.0, values
            with pytest.raises(asyncio.TimeoutError):
                await client.next_message(timeout=0.2)

            # (b) Subscribed: JPEG frames of the source, at its resolution.
            await client.subscribe([channel])
            msg, first = picture(decode, await client.next_message(timeout=10))
            assert first.shape == (IMAGE_SIZE[1], IMAGE_SIZE[0], 3)
            assert float(np.abs(first.astype(np.int16) - source_frame.astype(np.int16)).mean()) < 8.0
            stamp = msg.timestamp.seconds + msg.timestamp.nanos / 1e9
            assert abs(stamp - time.time()) < 5.0, stamp

            # (c) The camera answers a robot: a later frame shows each detection's box drawn.
            async with DrvsClient.connect(cam.server, robot_id="watcher") as drvs:
                result = await drvs.detect(YELLOW, CAM1_REGION, timeout_s=10)
            assert not result.errors and result.detections, result
            boxes = [d.pixel_box for d in result.detections]
            assert all(box_drawn(first, b) < 0.1 for b in boxes), "boxes before any detection"
            deadline = time.monotonic() + 10
            while True:
                _, image = picture(decode, await client.next_message(timeout=10))
                if all(box_drawn(image, b) > 0.8 for b in boxes):
                    break
                assert time.monotonic() < deadline, [box_drawn(image, b) for b in boxes]

            # (e) Unsubscribed: the turns pass unwatched again, and nothing more is encoded.
            before = await scrape(cam.metrics)
            await client.unsubscribe_all()
            stopped = await metrics_at_least(cam.metrics, UNWATCHED, before[UNWATCHED] + 2)
            later = await metrics_at_least(cam.metrics, UNWATCHED, stopped[UNWATCHED] + 5)
            assert later[PUBLISHED] == stopped[PUBLISHED] > 0, (stopped, later)
            assert later[BYTES] == stopped[BYTES]
        finally:
            await client.close()


async def test_the_operator_caps_the_frame_rate(recorded: dict[str, RecordedCamera]) -> None:
    """(d) --foxglove-fps 2 on 20 fps footage: at most 2 frames a second arrive, each a different frame
    taken at least half a second (less a source frame) after the one before."""
    async with live_camera(recorded["cam1"], "--foxglove-fps", "2") as cam:
        client = await FoxgloveClient.connect(cam.url)
        try:
            channel = (await client.wait_for_topics([TOPIC]))[TOPIC]
            decode = decoder(channel)
            await client.subscribe([channel])
            arrivals: list[float] = []
            stamps: list[float] = []
            while not arrivals or time.monotonic() - arrivals[0] < 2.6:
                msg, _ = picture(decode, await client.next_message(timeout=5))
                arrivals.append(time.monotonic())
                stamps.append(msg.timestamp.seconds + msg.timestamp.nanos / 1e9)
        finally:
            await client.close()
    span = arrivals[-1] - arrivals[0]
    assert len(arrivals) >= 3, arrivals
    assert len(arrivals) - 1 <= 2 * span + 1, (len(arrivals), span)
    # Frames taken 0.5 s apart, give or take the source's own timing (a busy machine delays its grabber).
    gaps = np.diff(stamps)
    assert gaps.min() > 0.3, gaps


class CountingSource(PushSource):
    """Frames pushed by the test; counts how often the node's side reads one."""

    def __init__(self) -> None:
        super().__init__("test frames")
        self.reads = 0

    def latest(self) -> Any:
        self.reads += 1
        return super().latest()


async def test_an_unwatched_view_reads_no_frame() -> None:
    """In process: while nobody subscribes the view does not even look at the source."""
    source = CountingSource()
    source.push(np.full((48, 64, 3), 128, np.uint8))
    view = CameraLiveView("cam1", source, ("127.0.0.1", 0), fps=30)
    view.start()
    try:
        client = await FoxgloveClient.connect(view.url)
        try:
            channel = (await client.wait_for_topics([TOPIC]))[TOPIC]
            await wait_until(lambda: view.frames_skipped_unwatched >= 5, "5 turns unwatched")
            assert source.reads == 0 and view.frames_published == 0
            await client.subscribe([channel])
            await client.next_message(timeout=5)
            assert source.reads > 0 and view.frames_published == 1
            await client.unsubscribe_all()
            skipped = view.frames_skipped_unwatched
            await wait_until(lambda: view.frames_skipped_unwatched > skipped, "unwatched again")
            reads = source.reads
            await wait_until(lambda: view.frames_skipped_unwatched >= skipped + 5, "5 more turns unwatched")
            assert source.reads == reads and view.frames_published == 1
        finally:
            await client.close()
    finally:
        await view.stop()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--foxglove", "nonsense"], "foxglove (from --foxglove): 'nonsense' is not host:port"),
        (["--foxglove", "99999"], "foxglove (from --foxglove): port 99999 is out of range"),
        (["--foxglove", "127.0.0.1:x"], "foxglove (from --foxglove): port 'x' is not a number"),
        (
            ["--foxglove", "0", "--foxglove-fps", "0"],
            "foxglove_fps (from --foxglove-fps): 0 must be a number above 0 and at most 30 (frames a second)",
        ),
        (
            ["--foxglove", "0", "--foxglove-fps", "31"],
            "foxglove_fps (from --foxglove-fps): 31 must be a number above 0 and at most 30 (frames a second)",
        ),
        (["--foxglove", "0", "--foxglove-fps", "fast"], "foxglove_fps (from --foxglove-fps): 'fast' is not a number"),
        (["--foxglove-fps", "5"], "foxglove_fps (--foxglove-fps): only with --foxglove"),
    ],
)
def test_bad_live_view_flags_are_refused_naming_the_flag(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("DRVS_CAMERA_FOXGLOVE", "DRVS_CAMERA_FOXGLOVE_FPS"):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(SystemExit) as exit_:
        camera_main(["--id", "cam1", "--source", "video.avi", "--homography", "h.yaml", *args])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"drvs-camera: error: {message}" in err, err
    assert "Traceback" not in err


def test_the_environment_sets_the_rate_and_is_checked_too(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("DRVS_CAMERA_FOXGLOVE", "0")
    monkeypatch.setenv("DRVS_CAMERA_FOXGLOVE_FPS", "inf")
    with pytest.raises(SystemExit) as exit_:
        camera_main(["--id", "cam1", "--source", "video.avi", "--homography", "h.yaml"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "foxglove_fps (from DRVS_CAMERA_FOXGLOVE_FPS): inf must be a number above 0 and at most 30" in err, err


def test_without_the_live_extra_the_camera_names_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """A camera with a live view needs foxglove-sdk and says which extra brings it; one without does not."""
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "foxglove" else find_spec(name, *a)
    )
    h = Homography.from_values(np.eye(3))
    with pytest.raises(FailedPrecondition, match=r"^--foxglove: needs the live view and recordings: pip install"):
        CameraNode("cam1", PushSource(), h, "127.0.0.1:1", foxglove=("127.0.0.1", 0))
    assert CameraNode("cam1", PushSource(), h, "127.0.0.1:1").live is None


async def test_a_live_view_port_in_use_stops_the_camera_at_start(recorded: dict[str, RecordedCamera]) -> None:
    rec = recorded["cam1"]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = ManagedProcess.entry_point(
            "cam1", "drvs-camera", "--id", "cam1", "--source", str(rec.video), "--homography",
            str(rec.homography_file), "--server", "127.0.0.1:1", "--foxglove", f"127.0.0.1:{port}",
        )  # fmt: skip
        await proc.start()
        code = await proc.wait(timeout=30)
    assert code == 1, proc.output()
    assert f"camera cam1 cannot start: --foxglove: cannot listen on 127.0.0.1:{port}" in proc.output()
    assert "Traceback" not in proc.output()
