"""Domain objects that robot code and camera logic see: dataclasses and shapely geometry."""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, overload

from shapely.geometry import Point, Polygon

from drvs.core.errors import DrvsError, InvalidArgument, error_for, expect_str
from drvs.core.net import parse_address
from drvs.core.object_types import detector_kind, is_known_type

#: Continuous requests are bounded so one request cannot keep cameras busy forever: reports a
#: second, and seconds.
MAX_RATE_HZ = 100.0
MAX_DURATION_S = 3600.0
#: Longest id (request, robot, camera), characters.
MAX_ID_LENGTH = 128
#: The frame of a camera or request that names none: one floor plan, the map.
DEFAULT_FRAME = "map"
MAX_FRAME_LENGTH = 128
#: Longest report key, bytes.
MAX_KEY_BYTES = 64


@dataclass(frozen=True, slots=True)
class PixelBox:
    """An axis-aligned box in the camera's image, in pixels: top-left corner (x, y), width, height."""

    x: int
    y: int
    width: int
    height: int


@dataclass(frozen=True)
class Detection:
    """One object seen by one camera, in floor coordinates (metres).

    - `outline`: the object's floor outline, a shapely Polygon in metres (empty when the request
      asked for no outlines);
    - `bounds`: (x0, y0, x1, y1) of the outline, metres;
    - `centroid_xy` / `centroid`: the outline's centre, metres (`centroid` is a shapely Point);
    - `ground_contact_xy` / `ground_contact`: where the object meets the floor, metres: the
      bottom-centre of the pixel box mapped to the floor (right for upright objects);
    - `pixel_box`: the object's box in the camera image, pixels;
    - `area_m2`: floor area, square metres; `area_px`: image area, pixels;
    - `score`: the detector's confidence in [0, 1];
    - `filter_def`: the filter that found it; `camera_id`: the camera that saw it;
    - `capture_time`: when the frame was taken, seconds since the Unix epoch (the camera's clock).

    `centroid` and `ground_contact` are shapely Points, built when first asked for: a robot that
    reads only the coordinates (or only counts) never pays for the geometry objects.
    """

    outline: Polygon
    bounds: tuple[float, float, float, float]
    centroid_xy: tuple[float, float]
    ground_contact_xy: tuple[float, float]
    pixel_box: PixelBox
    area_m2: float
    area_px: float
    score: float
    filter_def: str
    camera_id: str = ""
    capture_time: float = 0.0
    #: Fiducial markers (aruco_...): the marker's id in its dictionary, else None.
    marker_id: int | None = None
    #: Fiducial markers: the marker's heading on the floor, degrees counter-clockwise from the
    #: world x axis to the marker's x axis, in (-180, 180]; else None.
    heading_deg: float | None = None
    #: Models and people: the class label ("person", a model's class name); else "".
    label: str = ""

    @functools.cached_property
    def centroid(self) -> Point:
        """The outline's centre as a shapely Point, metres."""
        return Point(self.centroid_xy)

    @functools.cached_property
    def ground_contact(self) -> Point:
        """Where the object meets the floor as a shapely Point, metres."""
        return Point(self.ground_contact_xy)


@dataclass(frozen=True, slots=True)
class Pose2:
    """A pose on the floor: position (x, y), metres, and heading `yaw`, radians counter-clockwise
    from the x axis (map frame unless said otherwise). A mobile camera's pose is its robot's base."""

    x: float
    y: float
    yaw: float

    def check(self, name: str = "pose") -> Pose2:
        """InvalidArgument naming `name` when a value is not finite; returns self."""
        for part in ("x", "y", "yaw"):
            if not math.isfinite(getattr(self, part)):
                raise InvalidArgument(f"{name}.{part}: {getattr(self, part)} is not a finite number")
        return self


