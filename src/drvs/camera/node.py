"""The camera node role: serves DetectObjectBoundary to the server, reports to robots."""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import math
import secrets
import time
from collections.abc import AsyncIterator, Callable, Mapping
from typing import Any

import grpc
import numpy as np
from grpc import aio
from numpy.typing import NDArray

from drvs.core.errors import DrvsError, FailedPrecondition, InvalidArgument
from drvs.core.filters import object_type
from drvs.core.geometry import DEFAULT_MAX_RANGE_M, FieldOfView, Homography
from drvs.core.imaging import encode_jpeg
from drvs.core.mobile import DEFAULT_MAX_POSE_GAP_S, Mount, PoseBuffer, move_detection
from drvs.core.model import DEFAULT_FRAME, Detection, DetectionReport, DetectionRequest, Pose2, check_frame, check_id
from drvs.core.net import dialable_address, parse_address, parse_address_list
from drvs.detectors import (
    DEFAULT_MIN_AREA_PX,
    REGISTRY,
    CameraView,
    Detector,
    DetectorUnavailable,
    Frame,
    FrameAnalysis,
    ObjectType,
    prefixes,
    select,
)
from drvs.live import liveview
from drvs.v1 import detection_pb2, detection_pb2_grpc, registry_pb2, stream_pb2, stream_pb2_grpc
from drvs.wire import logs, metrics
from drvs.wire._service import Endpoint, Lifecycle
from drvs.wire.callback import CallbackSender
from drvs.wire.convert import homography_to_pb, request_from_pb
from drvs.wire.request_stream import serve_request_batches
from drvs.wire.security import Security

from .config import (
    DEFAULT_DETECT_WORKERS,
    DEFAULT_FOXGLOVE_FPS,
    DEFAULT_MAX_CONTINUOUS_PER_ROBOT,
    DEFAULT_MAX_FRAME_AGE_S,
    check_settings,
)
from .detectors import build_detectors, log_detectors, run_detector
from .liveview import CameraLiveView, check_fps
from .poses import open_pose_source
from .prefetch import Analyses
from .registration import PoseUpdates, Registration
from .shares import Robot, Shares
from .source import FrameSource
from .trust import FRAME_STREAMS, ReportTargets, check_caller

log = logging.getLogger("drvs.camera")

SERVICE_NAMES = (detection_pb2.DESCRIPTOR.services_by_name["DetectObjectBoundary"].full_name,)
FRAME_STREAM_SERVICE = stream_pb2.DESCRIPTOR.services_by_name["FrameStream"].full_name
#: How often a frame stream looks for a newer frame.
FRAME_POLL_S = 0.005


def default_detectors() -> tuple[str, ...]:
    """Every built-in detector prefix (models serve nothing until a camera configures one)."""
    return prefixes()


