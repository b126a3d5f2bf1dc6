"""Render a simulated camera's frames: the floor plan and its objects seen through the camera's
pinhole model (pose -> homography, OpenCV warp), the robot's marker, lighting and sensor noise."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Point, Polygon

from drvs.geometry import FieldOfView
from drvs.sim.scenario import CameraDef, Scenario
from drvs.sim.scene import fill_floor_shape, fill_polygon

FLOOR_BGR = (128, 132, 136)
WALL_BGR = (72, 72, 72)
BEYOND_BGR = (205, 200, 196)  # above the horizon and outside the building
TEXTURE_PX_PER_M = 100.0
_NOISE_BANK = 8


class CameraRenderer:
    """Everything static is warped once; each frame adds the robot, lighting and noise.

    A frame is a pure function of (seed, camera, robot pose version): the same seed gives the
    same pixels for the same world state, whatever the timing of the processes.
    """

    def __init__(self, scenario: Scenario, camera: CameraDef, seed: int = 0) -> None:
        self.scenario = scenario
        self.camera = camera
        self.size = camera.resolution
        self.homography = camera.homography
        self._to_image = self.homography.inverse()
        width, height = self.size
        fov = FieldOfView.compute(self.homography, self.size, max_range_m=1000.0)
        self._fov_floor = fov.floor
        texture, world_to_texture = _floor_texture(scenario, seed)
        image_to_texture = world_to_texture @ self.homography.matrix
        static = cv2.warpPerspective(
            texture,
            image_to_texture,
            (width, height),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=BEYOND_BGR,
        )
        # Above the horizon the warp would show the floor behind the camera: paint it as distance.
        mask = np.zeros((height, width), dtype=np.uint8)
        fill_polygon(mask, np.asarray(fov.image.exterior.coords)[:-1], 255)
        static[mask == 0] = BEYOND_BGR
        # Uneven lighting across the image (a window on one side), fixed per camera.
        rng = np.random.default_rng([seed, _stable_hash(camera.id)])
        swing = scenario.render.lighting
        ramp = 1.0 + swing * np.linspace(-0.5, 0.5, width, dtype=np.float32) * rng.choice([-1.0, 1.0])
        self._static = np.clip(static.astype(np.float32) * ramp[None, :, None], 0, 255).astype(np.uint8)
        self._phase = float(rng.uniform(0, 2 * math.pi))
        sigma = scenario.render.noise_sigma
        self._noise_up: list[NDArray[np.uint8]] = []
        self._noise_down: list[NDArray[np.uint8]] = []
        for _ in range(_NOISE_BANK if sigma > 0 else 0):
            n = rng.normal(0.0, sigma, (height, width, 3))
            self._noise_up.append(np.clip(n, 0, 255).astype(np.uint8))
            self._noise_down.append(np.clip(-n, 0, 255).astype(np.uint8))

    def render(self, robot_xy: tuple[float, float] | None, version: int) -> NDArray[np.uint8]:
        """A BGR frame of world state `version` with the robot's marker at robot_xy (None: no robot).

        Lighting drifts and the sensor noise changes as the world state advances.
        """
        image = self._static.copy()
        if robot_xy is not None:
            marker = Point(robot_xy).buffer(self.scenario.robot.radius, quad_segs=16)
            fill_floor_shape(image, marker, self._to_image, self._fov_floor, self.scenario.robot.color.bgr)
        gain = 1.0 + self.scenario.render.lighting * math.sin(2 * math.pi * version / 70.0 + self._phase)
        image = cv2.convertScaleAbs(image, alpha=gain)
        if self._noise_up:
            i = (version * 5) % len(self._noise_up)
            image = cv2.subtract(cv2.add(image, self._noise_up[i]), self._noise_down[i])
        return np.asarray(image, dtype=np.uint8)


def _floor_texture(scenario: Scenario, seed: int = 0) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """A top-down image of the floor plan and objects, and the world -> texture pixel matrix.

    The floor gets a colourless carpet-like texture (noise at several scales): real floors are not
    flat colour, and a flat floor would make compressed video unrealistically small.
    """
    x0, y0, x1, y1 = scenario.bounds
    s = TEXTURE_PX_PER_M
    width, height = math.ceil((x1 - x0) * s), math.ceil((y1 - y0) * s)
    world_to_texture = np.array([[s, 0.0, -x0 * s], [0.0, -s, y1 * s], [0.0, 0.0, 1.0]])
    texture = np.empty((height, width, 3), dtype=np.uint8)
    texture[:] = FLOOR_BGR
    amplitude = scenario.render.floor_texture
    if amplitude > 0:
        rng = np.random.default_rng([seed, 7])
        grain = np.zeros((height, width), dtype=np.float32)
        for cell, weight in ((2, 0.6), (8, 0.3), (40, 0.4)):
            coarse = rng.normal(0.0, 1.0, (max(2, height // cell), max(2, width // cell))).astype(np.float32)
            grain += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_LINEAR)
        shaded = texture.astype(np.float32) + amplitude * grain[:, :, None]
        texture = np.clip(shaded, 0, 255).astype(np.uint8)

    def fill(poly: Polygon, bgr: tuple[int, int, int]) -> None:
        pts = np.asarray(poly.exterior.coords)[:-1]
        fill_polygon(texture, pts @ world_to_texture[:2, :2].T + world_to_texture[:2, 2], bgr)

    for wall in scenario.walls:
        fill(wall, WALL_BGR)
    for obj in scenario.objects:
        if obj.color is not None:
            fill(obj.shape, obj.color.bgr)
    return texture, world_to_texture


def _stable_hash(text: str) -> int:
    return sum((i + 1) * ord(c) for i, c in enumerate(text)) % (2**31)
