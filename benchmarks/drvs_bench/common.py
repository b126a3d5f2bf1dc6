"""What the benchmarks share: a recorded two-camera scene, process CPU sampling, the machine."""

from __future__ import annotations

import asyncio
import json
import os
import platform
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from drvs.core.homography_file import save_homography
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import load_scenario
from drvs.sim.scene import RecordedCamera, write_video
from drvs.tools.launch import ManagedProcess
from drvs.tools.launch import cpu_seconds as cpu_seconds  # re-exported for the benchmarks

YELLOW = "hsv_014110130035225200"
IMAGE_SIZE = (640, 480)
FPS = 20.0
SCENE = Path(__file__).parent / "scene.yaml"
#: Covers cam1's and cam2's fields of view (the paper benchmark's two cameras).
BOTH_REGION = (-6.0, 0.0, 26.0, 10.0)
#: Covers all three cameras' fields of view.
ALL_REGION = (-6.0, 0.0, 46.0, 10.0)

#: Real footage of people walking (Debian's opencv-doc; ./run test installs it where it can).
VTEST = Path("/usr/share/doc/opencv-doc/examples/data/vtest.avi")
#: The people cameras (drvs-bench paper's people modes) play vtest.avi at its own 10 fps, scaled
#: to IMAGE_SIZE, with the pose fitted to its people (5.6 m up, 26 degrees down, 60 degree lens:
#: tests/detectors/test_people.py's; the people detector searches by it), 100 m along x from the colour
#: scene: no request for one floor reaches the other's cameras.
PEOPLE_POSE = ((100.0, 0.0, 5.6), 90.0, 26.0, 60.0)
PEOPLE_MAX_RANGE_M = 40.0
#: Covers the people cameras' fields of view (and nothing of the colour scene's).
PEOPLE_REGION = (60.0, 0.0, 140.0, 60.0)
#: Frames of vtest.avi each people camera loops over: camera k plays [k * 400, k * 400 + 200).
PEOPLE_FRAMES = 200


def record_people(directory: Path, cameras: int = 2) -> dict[str, RecordedCamera] | None:
    """`cameras` looping videos of different stretches of vtest.avi at IMAGE_SIZE, with their
    homography files; None when the footage is not installed."""
    import cv2
    import numpy as np
    from numpy.typing import NDArray

    from drvs.core.geometry import homography_from_pose

    if not VTEST.is_file():
        return None
    cap = cv2.VideoCapture(str(VTEST))
    fps = float(cap.get(cv2.CAP_PROP_FPS)) or 10.0
    frames: list[NDArray[np.uint8]] = []
    try:
        while len(frames) < 400 * (cameras - 1) + PEOPLE_FRAMES:
            ok, image = cap.read()
            if not ok:
                break
            frames.append(np.asarray(cv2.resize(image, IMAGE_SIZE, interpolation=cv2.INTER_AREA), dtype=np.uint8))
    finally:
        cap.release()
    position, yaw, pitch, hfov = PEOPLE_POSE
    homography = homography_from_pose(position, yaw, pitch, hfov, IMAGE_SIZE)
    out = {}
    for k in range(cameras):
        camera_id = f"people{k + 1}"
        stretch = frames[400 * k : 400 * k + PEOPLE_FRAMES]
        if not stretch:
            raise ValueError(f"{VTEST}: {len(frames)} frames, too few for {cameras} people cameras")
        video = write_video(directory / f"{camera_id}.avi", stretch, fps)
        hfile = directory / f"{camera_id}.homography.yaml"
        save_homography(hfile, homography)
        out[camera_id] = RecordedCamera(camera_id, video, hfile, homography)
    return out


def record_scene(directory: Path, cameras: int = 2, frames: int = 40) -> dict[str, RecordedCamera]:
    """The first `cameras` cameras of scene.yaml rendered (textured floor, noise, lighting) to looping videos."""
    scenario = load_scenario(SCENE)
    out = {}
    for seed, cam in enumerate(scenario.cameras[:cameras]):
        renderer = CameraRenderer(scenario, cam, seed=seed)
        video = write_video(directory / f"{cam.id}.avi", (renderer.render(None, v) for v in range(frames)), cam.fps)
        hfile = directory / f"{cam.id}.homography.yaml"
        save_homography(hfile, cam.homography)
        out[cam.id] = RecordedCamera(cam.id, video, hfile, cam.homography)
    return out


def peak_rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return 0


@dataclass
class CpuSampler:
    """Samples a process's CPU time every `period` s: a timeline of CPU load (1.0 = one core)."""

    pid: int
    period: float = 0.1

    def __post_init__(self) -> None:
        self.samples: list[tuple[float, float]] = []
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        while True:
            try:
                self.samples.append((loop.time() - t0, cpu_seconds(self.pid)))
            except (FileNotFoundError, ProcessLookupError):
                return
            await asyncio.sleep(self.period)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    def load(self) -> list[tuple[float, float]]:
        return [
            (t1, (c1 - c0) / (t1 - t0))
            for (t0, c0), (t1, c1) in zip(self.samples, self.samples[1:], strict=False)
            if t1 > t0
        ]


def machine() -> dict[str, Any]:
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
    }


#: The service benchmarks measure capacity, not policy: the per-robot rate limit is lifted.
NO_RATE_LIMIT = ("--rate-limit", "1000000")


def bench_process(name: str, *args: str) -> ManagedProcess:
    """One of drvs-bench's own processes (a robot workload, a helper)."""
    return ManagedProcess.entry_point(name, "drvs-bench", *args)


def pyplot() -> ModuleType:
    """matplotlib's pyplot on the Agg backend (it draws to files only), imported when a benchmark
    plots: drvs-bench runs without a display, and only plotting needs matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_result(result: dict[str, Any], out: Path, name: str, plot: Callable[[dict[str, Any], Path], None]) -> None:
    """A benchmark's outputs: OUT/NAME.json (the result, indented) and its plot."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out)
