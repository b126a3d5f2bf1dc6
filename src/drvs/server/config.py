"""The server's configuration: one typed, frozen model, validated once.

`drvs-server`'s flags, its DRVS_* environment variables and `DrvsServer(...)`'s keyword arguments
all become a `ServerConfig`, so a bad value is refused by the same check with the same message
wherever it comes from: `DrvsServer(forward_timeout_s=0)` and `drvs-server --forward-timeout 0`
both say `forward_timeout_s (--forward-timeout): 0 must be in (0, 60]`. Each message starts with
the setting's name (the constructor's keyword) and gives its flag (and variable) in parentheses.
Precedence: flag > DRVS_* variable > default.

Each setting is declared once, as a `ServerConfig` field made by `setting(...)`: its default, flag,
variable, range, unit and help text. drvs-server's parser (`add_arguments`), the environment
(`ServerConfig.load`), the range checks (`ServerConfig.validate`) and `DrvsServer(**settings)` all
read `SETTINGS`, so a new setting is one field here. (The declaring itself is drvs.core.settings',
shared with the camera's settings; why a dataclass with field metadata: see there.)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drvs.core import settings
from drvs.core.errors import InvalidArgument, expect_str
from drvs.core.geometry import DEFAULT_MAX_RANGE_M
from drvs.core.net import host_of, parse_address
from drvs.server.admission import DEFAULT_TARGET_S
from drvs.server.claims import DEFAULT_GRACE_S, DEFAULT_MAX_CAMERAS_PER_IDENTITY
from drvs.server.etcd import Endpoints
from drvs.server.policy import (
    DEFAULT_FORWARD_BYTES_PER_S,
    DEFAULT_MAX_ACTIVE,
    DEFAULT_RATE_HZ,
    CallbackPolicy,
    RequestLimits,
)
from drvs.server.registry import (
    DEFAULT_LEASE_TTL_S,
    DEFAULT_MAX_FOV_AREA_M2,
    DEFAULT_MAX_FOV_RANGE_M,
    DEFAULT_MIN_POSE_INTERVAL_S,
    DEFAULT_POSE_LEASE_S,
    MAX_POSE_LEASE_S,
)
from drvs.server.shared import DEFAULT_POSE_WRITE_RATE, DEFAULT_REGISTRATION_RATE
from drvs.wire import _grpc
from drvs.wire._cli import env_number, format_number, parse_bool

DEFAULT_LISTEN = "127.0.0.1:50051"
#: Hosts that bind every interface: no address a camera can dial.
WILDCARDS = ("0.0.0.0", "::", "")
#: How long the server waits for a camera to accept a forwarded request.
DEFAULT_FORWARD_TIMEOUT_S = 2.0
#: Forwards to one camera waiting for its acceptance at once; past this the server sheds load:
#: the robot gets an error report for that camera at once (RESOURCE_EXHAUSTED, "busy").
DEFAULT_MAX_QUEUED_FORWARDS = 64

#: drvs-server's argument groups (--help's sections); a setting without one is in the main list.
CONNECTIONS = "connections (0: no limit)"
MOBILE = "mobile cameras (cameras on robots, whose field of view moves)"
ETCD_TLS = "TLS to etcd (with --registry etcd://...)"


@dataclass(frozen=True)
class Setting(settings.Setting):
    """One server setting's declaration, kept in its ServerConfig field's metadata (see `setting`):
    drvs.core.settings' flag, variable, help and group, and the server's range; name, kind (bool,
    int, float, str or tuple: a repeatable flag) and default are the field's."""

    #: Inclusive (lowest, highest); the lowest itself only if `low_allowed`. None: no range.
    range: tuple[float, float] | None = None
    low_allowed: bool = True
    #: Said after the interval in a range message, e.g. " seconds".
    unit: str = ""
    kind: type = object

    @property
    def integer(self) -> bool:
        return self.kind is int

    def check_range(self, value: Any) -> None:
        """InvalidArgument('name (--flag): value must be in (low, high]unit') unless `value` (None:
        not set) is a number in the range, whole for an integer setting."""
        if value is None or self.range is None:
            return
        low, high = self.range
        number = math.nan if isinstance(value, bool) or not isinstance(value, (int, float)) else value
        if self.integer and number == number and number != int(number):
            number = math.nan
        if not ((low <= number if self.low_allowed else low < number) and number <= high):
            interval = f"{'[' if self.low_allowed else '('}{format_number(low)}, {format_number(high)}]"
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            shown = format_number(value) if numeric else repr(value)
            raise InvalidArgument(f"{described(self.name)}: {shown} must be in {interval}{self.unit}")

    def flag_options(self) -> dict[str, Any]:
        if self.kind is bool:
            return {"action": "store_const", "const": True}
        if self.kind is tuple:
            return {"action": "append", "metavar": self.metavar}
        if self.kind in (int, float):
            return {"metavar": self.metavar, "type": self.kind}
        return {"metavar": self.metavar}


