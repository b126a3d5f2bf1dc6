"""The fusion benchmark's scene, shared by its in-process parts (drvs_bench.fusion: accuracy,
tracking) and its networked part (drvs_bench.fusion_cost): two overlapping simulated cameras, yellow
discs on the floor, and the cameras as camera nodes (render, detect, report through the wire).
Its own module so that neither part imports the other for it."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Point, Polygon, box

from drvs.core.filters import object_type
from drvs.core.geometry import FieldOfView, Homography, homography_from_pose
from drvs.core.model import DetectionReport
from drvs.detectors import REGISTRY, CameraView, Detector, Frame, FrameAnalysis, select
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import CameraDef, Scenario, parse_scenario
from drvs.sim.scene import fill_floor_shape
from drvs.wire.convert import report_from_pb, report_to_pb

from .common import YELLOW

#: Two cameras facing each other across a 9 m room, 8.5 m apart: a disc near one is far from the
#: other, which sees it with coarser pixels (its ground sampling distance there is larger). They
#: overlap over about 25 m²; cam-b is offset 0.8 m and mounted a little higher, so the two views are
#: not mirror images.
SCENE_TEXT = """
name: bench-fusion-overlap
floor_plan: {bounds: [-4, -1, 5, 10], walls: []}
colors:
  yellow: {filter_def: hsv_014110130035225200, bgr: [57, 143, 165]}
  blue:   {filter_def: hsv_100120080130255255, bgr: [167, 100, 42]}
cameras:
  - {id: cam-a, position: [0.0, 0.0, 3.0], yaw_deg: 90, pitch_deg: 40, hfov_deg: 60, resolution: [640, 480], fps: 20,
     max_range_m: 6.5}
  - {id: cam-b, position: [0.8, 8.5, 3.2], yaw_deg: -90, pitch_deg: 38, hfov_deg: 60, resolution: [640, 480], fps: 20,
     max_range_m: 6.5}
objects: []
robot: {start: [4.5, 9.5], goal: [4.5, 9.0], radius: 0.2, color: blue}
mission: navigate
render: {noise_sigma: 3, lighting: 0.08, floor_texture: 10}
"""
#: A calibration's error, one standard deviation: of the yaw and the pitch (degrees), of each
#: coordinate of the position (m). A camera 3 m up that is 0.2 degrees off in pitch misplaces a
#: point 5 m away by about 4 cm; the two cameras' errors differ, as two calibrations' do.
CALIBRATION_ERROR = (0.2, 0.02)
#: The request's region: the whole room (both views).
REGION = (-4.0, -1.0, 5.0, 10.0)


def fusion_scenario() -> Scenario:
    return parse_scenario(SCENE_TEXT, "drvs_bench.fusion_scene.SCENE_TEXT")


class ObjectsRenderer(CameraRenderer):
    """The simulator's camera renderer, with flat objects drawn per frame where they are at that
    instant (as it draws the robot): its static floor is warped once, not once per placement."""

    def render_objects(self, shapes: Sequence[tuple[Polygon, tuple[int, int, int]]], version: int) -> NDArray[np.uint8]:
        image = self._static.copy()
        for shape, bgr in shapes:
            fill_floor_shape(image, shape, self._to_image, self._fov_floor, bgr)
        return self.finish(image, version)


@dataclasses.dataclass
class Disc:
    """A yellow disc on the floor: the truth."""

    xy: tuple[float, float]
    radius: float

    @property
    def shape(self) -> Polygon:
        return Point(self.xy).buffer(self.radius, quad_segs=16)


class Cameras:
    """The scene's cameras as camera nodes: render, detect, report (and through the wire)."""

    def __init__(
        self,
        seed: int,
        miscalibrated: bool = False,
        scenario: Scenario | None = None,
        calibration_error: tuple[float, float] = CALIBRATION_ERROR,
        region: tuple[float, float, float, float] = REGION,
        exact_error: bool = False,
    ) -> None:
        """miscalibrated: each camera's homography (what it detects with and registers with the server)
        comes from a pose off the true one by `calibration_error` (degrees, metres; drawn from the seed);
        the pixels come from the true pose, as a real camera's do whatever its calibration says.
        exact_error: the error is `calibration_error` in size, not its standard deviation: the position off
        by that many metres in a random direction, yaw and pitch each by that many degrees, up or down.
        scenario: another scene than this module's two cameras (its yellow colour is the discs'), with
        the request's `region`."""
        self.scenario = scenario or fusion_scenario()
        self.yellow = self.scenario.colors["yellow"].bgr
        self.cameras: list[CameraDef] = list(self.scenario.cameras)
        self.renderers = [ObjectsRenderer(self.scenario, cam, seed=seed + k) for k, cam in enumerate(self.cameras)]
        self.detectors: list[Detector] = []
        self.homographies: dict[str, Homography] = {}
        rng = np.random.default_rng([seed, 43])
        for cam in self.cameras:
            h = cam.homography
            if miscalibrated:
                degrees, metres = calibration_error
                if exact_error:
                    shift = rng.normal(0.0, 1.0, 3)
                    x, y, z = (
                        v + float(d) for v, d in zip(cam.position, shift / np.linalg.norm(shift) * metres, strict=True)
                    )
                    yaw, pitch = (v + degrees * float(rng.choice([-1.0, 1.0])) for v in (cam.yaw_deg, cam.pitch_deg))
                else:
                    x, y, z = (v + float(rng.normal(0.0, metres)) for v in cam.position)
                    yaw, pitch = (v + float(rng.normal(0.0, degrees)) for v in (cam.yaw_deg, cam.pitch_deg))
                h = homography_from_pose((x, y, z), yaw, pitch, cam.hfov_deg, cam.resolution)
            fov = FieldOfView.compute(h, cam.resolution, cam.max_range_m)
            view = CameraView(h, fov, cam.resolution, camera_id=cam.id)
            self.detectors.append(REGISTRY["hsv"](view, None))
            self.homographies[cam.id] = h
        self.fovs = {cam.id: cam.field_of_view.floor for cam in self.cameras}
        self.wanted = object_type(YELLOW)
        self.region = box(*region)
        self.version = 0

    @property
    def overlap(self) -> Polygon:
        result: Polygon = shapely.intersection_all(list(self.fovs.values()))
        return result

    def homography_of(self, camera_id: str) -> Homography | None:
        return self.homographies.get(camera_id)

    def seen_by(self, disc: Disc) -> list[str]:
        """The cameras whose field of view holds the whole disc."""
        shape = disc.shape
        return [cid for cid, fov in self.fovs.items() if shape.within(fov)]

    def reports(
        self, discs: Sequence[Disc], at: float, request_id: str = "bench", lag_s: Sequence[float] = ()
    ) -> list[DetectionReport]:
        """Each camera's report of one look at the discs (camera k's frame taken lag_s[k] after `at`)."""
        self.version += 1
        out = []
        for k, (cam, renderer, detector) in enumerate(zip(self.cameras, self.renderers, self.detectors, strict=True)):
            image = renderer.render_objects([(d.shape, self.yellow) for d in discs], self.version)
            capture = at + (lag_s[k] if k < len(lag_s) else 0.0)
            analysis = FrameAnalysis(Frame(image, capture, self.version))
            found = detector.find(analysis, self.wanted)
            detections = select(detector.narrow(found, self.wanted), self.region)
            report = DetectionReport(request_id, cam.id, capture, 0, True, tuple(detections))
            # What the server gets: the camera's report through the wire format (float32, simplified outline).
            out.append(report_from_pb(report_to_pb(report, outlines=True), YELLOW))
        return out
