"""What the benchmarks share: a recorded two-camera scene, process CPU sampling, the machine."""

from __future__ import annotations

import asyncio
import os
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drvs.filters import HsvRange
from drvs.geometry import homography_from_pose
from drvs.sim.scene import FloorPatch, RecordedCamera, record_camera

YELLOW = "hsv_014110130035225200"
IMAGE_SIZE = (640, 480)
FPS = 20.0
#: Two cameras 20 m apart, as in the tests; the region covers both.
CAMERA_POSES = {"cam1": (0.0, 0.0, 3.0), "cam2": (20.0, 0.0, 3.0)}
BOTH_REGION = (-6.0, 0.0, 26.0, 10.0)
OBJECTS = [((-1.0, 4.0), 0.25), ((1.5, 3.0), 0.20), ((19.0, 4.5), 0.30)]
_TICK = os.sysconf("SC_CLK_TCK")


def record_scene(directory: Path, noise_sigma: float = 2.0) -> dict[str, RecordedCamera]:
    """Two 640x480 20 fps cameras watching yellow objects on a floor (2 s of video, looped)."""
    patches = [FloorPatch.disc(c, r, HsvRange.parse(YELLOW).centre_bgr()) for c, r in OBJECTS]
    out = {}
    for seed, (camera_id, position) in enumerate(CAMERA_POSES.items()):
        h = homography_from_pose(position, 90.0, 40.0, 60.0, IMAGE_SIZE)
        out[camera_id] = record_camera(
            directory, camera_id, h, IMAGE_SIZE, patches, frames=40, fps=FPS, noise_sigma=noise_sigma, seed=seed
        )
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all its threads), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


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