def setting(
    default: Any,
    *,
    flag: str | None = None,
    env: str | None = None,
    range: tuple[float, float] | None = None,
    low_allowed: bool = True,
    unit: str = "",
    help: str = "",
    metavar: str | None = None,
    group: str | None = None,
) -> Any:
    """A ServerConfig field with its whole declaration: flag, variable, range, help, …"""
    declared = Setting(
        flag=flag, env=env, help=help, metavar=metavar, group=group, range=range, low_allowed=low_allowed, unit=unit
    )
    return settings.field(declared, default)


@dataclass(frozen=True)
class ServerConfig:
    """Every setting of the server role. Constructing one validates it (InvalidArgument naming the
    setting); `DrvsServer(...)` and `drvs-server` both build one, so they accept the same values.
    Each field declares its setting whole (see `setting`); drvs-server adds the flags in this order."""

    listen: str = setting(
        DEFAULT_LISTEN,
        flag="--listen",
        env="DRVS_SERVER_LISTEN",
        help="HOST:PORT to serve on; port 0 picks a free one (env %(env)s; default %(default)s)",
    )
    lease_ttl_s: float = setting(
        DEFAULT_LEASE_TTL_S,
        flag="--lease-ttl",
        env="DRVS_LEASE_TTL",
        range=(0, 3600),
        low_allowed=False,
        metavar="SECONDS",
        help="camera lease time-to-live (env %(env)s; default %(default)g)",
    )
    forward_timeout_s: float = setting(
        DEFAULT_FORWARD_TIMEOUT_S,
        flag="--forward-timeout",
        range=(0, 60),
        low_allowed=False,
        metavar="SECONDS",
        help="how long a camera may take to accept a forwarded request (default %(default)s)",
    )
    #: Past it the robot hears "busy" at once.
    max_queued_forwards: int = setting(
        DEFAULT_MAX_QUEUED_FORWARDS,
        flag="--max-queued-forwards",
        range=(1, 100_000),
        metavar="N",
        help="requests waiting for one camera's acceptance at once; past this the robot is told at once "
        "that the camera is busy (default %(default)s)",
    )
    #: Metres a camera sees when it registers without a max_range_m; at most max_fov_range_m.
    #: DrvsServer(...) only: no flag.
    default_max_range_m: float = setting(DEFAULT_MAX_RANGE_M)
    allow_callback: tuple[str, ...] = setting(
        (),
        flag="--allow-callback",
        metavar="CIDR",
        help="also let robots have reports sent to hosts in this network (repeatable); by default only to "
        "the requesting robot's own address",
    )
    allow_any_callback: bool = setting(
        False, flag="--allow-any-callback", help="send reports wherever a request says (trusted networks only)"
    )
    #: None: the lease TTL (see `warm_up`).
    warm_up_s: float | None = setting(
        None,
        flag="--warm-up",
        range=(0, 3600),
        metavar="SECONDS",
        help="after a start, replies say coverage is uncertain for this long: cameras registered with the "
        "server's previous run may not have registered again yet (default: the lease TTL; 0 for a new site)",
    )
    rate_limit_hz: float = setting(
        DEFAULT_RATE_HZ,
        flag="--rate-limit",
        range=(0, 1e6),
        low_allowed=False,
        metavar="HZ",
        help="requests a second per robot (its credential, or its connection); burst twice that (default %(default)s)",
    )
    max_continuous: int = setting(
        DEFAULT_MAX_ACTIVE,
        flag="--max-continuous",
        range=(1, 1e6),
        metavar="N",
        help="continuous requests one robot may have running at once (default %(default)s)",
    )
    max_forward_bytes_per_s: float = setting(
        DEFAULT_FORWARD_BYTES_PER_S,
        flag="--max-forward-bytes",
        range=(1, 1e12),
        metavar="BYTES",
        help="bytes a second the server may forward to cameras for one robot (a request's size times the "
        "cameras it goes to); burst twice that (default %(default)d)",
    )
    max_streams_per_connection: int = setting(
        _grpc.DEFAULT_MAX_STREAMS_PER_CONNECTION,
        flag="--max-streams-per-connection",
        range=(0, 1e9),
        unit=" (0: no limit)",
        metavar="N",
        group=CONNECTIONS,
        help="calls one connection may have open at once; more wait on the client (default %(default)s)",
    )
    max_pending_calls: int = setting(
        _grpc.DEFAULT_MAX_PENDING_CALLS,
        flag="--max-pending-calls",
        range=(0, 1e6),
        unit=" (0: no limit)",
        metavar="N",
        group=CONNECTIONS,
        help="calls of one method that may wait for the server to take them in; past N gRPC drops new ones at once "
        "(CANCELLED), some up to 2N and all beyond, so that a busy server's callers do not wait there until their "
        "deadline (default %(default)s)",
    )
    max_connection_idle_s: float = setting(
        _grpc.DEFAULT_MAX_CONNECTION_IDLE_S,
        flag="--max-connection-idle",
        range=(0, 1e9),
        unit=" (0: no limit)",
        metavar="SECONDS",
        group=CONNECTIONS,
        help="close a connection that has had no call open this long (default %(default)g)",
    )
    max_connection_age_s: float = setting(
        _grpc.DEFAULT_MAX_CONNECTION_AGE_S,
        flag="--max-connection-age",
        range=(0, 1e9),
        unit=" (0: no limit)",
        metavar="SECONDS",
        group=CONNECTIONS,
        help="ask a client to reconnect after this long; clients reconnect by themselves (default %(default)g)",
    )
    max_connection_age_grace_s: float = setting(
        _grpc.DEFAULT_MAX_CONNECTION_AGE_GRACE_S,
        flag="--max-connection-age-grace",
        range=(0, 1e9),
        unit=" (0: no limit)",
        metavar="SECONDS",
        group=CONNECTIONS,
        help="then end the old connection's calls this much later (default %(default)g)",
    )
    trust_network: bool = setting(
        False,
        flag="--trust-network",
        env="DRVS_TRUST_NETWORK",
        help="let cameras register without a credential although --listen is beyond this host: everyone who "
        "can reach the port is trusted (env %(env)s=1; default: only on loopback)",
    )
    registration_grace_s: float = setting(
        DEFAULT_GRACE_S,
        flag="--registration-grace",
        range=(0, 86400),
        metavar="SECONDS",
        help="a camera id stays with whoever registered it this long after its lease ran out (default %(default)s)",
    )
    max_cameras_per_identity: int = setting(
        DEFAULT_MAX_CAMERAS_PER_IDENTITY,
        flag="--max-cameras-per-identity",
        range=(1, 1_000_000),
        metavar="N",
        help="camera ids one credential (without one: one IP address) may hold (default %(default)s)",
    )
    max_fov_range_m: float = setting(
        DEFAULT_MAX_FOV_RANGE_M,
        flag="--max-fov-range",
        range=(15, 10_000),
        unit=" metres",
        metavar="M",
        help="largest max_range_m a camera may register with, metres (default %(default)s)",
    )
    max_fov_area_m2: float = setting(
        DEFAULT_MAX_FOV_AREA_M2,
        flag="--max-fov-area",
        range=(1, 1e8),
        unit=" square metres",
        metavar="M2",
        help="largest field of view one camera may register, square metres (default %(default)s)",
    )
    pose_lease_s: float = setting(
        DEFAULT_POSE_LEASE_S,
        flag="--pose-lease",
        range=(0, 3600),
        low_allowed=False,
        unit=" seconds",
        metavar="SECONDS",
        group=MOBILE,
        help="route a mobile camera this long after its last pose update, unless it asks for another "
        "lease (default %(default)g)",
    )
    #: At least pose_lease_s.
    max_pose_lease_s: float = setting(
        MAX_POSE_LEASE_S,
        flag="--max-pose-lease",
        range=(0, 3600),
        low_allowed=False,
        unit=" seconds",
        metavar="SECONDS",
        group=MOBILE,
        help="longest pose lease a mobile camera may ask for (default %(default)g)",
    )
    min_pose_interval_s: float = setting(
        DEFAULT_MIN_POSE_INTERVAL_S,
        flag="--min-pose-interval",
        range=(0, 3600),
        unit=" seconds",
        metavar="SECONDS",
        group=MOBILE,
        help="refuse a mobile camera's pose update sooner than this after its previous one (default %(default)g)",
    )
    #: "memory" (this server alone) or etcd://HOST:PORT[,HOST:PORT...], shared by every server given
    #: the same etcd (drvs.server.shared).
    registry: str = setting(
        "memory",
        flag="--registry",
        env="DRVS_REGISTRY",
        metavar="memory|etcd://HOST:PORT[,HOST:PORT...]",
        help="where the camera registry lives: in this server's memory (default), or in etcd, shared by "
        "every server given the same etcd (%(env)s)",
    )
    #: On a registry in etcd, per identity, each in bursts of as many (every one is a write etcd
    #: keeps until it is compacted).
    registration_rate: float = setting(
        DEFAULT_REGISTRATION_RATE,
        flag="--registration-rate",
        range=(0, 1e9),
        low_allowed=False,
        unit=" registrations a minute",
        metavar="N",
        help="on a registry in etcd: registrations one identity may make a minute, in bursts of N; more are "
        "refused RESOURCE_EXHAUSTED with a retry hint (default %(default)g)",
    )
    pose_write_rate: float = setting(
        DEFAULT_POSE_WRITE_RATE,
        flag="--pose-write-rate",
        range=(0, 1e9),
        low_allowed=False,
        unit=" pose updates a second",
        metavar="HZ",
        help="on a registry in etcd: pose updates one identity's mobile cameras may send a second, in bursts "
        "of HZ (default %(default)g)",
    )
    #: Needed when cameras know several servers (they must report to the one that asked) and this
    #: one listens on 0.0.0.0. "": the bound address, unless it is a wildcard.
    advertise: str = setting(
        "",
        flag="--advertise",
        env="DRVS_SERVER_ADVERTISE",
        metavar="HOST:PORT",
        help="where cameras send this server fused requests' reports, if not the --listen address (needed "
        "when cameras know several servers and this one listens on 0.0.0.0; %(env)s)",
    )
    #: TLS to etcd: PEM files; "" none.
    etcd_ca: str = setting(
        "",
        flag="--etcd-ca",
        env="DRVS_ETCD_CA",
        metavar="FILE",
        group=ETCD_TLS,
        help="CA certificate etcd's members are checked against",
    )
    #: Only when etcd asks for one (--client-cert-auth).
    etcd_cert: str = setting(
        "",
        flag="--etcd-cert",
        env="DRVS_ETCD_CERT",
        metavar="FILE",
        group=ETCD_TLS,
        help="this server's certificate, when etcd asks for one",
    )
    etcd_key: str = setting(
        "", flag="--etcd-key", env="DRVS_ETCD_KEY", metavar="FILE", group=ETCD_TLS, help="its private key"
    )
    #: Server processes serving `listen` together (SO_REUSEPORT), sharing the registry in etcd;
    #: drvs-server starts them. 1: this process alone.
    workers: int = setting(
        1,
        flag="--workers",
        range=(1, 256),
        unit=" processes",
        metavar="N",
        help="serve --listen with N processes, so one host's cores all serve (the kernel spreads connections "
        "over them; they share the registry, so --registry etcd://... is needed; default %(default)s)",
    )
    #: The standing queue delay tolerated before requests are refused at the door (the server's
    #: loop; a camera link beyond its fastest round trip).
    admission_target_s: float = setting(
        DEFAULT_TARGET_S,
        flag="--admission-target",
        range=(0, 10),
        unit=" seconds (0: admission off)",
        metavar="SECONDS",
        help="refuse requests at once (RESOURCE_EXHAUSTED, with a retry hint) while the server's or a camera's "
        "queue stands longer than this (default %(default)g; 0: admission off, for measuring raw capacity)",
    )

    def __post_init__(self) -> None:
        callbacks = self.allow_callback
        if isinstance(callbacks, str) or not isinstance(callbacks, typing.Iterable):
            raise InvalidArgument(
                f"{described('allow_callback')}: expected a list of networks, got {type(callbacks).__name__}"
            )
        object.__setattr__(self, "allow_callback", tuple(callbacks))
        self.validate()

    def validate(self) -> None:
        """Refuse the first bad setting: InvalidArgument('name (--flag): value must be …')."""
        for declared in dataclasses.fields(self):  # DrvsServer(...) from Python: a text setting given a number
            if declared.type == "str":
                expect_str(getattr(self, declared.name), described(declared.name))
        for network in self.allow_callback:
            expect_str(network, described("allow_callback"), "such as '10.0.0.0/8'")
        parse_address(self.listen, described("listen"), allow_port_zero=True)
        for s in SETTINGS.values():
            if s.range is not None:
                s.check_range(getattr(self, s.name))
        if not (0 < self.default_max_range_m <= self.max_fov_range_m):
            raise InvalidArgument(
                f"{described('default_max_range_m')}: {self.default_max_range_m:g} m must be in "
                f"(0, max_fov_range_m {self.max_fov_range_m:g} m]"
            )
        if self.pose_lease_s > self.max_pose_lease_s:
            raise InvalidArgument(
                f"{described('pose_lease_s')}: {self.pose_lease_s:g} s is more than "
                f"max_pose_lease_s {self.max_pose_lease_s:g} s"
            )
        CallbackPolicy(self.allow_callback)  # refuses a malformed network
        if self.advertise:
            parse_address(self.advertise, described("advertise"))
        if self.registry != "memory":
            Endpoints.parse(self.registry, described("registry"))
        if bool(self.etcd_cert) != bool(self.etcd_key):
            raise InvalidArgument(f"{described('etcd_cert')} and {described('etcd_key')}: give both or neither")
        if (self.etcd_cert or self.etcd_key) and not self.etcd_ca:
            raise InvalidArgument(f"{described('etcd_ca')}: needed with a certificate for etcd (TLS)")
        if self.workers > 1 and self.registry == "memory":
            raise InvalidArgument(
                f"{described('workers')}: {self.workers} processes need a shared registry, --registry "
                "etcd://HOST:PORT: a camera registers with one of them and is routed by all"
            )
        if self.workers > 1 and host_of(self.listen) in WILDCARDS and not self.advertise:
            raise InvalidArgument(
                f"{described('advertise')}: needed with --workers on a wildcard address ({self.listen}): each "
                "worker takes the reports of its fused requests on a port of its own, at the advertised host"
            )
        if self.etcd_ca and self.registry == "memory":
            raise InvalidArgument(f"{described('etcd_ca')}: only with --registry etcd://...")
        for name in ("etcd_ca", "etcd_cert", "etcd_key"):
            path = getattr(self, name)
            if path and not os.path.isfile(path):
                raise InvalidArgument(f"{described(name)}: {path!r} is not a file")
        if self.etcd_cert:
            from drvs.wire.security import SERVER, certificate_fields

            with open(self.etcd_cert, "rb") as f:
                common_name, role = certificate_fields(f.read())
            if role and role != SERVER:  # etcd's users are servers (drvs.server.etcd_auth)
                raise InvalidArgument(
                    f"{described('etcd_cert')}: {common_name!r} is a {role} certificate (OU={role}); "
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
            max_pending_calls=self.max_pending_calls,
            max_idle_s=self.max_connection_idle_s,
            max_age_s=self.max_connection_age_s,
            age_grace_s=self.max_connection_age_grace_s,
        )

    @classmethod
    def load(cls, flags: Mapping[str, Any], environ: Mapping[str, str] = os.environ) -> ServerConfig:
        """From flag values by setting name (None or absent: not given), then the DRVS_* variables,
        then the defaults. A variable that is not a number (or not true/false) names itself."""
        values = {k: v for k, v in flags.items() if v is not None}
        for s in SETTINGS.values():
            text = environ.get(s.env, "") if s.env else ""
            if s.env is None or s.name in values or text == "":
                continue
            if s.kind in (int, float):
                values[s.name] = env_number(s.env, s.default, integer=s.integer, environ=environ)
            elif s.kind is bool:
                values[s.name] = parse_bool(text.strip().lower(), s.env)
            elif s.kind is tuple:
                values[s.name] = tuple(t.strip() for t in text.split(",") if t.strip())
            else:
                values[s.name] = text
        return cls(**values)


