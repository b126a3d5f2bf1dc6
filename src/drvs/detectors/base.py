"""What every detector shares: frames, per-frame caches, mapping to the floor, and the registry.

A detector is a plug-in keyed by the prefix of the `filter_def` strings it serves (``hsv``,
``aruco``, ``people``, ``foreground``, ``model``), as frigate's detectors are keyed by type: one
file defines a `Detector` subclass decorated with `@register`, and `drvs.detectors` imports it.
The strings' grammar is the core's (`drvs.core.object_types`: pure, cheap, the server and robots parse
with it and never load a detector): a built-in detector's `parse` is the grammar's, and `@register`
adds a plug-in's `parse` to the grammar's table. An instance runs on one camera and finds objects
in frames. Mapping pixels to the floor (`CameraView`), selecting by region and sharing one frame's
work among requests stay common. See `drvs.core.object_types` for an `ObjectType`'s kind and key.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import cv2
import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon

from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.geometry import FieldOfView, Homography
from drvs.core.model import Detection, PixelBox
from drvs.core.object_types import MAX_FILTER_DEF_LENGTH as MAX_FILTER_DEF_LENGTH
from drvs.core.object_types import ObjectType as ObjectType
from drvs.core.object_types import add_grammar
from drvs.core.object_types import parse_object_type as parse_object_type

#: Blobs smaller than this many pixels are noise.
DEFAULT_MIN_AREA_PX = 30.0
#: Outlines are simplified (Douglas-Peucker) to within this many pixels before they are mapped:
#: a contour lists every boundary pixel, and reports would carry ten times the points for
#: no information the image resolution supports.
OUTLINE_TOLERANCE_PX = 1.0


@dataclass(frozen=True)
class Frame:
    """A captured image (BGR) with its capture time (Unix seconds, for reports) and a per-source
    sequence number. `captured_at` is the same instant on the monotonic clock: a frame's age is
    measured on it, so a wall clock that steps (NTP, an operator) never makes a stale frame look
    fresh or a fresh one stale."""

    image: NDArray[np.uint8]
    capture_time: float
    sequence: int
    captured_at: float = field(default_factory=time.monotonic)

    def age_s(self) -> float:
        """Seconds since capture, on the monotonic clock."""
        return time.monotonic() - self.captured_at

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[0])


@dataclass
class FrameAnalysis:
    """Per-frame caches shared by all requests served from this frame.

    `found(key, compute)` runs `compute` once per key and frame; a second caller of the same key
    waits for the first caller's result, and callers of other keys are not held up by it (one lock
    per key: a 100 ms people search never delays a colour request on the same frame).
    """

    frame: Frame
    _hsv: NDArray[np.uint8] | None = None
    _gray: NDArray[np.uint8] | None = None
    _blobs: dict[str, tuple[Detection, ...]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _key_locks: dict[str, threading.Lock] = field(default_factory=dict)
    #: Filters requests looked up on this frame, and on the frame before it (see drvs.camera.prefetch).
    wanted: set[str] = field(default_factory=set)
    inherited: frozenset[str] = frozenset()
    #: In-flight computations by key, for requests on the event loop (see drvs.camera.node).
    pending: dict[str, Any] = field(default_factory=dict)

    def cached_blobs(self, key: str) -> tuple[Detection, ...] | None:
        """This key's detections if someone already found them (a complete entry or none: the
        entry is stored whole, once), without waiting for a thread that is finding them."""
        return self._blobs.get(key)

    def found(self, key: str, compute: Callable[[], tuple[Detection, ...]]) -> tuple[Detection, ...]:
        """`compute()` for this frame and key, run once; later callers get the same tuple."""
        cached = self._blobs.get(key)
        if cached is not None:
            return cached
        with self._lock:
            lock = self._key_locks.setdefault(key, threading.Lock())
        with lock:
            cached = self._blobs.get(key)
            if cached is None:
                cached = compute()
                self._blobs[key] = cached
            return cached

    def hsv(self) -> NDArray[np.uint8]:
        if self._hsv is None:
            self._hsv = np.asarray(cv2.cvtColor(self.frame.image, cv2.COLOR_BGR2HSV), dtype=np.uint8)
        return self._hsv

    def gray(self) -> NDArray[np.uint8]:
        if self._gray is None:
            image = self.frame.image
            self._gray = np.asarray(
                image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8
            )
        return self._gray


class CameraView:
    """One camera's geometry: image size, image->floor homography and field of view, and the
    mapping of pixel shapes to floor detections every detector uses."""

    def __init__(
        self,
        homography: Homography,
        field_of_view: FieldOfView,
        image_size: tuple[int, int],
        *,
        camera_id: str = "",
        min_area_px: float = DEFAULT_MIN_AREA_PX,
    ) -> None:
        self.homography = homography
        self.field_of_view = field_of_view
        self.image_size = image_size
        self.camera_id = camera_id
        self.min_area_px = min_area_px
        width, height = image_size
        # Only pixels that map into the field of view may become detections: above the horizon the
        # homography maps to points behind the camera or at infinity.
        self.fov_mask = np.zeros((height, width), dtype=np.uint8)
        ring = np.round(np.asarray(field_of_view.image.exterior.coords)[:-1]).astype(np.int32)
        cv2.fillPoly(self.fov_mask, [ring], 255)

    def check_frame(self, frame: Frame) -> None:
        if frame.size != self.image_size:
            raise ValueError(f"frame size {frame.size} differs from the calibrated size {self.image_size}")

    def in_view(self, u: float, v: float) -> bool:
        """Is pixel (u, v) inside the field of view (so its floor point means something)?"""
        x, y = round(u), round(v)
        h, w = self.fov_mask.shape
        return 0 <= x < w and 0 <= y < h and bool(self.fov_mask[y, x])

    def floor_outline(self, pixel_points: NDArray[Any]) -> Polygon | None:
        """A pixel polygon (N x 2) mapped onto the floor as a valid polygon, or None."""
        pts = np.asarray(pixel_points, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 3:
            return None
        floor_pts = self.homography.apply(pts)
        if not np.all(np.isfinite(floor_pts)):
            return None
        outline = Polygon(floor_pts)
        if not outline.is_valid:
            fixed = shapely.make_valid(outline)
            polys = [g for g in getattr(fixed, "geoms", [fixed]) if isinstance(g, Polygon) and not g.is_empty]
            if not polys:
                return None
            outline = max(polys, key=lambda g: g.area)
        if outline.is_empty or outline.area <= 0:
            return None
        return outline

    def to_floor(self, pixel_xy: Sequence[float]) -> tuple[float, float]:
        x, y = self.homography.apply([list(pixel_xy)])[0]
        return float(x), float(y)

    def detection(
        self,
        pixel_outline: NDArray[Any],
        object_type: ObjectType | str,
        capture_time: float,
        *,
        score: float,
        area_px: float | None = None,
        contact_px: tuple[float, float] | None = None,
        centre_px: tuple[float, float] | None = None,
        marker_id: int | None = None,
        heading_deg: float | None = None,
        label: str = "",
    ) -> Detection | None:
        """A floor detection from a pixel outline (N x 2), or None when it does not map.

        `contact_px` defaults to the bottom centre of the pixel box (where an upright object meets
        the floor); `centre_px`, when given, is mapped as the centroid (a marker's centre) instead
        of the floor outline's centroid.
        """
        pts = np.asarray(pixel_outline, dtype=np.float64).reshape(-1, 2)
        outline = self.floor_outline(pts)
        if outline is None:
            return None
        x0, y0 = np.floor(pts.min(axis=0))
        x1, y1 = np.ceil(pts.max(axis=0))
        x, y, w, h = int(x0), int(y0), max(1, int(x1 - x0)), max(1, int(y1 - y0))
        if contact_px is None:
            contact_px = (x + (w - 1) / 2.0, y + h - 1.0)
        contact = self.to_floor(contact_px)
        if centre_px is not None:
            centroid_xy = self.to_floor(centre_px)
        else:
            c = outline.centroid
            centroid_xy = (float(c.x), float(c.y))
        filter_def = object_type if isinstance(object_type, str) else object_type.filter_def
        return Detection(
            outline=outline,
            bounds=tuple(float(v) for v in outline.bounds),  # type: ignore[arg-type]
            centroid_xy=centroid_xy,
            ground_contact_xy=contact,
            pixel_box=PixelBox(x, y, w, h),
            area_m2=float(outline.area),
            area_px=float(cv2.contourArea(pts.astype(np.float32))) if area_px is None else area_px,
            score=float(score),
            filter_def=filter_def,
            camera_id=self.camera_id,
            capture_time=capture_time,
            marker_id=marker_id,
            heading_deg=heading_deg,
            label=label,
        )

    def blobs(
        self, raw: NDArray[Any], cleaned: NDArray[Any], object_type: ObjectType, capture_time: float
    ) -> tuple[Detection, ...]:
        """The connected blobs of a cleaned-up mask (0/255) of at least min_area_px, largest first,
        mapped to the floor. score: the fraction of a blob's pixels set in `raw` (the mask before
        clean-up filled holes); ground contact: the bottom centre of its pixel box (the contour's)."""
        contours, _ = cv2.findContours(cleaned, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        found: list[Detection] = []
        for contour in contours:
            area_px = float(cv2.contourArea(contour))
            if area_px < self.min_area_px:
                continue
            x, y, w, h = (int(v) for v in cv2.boundingRect(contour))
            blob = np.zeros((h, w), dtype=np.uint8)
            cv2.drawContours(blob, [contour - np.array([x, y], dtype=np.int32)], -1, 255, thickness=cv2.FILLED)
            inside = int(np.count_nonzero(blob))
            hits = int(np.count_nonzero(cv2.bitwise_and(blob, raw[y : y + h, x : x + w])))
            detection = self.detection(
                self.simplified(contour),
                object_type,
                capture_time,
                score=hits / inside if inside else 0.0,
                area_px=area_px,
                contact_px=(x + (w - 1) / 2.0, y + h - 1.0),
            )
            if detection is not None:
                # The pixel box is the contour's, not the simplified outline's.
                found.append(dataclasses.replace(detection, pixel_box=PixelBox(x, y, w, h)))
        found.sort(key=lambda d: d.area_px, reverse=True)
        return tuple(found)

    def simplified(self, contour: NDArray[Any]) -> NDArray[np.float64]:
        """A contour simplified to OUTLINE_TOLERANCE_PX (the contour itself if that degenerates)."""
        simplified = cv2.approxPolyDP(contour, OUTLINE_TOLERANCE_PX, True)
        return (simplified if len(simplified) >= 3 else contour).reshape(-1, 2).astype(np.float64)


def select(found: Sequence[Detection], region: Polygon | None) -> list[Detection]:
    """The detections whose floor outline meets `region` (all of them when None): microseconds."""
    if region is None:
        return list(found)
    shapely.prepare(region)
    return [d for d in found if region.intersects(d.outline)]


#: The command that puts back OpenCV's contrib build when another package's plain cv2 replaced it
#: (opencv-python-headless, which many vision packages pull in, installs over the same cv2 files).
OPENCV_CONTRIB_FIX = (
    "pip uninstall -y opencv-python-headless opencv-python && "
    "pip install --force-reinstall 'opencv-contrib-python-headless>=4.9,<6'"
)


@dataclass(frozen=True)
class Backend:
    """Something a detector needs of this Python that a camera host may lack: an attribute of an
    installed module (`cv2.HOGDescriptor`, `cv2.aruco`), or a module (`onnxruntime`)."""

    #: The module, and the attribute of it ("" for the module itself).
    module: str
    attribute: str
    #: What it is, in an operator's words, and the command that installs it.
    what: str
    fix: str

    @property
    def name(self) -> str:
        return f"{self.module}.{self.attribute}" if self.attribute else self.module

    def missing(self) -> str | None:
        """None when this process has it; else why not (one sentence, without the fix)."""
        import importlib

        try:
            module = importlib.import_module(self.module)
        except ImportError as exc:
            return f"{self.what} needs the Python module {self.module}, which does not import here ({exc})"
        if self.attribute and getattr(module, self.attribute, None) is None:
            where = getattr(module, "__file__", None) or "?"
            version = getattr(module, "__version__", "")
            build = f"{self.module} {version} ({where})" if version else f"{self.module} ({where})"
            return f"{self.what} is missing: {build} has no {self.attribute}"
        return None


#: What the built-in detectors need beyond the base install's always-present parts, by prefix.
#: OpenCV's HOG people detector and ArUco are in the contrib build (OpenCV 5), which a plain
#: opencv-python-headless installed over it removes.
BUILTIN_BACKENDS: dict[str, tuple[Backend, ...]] = {
    "aruco": (Backend("cv2", "aruco", "OpenCV's ArUco module (cv2.aruco, in the contrib build)", OPENCV_CONTRIB_FIX),),
    "people": (
        Backend(
            "cv2",
            "HOGDescriptor",
            "OpenCV's HOG people detector (cv2.HOGDescriptor, in the contrib build)",
            OPENCV_CONTRIB_FIX,
        ),
    ),
}


class DetectorUnavailable(FailedPrecondition):
    """This process cannot run a detector, through no fault of the camera's configuration: a backend
    it needs is not installed, or a file it needs is absent. A camera serves its other detectors;
    `drvs-camera check` lists it as unavailable with `reason` and `fix`."""

    def __init__(self, prefix: str, reason: str, fix: str = "") -> None:
        self.prefix = prefix
        self.reason = reason
        self.fix = fix
        super().__init__(reason + (f"; fix: {fix}" if fix else ""))


class Detector(ABC):
    """A detector plug-in: subclass, set `prefix`, implement `parse` and `find`, and `@register`.

    One instance runs on one camera. `find` runs in a worker thread (a bounded pool when `heavy`),
    at most once per frame and key however many requests ask; it must be thread-safe with respect
    to other keys. Raise DrvsError subclasses (InvalidArgument, FailedPrecondition ...) with a
    message naming what is wrong; a configuration a detector cannot run with is refused in
    `__init__`, when the camera starts, never later request by request.
    """

    #: The filter_def prefix this detector serves ("hsv", "aruco", ...): the registry's key.
    prefix: ClassVar[str]
    #: One example filter_def, for error messages and docs.
    example: ClassVar[str]
    #: About 100 ms a frame or more: run in the camera's bounded worker pool, never prefetched.
    heavy: ClassVar[bool] = False
    #: Sees every frame through `observe` (a background model), not only frames requests look at.
    observes: ClassVar[bool] = False
    #: What it needs that a camera host may lack (a plug-in lists its own; built-ins: BUILTIN_BACKENDS).
    backends: ClassVar[tuple[Backend, ...]] = ()

    @classmethod
    def unavailable(cls) -> DetectorUnavailable | None:
        """Why this process cannot run the detector (the first backend it lacks), or None."""
        for backend in (*BUILTIN_BACKENDS.get(cls.prefix, ()), *cls.backends):
            reason = backend.missing()
            if reason is not None:
                return DetectorUnavailable(cls.prefix, reason, backend.fix)
        return None

    def __init__(self, view: CameraView, options: Mapping[str, Any] | None = None) -> None:
        self.view = view
        self.options: Mapping[str, Any] = options or {}

    def refuse_unknown_options(self, *known: str) -> None:
        """InvalidArgument naming the first option (in sorted order) that is not one of `known`."""
        unknown = sorted(str(key) for key in self.options if key not in known)
        if unknown:
            raise InvalidArgument(f"{self.prefix}: unknown option {unknown[0][:40]!r} (known: {', '.join(known)})")

    @classmethod
    @abstractmethod
    def parse(cls, filter_def: str) -> ObjectType:
        """Validate a filter_def with this prefix; InvalidArgument naming the part that is wrong."""

    def kinds(self) -> tuple[str, ...]:
        """The routing kinds this instance serves (what the camera registers)."""
        return (self.prefix,)

    def unavailable_kinds(self) -> dict[str, DetectorUnavailable]:
        """Kinds this instance was configured for but cannot serve, and why (a model whose file is
        absent, while the detector's other models serve); the camera logs them at start."""
        return {}

    def check(self, object_type: ObjectType) -> None:
        """Refuse (InvalidArgument) a well-formed type this camera's instance cannot serve."""
        return None

    @abstractmethod
    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        """Every object of `object_type.key` in the frame, mapped to the floor."""

    def narrow(self, found: tuple[Detection, ...], object_type: ObjectType) -> tuple[Detection, ...]:
        """Of what `find` returned for the key, what this filter_def asks for (cheap)."""
        return found

    def observe(self, frame: Frame) -> None:
        """Called with new frames when `observes` is set, from one thread."""
        return None

    def close(self) -> None:
        """Free what the detector holds (models, threads)."""
        return None


D = TypeVar("D", bound=type[Detector])

#: Detector classes by prefix, in registration order.
REGISTRY: dict[str, type[Detector]] = {}


def register(cls: D) -> D:
    """Class decorator: make a Detector subclass serve filter_defs starting with its prefix."""
    prefix = cls.prefix
    if not prefix.isalpha() or not prefix.islower():
        raise ValueError(f"detector prefix {prefix!r} must be lower-case letters")
    if prefix in REGISTRY and REGISTRY[prefix] is not cls:
        raise ValueError(f"two detectors claim prefix {prefix!r}: {REGISTRY[prefix].__name__} and {cls.__name__}")
    REGISTRY[prefix] = cls
    add_grammar(prefix, cls.parse, cls.example)  # the server and robots parse it without this module
    return cls


#: The built-in detectors in the order messages and defaults list them (plug-ins follow).
BUILTIN_ORDER = ("hsv", "aruco", "people", "foreground", "model")


def prefixes() -> tuple[str, ...]:
    """Every registered prefix: the built-ins in BUILTIN_ORDER, then plug-ins as they registered."""
    rank = {prefix: i for i, prefix in enumerate(BUILTIN_ORDER)}
    return tuple(sorted(REGISTRY, key=lambda p: rank.get(p, len(rank))))
