from drvs.v1 import geometry_pb2 as _geometry_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Homography(_message.Message):
    __slots__ = ("m",)
    M_FIELD_NUMBER: _ClassVar[int]
    m: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, m: _Optional[_Iterable[float]] = ...) -> None: ...

class RegisterRequest(_message.Message):
    __slots__ = ("camera_id", "address", "homography", "image_width", "image_height", "max_range_m", "detector_kinds", "registration_secret", "forward_secret", "mobile", "pose_lease_s", "frame", "max_speed_mps")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    ADDRESS_FIELD_NUMBER: _ClassVar[int]
    HOMOGRAPHY_FIELD_NUMBER: _ClassVar[int]
    IMAGE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    IMAGE_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_M_FIELD_NUMBER: _ClassVar[int]
    DETECTOR_KINDS_FIELD_NUMBER: _ClassVar[int]
    REGISTRATION_SECRET_FIELD_NUMBER: _ClassVar[int]
    FORWARD_SECRET_FIELD_NUMBER: _ClassVar[int]
    MOBILE_FIELD_NUMBER: _ClassVar[int]
    POSE_LEASE_S_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    MAX_SPEED_MPS_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    address: str
    homography: Homography
    image_width: int
    image_height: int
    max_range_m: float
    detector_kinds: _containers.RepeatedScalarFieldContainer[str]
    registration_secret: str
    forward_secret: str
    mobile: bool
    pose_lease_s: float
    frame: str
    max_speed_mps: float
    def __init__(self, camera_id: _Optional[str] = ..., address: _Optional[str] = ..., homography: _Optional[_Union[Homography, _Mapping]] = ..., image_width: _Optional[int] = ..., image_height: _Optional[int] = ..., max_range_m: _Optional[float] = ..., detector_kinds: _Optional[_Iterable[str]] = ..., registration_secret: _Optional[str] = ..., forward_secret: _Optional[str] = ..., mobile: bool = ..., pose_lease_s: _Optional[float] = ..., frame: _Optional[str] = ..., max_speed_mps: _Optional[float] = ...) -> None: ...

class RegisterReply(_message.Message):
    __slots__ = ("lease_ttl_s", "field_of_view", "registration_secret", "unroutable", "pose_lease_s", "min_pose_interval_s")
    LEASE_TTL_S_FIELD_NUMBER: _ClassVar[int]
    FIELD_OF_VIEW_FIELD_NUMBER: _ClassVar[int]
    REGISTRATION_SECRET_FIELD_NUMBER: _ClassVar[int]
    UNROUTABLE_FIELD_NUMBER: _ClassVar[int]
    POSE_LEASE_S_FIELD_NUMBER: _ClassVar[int]
    MIN_POSE_INTERVAL_S_FIELD_NUMBER: _ClassVar[int]
    lease_ttl_s: float
    field_of_view: _geometry_pb2.Polygon
    registration_secret: str
    unroutable: str
    pose_lease_s: float
    min_pose_interval_s: float
    def __init__(self, lease_ttl_s: _Optional[float] = ..., field_of_view: _Optional[_Union[_geometry_pb2.Polygon, _Mapping]] = ..., registration_secret: _Optional[str] = ..., unroutable: _Optional[str] = ..., pose_lease_s: _Optional[float] = ..., min_pose_interval_s: _Optional[float] = ...) -> None: ...

class UpdatePoseRequest(_message.Message):
    __slots__ = ("camera_id", "registration_secret", "pose", "pose_time_unix")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    REGISTRATION_SECRET_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    POSE_TIME_UNIX_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    registration_secret: str
    pose: _geometry_pb2.Pose2
    pose_time_unix: float
    def __init__(self, camera_id: _Optional[str] = ..., registration_secret: _Optional[str] = ..., pose: _Optional[_Union[_geometry_pb2.Pose2, _Mapping]] = ..., pose_time_unix: _Optional[float] = ...) -> None: ...

