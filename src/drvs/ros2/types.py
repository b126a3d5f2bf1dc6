"""The ROS 2 message types drvs-ros2 publishes, made from the upstream .msg files shipped beside
this module (drvs/ros2/msg/<package>/msg/<Name>.msg; msg/SOURCES.md says where each came from).

The .msg files are the one definition: rosbags parses them (`typestore()`: a rosbags Typestore
that knows only them, for the rosbag2 export and for decoding), and `idl_types()` turns the same
parsed fields into Cyclone DDS IDL structs named as rmw_cyclonedds names ROS 2 types on the wire
(`pkg/msg/Name` is `pkg::msg::dds_::Name_`), so ROS 2 nodes see ordinary topics.

Every field of an IDL struct has a default (0, "", False, an empty sequence, a default nested
message), so a message is built naming only what it sets: `idl("std_msgs/msg/Header")(frame_id="map")`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from importlib import resources
from types import new_class
from typing import Any

import numpy as np
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as _idl_types
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

#: Cyclone's IDL annotations (array[T, N], sequence[T], bounded_str[N]) index at run time; typed Any.
idl_t: Any = _idl_types
#: ROS 2 base types as Cyclone's Python IDL spells them (rosidl maps `byte` to octet and `char` to
#: uint8: both one unsigned byte on the wire).
BASE = {
    "bool": bool,
    "byte": idl_t.uint8,
    "char": idl_t.uint8,
    "int8": idl_t.int8,
    "uint8": idl_t.uint8,
    "int16": idl_t.int16,
    "uint16": idl_t.uint16,
    "int32": idl_t.int32,
    "uint32": idl_t.uint32,
    "int64": idl_t.int64,
    "uint64": idl_t.uint64,
    "float32": idl_t.float32,
    "float64": idl_t.float64,
}


def dds_type_name(ros_type: str) -> str:
    """`pkg/msg/Name` -> `pkg::msg::dds_::Name_`, the DDS type name rmw_cyclonedds gives it."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def dds_topic_name(ros_topic: str) -> str:
    """`/a/b` -> `rt/a/b`, the DDS topic rmw_cyclonedds gives a ROS 2 topic."""
    if not ros_topic.startswith("/") or ros_topic.endswith("/") or "//" in ros_topic:
        raise ValueError(f"{ros_topic!r} is not an absolute ROS 2 topic name (/a/b)")
    return "rt" + ros_topic


def msg_files() -> dict[str, str]:
    """The shipped definitions: `pkg/msg/Name` -> the .msg file's text."""
    root = resources.files("drvs.ros2") / "msg"
    found: dict[str, str] = {}
    for package in sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: p.name):
        kind = package / "msg"
        for msg in sorted((f for f in kind.iterdir() if f.name.endswith(".msg")), key=lambda f: f.name):
            found[f"{package.name}/msg/{msg.name[: -len('.msg')]}"] = msg.read_text(encoding="utf-8")
    return found


@functools.cache
def typestore() -> Typestore:
    """A rosbags typestore holding exactly the shipped definitions (none of rosbags' own)."""
    store = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    for name, text in msg_files().items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _field_type(node: tuple[Any, Any], structs: dict[str, type]) -> tuple[Any, Any]:
    """(IDL annotation, default factory) for one parsed field type."""
    kind, detail = node
    if kind == Nodetype.BASE:
        name, bound = detail
        if name == "string":
            return (idl_t.bounded_str[bound] if bound else str), str
        if name not in BASE:
            raise TypeError(f"ROS 2 base type {name!r} has no IDL mapping here")
        python = BASE[name]
        return python, (bool if python is bool else (float if name.startswith("float") else int))
    if kind == Nodetype.NAME:
        struct = structs[detail]
        return struct, struct
    inner, size = detail
    element, _ = _field_type(inner, structs)
    if kind == Nodetype.ARRAY:
        zero = _field_type(inner, structs)[1]
        return idl_t.array[element, size], functools.partial(lambda n, z: [z() for _ in range(n)], size, zero)
    if kind == Nodetype.SEQUENCE:
        return (idl_t.sequence[element, size] if size else idl_t.sequence[element]), list
    raise TypeError(f"unknown field kind {kind!r}")


def _depends(store: Typestore, name: str) -> list[str]:
    """The named message types a type's fields use, directly."""
    out = []
    node: Any
    for _, node in store.fielddefs[name][1]:
        kind, detail = node
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            kind, detail = detail[0]
        if kind == Nodetype.NAME:
            out.append(detail)
    return out