@dataclass(frozen=True)
class CameraError:
    """Why one camera's answer is missing from a result, as a value.

    `code` is a gRPC status name: UNAVAILABLE (the camera could not be reached, was skipped after a
    failure, is gone without deregistering, or had no fresh frame), DEADLINE_EXCEEDED (no final
    report within the timeout), RESOURCE_EXHAUSTED (busy), FAILED_PRECONDITION ...; `message` says
    what happened; `camera_id` names the camera ("" when the error came without one).
    `exception()` gives the matching drvs.core.errors exception, to raise.
    """

    code: str
    message: str
    camera_id: str = ""

    def exception(self) -> DrvsError:
        """The drvs.core.errors exception for this failure (e.g. Unavailable for UNAVAILABLE), its
        `.code` this code and its `.camera_id` this camera."""
        return error_for(self.code, self.message, camera_id=self.camera_id or None)


@dataclass(frozen=True)
class DetectionReport:
    """What one camera saw for one request at one instant.

    `capture_time`: when the frame was taken, seconds since the Unix epoch; `sequence`: the
    report's number within the request, from 0; `final`: the camera's last report for this
    request; `error` / `error_code`: the camera's failure as text and status name ("" when it
    looked), and `camera_error` the same as a CameraError value (None when it looked).
    """

    request_id: str
    camera_id: str
    capture_time: float
    sequence: int
    final: bool
    detections: tuple[Detection, ...] = ()
    error: str = ""
    #: With error: the gRPC status name that types it (UNAVAILABLE, DEADLINE_EXCEEDED ...).
    error_code: str = ""
    #: A mobile camera's robot base pose (map frame) at capture_time, through which its detections
    #: were mapped to the floor; None for a fixed camera.
    camera_pose: Pose2 | None = None

    @property
    def camera_error(self) -> CameraError | None:
        """The camera's failure as a typed value, or None when the camera looked."""
        if not self.error:
            return None
        return CameraError(self.error_code or "UNKNOWN", self.error, self.camera_id)


@dataclass(frozen=True)
class ContinuousMode:
    """How often and how long a camera reports: `rate_hz` reports a second for `duration_s`
    seconds; both 0 is a single shot (one report)."""

    rate_hz: float = 0.0
    duration_s: float = 0.0

    @property
    def single_shot(self) -> bool:
        return self.rate_hz == 0.0 and self.duration_s == 0.0

    def validate(self) -> None:
        for name, value, limit in (
            ("continuous.rate_hz", self.rate_hz, MAX_RATE_HZ),
            ("continuous.duration_s", self.duration_s, MAX_DURATION_S),
        ):
            if not math.isfinite(value) or value < 0:
                raise InvalidArgument(f"{name}: {value} must be a finite number >= 0")
            if value > limit:
                raise InvalidArgument(f"{name}: {value:g} exceeds the limit of {limit:g}")
        if (self.rate_hz == 0) != (self.duration_s == 0):
            raise InvalidArgument(
                "continuous: rate_hz and duration_s must both be > 0 (continuous) or both 0 (single shot); "
                f"got rate_hz={self.rate_hz:g}, duration_s={self.duration_s:g}"
            )

    def report_times(self) -> ReportTimes:
        """Offsets (s) from the start at which reports are taken; the last one is final."""
        if self.single_shot:
            return ReportTimes(1, 0.0)
        return ReportTimes(math.floor(self.duration_s * self.rate_hz + 1e-9) + 1, 1.0 / self.rate_hz)