class UpdatePoseReply(_message.Message):
    __slots__ = ("field_of_view", "pose_lease_s")
    FIELD_OF_VIEW_FIELD_NUMBER: _ClassVar[int]
    POSE_LEASE_S_FIELD_NUMBER: _ClassVar[int]
    field_of_view: _geometry_pb2.Polygon
    pose_lease_s: float
    def __init__(self, field_of_view: _Optional[_Union[_geometry_pb2.Polygon, _Mapping]] = ..., pose_lease_s: _Optional[float] = ...) -> None: ...

class HeartbeatRequest(_message.Message):
    __slots__ = ("camera_id", "registration_secret")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    REGISTRATION_SECRET_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    registration_secret: str
    def __init__(self, camera_id: _Optional[str] = ..., registration_secret: _Optional[str] = ...) -> None: ...

class HeartbeatReply(_message.Message):
    __slots__ = ("lease_ttl_s",)
    LEASE_TTL_S_FIELD_NUMBER: _ClassVar[int]
    lease_ttl_s: float
    def __init__(self, lease_ttl_s: _Optional[float] = ...) -> None: ...

class DeregisterRequest(_message.Message):
    __slots__ = ("camera_id", "registration_secret")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    REGISTRATION_SECRET_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    registration_secret: str
    def __init__(self, camera_id: _Optional[str] = ..., registration_secret: _Optional[str] = ...) -> None: ...

class DeregisterReply(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListCamerasRequest(_message.Message):
    __slots__ = ("region", "page_size", "page_token", "frame")
    REGION_FIELD_NUMBER: _ClassVar[int]
    PAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    region: _geometry_pb2.Region
    page_size: int
    page_token: str
    frame: str
    def __init__(self, region: _Optional[_Union[_geometry_pb2.Region, _Mapping]] = ..., page_size: _Optional[int] = ..., page_token: _Optional[str] = ..., frame: _Optional[str] = ...) -> None: ...

class CameraInfo(_message.Message):
    __slots__ = ("camera_id", "address", "field_of_view", "detector_kinds", "lease_remaining_s", "mobile", "pose", "pose_age_s", "unroutable", "frame")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    ADDRESS_FIELD_NUMBER: _ClassVar[int]
    FIELD_OF_VIEW_FIELD_NUMBER: _ClassVar[int]
    DETECTOR_KINDS_FIELD_NUMBER: _ClassVar[int]
    LEASE_REMAINING_S_FIELD_NUMBER: _ClassVar[int]
    MOBILE_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    POSE_AGE_S_FIELD_NUMBER: _ClassVar[int]
    UNROUTABLE_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    address: str
    field_of_view: _geometry_pb2.Polygon
    detector_kinds: _containers.RepeatedScalarFieldContainer[str]
    lease_remaining_s: float
    mobile: bool
    pose: _geometry_pb2.Pose2
    pose_age_s: float
    unroutable: str
    frame: str
    def __init__(self, camera_id: _Optional[str] = ..., address: _Optional[str] = ..., field_of_view: _Optional[_Union[_geometry_pb2.Polygon, _Mapping]] = ..., detector_kinds: _Optional[_Iterable[str]] = ..., lease_remaining_s: _Optional[float] = ..., mobile: bool = ..., pose: _Optional[_Union[_geometry_pb2.Pose2, _Mapping]] = ..., pose_age_s: _Optional[float] = ..., unroutable: _Optional[str] = ..., frame: _Optional[str] = ...) -> None: ...

class ListCamerasReply(_message.Message):
    __slots__ = ("cameras", "next_page_token")
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    NEXT_PAGE_TOKEN_FIELD_NUMBER: _ClassVar[int]
    cameras: _containers.RepeatedCompositeFieldContainer[CameraInfo]
    next_page_token: str
    def __init__(self, cameras: _Optional[_Iterable[_Union[CameraInfo, _Mapping]]] = ..., next_page_token: _Optional[str] = ...) -> None: ...
