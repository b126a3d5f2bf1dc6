"""A camera node's configuration: one typed model, loaded once at start.

Precedence for every setting: command-line flag > DRVS_* environment variable > config file >
default. Unknown keys and bad values are errors that name the key and where it came from.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from drvs._cli import SECURITY_ENV, format_number, parse_bool, read_token
from drvs._files import read_yaml
from drvs.detectors import DEFAULT_MIN_AREA_PX, DETECTOR_KINDS
from drvs.detectors.model import ModelSpec, parse_models
from drvs.errors import InvalidArgument
from drvs.geometry import DEFAULT_MAX_RANGE_M
from drvs.liveview import parse_listen
from drvs.logs import FORMATS
from drvs.metrics import DEFAULT_METRICS_HOST
from drvs.mobile import DEFAULT_MAX_POSE_GAP_S, Mount
from drvs.model import DEFAULT_FRAME, check_frame, check_id
from drvs.net import format_address, parse_address, parse_address_list
from drvs.security import Security

from .liveview import check_fps

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

#: Every environment variable a camera node reads, by setting.
ENVIRONMENT = {
    "id": "DRVS_CAMERA_ID",
    "source": "DRVS_CAMERA_SOURCE",
    "homography": "DRVS_CAMERA_HOMOGRAPHY",
    "server": "DRVS_SERVER",
    "frame": "DRVS_CAMERA_FRAME",
    "listen": "DRVS_CAMERA_LISTEN",
    "advertise": "DRVS_CAMERA_ADVERTISE",
    "max_range_m": "DRVS_CAMERA_MAX_RANGE",
    "min_area_px": "DRVS_CAMERA_MIN_AREA",
    "max_frame_age_s": "DRVS_CAMERA_MAX_FRAME_AGE",
    "loop": "DRVS_CAMERA_LOOP",
    "serve_frames": "DRVS_CAMERA_SERVE_FRAMES",
    "resolution": "DRVS_CAMERA_RESOLUTION",
    "fps": "DRVS_CAMERA_FPS",
    "detectors": "DRVS_CAMERA_DETECTORS",
    "background": "DRVS_CAMERA_BACKGROUND",
    "heartbeat_s": "DRVS_CAMERA_HEARTBEAT",
    "max_continuous": "DRVS_CAMERA_MAX_CONTINUOUS",
    "detect_workers": "DRVS_CAMERA_DETECT_WORKERS",
    "people_min_height_px": "DRVS_CAMERA_PEOPLE_MIN_HEIGHT",
    "foxglove": "DRVS_CAMERA_FOXGLOVE",
    "foxglove_fps": "DRVS_CAMERA_FOXGLOVE_FPS",
    "log_level": "DRVS_LOG_LEVEL",
    "log_format": "DRVS_LOG_FORMAT",
    "metrics_port": "DRVS_METRICS_PORT",
    "metrics_host": "DRVS_METRICS_HOST",
    **SECURITY_ENV,
}


@dataclass(frozen=True)
class CameraConfig:
    id: str
    source: str
    #: A fixed camera's image -> floor homography file; a mobile camera gives `mount` instead.
    homography: Path | None
    server: str = DEFAULT_SERVER
    listen: str = DEFAULT_LISTEN
    advertise: str | None = None
    max_range_m: float = DEFAULT_MAX_RANGE_M
    min_area_px: float = DEFAULT_MIN_AREA_PX
    max_frame_age_s: float = DEFAULT_MAX_FRAME_AGE_S
    loop: bool = True
    serve_frames: bool = False
    #: Asked of a device or stream; a source that gives another size is refused (the homography
    #: belongs to one image size).
    resolution: tuple[int, int] | None = None
    fps: float | None = None
    detectors: tuple[str, ...] = DETECTOR_KINDS
    #: A picture of the empty floor (drvs-camera snapshot) for the foreground detector; relative
    #: to the config file. The detector refuses, at start, a file it cannot read or of another size.
    background: Path | None = None
    #: Heartbeat interval; by default a third of the lease the server grants.
    heartbeat_s: float | None = None
    #: Continuous requests one robot (callback address) may have running on this camera at once.
    max_continuous: int = DEFAULT_MAX_CONTINUOUS_PER_ROBOT
    #: Threads that run heavy detectors (people, models); requests beyond them queue.
    detect_workers: int = DEFAULT_DETECT_WORKERS
    #: The people detector's smallest person, pixels tall (None: its default, 128, HOG's window).
    people_min_height_px: float | None = None
    log_level: str | None = None
    #: text, or json (one object per line, with the request id).
    log_format: str | None = None
    #: Serve Prometheus metrics on this port (0: any free port; None: off).
    metrics_port: int | None = None
    #: Where the metrics listen: this host only unless the operator says otherwise.
    metrics_host: str = DEFAULT_METRICS_HOST
    #: TLS and the registration token (see drvs.security); paths are relative to the config file.
    tls_cert: Path | None = None
    tls_key: Path | None = None
    tls_ca: Path | None = None
    tls_client_auth: bool = False
    token_file: Path | None = None
    #: The operator's object-detection models (config file only): {name: {path, classes, ...}}, see
    #: drvs.detectors.model; paths are relative to the config file.
    models: dict[str, ModelSpec] = field(default_factory=dict)
    #: A mobile camera (on a robot): "X,Y,Z,YAW,PITCH", where it sits on the robot (metres,
    #: degrees; see drvs.mobile.Mount), with `hfov_deg` or `camera_matrix` ("FX,FY,CX,CY", pixels),
    #: and where its robot's poses come from (`pose_source`, see drvs.camera.poses).
    mount: str | None = None
    hfov_deg: float | None = None
    camera_matrix: str | None = None
    pose_source: str | None = None
    #: A frame with no pose within this many seconds of its capture is not used.
    max_pose_gap_s: float = DEFAULT_MAX_POSE_GAP_S
    #: Seconds a pose update keeps the camera routed (0: the server's default).
    pose_lease_s: float = 0.0
    #: The fastest the robot moves, m/s (0: the server's default, 3): faster poses are refused.
    max_speed_mps: float = 0.0
    #: Send the server a pose when the robot moved this far (metres) or turned this much (degrees),
    #: at most max_pose_rate_hz times a second.
    pose_update_distance_m: float = 0.1
    pose_update_angle_deg: float = 5.0
    max_pose_rate_hz: float = 5.0
    #: The floor plan its homography maps to ("building-a/floor-2"; default "map").
    frame: str = DEFAULT_FRAME
    #: A Foxglove live view of the camera's frames, detections drawn (drvs.camera.liveview): where
    #: it listens (host, port; port 0 picks one; None: no live view), and at most how many frames a
    #: second it sends while someone watches (None: DEFAULT_FOXGLOVE_FPS).
    foxglove: tuple[str, int] | None = None
    foxglove_fps: float | None = None

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
            options["people"] = {"min_height_px": self.people_min_height_px}
        return options


_FLAGS = {"id": "--id", "source": "--source", "homography": "--homography", "max_range_m": "--max-range",
          "min_area_px": "--min-area", "max_frame_age_s": "--max-frame-age", "loop": "--no-loop",
          "serve_frames": "--serve-frames", "log_level": "--log-level", "server": "--server",
          "listen": "--listen", "advertise": "--advertise", "resolution": "--resolution", "fps": "--fps",
          "detectors": "--detectors", "heartbeat_s": "--heartbeat", "tls_cert": "--tls-cert",
          "tls_key": "--tls-key", "tls_ca": "--tls-ca", "tls_client_auth": "--tls-client-auth",
          "token_file": "--token-file", "log_format": "--log-format", "metrics_port": "--metrics-port",
          "metrics_host": "--metrics-host", "max_continuous": "--max-continuous",
          "detect_workers": "--detect-workers", "background": "--background",
          "people_min_height_px": "--people-min-height", "mount": "--mount", "hfov_deg": "--hfov",
          "camera_matrix": "--camera-matrix", "pose_source": "--pose-source", "max_pose_gap_s": "--max-pose-gap",
          "pose_lease_s": "--pose-lease", "max_speed_mps": "--max-speed",
          "pose_update_distance_m": "--pose-update-distance",
          "pose_update_angle_deg": "--pose-update-angle", "max_pose_rate_hz": "--max-pose-rate",
          "frame": "--frame", "foxglove": "--foxglove", "foxglove_fps": "--foxglove-fps"}  # fmt: skip


#: Numeric settings, checked wherever they come from (CameraConfig, CameraNode's constructor, the
#: CLI): name -> (lowest, highest, whole numbers only).
LIMITS: dict[str, tuple[float, float, bool]] = {
    "max_range_m": (0.1, 1000.0, False),
    "min_area_px": (1.0, 1e7, False),
    "max_frame_age_s": (0.05, 3600.0, False),
    "fps": (0.1, 1000.0, False),
    "heartbeat_s": (0.05, 3600.0, False),
    "people_min_height_px": (32.0, 1024.0, False),
    "max_continuous": (1, 1_000_000, True),
    "detect_workers": (1, 64, True),
    "hfov_deg": (1.0, 179.0, False),
    "max_pose_gap_s": (0.001, 60.0, False),
    "pose_lease_s": (0.0, 3600.0, False),
    "max_speed_mps": (0.0, 50.0, False),
    "pose_update_distance_m": (0.0, 1000.0, False),
    "pose_update_angle_deg": (0.0, 180.0, False),
    "max_pose_rate_hz": (0.01, 100.0, False),
}


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
