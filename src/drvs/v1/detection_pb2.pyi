import datetime

from drvs.v1 import geometry_pb2 as _geometry_pb2
from google.protobuf import timestamp_pb2 as _timestamp_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ContinuousMode(_message.Message):
    __slots__ = ("rate_hz", "duration_s")
    RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    DURATION_S_FIELD_NUMBER: _ClassVar[int]
    rate_hz: float
    duration_s: float
    def __init__(self, rate_hz: _Optional[float] = ..., duration_s: _Optional[float] = ...) -> None: ...

class DetectionRequest(_message.Message):
    __slots__ = ("request_id", "robot_id", "filter_def", "region", "callback_address", "continuous", "omit_outlines", "report_secret", "report_key", "cancel", "fusion", "report_to_server", "frame", "report_address", "requester")
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    ROBOT_ID_FIELD_NUMBER: _ClassVar[int]
    FILTER_DEF_FIELD_NUMBER: _ClassVar[int]
    REGION_FIELD_NUMBER: _ClassVar[int]
    CALLBACK_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    CONTINUOUS_FIELD_NUMBER: _ClassVar[int]
    OMIT_OUTLINES_FIELD_NUMBER: _ClassVar[int]
    REPORT_SECRET_FIELD_NUMBER: _ClassVar[int]
    REPORT_KEY_FIELD_NUMBER: _ClassVar[int]
    CANCEL_FIELD_NUMBER: _ClassVar[int]
    FUSION_FIELD_NUMBER: _ClassVar[int]
    REPORT_TO_SERVER_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    REPORT_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    REQUESTER_FIELD_NUMBER: _ClassVar[int]
    request_id: str
    robot_id: str
    filter_def: str
    region: _geometry_pb2.Region
    callback_address: str
    continuous: ContinuousMode
    omit_outlines: bool
    report_secret: bytes
    report_key: bytes
    cancel: bool
    fusion: FusionOptions
    report_to_server: bool
    frame: str
    report_address: str
    requester: str
    def __init__(self, request_id: _Optional[str] = ..., robot_id: _Optional[str] = ..., filter_def: _Optional[str] = ..., region: _Optional[_Union[_geometry_pb2.Region, _Mapping]] = ..., callback_address: _Optional[str] = ..., continuous: _Optional[_Union[ContinuousMode, _Mapping]] = ..., omit_outlines: bool = ..., report_secret: _Optional[bytes] = ..., report_key: _Optional[bytes] = ..., cancel: bool = ..., fusion: _Optional[_Union[FusionOptions, _Mapping]] = ..., report_to_server: bool = ..., frame: _Optional[str] = ..., report_address: _Optional[str] = ..., requester: _Optional[str] = ...) -> None: ...

class FusionOptions(_message.Message):
    __slots__ = ("deadline_s", "drop_after_s", "compact_geometry")
    DEADLINE_S_FIELD_NUMBER: _ClassVar[int]
    DROP_AFTER_S_FIELD_NUMBER: _ClassVar[int]
    COMPACT_GEOMETRY_FIELD_NUMBER: _ClassVar[int]
    deadline_s: float
    drop_after_s: float
    compact_geometry: bool
    def __init__(self, deadline_s: _Optional[float] = ..., drop_after_s: _Optional[float] = ..., compact_geometry: bool = ...) -> None: ...

