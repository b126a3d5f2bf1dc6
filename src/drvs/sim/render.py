"""Render a simulated camera's frames: the floor plan and its objects seen through the camera's
pinhole model (pose -> homography, OpenCV warp), printed ArUco markers on the floor and on the
robot's top plate, the robot, lighting and sensor noise."""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Point, Polygon

from drvs.core.geometry import FieldOfView, Homography
from drvs.core.imaging import fill_polygon
from drvs.sim.scenario import QUIET_ZONE_CELLS, ArucoDef, CameraDef, Scenario, ScoutDef
from drvs.sim.scene import fill_floor_shape

FLOOR_BGR = (128, 132, 136)
WALL_BGR = (72, 72, 72)
BEYOND_BGR = (205, 200, 196)  # above the horizon and outside the building
TEXTURE_PX_PER_M = 100.0
_NOISE_BANK = 8
#: A printed marker's black and its paper's white (not 0 and 255: ink and paper under room light).
INK_BGR = 28
PAPER_BGR = 232
#: At most this many pixels per marker cell in the image warped onto the floor; it gets about two
#: of its pixels per camera pixel, so that bilinear warping does not alias.
_MARKER_CELL_PX = 24


class CameraRenderer:
    """Everything static is warped once; each frame adds the robot, lighting and noise.

    A frame is a pure function of (seed, camera, robot pose version, world time): the same seed
    gives the same pixels for the same world state, whatever the timing of the processes. Moving
    obstacles are painted per frame where their path puts them at the world time.
    """

    def __init__(self, scenario: Scenario, camera: CameraDef | ScoutDef, seed: int = 0) -> None:
        self.scenario = scenario
        self.camera = camera
        #: The scout that carries this camera (its view moves with it), or None for a fixed camera.
        self.scout = camera if isinstance(camera, ScoutDef) else None
        camera_id = camera.camera_id if isinstance(camera, ScoutDef) else camera.id
        self.size = camera.resolution
        width, height = self.size
        self._texture, self._world_to_texture = _floor_texture(scenario, seed)
        # Uneven lighting across the image (a window on one side), fixed per camera.
        rng = np.random.default_rng([seed, _stable_hash(camera_id)])
        swing = scenario.render.lighting
        self._ramp = 1.0 + swing * np.linspace(-0.5, 0.5, width, dtype=np.float32) * rng.choice([-1.0, 1.0])
        self._phase = float(rng.uniform(0, 2 * math.pi))
        sigma = scenario.render.noise_sigma
        self._noise_up: list[NDArray[np.uint8]] = []
        self._noise_down: list[NDArray[np.uint8]] = []
        for _ in range(_NOISE_BANK if sigma > 0 else 0):
            n = rng.normal(0.0, sigma, (height, width, 3))
            self._noise_up.append(np.clip(n, 0, 255).astype(np.uint8))
            self._noise_down.append(np.clip(-n, 0, 255).astype(np.uint8))
        self._others = [s for s in scenario.scouts if s is not self.scout]
        self._look_through(camera.homography_at(0.0) if isinstance(camera, ScoutDef) else camera.homography)

    def _look_through(self, homography: Homography) -> None:
        """Warp the static world (floor, walls, still objects, markers) through `homography`."""
        self.homography = homography
        self._to_image = homography.inverse()
        width, height = self.size
        fov = FieldOfView.compute(homography, self.size, max_range_m=1000.0)
        self._fov_floor = fov.floor
        image_to_texture = self._world_to_texture @ homography.matrix
        static = np.asarray(
            cv2.warpPerspective(
                self._texture,
                image_to_texture,
                (width, height),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=BEYOND_BGR,
            ),
            dtype=np.uint8,
        )
        # Above the horizon the warp would show the floor behind the camera: paint it as distance.
        mask = np.zeros((height, width), dtype=np.uint8)
        fill_polygon(mask, np.asarray(fov.image.exterior.coords)[:-1], 255)
        static[mask == 0] = BEYOND_BGR
        self._ahead = float(np.sign(self._to_image.projective_scale(np.asarray(fov.floor.centroid.coords))[0]))
        for marker in self.scenario.aruco_markers:
            self.draw_marker(static, marker)
        self._static = np.clip(static.astype(np.float32) * self._ramp[None, :, None], 0, 255).astype(np.uint8)

    @property
    def moving(self) -> bool:
        """Does each frame depend on world time (moving obstacles, scouts), not only on the robot?"""
        return bool(self.scenario.moving_obstacles or self.scenario.scouts)

    def draw_marker(
        self, image: NDArray[np.uint8], marker: ArucoDef, at: tuple[float, float] = (0.0, 0.0), turn_deg: float = 0.0
    ) -> None:
        """Paint a printed marker (its quiet zone included) where it lies on the floor: OpenCV's marker
        image warped through floor -> image, blended at its edges. Skipped if any of it is behind the camera."""
        paper = marker.corners(at, turn_deg, side=marker.printed_size)
        if np.any(np.sign(self._to_image.projective_scale(paper)) != self._ahead):
            return
        draw_marker_image(image, marker, self._to_image.apply(paper))

    def render(
        self, robot_xy: tuple[float, float] | None, version: int, robot_theta: float = 0.0, world_time: float = 0.0
    ) -> NDArray[np.uint8]:
        """A BGR frame of world state `version` with the robot at robot_xy (None: no robot), heading
        robot_theta (radians CCW from x; it turns the marker on its top plate), and the moving
        obstacles and scouts where they are at `world_time` (seconds since the world's clock
        started); a scout's camera looks from where its scout is then.

        Lighting drifts and the sensor noise changes as the world state advances.
        """
        if self.scout is not None:
            self._look_through(self.scout.homography_at(world_time))
        image = self._static.copy()
        for other in self._others:
            fill_floor_shape(image, other.body_at(world_time), self._to_image, self._fov_floor, other.bgr)
        for obstacle in self.scenario.moving_obstacles:
            if obstacle.paint is not None:
                shape = obstacle.shape_at(world_time)
                fill_floor_shape(image, shape, self._to_image, self._fov_floor, obstacle.paint)
        if robot_xy is not None:
            plate = Point(robot_xy).buffer(self.scenario.robot.radius, quad_segs=16)
            fill_floor_shape(image, plate, self._to_image, self._fov_floor, self.scenario.robot.color.bgr)
            if self.scenario.robot.marker is not None:
                self.draw_marker(image, self.scenario.robot.marker, robot_xy, math.degrees(robot_theta))
        return self.finish(image, version)

    def finish(self, painted: NDArray[np.uint8], version: int) -> NDArray[np.uint8]:
        """The lighting's drift and the sensor's noise of world state `version` over a painted frame."""
        gain = 1.0 + self.scenario.render.lighting * math.sin(2 * math.pi * version / 70.0 + self._phase)
        image = cv2.convertScaleAbs(painted, alpha=gain)
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
        if obj.paint is not None and not obj.moving:  # moving ones are painted per frame
            fill(obj.shape, obj.paint)
    return texture, world_to_texture