def _kind(field: dataclasses.Field[Any], declared: Setting) -> Setting:
    """A setting with its kind, from its field's type (float | None is float)."""
    hint = typing.get_type_hints(ServerConfig)[field.name]
    union = typing.get_origin(hint) in (typing.Union, types.UnionType)
    [kind] = [k for k in typing.get_args(hint) if k is not type(None)] if union else [hint]
    return dataclasses.replace(declared, kind=typing.get_origin(kind) or kind)


#: Every setting by name, in ServerConfig's order: what the parser, environment and checks read.
SETTINGS: dict[str, Setting] = settings.declared(ServerConfig, Setting(), _kind)
#: The DRVS_* environment variables drvs-server reads, by setting (a flag given wins).
ENVIRONMENT = {s.name: s.env for s in SETTINGS.values() if s.env}
#: Each setting's command-line flag.
FLAGS = {s.name: s.flag for s in SETTINGS.values() if s.flag}


def described(name: str) -> str:
    """How messages name a setting: its keyword, then where an operator gives it."""
    where = ", ".join(w for w in (FLAGS.get(name), ENVIRONMENT.get(name)) if w)
    return f"{name} ({where})" if where else name


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Every setting's flag, in the declared order, each in its group (created on first use)."""
    settings.add_arguments(parser, SETTINGS.values())


def from_arguments(args: argparse.Namespace, environ: Mapping[str, str] = os.environ) -> ServerConfig:
    """The flags `add_arguments` added (None: not given) and the environment, as one ServerConfig."""
    return ServerConfig.load({name: getattr(args, name) for name in FLAGS}, environ)
