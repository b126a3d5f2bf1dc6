"""drvs-camera: turn a camera (device, video file or stream) into a DRVS camera node."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.camera.aruco import DEFAULT_DICTIONARY, BoardSpec, board_image, find_correspondences
from drvs.camera.calibration import fit_homography, load_points, save_calibration
from drvs.camera.check import check_main
from drvs.camera.config import DEFAULT_FOXGLOVE_FPS, ENVIRONMENT, add_arguments, load_config
from drvs.camera.node import CameraNode
from drvs.camera.source import FrameSource, VideoSource, plugin_source
from drvs.core.errors import DrvsError
from drvs.core.geometry import DEFAULT_MAX_RANGE_M, FieldOfView, polygon_coords
from drvs.core.homography_file import load_homography
from drvs.detectors import Frame
from drvs.wire._cli import add_security_arguments, join_negative_values, setup_logging, shutdown_event
from drvs.wire.metrics import DEFAULT_METRICS_HOST, serve_metrics

log = logging.getLogger("drvs.camera")


def build_parser() -> argparse.ArgumentParser:
    """Flags default to None so the config knows which were given (flag > env > file > default)."""
    e = ENVIRONMENT
    p = argparse.ArgumentParser(
        prog="drvs-camera",
        description="Run a DRVS camera node. Also: drvs-camera check | snapshot | calibrate | calibrate-aruco | "
        "aruco-board | fov (each with --help); check (or --check) takes the same settings as the node.",
        epilog="Every setting can also come from a DRVS_* environment variable or a --config YAML file whose keys "
        "are the setting names: " + ", ".join(f"{k} ({v})" for k, v in e.items()) + ".",
    )
    p.add_argument("--config", metavar="FILE", help="YAML file of settings (flags and environment override it)")
    add_arguments(p)  # every CameraConfig setting but the shared security ones (drvs.camera.config)
    add_security_arguments(p, "file holding this camera's registration token")
    return p


def make_source(
    spec: str,
    camera_id: str,
    *,
    loop_file: bool = True,
    resolution: tuple[int, int] | None = None,
    fps: float | None = None,
) -> FrameSource:
    """A scheme an installed plug-in claims (sim://HOST:PORT: the simulated world) goes to it;
    anything else to OpenCV."""
    plugin = plugin_source(spec, camera_id)
    if plugin is not None:
        return plugin
    return VideoSource(spec, loop_file=loop_file, resolution=resolution, fps=fps)


async def run(node: CameraNode, metrics_port: int | None = None, metrics_host: str = DEFAULT_METRICS_HOST) -> int:
    stop = shutdown_event()
    try:
        await node.start()
        serve_metrics(metrics_port, metrics_host)
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


SUBCOMMANDS = ("run", "check", "snapshot", "calibrate", "calibrate-aruco", "aruco-board", "fov")


def parse_size(text: str, name: str = "--image-size") -> tuple[int, int]:
    parts = text.lower().replace("x", ",").split(",")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise DrvsError(f"{name}: expected W,H in pixels, e.g. 640,480; got {text!r}")
    w, h = (int(p) for p in parts)
    if not (0 < w <= 100_000 and 0 < h <= 100_000):
        raise DrvsError(f"{name}: {w}x{h} is not a real image size")
    return w, h


async def grab_one(spec: str, timeout_s: float, source: FrameSource | None = None) -> Frame:
    source = VideoSource(spec, loop_file=False) if source is None else source
    source.start()
    try:
        return await source.wait_first_frame(timeout_s)
    finally:
        await asyncio.to_thread(source.stop)


#: The most frames `snapshot --frames` takes (a median over more changes nothing a camera sees).
MAX_SNAPSHOT_FRAMES = 100
#: How often `grab_frames` looks for a newer frame.
FRAME_POLL_S = 0.005


async def grab_frames(source: FrameSource, count: int, timeout_s: float) -> list[Frame]:
    """`count` successive frames of a source (each newer than the last), each within `timeout_s`."""
    source.start()
    try:
        frames = [await source.wait_first_frame(timeout_s)]
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while len(frames) < count:
            frame = source.latest()
            if frame is not None and frame.sequence != frames[-1].sequence:
                frames.append(frame)
                deadline = loop.time() + timeout_s
            elif loop.time() > deadline:
                raise DrvsError(
                    f"--frames {count}: the source gave {len(frames)} and then no new one in {timeout_s:g} s"
                )
            else:
                await asyncio.sleep(FRAME_POLL_S)
        return frames
    finally:
        await asyncio.to_thread(source.stop)


def median_picture(frames: list[Frame]) -> NDArray[np.uint8]:
    """The per-pixel median of frames (the frame itself for one): noise and jitter averaged out."""
    if len(frames) == 1:
        return frames[0].image
    sizes = {f.size for f in frames}
    if len(sizes) > 1:
        raise DrvsError(f"--frames: the source changed its frame size while the snapshot was taken: {sorted(sizes)}")
    return np.asarray(np.median(np.stack([f.image for f in frames]), axis=0).round(), dtype=np.uint8)


def check_writable(path: Path, name: str = "--out") -> None:
    """Refuse, before any frame is grabbed, an image path that cannot be written."""
    if path.is_dir():
        raise DrvsError(f"{name} {path}: is a directory")
    ext = path.suffix.lower()
    if not ext or not cv2.haveImageWriter(f"x{ext}"):
        raise DrvsError(f"{name} {path}: OpenCV cannot write {ext or 'files without an extension'}; use .png")
    parent = path.parent
    if not parent.is_dir():
        raise DrvsError(f"{name} {path}: no directory {parent}")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise DrvsError(f"{name} {path}: permission denied")


def snapshot_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        prog="drvs-camera snapshot",
        description="Save one frame of a camera's source: to pick floor points in, or as the picture of the empty "
        "floor the foreground detector compares frames with (background: in the camera's config).",
    )
    p.add_argument("--config", metavar="FILE", help="the camera's YAML config: its source, id, resolution and fps")
    p.add_argument("--source", help="device index, video file, stream URL or sim://HOST:PORT (overrides --config)")
    p.add_argument("--id", help="camera id (needed for a sim:// source without --config)")
    p.add_argument("--out", required=True, help="image file to write (PNG: lossless)")
    p.add_argument("--timeout", type=float, default=15.0, help="seconds to wait for a frame")
    p.add_argument(
        "--frames",
        type=int,
        default=1,
        metavar="N",
        help=f"save the per-pixel median of N successive frames (1-{MAX_SNAPSHOT_FRAMES}; default 1): a picture "
        "of the empty floor without one frame's noise",
    )
    args = p.parse_args(argv)
    setup_logging("WARNING")
    out = Path(args.out)
    code = 2  # bad flags or config, refused before a frame is grabbed
    try:
        if not 1 <= args.frames <= MAX_SNAPSHOT_FRAMES:
            raise DrvsError(f"--frames: {args.frames} must be 1-{MAX_SNAPSHOT_FRAMES}")
        check_writable(out)
        spec, camera_id = args.source, args.id or "snapshot"
        resolution, fps = None, None
        if args.config is not None:
            flags = {"source": args.source, "id": args.id, "homography": "-"}
            config = load_config(flags, os.environ, args.config)
            spec, camera_id, resolution, fps = config.source, config.id, config.resolution, config.fps
        if not spec:
            raise DrvsError("give --source SRC or --config FILE")
        source = make_source(spec, camera_id, loop_file=False, resolution=resolution, fps=fps)
        code = 1  # found only now: the source gives no frame, or the file cannot be written
        frames = asyncio.run(grab_frames(source, args.frames, args.timeout))
        picture = median_picture(frames)
        if not cv2.imwrite(str(out), picture):
            raise DrvsError(f"--out {out}: OpenCV could not write it")
    except (DrvsError, OSError, cv2.error) as exc:
        print(f"drvs-camera snapshot: {exc}", file=sys.stderr)
        return code
    width, height = frames[0].size
    median = f" (the median of {len(frames)} frames)" if len(frames) > 1 else ""
    print(f"{out}: {width}x{height} from {spec}{median}")
    return 0


def add_board_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", required=True, help="COLSxROWS:MARKER_M:GAP_M, e.g. 6x4:0.2:0.05")
    p.add_argument("--board-origin", default="0,0", help="X,Y of the board's top-left corner (as read), metres")
    p.add_argument("--board-yaw", type=float, default=0.0, help="direction of its top edge, degrees CCW from +x")
    p.add_argument("--dictionary", default=DEFAULT_DICTIONARY, help="OpenCV ArUco dictionary (default %(default)s)")


def board_spec(args: argparse.Namespace) -> BoardSpec:
    try:
        x, y = (float(v) for v in args.board_origin.split(","))
    except ValueError:
        raise DrvsError(f"--board-origin: {args.board_origin!r} is not X,Y") from None
    return BoardSpec.parse(args.board, (x, y), args.board_yaw, args.dictionary)


def calibrate_aruco_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        prog="drvs-camera calibrate-aruco",
        description="Calibrate from an ArUco grid board lying face up on the floor at a known place.",
    )
    p.add_argument("--source", required=True, help="device index, video file, stream URL, or an image file")
    add_board_arguments(p)
    p.add_argument("--out", required=True, help="homography file to write (for --homography)")
    args = p.parse_args(argv)
    setup_logging("WARNING")
    try:
        spec = board_spec(args)
        still = cv2.imread(args.source) if args.source.lower().endswith((".png", ".jpg", ".jpeg", ".bmp")) else None
        image = still if still is not None else asyncio.run(grab_one(args.source, 15.0)).image
        size = (int(image.shape[1]), int(image.shape[0]))
        points = find_correspondences(np.asarray(image, dtype=np.uint8), spec)
        calibration = fit_homography(points, size)
        save_calibration(args.out, calibration, size)
    except (DrvsError, OSError) as exc:
        print(f"drvs-camera calibrate-aruco: {exc}", file=sys.stderr)
        return 2
    used = sum(calibration.inliers)
    print(
        f"{len(points) // 4} markers, {len(points)} corners ({used} used): rms error "
        f"{calibration.rms_error_m * 1000:.1f} mm, max {calibration.max_error_m * 1000:.1f} mm on the board; "
        f"wrote {args.out}"
    )
    print("the error grows away from the board: check it with drvs-camera fov, or lay the board in several places")
    return 0


def aruco_board_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="drvs-camera aruco-board", description="Write the board image to print.")
    add_board_arguments(p)
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--px-per-m", type=float, default=2000.0)
    args = p.parse_args(argv)
    try:
        spec = board_spec(args)
    except DrvsError as exc:
        print(f"drvs-camera aruco-board: {exc}", file=sys.stderr)
        return 2
    cv2.imwrite(args.out, board_image(spec, args.px_per_m))
    print(f"{args.out}: print it so that each marker measures {spec.marker_m * 100:g} cm")
    return 0


def calibrate_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        prog="drvs-camera calibrate",
        description="Fit the image->floor homography from >= 4 measured points (RANSAC); print each point's error.",
    )
    p.add_argument("--points", required=True, help="YAML/JSON: [{image: [u, v], world: [x, y]}, ...]")
    p.add_argument("--image-size", required=True, help="W,H of the camera's images, e.g. 640,480")
    p.add_argument("--out", required=True, help="homography file to write (for --homography)")
    args = p.parse_args(argv)
    try:
        size = parse_size(args.image_size)
        calibration = fit_homography(load_points(args.points), size)
        save_calibration(args.out, calibration, size)
    except DrvsError as exc:
        print(f"drvs-camera calibrate: {exc}", file=sys.stderr)
        return 2
    print(f"{'#':>3} {'image (px)':>18} {'world (m)':>20} {'error':>10}")
    for i, (c, err, ok) in enumerate(zip(calibration.points, calibration.errors_m, calibration.inliers, strict=True)):
        image = f"({c.image[0]:.1f}, {c.image[1]:.1f})"
        world = f"({c.world[0]:.3f}, {c.world[1]:.3f})"
        note = "" if ok else "  outlier, not used"
        print(f"{i:>3} {image:>18} {world:>20} {err * 1000:>7.1f} mm{note}")
    used = sum(calibration.inliers)
    print(
        f"rms error {calibration.rms_error_m * 1000:.1f} mm, max {calibration.max_error_m * 1000:.1f} mm "
        f"over {used} of {len(calibration.points)} points; wrote {args.out}"
    )
    return 0


def fov_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        prog="drvs-camera fov", description="Print the floor a camera sees, and draw it over a snapshot."
    )
    p.add_argument("--homography", required=True, metavar="FILE")
    p.add_argument("--image-size", help="W,H (or give --source)")
    p.add_argument("--source", help="take a frame from this source: its size, and a picture to draw on")
    p.add_argument("--max-range", type=float, default=DEFAULT_MAX_RANGE_M, metavar="M")
    p.add_argument("--out", default="fov.png", help="picture with the field of view drawn (with --source)")
    args = p.parse_args(argv)
    setup_logging("WARNING")
    try:
        homography = load_homography(args.homography)
        frame = asyncio.run(grab_one(args.source, 15.0)) if args.source else None
        if frame is not None:
            size = frame.size
        elif args.image_size:
            size = parse_size(args.image_size)
        else:
            raise DrvsError("give --image-size W,H or --source SRC")
        fov = FieldOfView.compute(homography, size, args.max_range)
    except (DrvsError, OSError) as exc:
        print(f"drvs-camera fov: {exc}", file=sys.stderr)
        return 2
    x0, y0, x1, y1 = fov.floor.bounds
    print(f"field of view: {fov.floor.area:.2f} m² within x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f} (metres)")
    print("floor polygon: " + ", ".join(f"({x:.3f}, {y:.3f})" for x, y in polygon_coords(fov.floor)))
    if frame is not None:
        picture = frame.image.copy()
        ring = np.round(np.asarray(fov.image.exterior.coords)).astype(np.int32)
        shade = picture.copy()
        cv2.fillPoly(shade, [ring], (0, 200, 0))
        picture = np.asarray(cv2.addWeighted(shade, 0.25, picture, 0.75, 0), dtype=np.uint8)
        cv2.polylines(picture, [ring], True, (0, 255, 0), 2)
        for u, v in np.asarray(fov.image.exterior.coords)[:-1]:
            x, y = homography.apply([[u, v]])[0]
            label = f"({x:.1f},{y:.1f})"
            (text_w, text_h), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
            at = (int(min(max(u + 4, 2), size[0] - text_w - 2)), int(min(max(v - 4, text_h + 2), size[1] - 4)))
            cv2.putText(picture, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 0), 1)
        cv2.imwrite(args.out, picture)
        print(f"drawn over a frame of {args.source}: {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = join_negative_values(sys.argv[1:] if argv is None else argv, ("--board-origin",))
    if "--check" in argv and (not argv or argv[0] not in SUBCOMMANDS[2:]):
        argv = ["check", *(a for a in argv if a not in ("--check", "run"))]
    if argv and argv[0] in SUBCOMMANDS[1:]:
        commands = {
            "check": check_main,
            "snapshot": snapshot_main,
            "calibrate": calibrate_main,
            "calibrate-aruco": calibrate_aruco_main,
            "aruco-board": aruco_board_main,
            "fov": fov_main,
        }
        return commands[argv[0]](argv[1:])
    if argv and argv[0] == "run":
        argv = argv[1:]
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        config = load_config(vars(args), os.environ, args.config)
    except DrvsError as exc:
        parser.error(str(exc))
    setup_logging(config.log_level, config.log_format)
    try:
        node = CameraNode(
            config.id,
            make_source(config.source, config.id, loop_file=config.loop, resolution=config.resolution, fps=config.fps),
            load_homography(config.homography) if config.homography is not None else None,
            config.server,
            listen=config.listen,
            advertise=config.advertise,
            max_range_m=config.max_range_m,
            min_area_px=config.min_area_px,
            max_frame_age_s=config.max_frame_age_s,
            serve_frames=config.serve_frames,
            resolution=config.resolution,
            detectors=config.detectors,
            detect_workers=config.detect_workers,
            detector_options=config.detector_options(),
            heartbeat_s=config.heartbeat_s,
            max_continuous=config.max_continuous,
            security=config.security(),
            mount=config.mount_spec(),
            pose_source=config.pose_source,
            max_pose_gap_s=config.max_pose_gap_s,
            pose_lease_s=config.pose_lease_s,
            max_speed_mps=config.max_speed_mps,
            pose_update_distance_m=config.pose_update_distance_m,
            pose_update_angle_deg=config.pose_update_angle_deg,
            max_pose_rate_hz=config.max_pose_rate_hz,
            frame=config.frame,
            foxglove=config.foxglove,
            foxglove_fps=DEFAULT_FOXGLOVE_FPS if config.foxglove_fps is None else config.foxglove_fps,
        )
    except DrvsError as exc:
        parser.error(str(exc))
    return asyncio.run(run(node, config.metrics_port, config.metrics_host))