class CameraNode(Lifecycle):
    """A camera node as an object: start(), stop(grace), `async with`.

    The settings it shares with drvs-camera (max_range_m, min_area_px, max_frame_age_s,
    heartbeat_s, max_continuous, detect_workers; see CameraConfig for units and ranges) are
    checked by the same `check_settings` as the CLI's, with the same messages.

    `foxglove` (host, port; port 0 picks one): a Foxglove live view of its frames with its recent
    detections drawn, at most `foxglove_fps` frames a second and only while someone watches
    (drvs.camera.liveview; needs pip install 'drvs[live]'). It starts and stops with the node;
    `live` is it once started."""

    def __init__(
        self,
        camera_id: str,
        source: FrameSource,
        homography: Homography | None,
        server: str,
        *,
        listen: str = "127.0.0.1:0",
        advertise: str | None = None,
        max_range_m: float = DEFAULT_MAX_RANGE_M,
        min_area_px: float = DEFAULT_MIN_AREA_PX,
        first_frame_timeout_s: float = 15.0,
        max_frame_age_s: float = DEFAULT_MAX_FRAME_AGE_S,
        serve_frames: bool = False,
        resolution: tuple[int, int] | None = None,
        detectors: tuple[str, ...] | None = None,
        detector_options: Mapping[str, Mapping[str, Any]] | None = None,
        detect_workers: int = DEFAULT_DETECT_WORKERS,
        heartbeat_s: float | None = None,
        security: Security | None = None,
        max_continuous: int = DEFAULT_MAX_CONTINUOUS_PER_ROBOT,
        mount: Mount | None = None,
        max_pose_gap_s: float = DEFAULT_MAX_POSE_GAP_S,
        pose_lease_s: float = 0.0,
        pose_update_distance_m: float = 0.1,
        pose_update_angle_deg: float = 5.0,
        max_pose_rate_hz: float = 5.0,
        pose_source: str | None = None,
        max_speed_mps: float = 0.0,
        frame: str = DEFAULT_FRAME,
        foxglove: tuple[str, int] | None = None,
        foxglove_fps: float = DEFAULT_FOXGLOVE_FPS,
    ) -> None:
        check_settings(
            {
                "max_range_m": max_range_m,
                "min_area_px": min_area_px,
                "max_frame_age_s": max_frame_age_s,
                "heartbeat_s": heartbeat_s,
                "max_continuous": max_continuous,
                "detect_workers": detect_workers,
            }
        )
        self.security = security or Security()
        #: The floor plan its field of view is in; the server routes to it only in this frame.
        self.frame = check_frame(frame)
        #: Continuous requests one robot (as the server knows it) may have running here at once.
        self.max_continuous = max_continuous
        if resolution is not None and not (
            isinstance(resolution, tuple) and len(resolution) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in resolution)
        ):  # fmt: skip
            raise InvalidArgument(f"resolution: {resolution!r} is not (width, height) in whole pixels above 0")
        self.resolution = resolution
        #: Detector prefixes to run (default: every built-in); options per prefix from the config.
        self.detectors = default_detectors() if detectors is None else tuple(detectors)
        unknown = [d for d in self.detectors if d not in REGISTRY]
        if unknown or not self.detectors:
            raise InvalidArgument(f"detectors: {unknown or 'none'}; must be some of {', '.join(prefixes())}")
        options = detector_options or {}
        if not isinstance(options, Mapping) or not all(isinstance(o, Mapping) for o in options.values()):
            raise InvalidArgument("detector_options: expected {prefix: {option: value}}, e.g. {'people': {...}}")
        if stray := sorted(str(k) for k in options if k not in REGISTRY):  # a typo would be ignored
            raise InvalidArgument(
                f"detector_options: {stray}: no such detector; must be some of {', '.join(prefixes())}"
            )
        self.detector_options = dict(options)
        self.detect_workers = detect_workers
        self._heavy_pool: concurrent.futures.ThreadPoolExecutor | None = None
        #: Running detector instances by prefix, and by the routing kinds they serve.
        self.runners: dict[str, Detector] = {}
        self.kinds: dict[str, Detector] = {}
        #: Configured detectors this process cannot run (a backend missing, a model file absent), and why.
        self.unavailable: dict[str, DetectorUnavailable] = {}
        #: Heavy searches running now, by key: the analysis (frame) each is finding objects in.
        self._heavy_running: dict[str, FrameAnalysis] = {}
        self.heartbeat_s = heartbeat_s
        self.camera_id = check_id(camera_id, "camera_id")
        if not all(callable(getattr(source, m, None)) for m in ("start", "stop", "latest", "wait_first_frame")):
            kind = type(source).__name__
            raise InvalidArgument(
                f"source: expected a frame source (VideoSource, PushSource, any FrameSource), got {kind}"
            )
        self.source = source
        if (homography is None) == (mount is None):
            raise InvalidArgument(
                "homography: give a fixed camera's homography, or a mobile camera's mount (not both, not neither)"
            )
        if homography is not None and not isinstance(homography, Homography):
            raise InvalidArgument(
                f"homography: expected a Homography (Homography.from_values, a homography file's), "
                f"got {type(homography).__name__}"
            )
        self.homography: Homography = homography if homography is not None else Homography.from_values(np.eye(3))
        #: The server, or several (a,b,...: servers sharing one registry in etcd) tried in turn.
        self.server_address = server
        self.servers = parse_address_list(server, "server")
        #: Where a fused request's reports (and this node's token) may go: its servers' hosts only.
        self.report_targets = ReportTargets(self.camera_id, self.servers)
        self.listen = listen
        parse_address(listen, "listen", allow_port_zero=True)
        self.advertise = advertise
        if advertise is not None:
            parse_address(advertise, "advertise")
        self.max_range_m = max_range_m
        self.min_area_px = min_area_px
        self.first_frame_timeout_s = first_frame_timeout_s
        self.max_frame_age_s = max_frame_age_s
        self.view: CameraView | None = None
        self.field_of_view: FieldOfView | None = None
        self.registration = Registration(self.camera_id, server, self.security, heartbeat_s)
        #: A camera on a robot: where it sits on the robot (its homography is then the mount's, to
        #: the robot's base frame), the robot's poses over time (robot code, or a pose source,
        #: pushes them: `push_pose`), and the loop that keeps the server's field of view on it.
        self.mount = mount
        self.poses = PoseBuffer(max_pose_gap_s)
        for name, value in (
            ("pose_lease_s", pose_lease_s),
            ("max_speed_mps", max_speed_mps),
            ("pose_update_distance_m", pose_update_distance_m),
            ("pose_update_angle_deg", pose_update_angle_deg),
        ):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidArgument(f"{name}: {value} must be a number >= 0")
        if not (math.isfinite(max_pose_rate_hz) and max_pose_rate_hz > 0):
            raise InvalidArgument(f"max_pose_rate_hz: {max_pose_rate_hz} must be > 0")
        self.pose_lease_s = pose_lease_s
        #: Mobile: the fastest its robot moves, m/s, as told to the server (0: the server's default).
        self.max_speed_mps = max_speed_mps
        if pose_source is not None and mount is None:
            raise InvalidArgument("pose_source: only a mobile camera (one with a mount) reads poses")
        self.pose_source = open_pose_source(pose_source) if pose_source is not None else None
        self._pose_reader: asyncio.Task[None] | None = None
        self.pose_updates = (
            PoseUpdates(
                self.registration,
                self.poses,
                distance_m=pose_update_distance_m,
                angle_deg=pose_update_angle_deg,
                max_rate_hz=max_pose_rate_hz,
            )
            if mount is not None
            else None
        )
        self.serve_frames = serve_frames
        names = (*SERVICE_NAMES, FRAME_STREAM_SERVICE) if serve_frames else SERVICE_NAMES
        self._endpoint = Endpoint(listen, names, self._add_servicers, security=self.security)
        self._watchdog: asyncio.Task[None] | None = None
        self.has_fresh_frame = True
        self._jobs: set[asyncio.Task[None]] = set()
        #: What one robot, or one callback listener, may hold of this camera's requests.
        self.shares = Shares(camera_id, max_continuous)
        self._callbacks = CallbackSender(security=self.security)
        # Reports of fused requests go to the server this node registers with, on a channel secured
        # as registration's (its TLS, its token).
        self._server_reports = CallbackSender(security=self.security, metadata=self.security.metadata())
        self._analyses: Analyses | None = None
        self._stopped = False
        # Handed to the server at registration; the server presents it on every forward, so this
        # node takes requests only from the server it registered with (see _ServerFacing).
        self.forward_secret = secrets.token_urlsafe(24)
        self.foxglove = foxglove
        self.foxglove_fps = check_fps(foxglove_fps, "foxglove_fps")
        if foxglove is not None:
            liveview.require("--foxglove")
        #: The live view (with `foxglove`), from start() on.
        self.live: CameraLiveView | None = None

    @property
    def port(self) -> int:
        return self._endpoint.port

    @property
    def registered(self) -> asyncio.Event:
        """Set once the node has registered with its server."""
        return self.registration.registered

    @property
    def address(self) -> str:
        """The address the server is told to dial."""
        if self.advertise:
            return self.advertise
        return dialable_address(self.listen, self.port, self.servers[0])

    def _add_servicers(self, server: aio.Server) -> None:
        detection_pb2_grpc.add_DetectObjectBoundaryServicer_to_server(_ServerFacing(self), server)
        if self.serve_frames:
            stream_pb2_grpc.add_FrameStreamServicer_to_server(_FrameStreaming(self), server)

    async def start(self) -> None:
        self.source.start()
        frame = await self.source.wait_first_frame(self.first_frame_timeout_s)
        image_size = frame.size
        if self.resolution is not None and image_size != self.resolution:
            raise InvalidArgument(
                f"resolution: the source gives {image_size[0]}x{image_size[1]}, not the configured "
                f"{self.resolution[0]}x{self.resolution[1]}; the homography belongs to one image size"
            )
        if self.mount is not None:
            # Detectors map to the robot's base frame; each report moves them by the pose at capture.
            self.homography = self.mount.base_homography(image_size)
        self.field_of_view = FieldOfView.compute(self.homography, image_size, self.max_range_m)
        self.view = CameraView(
            self.homography, self.field_of_view, image_size, camera_id=self.camera_id, min_area_px=self.min_area_px
        )
        self._start_detectors(self.view)
        self._heavy_pool = concurrent.futures.ThreadPoolExecutor(self.detect_workers, f"detect:{self.camera_id}")
        observers = [d for d in self.runners.values() if d.observes]
        self._analyses = Analyses(self.source, self._prefetch, self.camera_id, observers=observers)
        self._analyses.start()
        if self.foxglove is not None:
            # Before the node listens: a port the view cannot take stops the camera at start.
            self.live = CameraLiveView(self.camera_id, self.source, self.foxglove, fps=self.foxglove_fps)
            self.live.start()
        log.info(
            "camera %s: source %s gives %dx%d; field of view %.1f m²",
            self.camera_id,
            self.source.description,
            *image_size,
            self.field_of_view.floor.area,
        )
        await self.report_targets.resolve()
        await self._endpoint.start()
        log.info("camera %s listening on %s (advertised as %s)", self.camera_id, self._endpoint.address, self.address)
        if self.serve_frames and not self.security.token:
            log.warning(
                "camera %s: --serve-frames without --token-file: frames go only to a caller that presents "
                "this camera's token, so nobody can stream them",
                self.camera_id,
            )
        self.registration.start(
            registry_pb2.RegisterRequest(
                camera_id=self.camera_id,
                address=self.address,
                homography=homography_to_pb(self.homography),
                image_width=image_size[0],
                image_height=image_size[1],
                max_range_m=self.max_range_m,
                detector_kinds=list(self.kinds),
                forward_secret=self.forward_secret,
                mobile=self.mount is not None,
                pose_lease_s=self.pose_lease_s,
                max_speed_mps=self.max_speed_mps,
                frame="" if self.frame == DEFAULT_FRAME else self.frame,
            ),
            self.field_of_view.floor.area,
        )
        if self.pose_source is not None:
            self._pose_reader = asyncio.get_running_loop().create_task(self.pose_source.run(self.poses.push))
        if self.pose_updates is not None:
            self.pose_updates.start()
        self._watchdog = asyncio.get_running_loop().create_task(self._watch_frames())

    async def stop(self, grace: float = 2.0) -> None:
        if self._stopped:
            return
        self._stopped = True
        if self._watchdog is not None:
            self._watchdog.cancel()
            await asyncio.gather(self._watchdog, return_exceptions=True)
        if self._pose_reader is not None:
            self._pose_reader.cancel()
            await asyncio.gather(self._pose_reader, return_exceptions=True)
        if self.pose_updates is not None:
            await self.pose_updates.stop()
        await self.registration.stop()
        await self._endpoint.stop(grace)
        for job in list(self._jobs):
            job.cancel()
        await asyncio.gather(*self._jobs, return_exceptions=True)
        await self._callbacks.close()
        await self._server_reports.close()
        if self.live is not None:
            await self.live.stop()
        if self._analyses is not None:
            await asyncio.to_thread(self._analyses.stop)
        if self._heavy_pool is not None:
            self._heavy_pool.shutdown(wait=False, cancel_futures=True)
        for runner in self.runners.values():
            runner.close()
        await asyncio.to_thread(self.source.stop)
        log.info("camera %s stopped", self.camera_id)

    async def wait_for_termination(self) -> None:
        await self._endpoint.wait_for_termination()

    def push_pose(self, pose: Pose2, t: float | None = None) -> None:
        """A mobile camera's robot was at `pose` (map frame) at time t (seconds since the Unix
        epoch; None: now). Thread-safe. InvalidArgument for a pose or time that is not finite."""
        if self.mount is None:
            raise FailedPrecondition(f"camera {self.camera_id} is fixed (no mount): it takes no poses")
        self.poses.push(time.time() if t is None else t, pose)

    def frame_is_fresh(self) -> bool:
        frame = self.source.latest()
        return frame is not None and frame.age_s() <= self.max_frame_age_s

    async def _watch_frames(self) -> None:
        """Health follows the frames: NOT_SERVING while none is fresh. Registration is kept, so
        the camera does not flap in and out of routing while its source reconnects."""
        while True:
            await asyncio.sleep(min(0.5, self.max_frame_age_s / 2))
            fresh = self.frame_is_fresh()
            if fresh != self.has_fresh_frame:
                self.has_fresh_frame = fresh
                await self._endpoint.set_serving(fresh)
                if fresh:
                    log.info("camera %s: frames again from %s; SERVING", self.camera_id, self.source.description)
                else:
                    log.warning(
                        "camera %s: no frame newer than %.1f s from %s; NOT_SERVING until frames come back",
                        self.camera_id,
                        self.max_frame_age_s,
                        self.source.description,
                    )

    async def frames(
        self, max_fps: float, encode: Callable[[NDArray[np.uint8]], bytes]
    ) -> AsyncIterator[tuple[Frame, bytes]]:
        """Every new frame of the source (at most `max_fps` a second; 0: every one), encoded by
        `encode` in a thread: the baseline DRVS replaces, for --serve-frames."""
        period = 1.0 / max_fps if max_fps else 0.0
        loop = asyncio.get_running_loop()
        last_sequence = -1
        next_at = loop.time()
        while True:
            frame = self.source.latest()
            if frame is None or frame.sequence == last_sequence or loop.time() < next_at:
                await asyncio.sleep(FRAME_POLL_S)
                continue
            last_sequence = frame.sequence
            next_at = max(next_at + period, loop.time()) if period else 0.0
            yield frame, await asyncio.to_thread(encode, frame.image)

    # --- detectors ---------------------------------------------------------------------------

    def _start_detectors(self, view: CameraView) -> None:
        """Build every configured detector this process can run (drvs.camera.detectors); one whose
        configuration is wrong stops the camera here, at start."""
        built = build_detectors(self.detectors, view, self.detector_options)
        self.runners, self.kinds, self.unavailable = built.runners, built.kinds, built.unavailable
        log_detectors(self.camera_id, built)
        if not self.kinds:
            built.close()
            why = "; ".join(f"{p}: {e}" for p, e in self.unavailable.items())
            raise (FailedPrecondition if why else InvalidArgument)(
                f"detectors: camera {self.camera_id} would serve no object type" + (f" ({why})" if why else "")
            )

    async def _find(self, runner: Detector, analysis: FrameAnalysis, wanted: ObjectType) -> tuple[Detection, ...]:
        """The frame's objects of the key, found once: a request that arrives while another is
        finding them waits for that result instead of starting another search."""
        pending = analysis.pending.get(wanted.key)
        if pending is None:
            loop = asyncio.get_running_loop()
            pool = self._heavy_pool if runner.heavy else None
            search = functools.partial(run_detector, runner, analysis, wanted)
            pending = loop.run_in_executor(pool, analysis.found, wanted.key, search)
            analysis.pending[wanted.key] = pending
            if runner.heavy:
                self._heavy_running[wanted.key] = analysis

            def finished(_f: object) -> None:
                analysis.pending.pop(wanted.key, None)
                if self._heavy_running.get(wanted.key) is analysis:
                    del self._heavy_running[wanted.key]

            pending.add_done_callback(finished)
        found: tuple[Detection, ...] = await asyncio.shield(pending)
        return found

    def _prefetch(self, analysis: FrameAnalysis, filter_def: str) -> None:
        """The prefetcher's work for one filter on a new frame (light detectors only)."""
        wanted = object_type(filter_def)
        runner = self.kinds.get(wanted.kind)
        if runner is not None and not runner.heavy:
            analysis.found(wanted.key, lambda: run_detector(runner, analysis, wanted))

    # --- serving requests --------------------------------------------------------------------

    def accept(self, request: DetectionRequest, requester: str = "") -> None:
        """Take a request: check it against this camera (its detectors, its load, the robot's
        continuous requests here, counted by `requester`: whom the server knows the robot as)
        and start serving it; its reports go to its callback address."""
        if self.view is None:
            raise FailedPrecondition(f"camera {self.camera_id} is not started")
        wanted = object_type(request.filter_def)
        runner = self.kinds.get(wanted.kind)
        if runner is None:
            why = self.unavailable.get(wanted.kind) or self.unavailable.get(wanted.prefix)
            served = ", ".join(self.kinds) or "nothing"
            raise (InvalidArgument if why is None else FailedPrecondition)(
                f"filter_def: camera {self.camera_id} does not serve {wanted.kind!r} (it serves {served})"
                + (f"; {wanted.prefix}: {why.reason}" if why else "")
            )
        runner.check(wanted)
        robot: Robot = ("robot", requester) if requester else request.callback_address
        callback = request.callback_address
        if request.report_to_server:
            if not self.registration.registered.is_set():
                raise FailedPrecondition(
                    f"report_to_server: camera {self.camera_id} is not registered with its server "
                    f"({self.server_address}), so it has nowhere to report"
                )
            if request.report_address:
                self.report_targets.check(request.report_address)
            robot, callback = ("server", requester or request.robot_id), ""
        continuous = not request.continuous.single_shot
        self.shares.max_continuous = self.max_continuous
        self.shares.check(robot, callback, continuous)
        self._callbacks.check(callback)
        if log.isEnabledFor(logging.DEBUG):
            log.debug(
                "camera %s: request %s from robot %r: %s, %s",
                self.camera_id,
                request.request_id,
                request.robot_id,
                request.filter_def,
                "single shot"
                if request.continuous.single_shot
                else f"{request.continuous.rate_hz:g} Hz for {request.continuous.duration_s:g} s",
            )
        # The job's task copies this context: everything it logs carries the request id.
        token = logs.request_id.set(request.request_id)
        try:
            job = asyncio.get_running_loop().create_task(self._serve(request))
        finally:
            logs.request_id.reset(token)
        self._jobs.add(job)
        job.add_done_callback(self._jobs.discard)
        self.shares.hold(job, robot, callback, continuous)

    async def _serve(self, request: DetectionRequest) -> None:
        loop = asyncio.get_running_loop()
        offsets = request.continuous.report_times()  # lazy: nothing is allocated per report time
        last = len(offsets) - 1
        start = loop.time()
        if request.report_to_server:
            # The server that forwarded the request says where (several servers share a registry).
            sender, address = self._server_reports, request.report_address or self.servers[0]
            if not await self.report_targets.allowed(address):
                return  # (a name that resolved elsewhere: logged)
        else:
            sender, address = self._callbacks, request.callback_address
        try:
            for sequence, offset in enumerate(offsets):
                delay = start + offset - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                report = await self._look(request, sequence, final=sequence == last)
                sending = time.perf_counter()
                sent = await sender.send(address, report, not request.omit_outlines, request.report_key)
                metrics.STAGE_REPORT.observe(time.perf_counter() - sending)
                (metrics.REPORTS_SENT if sent else metrics.REPORTS_DROPPED).inc()
                if not sent:
                    log.debug("camera %s: request %s cancelled by the robot", self.camera_id, request.request_id)
                    return
                metrics.DETECTIONS.inc(len(report.detections))
        except DrvsError as exc:
            log.warning("camera %s: request %s: %s", self.camera_id, request.request_id, exc)

    async def _look(self, request: DetectionRequest, sequence: int, final: bool) -> DetectionReport:
        frame = self.source.latest()
        frame_age = frame.age_s() if frame is not None else math.inf
        # Every report of this look names the request, this camera, its place and the frame's time.
        report = functools.partial(
            DetectionReport,
            request_id=request.request_id,
            camera_id=self.camera_id,
            capture_time=frame.capture_time if frame is not None else 0.0,
            sequence=sequence,
            final=final,
        )
        if frame is None or frame_age > self.max_frame_age_s:
            age = "no frame" if frame is None else f"newest frame is {frame_age:.1f} s old"
            return report(error=f"camera {self.camera_id}: no fresh frame ({age})", error_code="UNAVAILABLE")
        assert self._analyses is not None
        wanted = object_type(request.filter_def)
        runner = self.kinds[wanted.kind]
        analysis = self._analyses.for_frame(frame)
        if runner.observes:
            self._analyses.asked(runner)
        if not runner.heavy:
            self._analyses.want(analysis, request.filter_def)
        elif analysis.cached_blobs(wanted.key) is None:
            # One heavy search per key at a time: a request that arrives while one runs on an older
            # frame takes its result (tens of milliseconds older) instead of queueing another search
            # behind it, which would delay every answer and keep the pool busy for nobody.
            analysis = self._heavy_running.get(wanted.key, analysis)
            frame = analysis.frame
        started = time.perf_counter()
        found = analysis.cached_blobs(wanted.key)
        if found is None:
            found = await self._find(runner, analysis, wanted)
        narrowed = runner.narrow(found, wanted)
        pose = None
        if self.mount is not None:
            pose = self.poses.at(frame.capture_time)
            if pose is None:
                latest = self.poses.latest()
                gap = "no pose yet" if latest is None else f"newest pose {frame.capture_time - latest[0]:+.2f} s away"
                return report(
                    capture_time=frame.capture_time,
                    error=f"camera {self.camera_id}: no pose within {self.poses.max_gap_s:g} s of the frame's "
                    f"capture ({gap})",
                    error_code="UNAVAILABLE",
                )
            narrowed = tuple(move_detection(d, pose) for d in narrowed)
        # Selecting what the frame holds is microseconds: done here, on the event loop, rather than
        # paying a hop to a thread and back.
        detections = select(narrowed, request.region)
        metrics.STAGE_DETECT.observe(time.perf_counter() - started)
        if self.live is not None:
            self.live.show(request.request_id, detections)
        return report(capture_time=frame.capture_time, detections=tuple(detections), camera_pose=pose)