class ReportTimes(Sequence[float]):
    """A request's report offsets, each computed when asked for: a 100 Hz request for an hour has
    360 001 of them, which as a list of floats took 14 MB per request on the camera."""

    __slots__ = ("_count", "_period")

    def __init__(self, count: int, period: float) -> None:
        self._count = count
        self._period = period

    def __len__(self) -> int:
        return self._count

    @overload
    def __getitem__(self, index: int) -> float: ...

    @overload
    def __getitem__(self, index: slice) -> list[float]: ...

    def __getitem__(self, index: int | slice) -> float | list[float]:
        if isinstance(index, slice):
            return [i * self._period for i in range(*index.indices(self._count))]
        i = index + self._count if index < 0 else index
        if not 0 <= i < self._count:
            raise IndexError(f"report {index} of {self._count}")
        return i * self._period

    def __eq__(self, other: object) -> bool:
        if isinstance(other, ReportTimes):
            return (self._count, self._period) == (other._count, other._period)
        if isinstance(other, Sequence) and not isinstance(other, str):
            return len(other) == self._count and all(a == b for a, b in zip(self, other, strict=True))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"ReportTimes(count={self._count}, period={self._period:g})"


#: Fused requests: the longest a single shot may wait for its cameras, and the longest a track may
#: go unseen before it is dropped, seconds.
MAX_FUSION_DEADLINE_S = 30.0
MAX_FUSION_DROP_AFTER_S = 60.0
#: ... and what zero means.
DEFAULT_FUSION_DEADLINE_S = 2.0
DEFAULT_FUSION_DROP_AFTER_S = 1.0


@dataclass(frozen=True)
class FusionOptions:
    """How the server fuses a request's reports into world objects (see `WorldObject`).

    - `deadline_s`: a single shot answers with what it has this many seconds after dispatch, naming
      the cameras that did not report; in a continuous request, how late after its period a report
      may still count. 0: the default (2 s single shot, one period continuous).
    - `drop_after_s`: continuous requests: a track no camera has seen for this long is dropped.
      0: the default (1 s).
    - `compact_geometry`: the server may send centroids, bounds and velocities as millimetre
      integers (`WorldObject.geometry_mm`), which this package reads; False for a request from a
      robot that did not say so (an older one), which gets them as floats.
    """

    deadline_s: float = 0.0
    drop_after_s: float = 0.0
    compact_geometry: bool = True

    def validate(self) -> None:
        for name, value, most in (
            ("deadline_s", self.deadline_s, MAX_FUSION_DEADLINE_S),
            ("drop_after_s", self.drop_after_s, MAX_FUSION_DROP_AFTER_S),
        ):
            if not (math.isfinite(value) and 0 <= value <= most):
                raise InvalidArgument(f"fusion.{name}: {value!r} is not between 0 and {most:g} seconds")

    @property
    def single_shot_deadline_s(self) -> float:
        return self.deadline_s or DEFAULT_FUSION_DEADLINE_S

    @property
    def track_drop_after_s(self) -> float:
        return self.drop_after_s or DEFAULT_FUSION_DROP_AFTER_S


class _Unset:
    """A keyword not given (None is a value: no course)."""


_UNSET = _Unset()


