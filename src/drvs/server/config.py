"""The server's configuration: one typed, frozen model, validated once.

`drvs-server`'s flags, its DRVS_* environment variables and `DrvsServer(...)`'s keyword arguments
all become a `ServerConfig`, so a bad value is refused by the same check with the same message
wherever it comes from: `DrvsServer(forward_timeout_s=0)` and `drvs-server --forward-timeout 0`
both say `forward_timeout_s (--forward-timeout): 0 must be in (0, 60]`. Each message starts with
the setting's name (the constructor's keyword) and gives its flag (and variable) in parentheses.
Precedence: flag > DRVS_* variable > default.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drvs import _grpc
from drvs._cli import env_number, format_number, parse_bool
from drvs.errors import InvalidArgument
from drvs.etcd import Endpoints
from drvs.geometry import DEFAULT_MAX_RANGE_M
from drvs.net import host_of, parse_address
from drvs.registry import (
    DEFAULT_GRACE_S,
    DEFAULT_LEASE_TTL_S,
    DEFAULT_MAX_CAMERAS_PER_IDENTITY,
    DEFAULT_MAX_FOV_AREA_M2,
    DEFAULT_MAX_FOV_RANGE_M,
    DEFAULT_MIN_POSE_INTERVAL_S,
    DEFAULT_POSE_LEASE_S,
    MAX_POSE_LEASE_S,
)
from drvs.server.admission import DEFAULT_TARGET_S
from drvs.server.policy import (
    DEFAULT_FORWARD_BYTES_PER_S,
    DEFAULT_MAX_ACTIVE,
    DEFAULT_RATE_HZ,
    CallbackPolicy,
    RequestLimits,
)
from drvs.server.shared import DEFAULT_POSE_WRITE_RATE, DEFAULT_REGISTRATION_RATE

DEFAULT_LISTEN = "127.0.0.1:50051"
#: Hosts that bind every interface: no address a camera can dial.
WILDCARDS = ("0.0.0.0", "::", "")
#: How long the server waits for a camera to accept a forwarded request.
DEFAULT_FORWARD_TIMEOUT_S = 2.0
#: Forwards to one camera waiting for its acceptance at once; past this the server sheds load:
#: the robot gets an error report for that camera at once (RESOURCE_EXHAUSTED, "busy").
DEFAULT_MAX_QUEUED_FORWARDS = 64

#: The DRVS_* environment variables drvs-server reads, by setting (a flag given wins).
ENVIRONMENT = {
    "listen": "DRVS_SERVER_LISTEN",
    "lease_ttl_s": "DRVS_LEASE_TTL",
    "trust_network": "DRVS_TRUST_NETWORK",
    "registry": "DRVS_REGISTRY",
    "advertise": "DRVS_SERVER_ADVERTISE",
    "etcd_ca": "DRVS_ETCD_CA",
    "etcd_cert": "DRVS_ETCD_CERT",
    "etcd_key": "DRVS_ETCD_KEY",
}

#: Each setting's command-line flag.
FLAGS = {
    "listen": "--listen",
    "lease_ttl_s": "--lease-ttl",
    "forward_timeout_s": "--forward-timeout",
    "max_queued_forwards": "--max-queued-forwards",
    "allow_callback": "--allow-callback",
    "allow_any_callback": "--allow-any-callback",
    "warm_up_s": "--warm-up",
    "rate_limit_hz": "--rate-limit",
    "max_continuous": "--max-continuous",
    "max_forward_bytes_per_s": "--max-forward-bytes",
    "max_streams_per_connection": "--max-streams-per-connection",
    "max_connection_idle_s": "--max-connection-idle",
    "max_connection_age_s": "--max-connection-age",
    "max_connection_age_grace_s": "--max-connection-age-grace",
    "trust_network": "--trust-network",
    "registration_grace_s": "--registration-grace",
    "max_cameras_per_identity": "--max-cameras-per-identity",
    "max_fov_range_m": "--max-fov-range",
    "max_fov_area_m2": "--max-fov-area",
    "pose_lease_s": "--pose-lease",
    "max_pose_lease_s": "--max-pose-lease",
    "min_pose_interval_s": "--min-pose-interval",
    "registry": "--registry",
    "registration_rate": "--registration-rate",
    "pose_write_rate": "--pose-write-rate",
    "advertise": "--advertise",
    "etcd_ca": "--etcd-ca",
    "etcd_cert": "--etcd-cert",
    "etcd_key": "--etcd-key",
    "workers": "--workers",
    "admission_target_s": "--admission-target",
}

#: Inclusive numeric ranges: setting -> (lowest, highest, whether the lowest is allowed, unit text).
_RANGES: dict[str, tuple[float, float, bool, str]] = {
    "lease_ttl_s": (0, 3600, False, ""),
    "forward_timeout_s": (0, 60, False, ""),
    "max_queued_forwards": (1, 100_000, True, ""),
    "warm_up_s": (0, 3600, True, ""),
    "rate_limit_hz": (0, 1e6, False, ""),
    "max_continuous": (1, 1e6, True, ""),
    "max_forward_bytes_per_s": (1, 1e12, True, ""),
    "max_streams_per_connection": (0, 1e9, True, " (0: no limit)"),
    "max_connection_idle_s": (0, 1e9, True, " (0: no limit)"),
    "max_connection_age_s": (0, 1e9, True, " (0: no limit)"),
    "max_connection_age_grace_s": (0, 1e9, True, " (0: no limit)"),
    "registration_grace_s": (0, 86400, True, ""),
    "max_cameras_per_identity": (1, 1_000_000, True, ""),
    "max_fov_range_m": (15, 10_000, True, " metres"),
    "max_fov_area_m2": (1, 1e8, True, " square metres"),
    "pose_lease_s": (0, 3600, False, " seconds"),
    "max_pose_lease_s": (0, 3600, False, " seconds"),
    "min_pose_interval_s": (0, 3600, True, " seconds"),
    "workers": (1, 256, True, " processes"),
    "registration_rate": (0, 1e9, False, " registrations a minute"),
    "pose_write_rate": (0, 1e9, False, " pose updates a second"),
    "admission_target_s": (0, 10, True, " seconds (0: admission off)"),
}
_INTEGERS = (
    "max_queued_forwards",
    "max_continuous",
    "max_streams_per_connection",
    "max_cameras_per_identity",
    "workers",
)


def setting(name: str) -> str:
    """How messages name a setting: its keyword, then where an operator gives it."""
    where = ", ".join(w for w in (FLAGS.get(name), ENVIRONMENT.get(name)) if w)
    return f"{name} ({where})" if where else name


@dataclass(frozen=True)
class ServerConfig:
    """Every setting of the server role. Constructing one validates it (InvalidArgument naming the
    setting); `DrvsServer(...)` and `drvs-server` both build one, so they accept the same values."""

    #: HOST:PORT to serve on; port 0 picks a free one.
    listen: str = DEFAULT_LISTEN
    #: Seconds a camera's registration lasts without a heartbeat, in (0, 3600].
    lease_ttl_s: float = DEFAULT_LEASE_TTL_S
    #: Seconds a camera may take to accept a forwarded request, in (0, 60].
    forward_timeout_s: float = DEFAULT_FORWARD_TIMEOUT_S
    #: Forwards waiting for one camera's acceptance at once; past it the robot hears "busy".
    max_queued_forwards: int = DEFAULT_MAX_QUEUED_FORWARDS
    #: Metres a camera sees when it registers without a max_range_m; at most max_fov_range_m.
    default_max_range_m: float = DEFAULT_MAX_RANGE_M
    #: IP networks (CIDR) reports may also be sent to, besides the requesting robot's own address.
    allow_callback: tuple[str, ...] = ()
    #: Send reports wherever a request says (trusted networks only).
    allow_any_callback: bool = False
    #: Seconds after a start during which replies say coverage is uncertain (None: the lease TTL).
    warm_up_s: float | None = None
    #: Requests a second per robot; bursts of twice that.
    rate_limit_hz: float = DEFAULT_RATE_HZ
    #: Continuous requests one robot may have running at once.
    max_continuous: int = DEFAULT_MAX_ACTIVE
    #: Bytes a second forwarded to cameras on one robot's behalf; bursts of twice that.
    max_forward_bytes_per_s: float = DEFAULT_FORWARD_BYTES_PER_S
    #: Calls one connection may have open at once (0: no limit).
    max_streams_per_connection: int = _grpc.DEFAULT_MAX_STREAMS_PER_CONNECTION
    #: Seconds a connection may stay without a call before it is closed (0: no limit).
    max_connection_idle_s: float = _grpc.DEFAULT_MAX_CONNECTION_IDLE_S
    #: Seconds after which a client is asked to reconnect (0: no limit).
    max_connection_age_s: float = _grpc.DEFAULT_MAX_CONNECTION_AGE_S
    #: Seconds the old connection's calls then have to finish.
    max_connection_age_grace_s: float = _grpc.DEFAULT_MAX_CONNECTION_AGE_GRACE_S
    #: Let cameras register without a credential although `listen` is beyond this host.
    trust_network: bool = False
    #: Seconds a camera id stays with whoever registered it after its lease ran out.
    registration_grace_s: float = DEFAULT_GRACE_S
    #: Camera ids one credential (without one: one IP address) may hold.
    max_cameras_per_identity: int = DEFAULT_MAX_CAMERAS_PER_IDENTITY
    #: Largest max_range_m a camera may register with, metres.
    max_fov_range_m: float = DEFAULT_MAX_FOV_RANGE_M
    #: Largest field of view one camera may register, square metres.
    max_fov_area_m2: float = DEFAULT_MAX_FOV_AREA_M2
    #: Seconds a mobile camera is routed after a pose update (unless it asks for another lease).
    pose_lease_s: float = DEFAULT_POSE_LEASE_S
    #: Longest pose lease a mobile camera may ask for, seconds; at least pose_lease_s.
    max_pose_lease_s: float = MAX_POSE_LEASE_S
    #: A mobile camera's pose updates closer together than this are refused, seconds.
    min_pose_interval_s: float = DEFAULT_MIN_POSE_INTERVAL_S
    #: Where the registry lives: "memory" (this server alone) or etcd://HOST:PORT[,HOST:PORT...],
    #: shared by every server given the same etcd (drvs.server.shared).
    registry: str = "memory"
    #: On a registry in etcd, per identity: registrations a minute, and pose updates a second, each
    #: in bursts of as many (every one is a write etcd keeps until it is compacted).
    registration_rate: float = DEFAULT_REGISTRATION_RATE
    pose_write_rate: float = DEFAULT_POSE_WRITE_RATE
    #: HOST:PORT cameras dial to send this server a fused request's reports ("": the bound address,
    #: unless it is a wildcard). Needed when cameras know several servers (they must report to the
    #: one that asked) and this one listens on 0.0.0.0.
    advertise: str = ""
    #: TLS to etcd: the CA its members' certificates are checked against, and this server's own
    #: certificate and key when etcd asks for one (--client-cert-auth). PEM files; "" none.
    etcd_ca: str = ""
    etcd_cert: str = ""
    etcd_key: str = ""
    #: Server processes serving `listen` together (SO_REUSEPORT: the kernel spreads connections
    #: over them), sharing the registry in etcd; drvs-server starts them. 1: this process alone.
    workers: int = 1
    #: The standing queue delay tolerated before requests are refused at the door (the server's
    #: loop; a camera link beyond its fastest round trip), seconds; 0 turns admission off.
    admission_target_s: float = DEFAULT_TARGET_S

    def __post_init__(self) -> None:
        object.__setattr__(self, "allow_callback", tuple(self.allow_callback))
        self.validate()

    def validate(self) -> None:
        """Refuse the first bad setting: InvalidArgument('name (--flag): value must be …')."""
        parse_address(self.listen, setting("listen"), allow_port_zero=True)
        for name, (low, high, closed, unit) in _RANGES.items():
            value = getattr(self, name)
            if value is None:
                continue
            number = math.nan if isinstance(value, bool) or not isinstance(value, (int, float)) else value
            if name in _INTEGERS and number == number and number != int(number):
                number = math.nan
            inside = (low <= number if closed else low < number) and number <= high
            if not inside:
                interval = f"{'[' if closed else '('}{format_number(low)}, {format_number(high)}]"
                numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
                shown = format_number(value) if numeric else repr(value)
                raise InvalidArgument(f"{setting(name)}: {shown} must be in {interval}{unit}")
        if not (0 < self.default_max_range_m <= self.max_fov_range_m):
            raise InvalidArgument(
                f"{setting('default_max_range_m')}: {self.default_max_range_m:g} m must be in "
                f"(0, max_fov_range_m {self.max_fov_range_m:g} m]"
            )
        if self.pose_lease_s > self.max_pose_lease_s:
            raise InvalidArgument(
                f"{setting('pose_lease_s')}: {self.pose_lease_s:g} s is more than "
                f"max_pose_lease_s {self.max_pose_lease_s:g} s"
            )
        CallbackPolicy(self.allow_callback)  # refuses a malformed network
        if self.advertise:
            parse_address(self.advertise, setting("advertise"))
        if self.registry != "memory":
            Endpoints.parse(self.registry, setting("registry"))
        if bool(self.etcd_cert) != bool(self.etcd_key):
            raise InvalidArgument(f"{setting('etcd_cert')} and {setting('etcd_key')}: give both or neither")
        if (self.etcd_cert or self.etcd_key) and not self.etcd_ca:
            raise InvalidArgument(f"{setting('etcd_ca')}: needed with a certificate for etcd (TLS)")
        if self.workers > 1 and self.registry == "memory":
            raise InvalidArgument(
                f"{setting('workers')}: {self.workers} processes need a shared registry, --registry "
                "etcd://HOST:PORT: a camera registers with one of them and is routed by all"
            )
        if self.workers > 1 and host_of(self.listen) in WILDCARDS and not self.advertise:
            raise InvalidArgument(
                f"{setting('advertise')}: needed with --workers on a wildcard address ({self.listen}): each "
                "worker takes the reports of its fused requests on a port of its own, at the advertised host"
            )
        if self.etcd_ca and self.registry == "memory":
            raise InvalidArgument(f"{setting('etcd_ca')}: only with --registry etcd://...")
        for name in ("etcd_ca", "etcd_cert", "etcd_key"):
            path = getattr(self, name)
            if path and not os.path.isfile(path):
                raise InvalidArgument(f"{setting(name)}: {path!r} is not a file")
        if self.etcd_cert:
            from drvs.security import SERVER, certificate_fields

            with open(self.etcd_cert, "rb") as f:
                common_name, role = certificate_fields(f.read())
            if role and role != SERVER:  # etcd's users are servers (drvs.etcd_auth)
                raise InvalidArgument(
                    f"{setting('etcd_cert')}: {common_name!r} is a {role} certificate (OU={role}); "
                    "etcd is for servers' certificates (OU=server)"
                )

    def etcd_credentials(self) -> Any:
        """grpc.ChannelCredentials for etcd over TLS, or None (plain TCP)."""
        if not self.etcd_ca:
            return None
        import grpc

        def read(path: str) -> bytes | None:
            return open(path, "rb").read() if path else None

        return grpc.ssl_channel_credentials(
            root_certificates=read(self.etcd_ca),
            private_key=read(self.etcd_key),
            certificate_chain=read(self.etcd_cert),
        )

    @property
    def warm_up(self) -> float:
        """Seconds of uncertain coverage after a start (the lease TTL unless set)."""
        return self.lease_ttl_s if self.warm_up_s is None else self.warm_up_s

    def request_limits(self) -> RequestLimits:
        return RequestLimits(
            self.rate_limit_hz,
            max(1, round(2 * self.rate_limit_hz)),
            self.max_continuous,
            forward_bytes_per_s=self.max_forward_bytes_per_s,
        )

    def connection_limits(self) -> _grpc.ConnectionLimits:
        return _grpc.ConnectionLimits(
            max_streams=self.max_streams_per_connection,
            max_idle_s=self.max_connection_idle_s,
            max_age_s=self.max_connection_age_s,
            age_grace_s=self.max_connection_age_grace_s,
        )

    @classmethod
    def load(cls, flags: Mapping[str, Any], environ: Mapping[str, str] = os.environ) -> ServerConfig:
        """From flag values by setting name (None or absent: not given), then the DRVS_* variables,
        then the defaults. A variable that is not a number (or not true/false) names itself."""
        values = {k: v for k, v in flags.items() if v is not None}
        for name, variable in ENVIRONMENT.items():
            text = environ.get(variable, "")
            if name in values or text == "":
                continue
            if name == "lease_ttl_s":
                values[name] = env_number(variable, DEFAULT_LEASE_TTL_S, environ=environ)
            elif name == "trust_network":
                values[name] = parse_bool(text.strip().lower(), variable)
            else:
                values[name] = text
        if "allow_callback" in values:
            values["allow_callback"] = tuple(values["allow_callback"])
        return cls(**values)