#: What a camera answers on the robot-facing methods of the service it shares with the server.
NOT_SERVED_HERE = (
    "{method}: a camera takes requests only from the server it registered with, on DetectBatches; "
    "robots send requests to the server"
)


class _ServerFacing(detection_pb2_grpc.DetectObjectBoundaryServicer):
    """Converts and delegates: the server's request batches to `CameraNode.accept`.

    The camera serves the DetectObjectBoundary service the robots use on the server, but only its
    DetectBatches method: the server forwards on nothing else. DetectObjects and DetectStream
    answer UNIMPLEMENTED (no caller, so no code path to keep, secure and test)."""

    def __init__(self, node: CameraNode) -> None:
        self._node = node

    def _accept(self, message: detection_pb2.DetectionRequest) -> detection_pb2.DetectionReply:
        request = request_from_pb(message, require_request_id=True)
        self._node.accept(request, message.requester)
        return detection_pb2.DetectionReply(request_id=request.request_id, camera_ids=[self._node.camera_id])

    async def DetectObjects(
        self, message: detection_pb2.DetectionRequest, context: aio.ServicerContext[Any, Any]
    ) -> detection_pb2.DetectionReply:
        await context.abort(grpc.StatusCode.UNIMPLEMENTED, NOT_SERVED_HERE.format(method="DetectObjects"))
        raise AssertionError("abort raises")

    async def DetectStream(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequest],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReply]:
        await context.abort(grpc.StatusCode.UNIMPLEMENTED, NOT_SERVED_HERE.format(method="DetectStream"))
        yield detection_pb2.DetectionReply()  # never reached: abort raises

    async def DetectBatches(
        self,
        request_iterator: AsyncIterator[detection_pb2.DetectionRequests],
        context: aio.ServicerContext[Any, Any],
    ) -> AsyncIterator[detection_pb2.DetectionReplies]:
        await check_caller(self._node, context, "requests", request_iterator)
        async for replies in serve_request_batches(request_iterator, self._accept, f"camera {self._node.camera_id}"):
            yield replies


