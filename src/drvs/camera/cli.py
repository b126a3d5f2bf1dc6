"""drvs-camera: turn a camera (device, video file or stream) into a DRVS camera node."""

from __future__ import annotations

import argparse
import asyncio
import logging

from drvs._cli import env, setup_logging, shutdown_event
from drvs.camera.homography_file import load_homography
from drvs.camera.node import CameraNode
from drvs.camera.source import FrameSource, VideoSource
from drvs.detection import DEFAULT_MIN_AREA_PX
from drvs.errors import DrvsError
from drvs.geometry import DEFAULT_MAX_RANGE_M

log = logging.getLogger("drvs.camera")

ENV_SERVER = "DRVS_SERVER"
ENV_CAMERA_LISTEN = "DRVS_CAMERA_LISTEN"
ENV_CAMERA_ADVERTISE = "DRVS_CAMERA_ADVERTISE"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drvs-camera", description="Run a DRVS camera node.")
    p.add_argument("--id", required=True, help="camera id, unique in the building")
    p.add_argument(
        "--source",
        required=True,
        help="device index (0), video file path, stream URL, or sim://HOST:PORT (simulated world)",
    )
    p.add_argument(
        "--homography",
        required=True,
        metavar="FILE",
        help="JSON/YAML file whose 'homography' is the 3x3 image->floor matrix",
    )
    p.add_argument(
        "--server",
        default=env(ENV_SERVER, "127.0.0.1:50051"),
        help=f"DRVS server HOST:PORT (env {ENV_SERVER})",
    )
    p.add_argument(
        "--listen",
        default=env(ENV_CAMERA_LISTEN, "127.0.0.1:0"),
        help=f"HOST:PORT to serve on; port 0 picks a free one (env {ENV_CAMERA_LISTEN}; default %(default)s)",
    )
    p.add_argument(
        "--advertise",
        default=env(ENV_CAMERA_ADVERTISE),
        help=f"HOST:PORT the server should dial, when it differs from --listen (env {ENV_CAMERA_ADVERTISE})",
    )
    p.add_argument(
        "--max-range",
        type=float,
        default=DEFAULT_MAX_RANGE_M,
        metavar="M",
        help="field-of-view range, metres",
    )
    p.add_argument("--min-area", type=float, default=DEFAULT_MIN_AREA_PX, metavar="PX", help="smallest blob, pixels")
    p.add_argument("--no-loop", action="store_true", help="play a video file once instead of looping it")
    p.add_argument(
        "--serve-frames",
        action="store_true",
        help="also stream whole frames (FrameStream service): the no-DRVS baseline, for benchmarks",
    )
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING (env DRVS_LOG_LEVEL)")
    return p


def make_source(spec: str, camera_id: str, *, loop_file: bool = True) -> FrameSource:
    """A sim://HOST:PORT source renders the simulated world; anything else goes to OpenCV."""
    if spec.startswith("sim://"):
        from drvs.sim.source import SimSource

        return SimSource(spec, camera_id)
    return VideoSource(spec, loop_file=loop_file)


async def run(node: CameraNode) -> int:
    stop = shutdown_event()
    try:
        await node.start()
    except (DrvsError, OSError) as exc:
        log.error("camera %s cannot start: %s", node.camera_id, exc)
        await node.stop(grace=0)
        return 1
    try:
        await stop.wait()
        log.info("camera %s shutting down", node.camera_id)
    finally:
        await node.stop(grace=2.0)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.log_level)
    try:
        homography = load_homography(args.homography)
        node = CameraNode(
            args.id,
            make_source(args.source, args.id, loop_file=not args.no_loop),
            homography,
            args.server,
            listen=args.listen,
            advertise=args.advertise,
            max_range_m=args.max_range,
            min_area_px=args.min_area,
            serve_frames=args.serve_frames,
        )
    except DrvsError as exc:
        parser.error(str(exc))
    return asyncio.run(run(node))
