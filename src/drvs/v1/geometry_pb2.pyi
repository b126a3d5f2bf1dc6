from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Point2(_message.Message):
    __slots__ = ("x", "y")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

class Pose2(_message.Message):
    __slots__ = ("x", "y", "yaw")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    YAW_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    yaw: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., yaw: _Optional[float] = ...) -> None: ...

class Polygon(_message.Message):
    __slots__ = ("points",)
    POINTS_FIELD_NUMBER: _ClassVar[int]
    points: _containers.RepeatedCompositeFieldContainer[Point2]
    def __init__(self, points: _Optional[_Iterable[_Union[Point2, _Mapping]]] = ...) -> None: ...

class Box(_message.Message):
    __slots__ = ("x_lower", "y_lower", "x_upper", "y_upper")
    X_LOWER_FIELD_NUMBER: _ClassVar[int]
    Y_LOWER_FIELD_NUMBER: _ClassVar[int]
    X_UPPER_FIELD_NUMBER: _ClassVar[int]
    Y_UPPER_FIELD_NUMBER: _ClassVar[int]
    x_lower: float
    y_lower: float
    x_upper: float
    y_upper: float
    def __init__(self, x_lower: _Optional[float] = ..., y_lower: _Optional[float] = ..., x_upper: _Optional[float] = ..., y_upper: _Optional[float] = ...) -> None: ...

class Region(_message.Message):
    __slots__ = ("box", "polygon")
    BOX_FIELD_NUMBER: _ClassVar[int]
    POLYGON_FIELD_NUMBER: _ClassVar[int]
    box: Box
    polygon: Polygon
    def __init__(self, box: _Optional[_Union[Box, _Mapping]] = ..., polygon: _Optional[_Union[Polygon, _Mapping]] = ...) -> None: ...

class FloorPoint(_message.Message):
    __slots__ = ("x", "y")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

class FloorBox(_message.Message):
    __slots__ = ("x_lower", "y_lower", "x_upper", "y_upper")
    X_LOWER_FIELD_NUMBER: _ClassVar[int]
    Y_LOWER_FIELD_NUMBER: _ClassVar[int]
    X_UPPER_FIELD_NUMBER: _ClassVar[int]
    Y_UPPER_FIELD_NUMBER: _ClassVar[int]
    x_lower: float
    y_lower: float
    x_upper: float
    y_upper: float
    def __init__(self, x_lower: _Optional[float] = ..., y_lower: _Optional[float] = ..., x_upper: _Optional[float] = ..., y_upper: _Optional[float] = ...) -> None: ...

class PixelBox(_message.Message):
    __slots__ = ("x", "y", "width", "height")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    x: int
    y: int
    width: int
    height: int
    def __init__(self, x: _Optional[int] = ..., y: _Optional[int] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...