class WorldObject(_message.Message):
    __slots__ = ("track_id", "outline_xy", "bounds", "centroid", "velocity", "heading_deg", "uncertainty_m", "camera_ids", "marker_id", "label", "score", "area_m2", "last_seen", "marker_heading_deg", "last_seen_age_s", "camera_index", "geometry_mm")
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    OUTLINE_XY_FIELD_NUMBER: _ClassVar[int]
    BOUNDS_FIELD_NUMBER: _ClassVar[int]
    CENTROID_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_FIELD_NUMBER: _ClassVar[int]
    HEADING_DEG_FIELD_NUMBER: _ClassVar[int]
    UNCERTAINTY_M_FIELD_NUMBER: _ClassVar[int]
    CAMERA_IDS_FIELD_NUMBER: _ClassVar[int]
    MARKER_ID_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    AREA_M2_FIELD_NUMBER: _ClassVar[int]
    LAST_SEEN_FIELD_NUMBER: _ClassVar[int]
    MARKER_HEADING_DEG_FIELD_NUMBER: _ClassVar[int]
    LAST_SEEN_AGE_S_FIELD_NUMBER: _ClassVar[int]
    CAMERA_INDEX_FIELD_NUMBER: _ClassVar[int]
    GEOMETRY_MM_FIELD_NUMBER: _ClassVar[int]
    track_id: int
    outline_xy: _containers.RepeatedScalarFieldContainer[float]
    bounds: _geometry_pb2.FloorBox
    centroid: _geometry_pb2.FloorPoint
    velocity: _geometry_pb2.FloorPoint
    heading_deg: float
    uncertainty_m: float
    camera_ids: _containers.RepeatedScalarFieldContainer[str]
    marker_id: int
    label: str
    score: float
    area_m2: float
    last_seen: _timestamp_pb2.Timestamp
    marker_heading_deg: float
    last_seen_age_s: float
    camera_index: _containers.RepeatedScalarFieldContainer[int]
    geometry_mm: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, track_id: _Optional[int] = ..., outline_xy: _Optional[_Iterable[float]] = ..., bounds: _Optional[_Union[_geometry_pb2.FloorBox, _Mapping]] = ..., centroid: _Optional[_Union[_geometry_pb2.FloorPoint, _Mapping]] = ..., velocity: _Optional[_Union[_geometry_pb2.FloorPoint, _Mapping]] = ..., heading_deg: _Optional[float] = ..., uncertainty_m: _Optional[float] = ..., camera_ids: _Optional[_Iterable[str]] = ..., marker_id: _Optional[int] = ..., label: _Optional[str] = ..., score: _Optional[float] = ..., area_m2: _Optional[float] = ..., last_seen: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., marker_heading_deg: _Optional[float] = ..., last_seen_age_s: _Optional[float] = ..., camera_index: _Optional[_Iterable[int]] = ..., geometry_mm: _Optional[_Iterable[int]] = ...) -> None: ...

class WorldSnapshot(_message.Message):
    __slots__ = ("time", "sequence", "final", "objects", "missing_cameras", "camera_ids")
    TIME_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    FINAL_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    MISSING_CAMERAS_FIELD_NUMBER: _ClassVar[int]
    CAMERA_IDS_FIELD_NUMBER: _ClassVar[int]
    time: _timestamp_pb2.Timestamp
    sequence: int
    final: bool
    objects: _containers.RepeatedCompositeFieldContainer[WorldObject]
    missing_cameras: _containers.RepeatedCompositeFieldContainer[MissingCamera]
    camera_ids: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., sequence: _Optional[int] = ..., final: bool = ..., objects: _Optional[_Iterable[_Union[WorldObject, _Mapping]]] = ..., missing_cameras: _Optional[_Iterable[_Union[MissingCamera, _Mapping]]] = ..., camera_ids: _Optional[_Iterable[str]] = ...) -> None: ...

class RequestError(_message.Message):
    __slots__ = ("code", "message", "retry_after_s")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    RETRY_AFTER_S_FIELD_NUMBER: _ClassVar[int]
    code: str
    message: str
    retry_after_s: float
    def __init__(self, code: _Optional[str] = ..., message: _Optional[str] = ..., retry_after_s: _Optional[float] = ...) -> None: ...

class MissingCamera(_message.Message):
    __slots__ = ("camera_id", "code", "message")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    code: str
    message: str
    def __init__(self, camera_id: _Optional[str] = ..., code: _Optional[str] = ..., message: _Optional[str] = ...) -> None: ...

class DetectionReply(_message.Message):
    __slots__ = ("request_id", "camera_ids", "error", "missing_cameras", "uncovered", "coverage_uncertain_s", "snapshot")
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    CAMERA_IDS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    MISSING_CAMERAS_FIELD_NUMBER: _ClassVar[int]
    UNCOVERED_FIELD_NUMBER: _ClassVar[int]
    COVERAGE_UNCERTAIN_S_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    request_id: str
    camera_ids: _containers.RepeatedScalarFieldContainer[str]
    error: RequestError
    missing_cameras: _containers.RepeatedCompositeFieldContainer[MissingCamera]
    uncovered: _containers.RepeatedCompositeFieldContainer[_geometry_pb2.Polygon]
    coverage_uncertain_s: float
    snapshot: WorldSnapshot
    def __init__(self, request_id: _Optional[str] = ..., camera_ids: _Optional[_Iterable[str]] = ..., error: _Optional[_Union[RequestError, _Mapping]] = ..., missing_cameras: _Optional[_Iterable[_Union[MissingCamera, _Mapping]]] = ..., uncovered: _Optional[_Iterable[_Union[_geometry_pb2.Polygon, _Mapping]]] = ..., coverage_uncertain_s: _Optional[float] = ..., snapshot: _Optional[_Union[WorldSnapshot, _Mapping]] = ...) -> None: ...

