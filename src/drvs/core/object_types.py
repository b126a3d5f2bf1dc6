"""The object-type grammar: every filter_def syntax DRVS knows, parsed into a typed `ObjectType`.

A robot asks for an object type with a short string, the filter_def:

- ``hsv_HloSloVloHhiShiVhi``: six zero-padded 3-digit numbers, an OpenCV HSV box (H 0-179,
  S and V 0-255); H low above H high wraps through 0 (red);
- ``aruco_<dictionary>`` or ``aruco_<dictionary>_<id>``: OpenCV's predefined marker dictionaries;
- ``people``, ``foreground``: no parameters;
- ``model_<name>`` or ``model_<name>_<class>``: an ONNX model a camera runs, and one of its classes.

Parsing is pure and cheap: this module imports no OpenCV, no numpy, no gRPC and no detector, so the
request model (`drvs.core.model`), the server and robots validate filter_defs without loading a detector.
The detectors that run on cameras (`drvs.detectors`) take their parsed parameters from here, and a
third-party detector plug-in adds its own prefix's grammar when it registers (`add_grammar`, called
by `drvs.detectors.register`). A process that meets a prefix it does not know loads the installed
plug-ins (the "drvs.detectors" entry points) once and looks again, so a server still parses its
plug-ins' types; the built-in types never load one.

Each filter_def parses to an `ObjectType` with three names:
- `kind`: what a camera registers and the server routes by (``hsv``, ``aruco``, ``model_yolo``);
- `key`: the per-frame work it shares with other types (``aruco_4x4_50`` serves every id of that
  dictionary; ``model_yolo`` serves every class of that model);
- `filter_def` itself, which a detector's `narrow` uses to keep what this type asks for.

`hsv`, `aruco`, `people`, `foreground` and `model` build filter_defs from typed arguments.
"""

from __future__ import annotations

import functools
import importlib.metadata
import logging
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from drvs.core.errors import InvalidArgument

__all__ = [
    "ARUCO_PREFIX",
    "DICTIONARIES",
    "DICTIONARY_SIZES",
    "FOREGROUND",
    "HSV_PREFIX",
    "MAX_FILTER_DEF_LENGTH",
    "MODEL_PREFIX",
    "PEOPLE",
    "HsvRange",
    "MarkerType",
    "ModelType",
    "ObjectType",
    "add_grammar",
    "aruco",
    "detector_kind",
    "foreground",
    "hsv",
    "is_known_type",
    "model",
    "model_type",
    "object_type",
    "parse_object_type",
    "people",
    "prefixes",
]

log = logging.getLogger(__name__)

#: filter_def strings are short; longer ones are refused before any parsing.
MAX_FILTER_DEF_LENGTH = 64


@dataclass(frozen=True)
class ObjectType:
    """A parsed, valid filter_def (see the module docstring for kind and key)."""

    filter_def: str
    prefix: str
    kind: str
    key: str
    #: What the grammar parsed out of the string (an HsvRange, a MarkerType, a ModelType ...).
    params: Any = None


# --- hsv ---------------------------------------------------------------------------------------

HSV_PREFIX = "hsv_"
_HSV_RE = re.compile(r"hsv_([0-9]{18})")
_HSV_LIMITS = {"H": 179, "S": 255, "V": 255}


