"""A camera node's configuration: one typed model, loaded once at start.

Precedence for every setting: command-line flag > DRVS_* environment variable > config file >
default. Unknown keys and bad values are errors that name the key and where it came from.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from drvs._cli import SECURITY_ENV, read_token
from drvs._files import read_yaml
from drvs.detection import DEFAULT_MIN_AREA_PX
from drvs.detectors.model import ModelSpec, parse_models
from drvs.errors import InvalidArgument
from drvs.filters import DETECTOR_KINDS
from drvs.geometry import DEFAULT_MAX_RANGE_M
from drvs.logs import FORMATS
from drvs.metrics import DEFAULT_METRICS_HOST
from drvs.model import check_id
from drvs.net import format_address, parse_address
from drvs.security import Security

DEFAULT_SERVER = "127.0.0.1:50051"
DEFAULT_LISTEN = "127.0.0.1:0"
DEFAULT_MAX_FRAME_AGE_S = 2.0
DEFAULT_MAX_CONTINUOUS_PER_ROBOT = 32  # as drvs.camera.node's

#: Every environment variable a camera node reads, by setting.
ENVIRONMENT = {
    "id": "DRVS_CAMERA_ID",
    "source": "DRVS_CAMERA_SOURCE",
    "homography": "DRVS_CAMERA_HOMOGRAPHY",
    "server": "DRVS_SERVER",
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
    homography: Path
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
        return options


_FLAGS = {"id": "--id", "source": "--source", "homography": "--homography", "max_range_m": "--max-range",
          "min_area_px": "--min-area", "max_frame_age_s": "--max-frame-age", "loop": "--no-loop",
          "serve_frames": "--serve-frames", "log_level": "--log-level", "server": "--server",
          "listen": "--listen", "advertise": "--advertise", "resolution": "--resolution", "fps": "--fps",
          "detectors": "--detectors", "heartbeat_s": "--heartbeat", "tls_cert": "--tls-cert",
          "tls_key": "--tls-key", "tls_ca": "--tls-ca", "tls_client_auth": "--tls-client-auth",
          "token_file": "--token-file", "log_format": "--log-format", "metrics_port": "--metrics-port",
          "metrics_host": "--metrics-host", "max_continuous": "--max-continuous",
          "background": "--background"}  # fmt: skip


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
        if name == "detectors":
            kinds = raw if isinstance(raw, list) else str(raw).split(",")
            kinds = [str(k).strip() for k in kinds if str(k).strip()]
            unknown = [k for k in kinds if k not in DETECTOR_KINDS]
            if not kinds or unknown:
                raise InvalidArgument(f"{where}: {raw!r}: detectors must be some of {', '.join(DETECTOR_KINDS)}")
            return tuple(kinds)
        if name in ("max_range_m", "min_area_px", "max_frame_age_s", "fps", "heartbeat_s"):
            value = float(raw) if not isinstance(raw, bool) else math.nan
            limits = {
                "max_range_m": (0.1, 1000.0),
                "min_area_px": (1.0, 1e7),
                "max_frame_age_s": (0.05, 3600.0),
                "fps": (0.1, 1000.0),
                "heartbeat_s": (0.05, 3600.0),
            }[name]
            if not (math.isfinite(value) and limits[0] <= value <= limits[1]):
                raise InvalidArgument(f"{where}: {raw!r} must be a number from {limits[0]:g} to {limits[1]:g}")
            return value
        if name == "max_continuous":
            count = int(raw) if not isinstance(raw, bool) and str(raw).strip().isdecimal() else 0
            if not 1 <= count <= 1_000_000:
                raise InvalidArgument(f"{where}: {raw!r} must be a whole number from 1 to 1000000")
            return count
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
            if isinstance(raw, bool):
                return raw
            text = str(raw).strip().lower()
            if text in ("1", "true", "yes", "on"):
                return True
            if text in ("0", "false", "no", "off"):
                return False
            raise InvalidArgument(f"{where}: {raw!r} is not true or false")
        if not isinstance(raw, (str, int)) or isinstance(raw, bool):
            raise InvalidArgument(f"{where}: expected a string, got {type(raw).__name__}")
        text = str(raw)
        if name == "id":
            return check_id(text, where)
        if name in ("server", "advertise"):
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
    except ValueError:
        raise InvalidArgument(f"{where}: {raw!r} is not a number") from None