def encode_frame(image: NDArray[np.uint8], encoding: int, quality: int) -> bytes:
    if encoding == stream_pb2.FRAME_ENCODING_RAW_BGR:
        return image.tobytes()
    return encode_jpeg(image, quality)


class _FrameStreaming(stream_pb2_grpc.FrameStreamServicer):
    """The baseline DRVS replaces: every frame to the client (only with --serve-frames)."""

    def __init__(self, node: CameraNode) -> None:
        self._node = node

    async def StreamFrames(
        self, request: stream_pb2.StreamFramesRequest, context: aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[stream_pb2.VideoFrame]:
        # Only for whoever holds this camera's token: never the forward secret, which the server holds.
        await check_caller(self._node, context, FRAME_STREAMS)
        encodings = (stream_pb2.FRAME_ENCODING_RAW_BGR, stream_pb2.FRAME_ENCODING_JPEG)
        if request.encoding not in encodings:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "encoding: must be RAW_BGR or JPEG")
        quality = request.jpeg_quality or 80
        if not 1 <= quality <= 100:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "jpeg_quality: must be 1-100")
        if not (math.isfinite(request.max_fps) and 0 <= request.max_fps <= 1000):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "max_fps: must be 0-1000")
        async for frame, data in self._node.frames(
            request.max_fps, functools.partial(encode_frame, encoding=request.encoding, quality=quality)
        ):
            msg = stream_pb2.VideoFrame(
                camera_id=self._node.camera_id,
                sequence=frame.sequence,
                width=frame.size[0],
                height=frame.size[1],
                encoding=request.encoding,
                data=data,
            )
            msg.capture_time.FromNanoseconds(round(frame.capture_time * 1e9))
            yield msg