@dataclass(frozen=True, slots=True)
class HsvRange:
    """An OpenCV HSV threshold box (H 0-179, S and V 0-255). h_lo > h_hi wraps through 0 (red)."""

    h_lo: int
    s_lo: int
    v_lo: int
    h_hi: int
    s_hi: int
    v_hi: int

    @classmethod
    def parse(cls, filter_def: str) -> HsvRange:
        """Parse ``hsv_`` + six zero-padded 3-digit numbers ``HloSloVloHhiShiVhi``."""
        if not isinstance(filter_def, str) or not filter_def.startswith(HSV_PREFIX):
            raise InvalidArgument(f"filter_def: {str(filter_def)[:40]!r} does not start with 'hsv_'")
        m = _HSV_RE.fullmatch(filter_def)
        if m is None:
            raise InvalidArgument(
                f"filter_def: {filter_def[:40]!r} is not 'hsv_' followed by 18 digits "
                "(six zero-padded 3-digit numbers HloSloVloHhiShiVhi)"
            )
        digits = m.group(1)
        values = [int(digits[i : i + 3]) for i in range(0, 18, 3)]
        names = ("H", "S", "V", "H", "S", "V")
        for i, (name, value) in enumerate(zip(names, values, strict=True)):
            bound = "low" if i < 3 else "high"
            if value > _HSV_LIMITS[name]:
                raise InvalidArgument(
                    f"filter_def: {name} {bound} = {value} is out of range 0-{_HSV_LIMITS[name]} in {filter_def!r}"
                )
        h_lo, s_lo, v_lo, h_hi, s_hi, v_hi = values
        if s_lo > s_hi:
            raise InvalidArgument(f"filter_def: S low {s_lo} > S high {s_hi} in {filter_def!r}")
        if v_lo > v_hi:
            raise InvalidArgument(f"filter_def: V low {v_lo} > V high {v_hi} in {filter_def!r}")
        return cls(h_lo, s_lo, v_lo, h_hi, s_hi, v_hi)

    @property
    def wraps(self) -> bool:
        return self.h_lo > self.h_hi

    def to_filter_def(self) -> str:
        values = (self.h_lo, self.s_lo, self.v_lo, self.h_hi, self.s_hi, self.v_hi)
        return HSV_PREFIX + "".join(f"{v:03d}" for v in values)

    def centre_hsv(self) -> tuple[int, int, int]:
        """An HSV colour in the middle of the range (useful to paint test objects)."""
        if self.wraps:
            span = (179 - self.h_lo + 1) + self.h_hi
            h = (self.h_lo + span // 2) % 180
        else:
            h = (self.h_lo + self.h_hi) // 2
        return h, (self.s_lo + self.s_hi) // 2, (self.v_lo + self.v_hi) // 2

    # Pixel work, for cameras and tools: OpenCV is imported when first called, never by parsing.

    def mask(self, hsv: Any) -> Any:
        """Binary mask (0/255, uint8) of the pixels of an HSV image inside this range."""
        import cv2
        import numpy as np

        if not self.wraps:
            return np.asarray(
                cv2.inRange(hsv, (self.h_lo, self.s_lo, self.v_lo), (self.h_hi, self.s_hi, self.v_hi)), dtype=np.uint8
            )
        upper = cv2.inRange(hsv, (self.h_lo, self.s_lo, self.v_lo), (179, self.s_hi, self.v_hi))
        lower = cv2.inRange(hsv, (0, self.s_lo, self.v_lo), (self.h_hi, self.s_hi, self.v_hi))
        return np.asarray(cv2.bitwise_or(upper, lower), dtype=np.uint8)

    def centre_bgr(self) -> tuple[int, int, int]:
        """`centre_hsv` as a BGR colour."""
        import cv2
        import numpy as np

        hsv = np.array([[self.centre_hsv()]], dtype=np.uint8)
        b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
        return int(b), int(g), int(r)


def parse_hsv(filter_def: str) -> ObjectType:
    return ObjectType(filter_def, "hsv", "hsv", filter_def, HsvRange.parse(filter_def))


# --- aruco -------------------------------------------------------------------------------------

ARUCO_PREFIX = "aruco_"
_ID_RE = re.compile(r"[0-9]+")

#: OpenCV's predefined dictionaries by filter_def name: (the cv2.aruco.DICT_* constant, markers in
#: it), in OpenCV's order. Names are OpenCV's without ``DICT_``, in lower case; the two whose names
#: repeat the word drop it (DICT_ARUCO_ORIGINAL: ``original``). drvs.detectors.aruco checks this
#: table against the cv2 it runs with when it loads.
_ARUCO: dict[str, tuple[int, int]] = {
    "4x4_50": (0, 50),
    "4x4_100": (1, 100),
    "4x4_250": (2, 250),
    "4x4_1000": (3, 1000),
    "5x5_50": (4, 50),
    "5x5_100": (5, 100),
    "5x5_250": (6, 250),
    "5x5_1000": (7, 1000),
    "6x6_50": (8, 50),
    "6x6_100": (9, 100),
    "6x6_250": (10, 250),
    "6x6_1000": (11, 1000),
    "7x7_50": (12, 50),
    "7x7_100": (13, 100),
    "7x7_250": (14, 250),
    "7x7_1000": (15, 1000),
    "original": (16, 1024),
    "apriltag_16h5": (17, 30),
    "apriltag_25h9": (18, 35),
    "apriltag_36h10": (19, 2320),
    "apriltag_36h11": (20, 587),
    "mip_36h12": (21, 250),
}
#: Dictionary name (as in filter_defs) -> cv2.aruco predefined dictionary constant.
DICTIONARIES: dict[str, int] = {name: value for name, (value, _size) in _ARUCO.items()}
#: Number of markers in each dictionary (valid ids are 0 .. size - 1).
DICTIONARY_SIZES: dict[str, int] = {name: size for name, (_value, size) in _ARUCO.items()}


@dataclass(frozen=True, slots=True)
class MarkerType:
    """What an ``aruco_`` filter_def asks for: a dictionary, and one marker id or every one."""

    dictionary: str
    marker_id: int | None = None


def _unknown_dictionary(name: str, filter_def: str) -> InvalidArgument:
    hint = "; dictionary names are lower case" if name.lower() in DICTIONARIES and name != name.lower() else ""
    return InvalidArgument(
        f"filter_def: unknown ArUco dictionary {name[:40]!r} in {filter_def[:64]!r}; "
        f"OpenCV's dictionaries are {', '.join(DICTIONARIES)} "
        f"(e.g. 'aruco_4x4_50' for every marker, 'aruco_4x4_50_7' for marker 7){hint}"
    )


def parse_marker_type(filter_def: str) -> MarkerType:
    """Parse ``aruco_<dictionary>`` or ``aruco_<dictionary>_<id>``; InvalidArgument naming the wrong part."""
    if not isinstance(filter_def, str) or not (filter_def + "_").startswith(ARUCO_PREFIX):
        raise InvalidArgument(f"filter_def: {str(filter_def)[:40]!r} does not start with 'aruco_'")
    rest = filter_def[len(ARUCO_PREFIX) :]
    if not rest:
        raise InvalidArgument(
            f"filter_def: {filter_def!r} names no ArUco dictionary; expected aruco_<dictionary> or "
            f"aruco_<dictionary>_<id>, e.g. 'aruco_4x4_50' or 'aruco_4x4_50_7'"
        )
    if rest in DICTIONARIES:
        return MarkerType(rest)
    # No dictionary's name followed by "_" starts another's, so at most one matches.
    head = next((name for name in DICTIONARIES if rest.startswith(name + "_")), None)
    if head is None:
        raise _unknown_dictionary(rest, filter_def)
    tail = rest[len(head) + 1 :]
    size = DICTIONARY_SIZES[head]
    if not _ID_RE.fullmatch(tail) or int(tail) >= size:
        raise InvalidArgument(
            f"filter_def: marker id {tail[:20]!r} in {filter_def!r} is not an integer in 0-{size - 1} "
            f"(dictionary {head} has {size} markers)"
        )
    return MarkerType(head, int(tail))


def parse_aruco(filter_def: str) -> ObjectType:
    marker = parse_marker_type(filter_def)
    return ObjectType(filter_def, "aruco", "aruco", ARUCO_PREFIX + marker.dictionary, marker)


# --- people, foreground ------------------------------------------------------------------------

PEOPLE = "people"
FOREGROUND = "foreground"


def parse_people(filter_def: str) -> ObjectType:
    if filter_def != PEOPLE:
        raise InvalidArgument(f"filter_def: {filter_def[:40]!r}: the people type takes no parameters; write 'people'")
    return ObjectType(filter_def, PEOPLE, PEOPLE, PEOPLE)


def parse_foreground(filter_def: str) -> ObjectType:
    if filter_def != FOREGROUND:
        raise InvalidArgument(f"filter_def: {filter_def[:40]!r} is not {FOREGROUND!r} (it takes no parameters)")
    return ObjectType(FOREGROUND, FOREGROUND, FOREGROUND, FOREGROUND)


# --- model -------------------------------------------------------------------------------------

MODEL_PREFIX = "model_"
#: Model names: what filter_defs and routing kinds carry (model_<name>), so no "_".
MODEL_NAME_RE = re.compile(r"[a-z0-9-]{1,24}")
#: Class names as filter_defs may name them.
CLASS_NAME_RE = re.compile(r"[A-Za-z0-9_.-]{1,32}")
MODEL_EXAMPLE = "model_yolo_person"


class ModelType(NamedTuple):
    """What a ``model_`` filter_def asks for: a model, and one of its classes or every one."""

    name: str
    cls: str | None = None


def parse_model(filter_def: str) -> ObjectType:
    if not filter_def.startswith(MODEL_PREFIX):
        raise InvalidArgument(
            f"filter_def: {filter_def[:40]!r} names no model: expected model_<name> or model_<name>_<class> "
            f"(e.g. {MODEL_EXAMPLE!r})"
        )
    name, separator, label = filter_def[len(MODEL_PREFIX) :].partition("_")
    if not MODEL_NAME_RE.fullmatch(name):
        raise InvalidArgument(
            f"filter_def: model name {name[:40]!r} in {filter_def[:40]!r} must be 1-24 lower-case letters, "
            "digits and '-'"
        )
    if separator and not CLASS_NAME_RE.fullmatch(label):
        raise InvalidArgument(
            f"filter_def: class {label[:40]!r} in {filter_def[:40]!r} must be 1-32 letters, digits and '_ - .'"
        )
    kind = MODEL_PREFIX + name
    return ObjectType(filter_def, "model", kind, kind, ModelType(name, label or None))


# --- the table ---------------------------------------------------------------------------------

Parser = Callable[[str], ObjectType]


@dataclass(frozen=True)
class _Grammar:
    parse: Parser
    example: str


#: Built-in grammars in the order messages and defaults list them; plug-ins' follow as they register.
_GRAMMARS: dict[str, _Grammar] = {
    "hsv": _Grammar(parse_hsv, "hsv_014110130035225200"),
    "aruco": _Grammar(parse_aruco, "aruco_4x4_50_7"),
    "people": _Grammar(parse_people, PEOPLE),
    "foreground": _Grammar(parse_foreground, FOREGROUND),
    "model": _Grammar(parse_model, MODEL_EXAMPLE),
}
BUILTIN_PREFIXES = tuple(_GRAMMARS)
#: The entry-point group detector plug-ins are installed under (see drvs.detectors).
PLUGIN_GROUP = "drvs.detectors"


def add_grammar(prefix: str, parse: Parser, example: str) -> None:
    """Parse filter_defs starting with `prefix` (lower-case letters) with `parse`, which returns an
    ObjectType or raises InvalidArgument naming what is wrong. drvs.detectors.register calls it
    for every detector plug-in; a built-in prefix keeps this module's grammar."""
    if not prefix.isalpha() or not prefix.islower():
        raise ValueError(f"object type prefix {prefix!r} must be lower-case letters")
    if prefix in BUILTIN_PREFIXES:
        return
    _GRAMMARS[prefix] = _Grammar(parse, example)
    _parsed.cache_clear()


def prefixes() -> tuple[str, ...]:
    """Every prefix this process can parse: the built-ins, then plug-ins as they registered."""
    return tuple(_GRAMMARS)


@functools.cache
def _load_plugins() -> None:
    """Import the installed detector plug-ins (each registers its grammar), once, for a prefix
    nobody registered: a server parses its plug-ins' types without importing drvs.detectors
    itself. A broken plug-in is logged and skipped, as drvs.detectors does."""
    for entry in importlib.metadata.entry_points(group=PLUGIN_GROUP):
        try:
            entry.load()
        except Exception as exc:  # a third party's import error, whatever it is
            log.error(
                "detector plug-in %s (%s) failed to load: %s: %s", entry.name, entry.value, type(exc).__name__, exc
            )


def parse_object_type(filter_def: str) -> ObjectType:
    """The ObjectType a filter_def names; InvalidArgument naming what is wrong."""
    if not isinstance(filter_def, str) or not filter_def:
        raise InvalidArgument(f"filter_def: empty; expected e.g. {_examples()}")
    if len(filter_def) > MAX_FILTER_DEF_LENGTH:
        raise InvalidArgument(
            f"filter_def: {len(filter_def)} characters; at most {MAX_FILTER_DEF_LENGTH} (e.g. {_examples()})"
        )
    prefix = filter_def.split("_", 1)[0]
    grammar = _GRAMMARS.get(prefix)
    if grammar is None and prefix.isalpha() and prefix.islower():
        _load_plugins()
        grammar = _GRAMMARS.get(prefix)
    if grammar is None:
        raise InvalidArgument(
            f"filter_def: unknown object type {prefix[:40]!r} in {filter_def[:40]!r}; "
            f"known types: {', '.join(prefixes())} (e.g. {_examples()})"
        )
    return grammar.parse(filter_def)


def _examples() -> str:
    return ", ".join(repr(g.example) for g in _GRAMMARS.values())


def object_type(filter_def: str) -> ObjectType:
    """The parsed filter_def; InvalidArgument naming the part that is wrong."""
    if isinstance(filter_def, str) and len(filter_def) <= MAX_FILTER_DEF_LENGTH:
        return _parsed(filter_def)  # robots ask for the same few objects again and again
    return parse_object_type(filter_def)


@functools.lru_cache(maxsize=1024)
def _parsed(filter_def: str) -> ObjectType:
    return parse_object_type(filter_def)  # lru_cache keeps answers only: a bad filter_def raises every time


def detector_kind(filter_def: str) -> str:
    """The routing kind a well-formed filter_def asks for (what cameras register), or InvalidArgument
    saying what is wrong."""
    return object_type(filter_def).kind


def is_known_type(filter_def: str) -> bool:
    """Does this process know the filter_def's prefix (a built-in, or a plug-in it has loaded)?"""
    return isinstance(filter_def, str) and filter_def.split("_", 1)[0] in _GRAMMARS


# --- typed builders ----------------------------------------------------------------------------


def _checked(filter_def: str, what: str) -> str:
    try:
        parse_object_type(filter_def)
    except InvalidArgument as exc:  # the builders check their arguments first; this is a backstop
        raise InvalidArgument(f"{what}: {exc}") from None
    return filter_def


def _hsv_triple(value: Any, name: str) -> tuple[int, int, int]:
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 3:
        raise InvalidArgument(f"hsv: {name} = {value!r:.40} is not an (H, S, V) triple")
    for channel, part in zip("HSV", value, strict=True):
        if isinstance(part, bool) or not isinstance(part, int):
            raise InvalidArgument(f"hsv: {name} {channel} = {part!r:.40} is not an integer")
        if not 0 <= part <= _HSV_LIMITS[channel]:
            raise InvalidArgument(f"hsv: {name} {channel} = {part} is out of range 0-{_HSV_LIMITS[channel]}")
    return int(value[0]), int(value[1]), int(value[2])


def hsv(lo: Sequence[int], hi: Sequence[int]) -> str:
    """The filter_def of an HSV box: `lo` and `hi` are (H, S, V) in OpenCV's ranges (H 0-179, S and
    V 0-255); lo's H above hi's wraps through 0 (red). ``hsv((14, 110, 130), (35, 225, 200))``."""
    low, high = _hsv_triple(lo, "lo"), _hsv_triple(hi, "hi")
    for channel, a, b in (("S", low[1], high[1]), ("V", low[2], high[2])):
        if a > b:
            raise InvalidArgument(f"hsv: lo {channel} = {a} > hi {channel} = {b} (only H wraps)")
    return _checked(HsvRange(*low, *high).to_filter_def(), "hsv")


def aruco(dictionary: str, marker_id: int | None = None) -> str:
    """The filter_def of a dictionary's markers, or of one marker: ``aruco("4x4_50", 7)``."""
    if not isinstance(dictionary, str) or dictionary not in DICTIONARIES:
        raise InvalidArgument(f"aruco: dictionary {dictionary!r:.40} is not one of {', '.join(DICTIONARIES)}")
    if marker_id is None:
        return _checked(ARUCO_PREFIX + dictionary, "aruco")
    size = DICTIONARY_SIZES[dictionary]
    if isinstance(marker_id, bool) or not isinstance(marker_id, int) or not 0 <= marker_id < size:
        raise InvalidArgument(
            f"aruco: marker_id {marker_id!r:.40} is not an integer in 0-{size - 1} (dictionary {dictionary} "
            f"has {size} markers)"
        )
    return _checked(f"{ARUCO_PREFIX}{dictionary}_{marker_id}", "aruco")


def people() -> str:
    """The filter_def of people (HOG's pedestrian detector on cameras that run it)."""
    return PEOPLE


def foreground() -> str:
    """The filter_def of whatever differs from a camera's background model."""
    return FOREGROUND


def model(name: str, cls: str | None = None) -> str:
    """The filter_def of what a camera's ONNX model `name` finds, or only its class `cls`:
    ``model("yolo", "person")``."""
    if not isinstance(name, str) or not MODEL_NAME_RE.fullmatch(name):
        raise InvalidArgument(f"model: name {name!r:.40} must be 1-24 lower-case letters, digits and '-'")
    if cls is None:
        return _checked(MODEL_PREFIX + name, "model")
    if not isinstance(cls, str) or not CLASS_NAME_RE.fullmatch(cls):
        raise InvalidArgument(f"model: cls {cls!r:.40} must be 1-32 letters, digits and '_ - .'")
    return _checked(f"{MODEL_PREFIX}{name}_{cls}", "model")


#: `model` under the name the drvs package exports it as (there `drvs.core.model` is the module).
model_type = model
