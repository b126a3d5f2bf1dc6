"""drvs-camera check: what an installer runs before leaving a camera on a ceiling.

It takes the camera's own settings (the same flags, environment and --config file as the camera),
opens the source and reads a frame, loads the homography and computes the floor the camera sees,
and builds every configured detector on that frame's size, as the camera would at start. Each step
prints one line: `ok` with what it found, or `FAIL` with what is wrong and, where there is one, the
command that fixes it. Exit codes: 0 everything works; 1 something does not (the lines say what);
2 the settings themselves are refused (as `drvs-camera` refuses them, before anything is opened).
"""

from __future__ import annotations

import asyncio
import os
import sys
from typing import TextIO

import cv2

from drvs.core.errors import DrvsError
from drvs.core.geometry import FieldOfView, Homography
from drvs.core.homography_file import load_homography
from drvs.detectors import REGISTRY, CameraView, DetectorUnavailable, Frame, prefixes

from .config import CameraConfig, load_config
from .detectors import build_detector

#: Exit codes.
OK, FAILED, BAD_SETTINGS = 0, 1, 2
#: How long to wait for the source's first frame (as long as the camera waits at start).
FIRST_FRAME_TIMEOUT_S = 15.0


class Report:
    """The lines `check` prints, and whether any failed."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.failures = 0

    def ok(self, what: str, detail: str) -> None:
        print(f"  ok    {what}: {detail}", file=self.out)

    def skip(self, what: str, detail: str) -> None:
        """Not checked, for a failure already reported."""
        print(f"  --    {what}: {detail}", file=self.out)

    def fail(self, what: str, detail: str) -> None:
        self.failures += 1
        print(f"  FAIL  {what}: {detail}", file=self.out)


def check_main(argv: list[str], out: TextIO = sys.stdout) -> int:
    from .cli import build_parser  # the camera's own flags (cli imports this module lazily too)

    parser = build_parser()
    parser.prog = "drvs-camera check"
    parser.description = (
        "Check a camera before leaving it: open its source and read a frame, load its homography, build "
        "every configured detector. Prints ok or FAIL (with why and the fix) for each; exit 0 when all "
        "work, 1 when any does not, 2 for settings drvs-camera would refuse."
    )
    args = parser.parse_args(argv)
    try:
        config = load_config(vars(args), os.environ, args.config)
        mount = config.mount_spec()
    except DrvsError as exc:
        print(f"drvs-camera check: {exc}", file=sys.stderr)
        return BAD_SETTINGS
    print(f"drvs-camera check: camera {config.id}", file=out)
    report = Report(out)
    frame = _source(config, report)
    homography = _homography(config, report)
    size = frame.size if frame is not None else config.resolution
    if mount is not None and size is not None:
        homography = mount.base_homography(size)
    view = None
    if homography is not None and size is not None:
        try:
            fov = FieldOfView.compute(homography, size, config.max_range_m)
            view = CameraView(homography, fov, size, camera_id=config.id, min_area_px=config.min_area_px)
            report.ok("field of view", f"{fov.floor.area:.1f} m² of floor within {config.max_range_m:g} m")
        except DrvsError as exc:
            report.fail("field of view", str(exc))
    _detectors(config, view, report)
    if report.failures:
        print(f"{report.failures} problem(s): fix them before leaving this camera", file=out)
        return FAILED
    print("everything works", file=out)
    return OK


def _source(config: CameraConfig, report: Report) -> Frame | None:
    from .cli import grab_one, make_source

    what = f"source {config.source}"
    try:
        source = make_source(config.source, config.id, loop_file=False, resolution=config.resolution, fps=config.fps)
        frame = asyncio.run(grab_one(config.source, FIRST_FRAME_TIMEOUT_S, source))
    except (DrvsError, OSError, ValueError, TimeoutError, cv2.error) as exc:
        report.fail(what, f"no frame: {exc}")
        return None
    width, height = frame.size
    if config.resolution is not None and frame.size != config.resolution:
        report.fail(
            what,
            f"gives {width}x{height} frames, not the configured {config.resolution[0]}x{config.resolution[1]} "
            "(the homography belongs to one image size)",
        )
        return None
    report.ok(what, f"read a {width}x{height} frame")
    return frame


def _homography(config: CameraConfig, report: Report) -> Homography | None:
    if config.homography is None:
        report.ok("homography", "a mobile camera: its mount gives it")
        return None
    what = f"homography {config.homography}"
    try:
        homography = load_homography(config.homography)
    except (DrvsError, OSError) as exc:
        report.fail(what, str(exc))
        return None
    report.ok(what, "loaded")
    return homography


def _detectors(config: CameraConfig, view: CameraView | None, report: Report) -> None:
    options = config.detector_options()
    for prefix in config.detectors or prefixes():
        what = f"detector {prefix}"
        try:
            if view is None:
                missing = REGISTRY[prefix].unavailable()
                if missing is not None:
                    raise missing
                report.skip(what, "its backend is here; not built without a frame and the homography (above)")
                continue
            runner = build_detector(prefix, view, options.get(prefix))
        except DetectorUnavailable as exc:
            fix = f". Fix: {exc.fix}" if exc.fix else ""
            report.fail(what, f"unavailable (the camera would serve without it): {exc.reason}{fix}")
            continue
        except DrvsError as exc:
            report.fail(what, f"refused (the camera would not start): {exc}")
            continue
        try:
            kinds = runner.kinds()
            if kinds:
                report.ok(what, f"ready, serves {', '.join(kinds)}")
            else:
                report.ok(what, "ready, serves nothing (no models: configured)")
            for kind, why in runner.unavailable_kinds().items():
                fix = f". Fix: {why.fix}" if why.fix else ""
                report.fail(f"{what} {kind}", f"unavailable (the camera would serve without it): {why.reason}{fix}")
        finally:
            runner.close()
