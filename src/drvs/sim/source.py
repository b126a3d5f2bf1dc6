"""A camera node frame source that renders the simulated world (`drvs-camera --source sim://HOST:PORT`)."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import grpc

from drvs.core.errors import Unavailable
from drvs.core.frames import NewestFrame
from drvs.sim.render import CameraRenderer
from drvs.sim.world import fetch_scene
from drvs.v1 import sim_pb2, sim_pb2_grpc
from drvs.wire import _grpc

log = logging.getLogger("drvs.sim.source")
SCHEME = "sim://"


class SimSource(NewestFrame):
    """Renders this camera's view of the world at its frame rate, and at once whenever the robot moves.

    Frames carry real capture times; their pixels depend only on the world's state: the robot's
    pose and, when obstacles move, the world time of the capture (Unix time minus the clock's start).
    """

    def __init__(self, spec: str, camera_id: str) -> None:
        self.world = spec[len(SCHEME) :] if spec.startswith(SCHEME) else spec
        self.camera_id = camera_id
        self.description = f"{SCHEME}{self.world} ({camera_id})"
        self._lock: threading.Condition
        super().__init__(threading.Condition())
        self._stop = threading.Event()
        self._robot: tuple[float, float] | None = None
        self._robot_theta = 0.0
        self._robot_version = -1
        self._clock_start = 0.0
        self._threads: list[threading.Thread] = []
        self._channel: grpc.Channel | None = None
        self._watch: Any = None
        self.error: str | None = None

    def start(self) -> None:
        self._channel = grpc.insecure_channel(self.world, options=_grpc.CHANNEL_OPTIONS)
        stub = sim_pb2_grpc.SimulatedWorldStub(self._channel)
        try:
            scenario, seed = fetch_scene(self._channel, self.world, 10)
        except Unavailable as exc:
            raise OSError(f"source {self.description}: {exc}") from None
        camera = scenario.scout_camera(self.camera_id) or scenario.camera(self.camera_id)
        self.renderer = CameraRenderer(scenario, camera, seed=seed)
        self.fps = camera.fps
        self._watch = stub.WatchRobot(sim_pb2.WatchRobotRequest())
        self._threads = [
            threading.Thread(target=self._follow_robot, name="sim-watch", daemon=True),
            threading.Thread(target=self._render_loop, name="sim-render", daemon=True),
        ]
        for t in self._threads:
            t.start()
        log.info("source %s: rendering %dx%d at %g fps", self.description, *self.renderer.size, self.fps)

    def stop(self) -> None:
        self._stop.set()
        if self._watch is not None:
            self._watch.cancel()
        with self._lock:
            self._lock.notify_all()
        for t in self._threads:
            t.join(timeout=5)
        if self._channel is not None:
            self._channel.close()

    def _follow_robot(self) -> None:
        try:
            for pose in self._watch:
                with self._lock:
                    self._robot = (pose.x, pose.y)
                    self._robot_theta = pose.theta
                    self._robot_version = pose.version
                    self._clock_start = pose.clock_start_unix
                    self._lock.notify_all()
        except grpc.RpcError as exc:
            if not self._stop.is_set():
                self.error = f"world stream ended: {exc.code().name}"
                log.warning("source %s: %s", self.description, self.error)

    def _render_loop(self) -> None:
        period = 1.0 / self.fps
        rendered_version = -2
        image = None
        moving = self.renderer.moving
        while not self._stop.is_set():
            with self._lock:
                if self._robot_version == rendered_version:
                    self._lock.wait(period)  # a new frame at the frame rate, or at once when the robot moves
                robot, theta, version, clock_start = (
                    self._robot, self._robot_theta, self._robot_version, self._clock_start
                )  # fmt: skip
            if self._stop.is_set():
                return
            now = time.time()
            if moving and clock_start:  # obstacles and scouts move with world time: every frame differs
                image = self.renderer.render(robot, max(version, 0), theta, max(0.0, now - clock_start))
            elif image is None or version != rendered_version:  # pixels depend only on the world state
                image = self.renderer.render(robot, max(version, 0), theta)
            self._keep(image, now, time.monotonic())
            rendered_version = version
