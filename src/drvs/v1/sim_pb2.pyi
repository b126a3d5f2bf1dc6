from drvs.v1 import geometry_pb2 as _geometry_pb2
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class GetSceneRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class Scene(_message.Message):
    __slots__ = ("scenario_yaml", "seed")
    SCENARIO_YAML_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    scenario_yaml: str
    seed: int
    def __init__(self, scenario_yaml: _Optional[str] = ..., seed: _Optional[int] = ...) -> None: ...

class RobotPose(_message.Message):
    __slots__ = ("x", "y", "theta", "version", "clock_start_unix")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    CLOCK_START_UNIX_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    theta: float
    version: int
    clock_start_unix: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., theta: _Optional[float] = ..., version: _Optional[int] = ..., clock_start_unix: _Optional[float] = ...) -> None: ...

class MoveRequest(_message.Message):
    __slots__ = ("pose",)
    POSE_FIELD_NUMBER: _ClassVar[int]
    pose: RobotPose
    def __init__(self, pose: _Optional[_Union[RobotPose, _Mapping]] = ...) -> None: ...

class MoveReply(_message.Message):
    __slots__ = ("pose", "collided", "contact", "world_time_s")
    POSE_FIELD_NUMBER: _ClassVar[int]
    COLLIDED_FIELD_NUMBER: _ClassVar[int]
    CONTACT_FIELD_NUMBER: _ClassVar[int]
    WORLD_TIME_S_FIELD_NUMBER: _ClassVar[int]
    pose: RobotPose
    collided: bool
    contact: _geometry_pb2.Polygon
    world_time_s: float
    def __init__(self, pose: _Optional[_Union[RobotPose, _Mapping]] = ..., collided: bool = ..., contact: _Optional[_Union[_geometry_pb2.Polygon, _Mapping]] = ..., world_time_s: _Optional[float] = ...) -> None: ...

class WatchRobotRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class StartRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class StartReply(_message.Message):
    __slots__ = ("clock_start_unix",)
    CLOCK_START_UNIX_FIELD_NUMBER: _ClassVar[int]
    clock_start_unix: float
    def __init__(self, clock_start_unix: _Optional[float] = ...) -> None: ...

class WatchScoutRequest(_message.Message):
    __slots__ = ("scout_id", "rate_hz")
    SCOUT_ID_FIELD_NUMBER: _ClassVar[int]
    RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    scout_id: str
    rate_hz: float
    def __init__(self, scout_id: _Optional[str] = ..., rate_hz: _Optional[float] = ...) -> None: ...

class ScoutPose(_message.Message):
    __slots__ = ("x", "y", "theta", "time_unix", "world_time_s")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    TIME_UNIX_FIELD_NUMBER: _ClassVar[int]
    WORLD_TIME_S_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    theta: float
    time_unix: float
    world_time_s: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., theta: _Optional[float] = ..., time_unix: _Optional[float] = ..., world_time_s: _Optional[float] = ...) -> None: ...

class DockRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class DockReply(_message.Message):
    __slots__ = ("docked",)
    DOCKED_FIELD_NUMBER: _ClassVar[int]
    docked: bool
    def __init__(self, docked: bool = ...) -> None: ...