@functools.lru_cache(maxsize=64)
def marker_image(marker: ArucoDef, cell_px: int = _MARKER_CELL_PX) -> NDArray[np.uint8]:
    """OpenCV's image of the marker with its white quiet zone, in grey levels of ink and paper."""
    cells = marker.cells
    bits = cv2.aruco.generateImageMarker(marker.cv_dictionary, marker.id, cells * cell_px)
    zone = QUIET_ZONE_CELLS * cell_px
    printed = cv2.copyMakeBorder(bits, zone, zone, zone, zone, cv2.BORDER_CONSTANT, value=255)
    return np.asarray(INK_BGR + (printed.astype(np.uint16) * (PAPER_BGR - INK_BGR) // 255), dtype=np.uint8)


def draw_marker_image(image: NDArray[np.uint8], marker: ArucoDef, corners_px: NDArray[np.float64]) -> None:
    """Warp the printed marker so that its paper's corners (OpenCV order) land on `corners_px`, and
    blend it in by its warped coverage (anti-aliased edges). Works on the bounding box only."""
    height, width = image.shape[:2]
    x0, y0 = np.floor(corners_px.min(axis=0)).astype(int) - 1
    x1, y1 = np.ceil(corners_px.max(axis=0)).astype(int) + 2
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x0 >= x1 or y0 >= y1:
        return
    longest = float(np.max(np.linalg.norm(corners_px - np.roll(corners_px, 1, axis=0), axis=1)))
    cell_px = min(_MARKER_CELL_PX, max(2, math.ceil(2 * longest / (marker.cells + 2 * QUIET_ZONE_CELLS))))
    printed = marker_image(marker, cell_px)
    side = printed.shape[0]
    # Pixel centres are at integers: the image's outer edges are at -0.5 and side - 0.5.
    src = np.array([[-0.5, -0.5], [side - 0.5, -0.5], [side - 0.5, side - 0.5], [-0.5, side - 0.5]], np.float32)
    dst = (corners_px - np.array([x0, y0])).astype(np.float32)
    warp = cv2.getPerspectiveTransform(src, dst)
    size = (x1 - x0, y1 - y0)
    grey = cv2.warpPerspective(printed, warp, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    cover = cv2.warpPerspective(np.full_like(printed, 255), warp, size, flags=cv2.INTER_LINEAR)
    roi = image[y0:y1, x0:x1].astype(np.float32)
    alpha = cover.astype(np.float32)[:, :, None] / 255.0
    roi = roi * (1.0 - alpha) + grey.astype(np.float32)[:, :, None] * alpha
    image[y0:y1, x0:x1] = np.clip(roi + 0.5, 0, 255).astype(np.uint8)


def _stable_hash(text: str) -> int:
    return sum((i + 1) * ord(c) for i, c in enumerate(text)) % (2**31)