class DetectionRequests(_message.Message):
    __slots__ = ("requests",)
    REQUESTS_FIELD_NUMBER: _ClassVar[int]
    requests: _containers.RepeatedCompositeFieldContainer[DetectionRequest]
    def __init__(self, requests: _Optional[_Iterable[_Union[DetectionRequest, _Mapping]]] = ...) -> None: ...

class DetectionReplies(_message.Message):
    __slots__ = ("replies",)
    REPLIES_FIELD_NUMBER: _ClassVar[int]
    replies: _containers.RepeatedCompositeFieldContainer[DetectionReply]
    def __init__(self, replies: _Optional[_Iterable[_Union[DetectionReply, _Mapping]]] = ...) -> None: ...

class Detection(_message.Message):
    __slots__ = ("outline_xy", "bounds", "centroid", "ground_contact", "pixel_box", "area_m2", "area_px", "score", "marker_id", "heading_deg", "label")
    OUTLINE_XY_FIELD_NUMBER: _ClassVar[int]
    BOUNDS_FIELD_NUMBER: _ClassVar[int]
    CENTROID_FIELD_NUMBER: _ClassVar[int]
    GROUND_CONTACT_FIELD_NUMBER: _ClassVar[int]
    PIXEL_BOX_FIELD_NUMBER: _ClassVar[int]
    AREA_M2_FIELD_NUMBER: _ClassVar[int]
    AREA_PX_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    MARKER_ID_FIELD_NUMBER: _ClassVar[int]
    HEADING_DEG_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    outline_xy: _containers.RepeatedScalarFieldContainer[float]
    bounds: _geometry_pb2.FloorBox
    centroid: _geometry_pb2.FloorPoint
    ground_contact: _geometry_pb2.FloorPoint
    pixel_box: _geometry_pb2.PixelBox
    area_m2: float
    area_px: float
    score: float
    marker_id: int
    heading_deg: float
    label: str
    def __init__(self, outline_xy: _Optional[_Iterable[float]] = ..., bounds: _Optional[_Union[_geometry_pb2.FloorBox, _Mapping]] = ..., centroid: _Optional[_Union[_geometry_pb2.FloorPoint, _Mapping]] = ..., ground_contact: _Optional[_Union[_geometry_pb2.FloorPoint, _Mapping]] = ..., pixel_box: _Optional[_Union[_geometry_pb2.PixelBox, _Mapping]] = ..., area_m2: _Optional[float] = ..., area_px: _Optional[float] = ..., score: _Optional[float] = ..., marker_id: _Optional[int] = ..., heading_deg: _Optional[float] = ..., label: _Optional[str] = ...) -> None: ...

class DetectionReport(_message.Message):
    __slots__ = ("request_id", "camera_id", "capture_time", "sequence", "final", "detections", "error", "report_key", "error_code", "camera_pose")
    REQUEST_ID_FIELD_NUMBER: _ClassVar[int]
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_TIME_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    FINAL_FIELD_NUMBER: _ClassVar[int]
    DETECTIONS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    REPORT_KEY_FIELD_NUMBER: _ClassVar[int]
    ERROR_CODE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_POSE_FIELD_NUMBER: _ClassVar[int]
    request_id: str
    camera_id: str
    capture_time: _timestamp_pb2.Timestamp
    sequence: int
    final: bool
    detections: _containers.RepeatedCompositeFieldContainer[Detection]
    error: str
    report_key: bytes
    error_code: str
    camera_pose: _geometry_pb2.Pose2
    def __init__(self, request_id: _Optional[str] = ..., camera_id: _Optional[str] = ..., capture_time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ..., sequence: _Optional[int] = ..., final: bool = ..., detections: _Optional[_Iterable[_Union[Detection, _Mapping]]] = ..., error: _Optional[str] = ..., report_key: _Optional[bytes] = ..., error_code: _Optional[str] = ..., camera_pose: _Optional[_Union[_geometry_pb2.Pose2, _Mapping]] = ...) -> None: ...

class ReportControl(_message.Message):
    __slots__ = ("cancelled_request_ids",)
    CANCELLED_REQUEST_IDS_FIELD_NUMBER: _ClassVar[int]
    cancelled_request_ids: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, cancelled_request_ids: _Optional[_Iterable[str]] = ...) -> None: ...