@functools.cache
def idl_types() -> dict[str, type[IdlStruct]]:
    """`pkg/msg/Name` -> its Cyclone DDS IDL struct (a dataclass), for every shipped definition."""
    store = typestore()
    structs: dict[str, type] = {}

    def make(name: str) -> type:
        if name in structs:
            return structs[name]
        for dependency in _depends(store, name):
            make(dependency)
        fields = [(field_name, *_field_type(node, structs)) for field_name, node in store.fielddefs[name][1]]

        def body(namespace: dict[str, Any]) -> None:
            namespace["__module__"] = __name__
            for field_name, annotation, factory in fields:
                namespace["__annotations__"][field_name] = annotation
                namespace[field_name] = dataclasses.field(default_factory=factory)

        # types.new_class runs IdlMeta.__prepare__, which takes the DDS type name.
        cls = new_class(name.rpartition("/")[2], (IdlStruct,), {"typename": dds_type_name(name)}, body)
        structs[name] = dataclasses.dataclass(cls)
        return structs[name]

    for name in sorted(store.fielddefs):
        if name in msg_files():
            make(name)
    return dict(structs)


def idl(ros_type: str) -> Any:
    """One type's IDL struct, e.g. idl("vision_msgs/msg/Detection3DArray") (typed Any: the
    classes are made at run time, from the .msg files)."""
    try:
        return idl_types()[ros_type]
    except KeyError:
        raise KeyError(f"{ros_type}: not among the shipped message types ({', '.join(sorted(idl_types()))})") from None


#: numpy dtypes of the ROS 2 base types rosbags keeps arrays of as numpy arrays.
DTYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8, "int16": np.int16,
    "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
    "float32": np.float32, "float64": np.float64,
}  # fmt: skip


def _rosbags_default(node: tuple[Any, Any]) -> Callable[[], Any]:
    """A factory of the default value of one field of a rosbags message."""
    kind, detail = node
    if kind == Nodetype.BASE:
        name = detail[0]
        return str if name == "string" else (bool if name == "bool" else (float if "float" in name else int))
    if kind == Nodetype.NAME:
        return functools.partial(ros, detail)
    (inner_kind, inner), size = detail
    if inner_kind == Nodetype.BASE and inner[0] in DTYPES:
        n = size if kind == Nodetype.ARRAY else 0
        return functools.partial(np.zeros, n, DTYPES[inner[0]])
    if kind == Nodetype.ARRAY:
        element = _rosbags_default((inner_kind, inner))
        return lambda: [element() for _ in range(size)]
    return list


@functools.cache
def _rosbags_fields(ros_type: str) -> tuple[type, tuple[tuple[str, Callable[[], Any]], ...]]:
    store = typestore()
    if ros_type not in msg_files():
        raise KeyError(f"{ros_type}: not among the shipped message types ({', '.join(sorted(msg_files()))})")
    fields = tuple((name, _rosbags_default(node)) for name, node in store.fielddefs[ros_type][1])
    return store.types[ros_type], fields


def message_class(ros_type: str) -> Any:
    """rosbags' class of a shipped type (every field must then be given)."""
    return _rosbags_fields(ros_type)[0]


def ros(ros_type: str, **values: Any) -> Any:
    """A message of `ros_type` as rosbags' class for it, every field not given at its default (0,
    "", False, empty, a default nested message); arrays of numbers are numpy arrays, as rosbags
    keeps them. What the bridge publishes and the rosbag2 export writes (to_cdr)."""
    cls, fields = _rosbags_fields(ros_type)
    for name, default in fields:
        if name not in values:
            values[name] = default()
    return cls(**values)


def to_cdr(message: Any) -> bytes:
    """A message as ROS 2 serializes it: XCDR1 (plain CDR), little-endian, with the 4-byte
    encapsulation header `00 01 00 00`: what goes on the DDS wire and into a rosbag2. A rosbags
    message (ros()) is serialized by rosbags, an IDL struct (idl()) by Cyclone: the same bytes
    (tests/ros2/test_ros2_convert.py)."""
    if isinstance(message, IdlStruct):
        return bytes(message.serialize(use_version_2=False))
    return bytes(typestore().serialize_cdr(message, message.__msgtype__))