class WorldObject:
    """One physical object as the server's fusion of several cameras sees it, in the map frame.

    - `track_id`: stable across a continuous request's snapshots while the object is tracked;
      numbered 1, 2, ... in a single shot;
    - `outline`: the fused floor outline (shapely Polygon, metres; empty when outlines were omitted);
      `bounds`: (x0, y0, x1, y1), metres;
    - `centroid_xy`: the precision-weighted (and, when tracked, filtered) centre, metres;
    - `velocity_xy`: m/s in the map frame, (0, 0) in a single shot; `course_deg`: the direction of
      motion, degrees counter-clockwise from +x, None when not moving (`heading_deg`, its old name,
      is deprecated: on a Detection `heading_deg` is a marker's heading, here `marker_heading_deg`);
    - `uncertainty_m`: one standard deviation of the centroid, metres;
    - `camera_ids`: the cameras merged into it in this snapshot (empty: predicted, unseen this period);
    - `last_seen`: capture time of the newest frame that saw it, seconds since the Unix epoch;
    - `marker_id`, `marker_heading_deg`, `label`: type fields as the cameras reported them;
      `score`: the best detector confidence merged; `area_m2`: the fused outline's area.
    """

    if TYPE_CHECKING:  # a dataclass (see below), which type checkers are told here
        __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    track_id: int
    outline: Polygon
    bounds: tuple[float, float, float, float]
    centroid_xy: tuple[float, float]
    velocity_xy: tuple[float, float] = (0.0, 0.0)
    course_deg: float | None = None
    uncertainty_m: float = 0.0
    camera_ids: tuple[str, ...] = ()
    last_seen: float = 0.0
    marker_id: int | None = None
    marker_heading_deg: float | None = None
    label: str = ""
    score: float = 0.0
    area_m2: float = 0.0

    def __init__(
        self,
        track_id: int,
        outline: Polygon,
        bounds: tuple[float, float, float, float],
        centroid_xy: tuple[float, float],
        velocity_xy: tuple[float, float] = (0.0, 0.0),
        course_deg: float | None = None,
        uncertainty_m: float = 0.0,
        camera_ids: tuple[str, ...] = (),
        last_seen: float = 0.0,
        marker_id: int | None = None,
        marker_heading_deg: float | None = None,
        label: str = "",
        score: float = 0.0,
        area_m2: float = 0.0,
        *,
        heading_deg: float | _Unset | None = _UNSET,
    ) -> None:
        """The dataclass's fields in order. `heading_deg=`, course_deg's old keyword, is accepted
        for one release, and when given it is the course (so dataclasses.replace(o, heading_deg=h)
        sets it); written out rather than generated only for it."""
        if not isinstance(heading_deg, _Unset):
            course_deg = heading_deg
        # Into the instance's dict, as the frozen dataclass's own __init__ does through
        # object.__setattr__, at a fifth of the cost: a robot following a track at 30 Hz builds one
        # for every object of every snapshot.
        d = self.__dict__
        d["track_id"] = track_id
        d["outline"] = outline
        d["bounds"] = bounds
        d["centroid_xy"] = centroid_xy
        d["velocity_xy"] = velocity_xy
        d["course_deg"] = course_deg
        d["uncertainty_m"] = uncertainty_m
        d["camera_ids"] = camera_ids
        d["last_seen"] = last_seen
        d["marker_id"] = marker_id
        d["marker_heading_deg"] = marker_heading_deg
        d["label"] = label
        d["score"] = score
        d["area_m2"] = area_m2

    @property
    def heading_deg(self) -> float | None:
        """Deprecated (removed next release): `course_deg`, the direction of motion."""
        warnings.warn(
            "WorldObject.heading_deg is deprecated: use WorldObject.course_deg (the direction of motion; "
            "a marker's heading is marker_heading_deg)",
            DeprecationWarning,
            stacklevel=2,
        )
        return self.course_deg

    @property
    def speed_mps(self) -> float:
        """|velocity|, m/s."""
        return math.hypot(*self.velocity_xy)

    def predicted_xy(self, at: float) -> tuple[float, float]:
        """The centroid moved on at constant velocity to time `at` (seconds since the Unix epoch)."""
        dt = at - self.last_seen
        return (self.centroid_xy[0] + self.velocity_xy[0] * dt, self.centroid_xy[1] + self.velocity_xy[1] * dt)


# A frozen dataclass (eq, hash, repr, fields, replace) with the __init__ written above: made by calling
# dataclass() rather than decorating, so that type checkers take that __init__, heading_deg= included,
# for its signature and for dataclasses.replace's. Back to @dataclass(frozen=True) with heading_deg gone.
dataclass(frozen=True, init=False)(WorldObject)


def errors_by_camera(errors: Iterable[CameraError]) -> dict[str, CameraError]:
    """CameraErrors as camera id -> CameraError, in their order (a camera named twice: its first)."""
    by_camera: dict[str, CameraError] = {}
    for error in errors:
        by_camera.setdefault(error.camera_id, error)
    return by_camera


