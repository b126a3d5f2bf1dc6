"""The tests' fakes: stand-in cameras (drvs.tools.fakes' AckingCamera and its helpers, which the
benchmarks' floors use too), stand-in processes (fault_roles.py, run as a script), and set-ups that
several test modules need."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

from drvs.sim.scene import RecordedCamera
from drvs.tools.fakes import AckingCamera as AckingCamera
from drvs.tools.fakes import register_message as register_message
from drvs.tools.fakes import serve_camera as serve_camera
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from tests.helpers import MAX_RANGE


async def start_recorded_camera(
    camera_id: str, rec: RecordedCamera, server: str, *args: str, env: dict[str, str] | None = None
) -> ManagedProcess:
    """drvs-camera `camera_id` on a recorded camera's footage and homography, registering with
    `server` and seeing as far as the scene's cameras (MAX_RANGE); `args`: more drvs-camera flags."""
    return await start_camera(
        camera_id, rec.video, rec.homography_file, server, "--max-range", MAX_RANGE, *args, env=env
    )


@contextlib.asynccontextmanager
async def server_process(*args: str) -> AsyncIterator[str]:
    """A drvs-server process started with `args`: its address; it is stopped on exit."""
    server, address = await start_server(*args)
    try:
        yield address
    finally:
        await server.stop()
