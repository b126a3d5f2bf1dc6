"""Building a camera's detectors: the ones this process can run serve, the others are unavailable.

A detector is unavailable when this Python lacks a backend it needs (`Detector.unavailable`: an
OpenCV build without contrib has neither `cv2.HOGDescriptor` nor `cv2.aruco`) or when building it
raises `DetectorUnavailable` (a model file that is absent). A camera serves and registers the rest,
and says once, at start, which detector is unavailable, why, and the command that fixes it. A
configuration the detector refuses (InvalidArgument, or FailedPrecondition for a file that is there
but wrong) still stops the camera at start: that is the operator's to fix, not something to serve
around. `drvs-camera check` builds the same way and prints the same verdicts.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from drvs.core.model import Detection
from drvs.detectors import REGISTRY, CameraView, Detector, DetectorUnavailable, FrameAnalysis, ObjectType
from drvs.wire import metrics

log = logging.getLogger("drvs.camera")


@dataclass
class BuiltDetectors:
    """The detectors a camera runs, by prefix and by the routing kinds they serve, and the ones it cannot."""

    runners: dict[str, Detector] = field(default_factory=dict)
    kinds: dict[str, Detector] = field(default_factory=dict)
    #: By prefix (the whole detector), or by kind (one of a detector's kinds, e.g. one model).
    unavailable: dict[str, DetectorUnavailable] = field(default_factory=dict)

    def close(self) -> None:
        for runner in self.runners.values():
            runner.close()


def build_detector(prefix: str, view: CameraView, options: Mapping[str, Any] | None) -> Detector:
    """One configured detector built for `view`; DetectorUnavailable when this process cannot run it,
    other DrvsErrors (InvalidArgument, FailedPrecondition) when its configuration is refused."""
    cls = REGISTRY[prefix]
    missing = cls.unavailable()
    if missing is not None:
        raise missing
    return cls(view, options)


def build_detectors(
    prefixes: Iterable[str], view: CameraView, options: Mapping[str, Mapping[str, Any]]
) -> BuiltDetectors:
    """Every configured detector that this process can run, built for `view`. Errors other than
    DetectorUnavailable propagate (after closing what was built)."""
    built = BuiltDetectors()
    try:
        for prefix in prefixes:
            try:
                runner = build_detector(prefix, view, options.get(prefix))
            except DetectorUnavailable as exc:
                built.unavailable[prefix] = exc
                continue
            built.runners[prefix] = runner
            for kind in runner.kinds():
                built.kinds[kind] = runner
            built.unavailable.update(runner.unavailable_kinds())
    except BaseException:
        built.close()
        raise
    return built


def log_detectors(camera_id: str, built: BuiltDetectors) -> None:
    """The start log's word on each detector (once), and the availability gauge."""
    for name, why in built.unavailable.items():
        log.warning(
            "camera %s: detector %s unavailable: %s%s; the camera serves its other object types",
            camera_id,
            name,
            why.reason,
            f". Fix: {why.fix}" if why.fix else "",
        )
        if name in REGISTRY:
            metrics.DETECTOR_AVAILABLE.labels(name).set(0)
    for prefix in built.runners:
        metrics.DETECTOR_AVAILABLE.labels(prefix).set(1)
    log.info("camera %s serves %s", camera_id, ", ".join(built.kinds) or "nothing")


def run_detector(runner: Detector, analysis: FrameAnalysis, wanted: ObjectType) -> tuple[Detection, ...]:
    """One search of a frame, counted and timed per detector (drvs_detector_runs_total)."""
    started = time.perf_counter()
    try:
        return runner.find(analysis, wanted)
    finally:
        metrics.DETECTOR_RUNS.labels(runner.prefix).inc()
        metrics.DETECTOR_SECONDS.labels(runner.prefix).inc(time.perf_counter() - started)
