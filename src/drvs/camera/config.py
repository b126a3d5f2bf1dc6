"""A camera node's configuration: one typed model, loaded once at start.

Precedence for every setting: command-line flag > DRVS_* environment variable > config file >
default. Unknown keys and bad values are errors that name the key and where it came from.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
from collections.abc import Mapping
from dataclasses import MISSING, Field, dataclass, fields
from pathlib import Path
from typing import Any

from drvs.core import settings
from drvs.core._files import read_yaml
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import DEFAULT_MAX_RANGE_M
from drvs.core.mobile import DEFAULT_MAX_POSE_GAP_S, Mount
from drvs.core.model import DEFAULT_FRAME, check_frame, check_id
from drvs.core.net import format_address, parse_address, parse_address_list
from drvs.detectors import DEFAULT_MIN_AREA_PX, DETECTOR_KINDS
from drvs.detectors.model import ModelSpec, parse_models
from drvs.live.liveview import parse_listen
from drvs.wire._cli import SECURITY_ENV, format_number, parse_bool, read_token
from drvs.wire.logs import FORMATS
from drvs.wire.metrics import DEFAULT_METRICS_HOST
from drvs.wire.security import Security

from .liveview import MAX_FPS, check_fps

DEFAULT_SERVER = "127.0.0.1:50051"
DEFAULT_LISTEN = "127.0.0.1:0"
#: A frame older than this (seconds) is not used for detection: the camera says so instead.
DEFAULT_MAX_FRAME_AGE_S = 2.0
#: Continuous requests one robot (its callback address, which the server checked is the robot's
#: own) may have running on this camera at once: the server's per-robot cap counts a robot per
#: credential or connection, and a robot with many connections would otherwise take every slot.
DEFAULT_MAX_CONTINUOUS_PER_ROBOT = 32
#: Threads that run heavy detectors (people, models: about 100 ms a frame here). Bounded: a burst
#: of requests queues for them instead of starting a thread per request. One on two cores,
#: leaving one for the rest.
DEFAULT_DETECT_WORKERS = max(1, min(2, (os.cpu_count() or 1) - 1))
#: Frames a second a live view (--foxglove) sends at most while someone watches, unless told.
DEFAULT_FOXGLOVE_FPS = 5.0

#: drvs-camera's argument groups (--help's sections); a setting without one is in the main list.
MOBILE = "a camera on a robot (mobile: its field of view moves with the robot's poses)"
LIVE = "live view (pip install 'drvs[live]'; docs/operations.md)"


@dataclass(frozen=True)
class Setting(settings.Setting):
    """One camera setting's declaration, kept in its CameraConfig field's metadata (see `setting`):
    drvs.core.settings' flag, variable, help and group, and the camera's own: `limits`: (lowest,
    highest), inclusive, whole numbers for an int field; `arg_type`: argparse's conversion (None: the
    text, converted by load_config with its own message); `shared`: the flag is added by
    drvs.wire._cli's shared helpers (security, logging), not from this declaration. The --config
    file's key is the field's name."""

    limits: tuple[float, float] | None = None
    arg_type: type | None = None
    shared: bool = False
    whole: bool = False

    def flag_options(self) -> dict[str, Any]:
        if isinstance(self.default, bool):
            return {"action": "store_const", "const": not self.default}
        return {"metavar": self.metavar, "type": self.arg_type}


def setting(
    default: Any = MISSING,
    *,
    flag: str | None = None,
    env: str | None = None,
    limits: tuple[float, float] | None = None,
    help: str = "",
    metavar: str | None = None,
    arg_type: type | None = None,
    group: str | None = None,
    shared: bool = False,
    default_factory: Any = MISSING,
) -> Any:
    """A CameraConfig field with its whole declaration (see `Setting`)."""
    declared = Setting(
        flag=flag, env=env, help=help, metavar=metavar, group=group, limits=limits, arg_type=arg_type, shared=shared
    )
    return settings.field(declared, default, default_factory)


@dataclass(frozen=True)
class CameraConfig:
    """A camera node's settings; each field declares its setting whole (see `setting`), and
    drvs-camera adds the flags in this order."""

    id: str = setting(flag="--id", env="DRVS_CAMERA_ID", help="camera id, unique in the building (%(env)s)")
    source: str = setting(
        flag="--source",
        env="DRVS_CAMERA_SOURCE",
        help="device index (0), video file, stream URL, or sim://HOST:PORT (%(env)s)",
    )
    #: A fixed camera's image -> floor homography file; a mobile camera gives `mount` instead.
    homography: Path | None = setting(  # noqa: RUF009
        flag="--homography",
        env="DRVS_CAMERA_HOMOGRAPHY",
        metavar="FILE",
        help="JSON/YAML file whose 'homography' is the 3x3 image->floor matrix (%(env)s)",
    )
    server: str = setting(
        DEFAULT_SERVER,
        flag="--server",
        env="DRVS_SERVER",
        help="DRVS server HOST:PORT, several sharing a registry (A:PORT,B:PORT: registration moves on from one "
        f"that dies), or a DNS name for several (default {DEFAULT_SERVER}; %(env)s)",
    )
    listen: str = setting(
        DEFAULT_LISTEN,
        flag="--listen",
        env="DRVS_CAMERA_LISTEN",
        help=f"HOST:PORT to serve on; port 0 picks a free one (default {DEFAULT_LISTEN}; %(env)s)",
    )
    advertise: str | None = setting(
        None,
        flag="--advertise",
        env="DRVS_CAMERA_ADVERTISE",
        help="HOST:PORT the server should dial, if not --listen (%(env)s)",
    )
    #: The floor plan its homography maps to ("building-a/floor-2"; default "map").
    frame: str = setting(
        DEFAULT_FRAME,
        flag="--frame",
        env="DRVS_CAMERA_FRAME",
        help="the floor plan its homography maps to, e.g. building-a/floor-2 (default map; %(env)s)",
    )
    max_range_m: float = setting(
        DEFAULT_MAX_RANGE_M,
        flag="--max-range",
        env="DRVS_CAMERA_MAX_RANGE",
        limits=(0.1, 1000.0),
        arg_type=float,
        metavar="M",
        help="field-of-view range, metres (default 15)",
    )
    min_area_px: float = setting(
        DEFAULT_MIN_AREA_PX,
        flag="--min-area",
        env="DRVS_CAMERA_MIN_AREA",
        limits=(1.0, 1e7),
        arg_type=float,
        metavar="PX",
        help="smallest blob, pixels",
    )
    max_frame_age_s: float = setting(
        DEFAULT_MAX_FRAME_AGE_S,
        flag="--max-frame-age",
        env="DRVS_CAMERA_MAX_FRAME_AGE",
        limits=(0.05, 3600.0),
        arg_type=float,
        metavar="S",
        help="older frames are not used; the node reports NOT_SERVING while it has none (default 2)",
    )
    loop: bool = setting(True, flag="--no-loop", env="DRVS_CAMERA_LOOP", help="play a video file once, do not loop it")
    serve_frames: bool = setting(
        False,
        flag="--serve-frames",
        env="DRVS_CAMERA_SERVE_FRAMES",
        help="also stream whole frames (FrameStream service): the no-DRVS baseline, for benchmarks",
    )
    #: Asked of a device or stream; a source that gives another size is refused (the homography
    #: belongs to one image size).
    resolution: tuple[int, int] | None = setting(
        None,
        flag="--resolution",
        env="DRVS_CAMERA_RESOLUTION",
        help="W,H to ask of a device or stream; another size is refused (%(env)s)",
    )
    fps: float | None = setting(
        None,
        flag="--fps",
        env="DRVS_CAMERA_FPS",
        limits=(0.1, 1000.0),
        arg_type=float,
        help="frame rate to ask of a device or stream (%(env)s)",
    )
    detectors: tuple[str, ...] = setting(
        DETECTOR_KINDS,
        flag="--detectors",
        env="DRVS_CAMERA_DETECTORS",
        help="detectors to run, comma-separated prefixes (default: every one installed; %(env)s)",
    )
    #: Threads that run heavy detectors (people, models); requests beyond them queue.
    detect_workers: int = setting(
        DEFAULT_DETECT_WORKERS,
        flag="--detect-workers",
        env="DRVS_CAMERA_DETECT_WORKERS",
        limits=(1, 64),
        metavar="N",
        help="threads for heavy detectors (people, models); requests beyond them queue (%(env)s)",
    )
    #: A picture of the empty floor (drvs-camera snapshot) for the foreground detector; relative
    #: to the config file. The detector refuses, at start, a file it cannot read or of another size.
    background: Path | None = setting(  # noqa: RUF009
        None,
        flag="--background",
        env="DRVS_CAMERA_BACKGROUND",
        metavar="FILE",
        help="picture of the empty floor (drvs-camera snapshot) for the foreground detector (%(env)s)",
    )
    #: The people detector's smallest person, pixels tall (None: its default, the search by geometry).
    people_min_height_px: float | None = setting(
        None,
        flag="--people-min-height",
        env="DRVS_CAMERA_PEOPLE_MIN_HEIGHT",
        limits=(32.0, 1024.0),
        metavar="PX",
        help="people: search the whole frame for people from this many pixels tall, 32-1024; below 128 costs "
        "more CPU (default: search by the homography's geometry; %(env)s)",
    )
    #: How tall the people detector's search by geometry expects people to be (None: 1.7 m).
    people_height_m: float | None = setting(
        None, flag="--people-height", env="DRVS_CAMERA_PEOPLE_HEIGHT", limits=(0.5, 2.5), metavar="M",
        help="people: how tall people are, metres, for the search by geometry (default 1.7; %(env)s)",
    )  # fmt: skip
    #: Heartbeat interval; by default a third of the lease the server grants.
    heartbeat_s: float | None = setting(
        None,
        flag="--heartbeat",
        env="DRVS_CAMERA_HEARTBEAT",
        limits=(0.05, 3600.0),
        arg_type=float,
        metavar="S",
        help="heartbeat interval (default: lease / 3)",
    )
    #: Continuous requests one robot (callback address) may have running on this camera at once.
    max_continuous: int = setting(
        DEFAULT_MAX_CONTINUOUS_PER_ROBOT,
        flag="--max-continuous",
        env="DRVS_CAMERA_MAX_CONTINUOUS",
        limits=(1, 1_000_000),
        metavar="N",
        help="continuous requests one robot may have running on this camera at once (default 32; %(env)s)",
    )
    #: A mobile camera (on a robot): "X,Y,Z,YAW,PITCH", where it sits on the robot (metres,
    #: degrees; see drvs.core.mobile.Mount), with `hfov_deg` or `camera_matrix` ("FX,FY,CX,CY", pixels),
    #: and where its robot's poses come from (`pose_source`, see drvs.camera.poses).
    mount: str | None = setting(
        None,
        flag="--mount",
        metavar="X,Y,Z,YAW,PITCH",
        group=MOBILE,
        help="where the camera sits on the robot: metres in the robot's base frame (x forward, y left, z up), "
        "yaw from forward and pitch below horizontal in degrees; instead of --homography",
    )
    hfov_deg: float | None = setting(
        None,
        flag="--hfov",
        limits=(1.0, 179.0),
        arg_type=float,
        metavar="DEG",
        group=MOBILE,
        help="the camera's horizontal field of view",
    )
    camera_matrix: str | None = setting(
        None,
        flag="--camera-matrix",
        metavar="FX,FY,CX,CY",
        group=MOBILE,
        help="the camera's intrinsics, pixels (instead of --hfov)",
    )
    pose_source: str | None = setting(
        None,
        flag="--pose-source",
        metavar="SOURCE",
        group=MOBILE,
        help="the robot's poses: tcp://HOST:PORT (newline-delimited "
        'JSON {"t", "x", "y", "yaw"}) or sim://HOST:PORT/SCOUT (the simulator)',
    )
    #: A frame with no pose within this many seconds of its capture is not used.
    max_pose_gap_s: float = setting(
        DEFAULT_MAX_POSE_GAP_S,
        flag="--max-pose-gap",
        limits=(0.001, 60.0),
        arg_type=float,
        metavar="S",
        group=MOBILE,
        help="a frame with no pose this close to its capture is not used (default 0.25)",
    )
    #: Seconds a pose update keeps the camera routed (0: the server's default).
    pose_lease_s: float = setting(
        0.0,
        flag="--pose-lease",
        limits=(0.0, 3600.0),
        arg_type=float,
        metavar="S",
        group=MOBILE,
        help="seconds one pose keeps the camera routed (default 0: the server's)",
    )
    #: The fastest the robot moves, m/s (0: the server's default, 3): faster poses are refused.
    max_speed_mps: float = setting(
        0.0,
        flag="--max-speed",
        limits=(0.0, 50.0),
        arg_type=float,
        metavar="M/S",
        group=MOBILE,
        help="the fastest the robot moves; the server refuses faster poses (default 0: its 3)",
    )
    #: Send the server a pose when the robot moved this far (metres) or turned this much (degrees),
    #: at most max_pose_rate_hz times a second.
    pose_update_distance_m: float = setting(
        0.1,
        flag="--pose-update-distance",
        limits=(0.0, 1000.0),
        arg_type=float,
        metavar="M",
        group=MOBILE,
        help="send a pose when the robot moved this far (default 0.1)",
    )
    pose_update_angle_deg: float = setting(
        5.0,
        flag="--pose-update-angle",
        limits=(0.0, 180.0),
        arg_type=float,
        metavar="DEG",
        group=MOBILE,
        help="... or turned this much (default 5)",
    )
    max_pose_rate_hz: float = setting(
        5.0,
        flag="--max-pose-rate",
        limits=(0.01, 100.0),
        arg_type=float,
        metavar="HZ",
        group=MOBILE,
        help="at most this many pose updates a second (default 5)",
    )
    #: A Foxglove live view of the camera's frames, detections drawn (drvs.camera.liveview): where
    #: it listens (host, port; port 0 picks one; None: no live view), and at most how many frames a
    #: second it sends while someone watches (None: DEFAULT_FOXGLOVE_FPS).
    foxglove: tuple[str, int] | None = setting(
        None,
        flag="--foxglove",
        env="DRVS_CAMERA_FOXGLOVE",
        metavar="[HOST:]PORT",
        group=LIVE,
        help="serve a Foxglove live view (WebSocket) of this camera's frames, JPEG, with its latest detections "
        "drawn, on topic /camera/ID/image; sent only while someone subscribes. PORT alone listens on 127.0.0.1, "
        "0 picks a free port. It has no access control: anyone who reaches it sees the images (%(env)s)",
    )
    foxglove_fps: float | None = setting(
        None,
        flag="--foxglove-fps",
        env="DRVS_CAMERA_FOXGLOVE_FPS",
        metavar="N",
        group=LIVE,
        help=f"at most N frames a second to the live view, above 0 and at most {MAX_FPS:g} "
        f"(default {DEFAULT_FOXGLOVE_FPS:g}; %(env)s)",
    )
    #: TLS and the registration token (see drvs.wire.security); paths are relative to the config file.
    #: Their flags are drvs.wire._cli.add_security_arguments'.
    tls_cert: Path | None = setting(None, flag="--tls-cert", env=SECURITY_ENV["tls_cert"], shared=True)  # noqa: RUF009
    tls_key: Path | None = setting(None, flag="--tls-key", env=SECURITY_ENV["tls_key"], shared=True)  # noqa: RUF009
    tls_ca: Path | None = setting(None, flag="--tls-ca", env=SECURITY_ENV["tls_ca"], shared=True)  # noqa: RUF009
    tls_client_auth: bool = setting(False, flag="--tls-client-auth", env=SECURITY_ENV["tls_client_auth"], shared=True)
    token_file: Path | None = setting(None, flag="--token-file", env=SECURITY_ENV["token_file"], shared=True)  # noqa: RUF009
    log_level: str | None = setting(
        None, flag="--log-level", env="DRVS_LOG_LEVEL", help="DEBUG, INFO, WARNING (%(env)s)"
    )
    #: text, or json (one object per line, with the request id).
    log_format: str | None = setting(
        None,
        flag="--log-format",
        env="DRVS_LOG_FORMAT",
        help="text, or json: one object per line with the request id (%(env)s)",
    )
    #: Serve Prometheus metrics on this port (0: any free port; None: off).
    metrics_port: int | None = setting(
        None,
        flag="--metrics-port",
        env="DRVS_METRICS_PORT",
        help="Prometheus metrics port; 0 picks one; default off (%(env)s)",
    )
    #: Where the metrics listen: this host only unless the operator says otherwise.
    metrics_host: str = setting(
        DEFAULT_METRICS_HOST,
        flag="--metrics-host",
        env="DRVS_METRICS_HOST",
        help="address the metrics listen on (default 127.0.0.1: this host only; %(env)s)",
    )
    #: The operator's object-detection models (config file only): {name: {path, classes, ...}}, see
    #: drvs.detectors.model; paths are relative to the config file.
    models: dict[str, ModelSpec] = setting(default_factory=dict)  # noqa: RUF009

    def __post_init__(self) -> None:
        check_settings({f.name: getattr(self, f.name) for f in fields(self)})
        if self.foxglove_fps is not None:
            check_fps(self.foxglove_fps, f"foxglove_fps ({_FLAGS['foxglove_fps']})")
            if self.foxglove is None:
                raise InvalidArgument("foxglove_fps (--foxglove-fps): only with --foxglove (a live view to send to)")
        self.mount_spec()  # refuses a malformed mount now, not at start
        check_frame(self.frame, f"frame ({_FLAGS['frame']})")

    def mount_spec(self) -> Mount | None:
        """The mount, parsed (None for a fixed camera); InvalidArgument naming the flag."""
        if self.mount is None:
            for name in ("hfov_deg", "camera_matrix", "pose_source"):
                if getattr(self, name) is not None:
                    raise InvalidArgument(f"{name} ({_FLAGS[name]}): only with --mount (a mobile camera)")
            return None
        if self.homography is not None:
            raise InvalidArgument("mount (--mount): a mobile camera has no --homography; give one or the other")
        if (self.hfov_deg is None) == (self.camera_matrix is None):
            raise InvalidArgument("mount (--mount): give the camera's --hfov or its --camera-matrix (one of them)")
        try:
            return Mount.parse(self.mount, self.hfov_deg or 0.0, self.camera_matrix)
        except InvalidArgument as exc:
            text = str(exc)
            flag = "--camera-matrix" if text.startswith("camera_matrix") else "--mount"
            raise InvalidArgument(f"{text.split(':', 1)[0]} ({flag}):{text.split(':', 1)[1]}") from None

    def security(self) -> Security:
        return Security(
            tls_cert=self.tls_cert,
            tls_key=self.tls_key,
            tls_ca=self.tls_ca,
            require_client_cert=self.tls_client_auth,
            token=read_token(self.token_file) if self.token_file else "",
        )

    def detector_options(self) -> dict[str, dict[str, Any]]:
        """Per-detector options for CameraNode(detector_options=...)."""
        options: dict[str, dict[str, Any]] = {}
        if self.background is not None:
            options["foreground"] = {"background": str(self.background)}
        if self.models:
            options["model"] = {"models": self.models}
        if self.people_min_height_px is not None:
            options.setdefault("people", {})["min_height_px"] = self.people_min_height_px
        if self.people_height_m is not None:
            options.setdefault("people", {})["person_height_m"] = self.people_height_m
        return options


def _whole(f: Field[Any], declared: Setting) -> Setting:
    return dataclasses.replace(declared, whole=f.type in ("int", "int | None"))


#: Every setting by name, in CameraConfig's order: what the parser, environment, file and checks read.
SETTINGS: dict[str, Setting] = settings.declared(CameraConfig, Setting(), _whole)
#: Every environment variable a camera node reads, by setting.
ENVIRONMENT = {s.name: s.env for s in SETTINGS.values() if s.env}
_FLAGS = {s.name: s.flag for s in SETTINGS.values() if s.flag}
#: Numeric settings, checked wherever they come from (CameraConfig, CameraNode's constructor, the
#: CLI): name -> (lowest, highest, whole numbers only).
LIMITS: dict[str, tuple[float, float, bool]] = {
    s.name: (*s.limits, s.whole) for s in SETTINGS.values() if s.limits is not None
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """drvs-camera's setting flags (all but the shared security ones), in the declared order, each
    in its group (created on first use). Each defaults to None: not given."""
    settings.add_arguments(parser, (s for s in SETTINGS.values() if not s.shared))


def check_setting(name: str, value: Any) -> None:
    """InvalidArgument('name: value must be …') when a numeric setting is out of its range (None:
    not set, allowed). The one check for the config, the CLI and CameraNode(...) alike."""
    if name not in LIMITS or value is None:
        return
    low, high, whole = LIMITS[name]
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan
    if whole and not (isinstance(number, int) or (math.isfinite(number) and number == int(number))):
        number = math.nan
    if not (math.isfinite(number) and low <= number <= high):
        shown = format_number(value) if not math.isnan(number) else repr(value)
        kind = "a whole number" if whole else "a number"
        bounds = f"{int(low)} to {int(high)}" if whole else f"{format_number(low)} to {format_number(high)}"
        raise InvalidArgument(f"{name}: {shown} must be {kind} from {bounds}")


def check_settings(values: Mapping[str, Any]) -> None:
    """check_setting for each of `values` (by setting name)."""
    for name, value in values.items():
        check_setting(name, value)


def load_config(
    flags: Mapping[str, Any], environ: Mapping[str, str], config_file: str | Path | None = None
) -> CameraConfig:
    """Merge flags (None = not given), environment and file; validate everything once."""
    file_values: dict[str, Any] = {}
    base = Path(".")
    if config_file is not None:
        path = Path(config_file)
        data = read_yaml(path, "config")
        data = {} if data is None else data
        if not isinstance(data, dict):
            raise InvalidArgument(f"config {path}: expected a mapping of settings")
        known = [f.name for f in fields(CameraConfig)]
        for key in data:
            if key not in known:
                raise InvalidArgument(f"config {path}: {key}: unknown key (expected one of: {', '.join(known)})")
        file_values = {k: (v, f"config {path}") for k, v in data.items()}
        base = path.parent
    values: dict[str, Any] = {}
    for f in fields(CameraConfig):
        name = f.name
        if flags.get(name) is not None:
            raw, origin = flags[name], _FLAGS[name]
        elif name in ENVIRONMENT and environ.get(ENVIRONMENT[name], "") != "":
            raw, origin = environ[ENVIRONMENT[name]], ENVIRONMENT[name]
        elif name in file_values:
            raw, origin = file_values[name]
        else:
            continue
        values[name] = _convert(name, raw, origin, base if origin.startswith("config") else Path("."))
        try:
            check_setting(name, values[name])
        except InvalidArgument as exc:
            # The same message as CameraNode(...) gives, and where the value came from.
            raise InvalidArgument(f"{name} (from {origin}){str(exc)[len(name) :]}") from None
    if "mount" in values:
        values.setdefault("homography", None)
    for required in ("id", "source", "homography"):
        if required not in values:
            raise InvalidArgument(
                f"{required}: missing; give {_FLAGS[required]}, {ENVIRONMENT[required]} "
                f"or {required}: in a --config file"
            )
    if values.get("models") and "model" not in values.get("detectors", DETECTOR_KINDS):
        raise InvalidArgument(
            f"models: {', '.join(values['models'])} configured, but detectors ({', '.join(values['detectors'])}) "
            "leaves out model"
        )
    if "background" in values and "foreground" not in values.get("detectors", DETECTOR_KINDS):
        raise InvalidArgument(
            f"background: {values['background']} is for the foreground detector, which detectors "
            f"({', '.join(values['detectors'])}) leaves out"
        )
    return CameraConfig(**values)


def _convert(name: str, raw: Any, origin: str, base: Path) -> Any:
    where = f"{name} (from {origin})"
    try:
        if name == "resolution":
            parts = raw if isinstance(raw, list) else str(raw).lower().replace("x", ",").split(",")
            if len(parts) != 2:
                raise InvalidArgument(f"{where}: {raw!r} is not W,H")
            w, h = (int(p) for p in parts)
            if not (16 <= w <= 16384 and 16 <= h <= 16384):
                raise InvalidArgument(f"{where}: {w}x{h} is not a camera resolution")
            return (w, h)
        if name == "models":
            return parse_models(raw, where, base)
        if name == "foxglove_fps":
            if isinstance(raw, bool):
                raise InvalidArgument(f"{where}: {raw!r} is not a number")
            return check_fps(float(raw), where)
        if name == "detectors":
            kinds = raw if isinstance(raw, list) else str(raw).split(",")
            kinds = [str(k).strip() for k in kinds if str(k).strip()]
            if not kinds:
                raise InvalidArgument(f"{where}: {raw!r}: name at least one of {', '.join(DETECTOR_KINDS)}")
            unknown = [k for k in kinds if k not in DETECTOR_KINDS]
            if unknown:
                raise InvalidArgument(
                    f"{where}: {', '.join(map(repr, unknown))} is not an installed detector; "
                    f"installed: {', '.join(DETECTOR_KINDS)}"
                )
            return tuple(dict.fromkeys(kinds))
        if name in LIMITS and not LIMITS[name][2]:
            if isinstance(raw, bool):
                raise InvalidArgument(f"{where}: {raw!r} is not a number")
            return float(raw)  # its range: check_setting
        if name in LIMITS:
            text = str(raw).strip()
            if isinstance(raw, bool) or not (isinstance(raw, int) or text.lstrip("-").isdecimal()):
                raise InvalidArgument(f"{where}: {raw!r} is not a whole number")
            return int(text)
        if name == "metrics_port":
            port = int(raw) if not isinstance(raw, bool) and str(raw).strip().isdecimal() else -1
            if not 0 <= port <= 65535:
                raise InvalidArgument(f"{where}: {raw!r} is not a port number (0 picks a free one)")
            return port
        if name == "log_format":
            if str(raw) not in FORMATS:
                raise InvalidArgument(f"{where}: {raw!r} must be one of {', '.join(FORMATS)}")
            return str(raw)
        if name in ("loop", "serve_frames", "tls_client_auth"):
            return parse_bool(raw, where)
        if not isinstance(raw, (str, int)) or isinstance(raw, bool):
            raise InvalidArgument(f"{where}: expected a string, got {type(raw).__name__}")
        text = str(raw)
        if name == "id":
            return check_id(text, where)
        if name == "foxglove":
            return parse_listen(text, where)
        if name == "server":
            parse_address_list(text, where)  # one server, or several sharing a registry (a,b,...)
        elif name == "advertise":
            parse_address(text, where)
        elif name == "listen":
            parse_address(text, where, allow_port_zero=True)
        elif name == "metrics_host":
            try:
                parse_address(format_address(text.strip("[]"), 1), where)
            except InvalidArgument:
                raise InvalidArgument(f"{where}: {text[:80]!r} is not a host name or IP address") from None
            return text.strip("[]")
        elif name in ("homography", "background", "tls_cert", "tls_key", "tls_ca", "token_file"):
            path = Path(text)
            return path if path.is_absolute() else base / path
        elif name == "source" and not text.strip():
            raise InvalidArgument(f"{where}: empty")
        return text
    except (ValueError, TypeError):
        raise InvalidArgument(f"{where}: {raw!r} is not a number") from None
