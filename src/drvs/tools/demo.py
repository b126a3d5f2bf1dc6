"""drvs-demo: the three roles live, as separate processes on loopback.

Two camera nodes watch two parts of a floor (recorded video with coloured objects at known
places); a robot asks for yellow objects, first where only one camera looks, then over both, then
continuously, and compares what came back with where the objects really are.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from drvs.core.filters import HsvRange
from drvs.core.geometry import homography_from_pose
from drvs.robot import DrvsClient
from drvs.sim.scene import FloorPatch, record_camera
from drvs.tools.launch import ManagedProcess, start_camera, start_server

YELLOW = "hsv_014110130035225200"
GREEN = "hsv_040080080080255255"
IMAGE_SIZE = (640, 480)


@dataclass(frozen=True)
class DemoObject:
    name: str
    filter_def: str
    center: tuple[float, float]
    radius: float


CAMERAS = {
    # id: (position x, y, z), yaw, pitch: two cameras 20 m apart, both looking along +y.
    "cam-lobby": ((0.0, 0.0, 3.0), 90.0, 40.0),
    "cam-hall": ((20.0, 0.0, 3.0), 90.0, 40.0),
}
OBJECTS = [
    DemoObject("box A", YELLOW, (-1.0, 4.0), 0.25),
    DemoObject("box B", YELLOW, (1.5, 3.0), 0.20),
    DemoObject("plant", GREEN, (0.0, 5.5), 0.30),
    DemoObject("cart", YELLOW, (19.0, 4.5), 0.30),
]


def build_world(directory: Path) -> dict[str, tuple[Path, Path]]:
    patches = [FloorPatch.disc(o.center, o.radius, HsvRange.parse(o.filter_def).centre_bgr()) for o in OBJECTS]
    files = {}
    for i, (camera_id, (position, yaw, pitch)) in enumerate(CAMERAS.items()):
        h = homography_from_pose(position, yaw, pitch, 60.0, IMAGE_SIZE)
        rec = record_camera(directory, camera_id, h, IMAGE_SIZE, patches, seed=i)
        files[camera_id] = (rec.video, rec.homography_file)
    return files


def nearest_error(x: float, y: float, filter_def: str) -> tuple[str, float]:
    best = min((o for o in OBJECTS if o.filter_def == filter_def), key=lambda o: math.dist(o.center, (x, y)))
    return best.name, math.dist(best.center, (x, y))


async def run(args: argparse.Namespace) -> int:
    echo = sys.stderr if args.verbose else None
    procs: list[ManagedProcess] = []
    worst = 0.0
    with tempfile.TemporaryDirectory(prefix="drvs-demo-") as tmp:
        print("drvs-demo: rendering two camera views of a floor with coloured objects ...")
        files = build_world(Path(tmp))
        try:
            server, address = await start_server("--lease-ttl", "3", echo=echo)
            procs.append(server)
            print(f"drvs-demo: drvs-server (pid {server.pid}) listening on {address}")
            for camera_id, (video, hfile) in files.items():
                cam = await start_camera(camera_id, video, hfile, address, "--max-range", "6", echo=echo)
                procs.append(cam)
                print(f"drvs-demo: drvs-camera {camera_id} (pid {cam.pid}) registered")

            async with DrvsClient(address, robot_id="demo-robot") as robot:
                print(f"drvs-demo: robot listening for reports on {await robot.start_listener()}\n")
                for info in await robot.cameras():
                    x0, y0, x1, y1 = info.field_of_view.bounds
                    print(
                        f"  {info.camera_id:10s} sees {info.field_of_view.area:5.1f} m² "
                        f"within x {x0:.1f}..{x1:.1f}, y {y0:.1f}..{y1:.1f}"
                    )
                for title, region in (
                    ("yellow objects near the lobby camera, box (-6, 0, 6, 10)", (-6.0, 0.0, 6.0, 10.0)),
                    ("yellow objects over the whole floor, box (-6, 0, 26, 10)", (-6.0, 0.0, 26.0, 10.0)),
                ):
                    result = await robot.detect(YELLOW, region, timeout_s=5.0)
                    print(f"\n{title}: dispatched to {', '.join(result.camera_ids)}")
                    for d in result.detections:
                        name, err = nearest_error(d.centroid.x, d.centroid.y, YELLOW)
                        worst = max(worst, err)
                        print(
                            f"  {d.camera_id:10s} ({d.centroid.x:6.3f}, {d.centroid.y:6.3f}) m  "
                            f"-> {name}, {err * 100:.1f} cm from the truth"
                        )
                    if not result.complete:
                        for camera_id, error in sorted(result.camera_errors.items()):
                            print(f"  no answer from {camera_id}: {error.code} {error.message}")
                        return 1
                print("\ncontinuous: yellow near the hall camera at 5 Hz for 1 s")
                sub = await robot.subscribe(YELLOW, (14.0, 0.0, 26.0, 10.0), rate_hz=5, duration_s=1.0)
                async for report in sub:
                    flag = " (final)" if report.final else ""
                    print(f"  {report.camera_id} report #{report.sequence}: {len(report.detections)} object(s){flag}")
                print(f"\nthe robot received {robot.reports_received} reports and never touched a pixel")
        finally:
            for proc in reversed(procs):
                await proc.stop()
    print(f"drvs-demo: worst position error {worst * 100:.1f} cm; all processes stopped")
    return 0 if worst < 0.05 else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="drvs-demo", description=__doc__.splitlines()[0])
    parser.add_argument("--verbose", action="store_true", help="show every process's log")
    return asyncio.run(run(parser.parse_args(argv)))