class Snapshot:
    """The fused answer to a request at one instant: once for a single shot, once per period for a
    continuous request. Unpacks as `time, objects, errors` (errors: the `CameraError`s, as a tuple).

    - `time`: the instant described, seconds since the Unix epoch;
    - `objects`: the world objects;
    - `camera_errors`: camera id -> `CameraError` for each camera that should have counted and did
      not (as on a DetectionResult and a Track); `missing_cameras`, the same CameraErrors as a
      tuple, is deprecated (next release it becomes the camera ids, as on a DetectionResult);
    - `camera_ids`: the cameras whose reports were merged; `sequence`: 0, 1, ...; `final`: the last;
    - `request_id`: the request it answers;
    - `uncovered`: the parts of the region (Polygons, metres) no camera asked sees: not known to be
      clear (the server's reply to the request; the same for each snapshot of a track).
    """

    if TYPE_CHECKING:  # a dataclass (see below), which type checkers are told here
        __dataclass_fields__: ClassVar[dict[str, dataclasses.Field[Any]]]

    time: float
    objects: tuple[WorldObject, ...] = ()
    #: In the order the server named them; not hashed (a dict).
    camera_errors: Mapping[str, CameraError] = field(default_factory=dict, hash=False)
    camera_ids: tuple[str, ...] = ()
    sequence: int = 0
    final: bool = True
    request_id: str = ""
    uncovered: tuple[Polygon, ...] = ()

    def __init__(
        self,
        time: float,
        objects: tuple[WorldObject, ...] = (),
        camera_errors: Mapping[str, CameraError] | None = None,
        camera_ids: tuple[str, ...] = (),
        sequence: int = 0,
        final: bool = True,
        request_id: str = "",
        uncovered: tuple[Polygon, ...] = (),
        *,
        missing_cameras: Sequence[CameraError] | _Unset = _UNSET,
    ) -> None:
        """The dataclass's fields in order. `missing_cameras=` (CameraErrors), camera_errors' old
        keyword, is accepted for one release, and when given it is the errors (so
        dataclasses.replace(s, missing_cameras=...) sets them); written out only for it."""
        if not isinstance(missing_cameras, _Unset):
            camera_errors = errors_by_camera(missing_cameras)
        d = self.__dict__  # as WorldObject's: one a period for a robot following a track
        d["time"] = time
        d["objects"] = objects
        d["camera_errors"] = {} if camera_errors is None else camera_errors
        d["camera_ids"] = camera_ids
        d["sequence"] = sequence
        d["final"] = final
        d["request_id"] = request_id
        d["uncovered"] = uncovered

    @property
    def all_seen(self) -> bool:
        """True when the whole region was looked at by every camera it needed: only then does no
        object mean nothing there."""
        return not self.camera_errors and not self.uncovered

    @property
    def missing_cameras(self) -> tuple[CameraError, ...]:
        """Deprecated (removed next release, when `missing_cameras` becomes the camera ids as on
        DetectionResult): the CameraErrors of `camera_errors`, as a tuple."""
        warnings.warn(
            "Snapshot.missing_cameras is deprecated: use Snapshot.camera_errors (camera id -> CameraError)",
            DeprecationWarning,
            stacklevel=2,
        )
        return tuple(self.camera_errors.values())

    def __iter__(self) -> Iterator[Any]:
        """`time, objects, errors = snapshot`: a float, a tuple of WorldObjects and a tuple of
        CameraErrors. Typed Any: one iterator cannot give each its own type (read `snapshot.time`,
        `.objects`, `.camera_errors` where a type checker should see them)."""
        return iter((self.time, self.objects, tuple(self.camera_errors.values())))


# As WorldObject: a frozen dataclass with the __init__ above (missing_cameras= for one release).
dataclass(frozen=True, init=False)(Snapshot)


