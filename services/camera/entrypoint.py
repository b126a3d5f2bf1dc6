"""Camera container entrypoint: `drvs-camera` with the container's flags and DRVS_CAMERA_* settings.

A simulated camera (`--source sim://WORLD`) given no homography gets the one drvs-office gives it:
derived from the camera's pose in the scenario the world serves (what calibration would measure),
written to /tmp, with the scenario's max range unless one is set. A scout's camera gets its mount
and field of view instead (give it `--pose-source`, e.g. the scout's mover: tcp://scout-1:50080). Then this process becomes
drvs-camera (exec), which handles SIGTERM itself: it deregisters and stops gracefully.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

DRVS_CAMERA = "drvs-camera"


def option(argv: list[str], flag: str, env: str) -> str | None:
    """A setting as drvs-camera would read it: --flag VALUE, --flag=VALUE, or the environment."""
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(flag + "="):
            return arg[len(flag) + 1 :]
    return os.environ.get(env) or None


def sim_settings(world: str, camera_id: str, argv: list[str]) -> list[str]:
    """What drvs-office gives a scenario's camera: a fixed camera's homography (from its pose in the
    scenario, written to /tmp), or a scout's camera's mount and field of view (its poses come from
    its --pose-source); the scenario's max range unless one is set."""
    import grpc

    from drvs.core.errors import Unavailable
    from drvs.core.homography_file import save_homography
    from drvs.sim.world import fetch_scene

    with grpc.insecure_channel(world) as channel:
        try:
            scenario, _seed = fetch_scene(channel, world, 60)
        except Unavailable as exc:
            raise SystemExit(f"camera {camera_id}: {exc}") from None
    extra: list[str] = []
    scout = scenario.scout_camera(camera_id)
    if scout is not None:
        m = scout.mount
        extra += ["--mount", f"{m.x:g},{m.y:g},{m.z:g},{m.yaw_deg:g},{m.pitch_deg:g}", "--hfov", f"{m.hfov_deg:g}"]
        print(f"camera {camera_id}: mobile, on scout {scout.id}: mount {extra[1]}, {m.hfov_deg:g}° wide", flush=True)
        max_range_m = scout.max_range_m
    else:
        cam = scenario.camera(camera_id)
        path = Path(tempfile.gettempdir()) / f"{camera_id}.homography.yaml"
        save_homography(path, cam.homography, image_size=list(cam.resolution))
        print(f"camera {camera_id}: homography from its pose in the world's scenario: {path}", flush=True)
        extra += ["--homography", str(path)]
        max_range_m = cam.max_range_m
    if not option(argv, "--max-range", "DRVS_CAMERA_MAX_RANGE"):
        extra += ["--max-range", str(max_range_m)]
    return extra


def main() -> None:
    argv = sys.argv[1:]
    subcommand = bool(argv) and not argv[0].startswith("-") and argv[0] != "run"
    source = option(argv, "--source", "DRVS_CAMERA_SOURCE")
    given_config = any(a == "--config" or a.startswith("--config=") for a in argv)
    configured = given_config or option(argv, "--homography", "DRVS_CAMERA_HOMOGRAPHY")
    if not subcommand and source and source.startswith("sim://") and not configured:
        camera_id = option(argv, "--id", "DRVS_CAMERA_ID")
        if not camera_id:
            raise SystemExit("camera: a sim:// source needs --id (or DRVS_CAMERA_ID): the scenario camera it is")
        argv += sim_settings(source[len("sim://") :], camera_id, argv)
    os.execvp(DRVS_CAMERA, [DRVS_CAMERA, *argv])


if __name__ == "__main__":
    main()