@dataclass(frozen=True)
class DetectionRequest:
    """A validated request: what to look for, where, and where to send the reports (or, with
    `fusion` set, that the server fuses them and answers on the request's own call)."""

    request_id: str
    robot_id: str
    filter_def: str
    region: Polygon
    callback_address: str
    continuous: ContinuousMode = field(default_factory=ContinuousMode)
    omit_outlines: bool = False
    #: What the camera presents to the robot for this request (see drvs.wire.report_auth); from the server.
    report_key: bytes = b""
    #: Set: the server fuses the cameras' reports; callback_address is not used.
    fusion: FusionOptions | None = None
    #: Server -> camera: report to the server this camera registered with, not to callback_address.
    report_to_server: bool = False
    #: Server -> camera, with report_to_server: the forwarding server's own address ("": the one
    #: the camera registered with).
    report_address: str = ""
    #: The floor plan the region is in ("building-a/floor-2"); only cameras of this frame are asked.
    frame: str = DEFAULT_FRAME

    def validate(self, *, require_request_id: bool = True, unknown_types: bool = False) -> None:
        """Everything but the region, which is validated when it is built. unknown_types=True (the
        robot's side): a filter_def whose type this process has no detector plug-in for is left to
        the server, which knows what its cameras serve; types it knows are checked here (by the
        grammar, drvs.core.object_types: no detector is loaded)."""
        if require_request_id and not self.request_id:
            raise InvalidArgument("request_id: empty")
        check_id(self.request_id, "request_id", allow_empty=not require_request_id)
        check_id(self.robot_id, "robot_id", allow_empty=True)
        expect_str(self.filter_def, "filter_def")  # robot code's Python, before the wire's types check it
        if not (unknown_types and self.filter_def and not is_known_type(self.filter_def)):
            detector_kind(self.filter_def)
        elif len(self.filter_def) > MAX_ID_LENGTH:
            raise InvalidArgument(f"filter_def: longer than {MAX_ID_LENGTH} characters")
        if self.fusion is not None:
            self.fusion.validate()
        if self.fusion is None and not self.report_to_server:
            parse_address(self.callback_address, "callback_address")
        if self.report_address:
            parse_address(self.report_address, "report_address")
        self.continuous.validate()
        check_frame(self.frame)
        if len(self.report_key) > MAX_KEY_BYTES:
            raise InvalidArgument(f"report_key: longer than {MAX_KEY_BYTES} bytes")

    @property
    def kind(self) -> str:
        """The routing kind of the filter_def (hsv, aruco, people, foreground, model_<name>)."""
        return detector_kind(self.filter_def)


def check_frame(value: str, name: str = "frame") -> str:
    """A frame: one or more ids joined by "/" ("building-a/floor-2"), at most MAX_FRAME_LENGTH
    characters; "" is the default, "map". InvalidArgument naming `name` otherwise."""
    expect_str(value, name)  # robot and camera code's Python, before the wire's types
    if not value:
        return DEFAULT_FRAME
    if len(value) > MAX_FRAME_LENGTH:
        raise InvalidArgument(f"{name}: longer than {MAX_FRAME_LENGTH} characters")
    for part in value.split("/"):
        if not part or not (part.isascii() and all(c.isalnum() or c in "-_.:" for c in part)):
            raise InvalidArgument(
                f"{name}: {value[:40]!r} is not ids joined by '/' (letters, digits and - _ . : in each), "
                "e.g. building-a/floor-2"
            )
    return value


def check_id(value: str, name: str, *, allow_empty: bool = False) -> str:
    """`value` if it is a valid id (at most MAX_ID_LENGTH characters: letters, digits, - _ . :),
    else InvalidArgument naming `name`."""
    expect_str(value, name)  # robot and camera code's Python, before the wire's types
    if not value:
        if allow_empty:
            return value
        raise InvalidArgument(f"{name}: empty")
    if len(value) > MAX_ID_LENGTH:
        raise InvalidArgument(f"{name}: longer than {MAX_ID_LENGTH} characters")
    if not (value.isascii() and all(c.isalnum() or c in "-_.:" for c in value)):
        raise InvalidArgument(f"{name}: {value[:40]!r} may hold only letters, digits and - _ . :")
    return value
