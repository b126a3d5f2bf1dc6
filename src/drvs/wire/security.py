"""Who may talk to whom: TLS (optionally mutual) on every hop, and bearer tokens checked by one
server interceptor.

Every role takes one `Security`: its certificate and key (for its own listener, and as a client
certificate under mutual TLS), the CA that signs its peers, and the token it presents to the
server. The server takes token tables, one for cameras (registration credentials) and one for
robots (client credentials). The identity a call carries (a token's name, or the client
certificate's common name) owns the camera ids it registers.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hmac
import logging
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import InvalidArgument, PermissionDenied
from drvs.wire import _grpc

log = logging.getLogger(__name__)

#: Tokens shorter than this are refused when loaded: they could be guessed.
MIN_TOKEN_LENGTH = 16
CAMERA = "camera"
ROBOT = "robot"
SERVER = "server"
#: A certificate's role is its subject's organizational unit (OU=camera, robot or server);
#: drvs-certs writes it, and any CA can.
ROLES = (SERVER, CAMERA, ROBOT)

_PREFIX = "/drvs.v1."
#: Which credential each method needs; methods not listed (health, reflection) are open.
METHOD_ROLES = {
    f"{_PREFIX}RegisterVisionService/Register": CAMERA,
    f"{_PREFIX}RegisterVisionService/Heartbeat": CAMERA,
    f"{_PREFIX}RegisterVisionService/Deregister": CAMERA,
    f"{_PREFIX}RegisterVisionService/UpdatePose": CAMERA,
    f"{_PREFIX}RegisterVisionService/ListCameras": ROBOT,
    f"{_PREFIX}DetectObjectBoundary/DetectObjects": ROBOT,
    f"{_PREFIX}DetectObjectBoundary/DetectStream": ROBOT,
    # On the server: cameras' reports for fused requests (a robot's own listener has no interceptor).
    f"{_PREFIX}CallbackCoordinates/ReportDetections": CAMERA,
}


def _read(path: Path | None, what: str) -> bytes | None:
    if path is None:
        return None
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InvalidArgument(f"{what}: cannot read {path}: {exc.strerror}") from None
    if b"-----BEGIN " not in data:
        raise InvalidArgument(f"{what}: {path} is not a PEM file")
    return data


@dataclass(frozen=True)
class Security:
    """One role's credentials. All empty: plain TCP, no token (the default, for loopback)."""

    tls_cert: Path | None = None
    tls_key: Path | None = None
    tls_ca: Path | None = None
    #: On this role's own listener: demand a client certificate signed by tls_ca (mutual TLS).
    require_client_cert: bool = False
    #: Presented to the server as `authorization: Bearer TOKEN`.
    token: str = ""
    _pem: dict[str, bytes | None] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        """Read and check the files now, so a bad path fails at start with the flag named."""
        if (self.tls_cert is None) != (self.tls_key is None):
            raise InvalidArgument("tls_cert and tls_key: give both or neither")
        if self.require_client_cert and (self.tls_ca is None or self.tls_cert is None):
            raise InvalidArgument("require_client_cert: needs tls_cert, tls_key and tls_ca")
        if self.token and (len(self.token) < MIN_TOKEN_LENGTH or not self.token.isprintable() or " " in self.token):
            raise InvalidArgument(f"token: must be at least {MIN_TOKEN_LENGTH} printable characters without spaces")
        self._pem["cert"] = _read(self.tls_cert, "tls_cert")
        self._pem["key"] = _read(self.tls_key, "tls_key")
        self._pem["ca"] = _read(self.tls_ca, "tls_ca")

    @property
    def tls(self) -> bool:
        return self.tls_ca is not None or self.tls_cert is not None

    @property
    def any(self) -> bool:
        return self.tls or bool(self.token)

    def server_credentials(self) -> grpc.ServerCredentials | None:
        """For this role's listener; None: plain TCP. Needs a certificate."""
        if not self.tls:
            return None
        if self._pem["cert"] is None or self._pem["key"] is None:
            raise InvalidArgument("tls_cert and tls_key: a listener with TLS needs its own certificate and key")
        return grpc.ssl_server_credentials(
            [(self._pem["key"], self._pem["cert"])],
            root_certificates=self._pem["ca"],
            require_client_auth=self.require_client_cert,
        )

    def channel_credentials(self) -> grpc.ChannelCredentials | None:
        if not self.tls:
            return None
        return grpc.ssl_channel_credentials(
            root_certificates=self._pem["ca"], private_key=self._pem["key"], certificate_chain=self._pem["cert"]
        )

    def channel(self, address: str) -> aio.Channel:
        """A channel to a peer: TLS verifying the peer against tls_ca (and presenting our certificate,
        for peers that demand one), or plain TCP."""
        creds = self.channel_credentials()
        if creds is None:
            return aio.insecure_channel(address, options=_grpc.CHANNEL_OPTIONS)
        return aio.secure_channel(address, creds, options=_grpc.CHANNEL_OPTIONS)

    def metadata(self, token: str | None = None) -> tuple[tuple[str, str], ...]:
        """Call metadata carrying `token` (default: this role's own), or none."""
        value = self.token if token is None else token
        return (("authorization", f"Bearer {value}"),) if value else ()

    def bind(self, server: aio.Server, address: str) -> int:
        creds = self.server_credentials()
        if creds is None:
            return _grpc.bind(server, address)
        return _grpc.bind(server, address, creds)


def load_tokens(path: Path, what: str) -> dict[str, str]:
    """A token file: one `NAME TOKEN` per line, # comments. Returns token -> name."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidArgument(f"{what}: cannot read {path}: {exc}") from None
    tokens: dict[str, str] = {}
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise InvalidArgument(f"{what}: {path}:{number}: expected 'NAME TOKEN'")
        name, token = parts
        if len(token) < MIN_TOKEN_LENGTH:
            raise InvalidArgument(f"{what}: {path}:{number}: the token for {name!r} is shorter than {MIN_TOKEN_LENGTH}")
        if token in tokens:
            raise InvalidArgument(f"{what}: {path}:{number}: {name!r} repeats the token of {tokens[token]!r}")
        tokens[token] = name
    if not tokens:
        raise InvalidArgument(f"{what}: {path} holds no tokens")
    return tokens


def bearer_token(metadata: Sequence[tuple[str, Any]] | None) -> str:
    for key, value in metadata or ():
        if key == "authorization" and isinstance(value, str) and value.startswith("Bearer "):
            return value[len("Bearer ") :]
    return ""


def _lookup(tokens: Mapping[str, str], token: str) -> str | None:
    """The name a token belongs to; compared in constant time, so timing tells nothing."""
    found = None
    for known, name in tokens.items():
        if hmac.compare_digest(known.encode(), token.encode()):
            found = name
    return found


class TokenAuthority:
    """The server's token tables. A role without a table is open to anyone who can connect."""

    def __init__(self, camera_tokens: Mapping[str, str] | None, robot_tokens: Mapping[str, str] | None) -> None:
        self.tables: dict[str, Mapping[str, str] | None] = {CAMERA: camera_tokens, ROBOT: robot_tokens}

    @property
    def enabled(self) -> bool:
        return any(t is not None for t in self.tables.values())

    def check(self, role: str, metadata: Sequence[tuple[str, Any]] | None) -> str | None:
        """The caller's name under `role`'s table; None when the table refuses it. "" for open roles."""
        table = self.tables.get(role)
        if table is None:
            return ""
        token = bearer_token(metadata)
        return _lookup(table, token) if token else None


class TokenInterceptor(aio.ServerInterceptor):
    """Refuses, with UNAUTHENTICATED, a call to a method whose role has a token table unless it
    carries one of that table's tokens. One place checks every call."""

    def __init__(self, authority: TokenAuthority) -> None:
        self._authority = authority

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler[Any, Any] | None]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler[Any, Any] | None:
        handler = await continuation(handler_call_details)
        method: str = handler_call_details.method
        role = METHOD_ROLES.get(method)
        if role is None or handler is None:
            return handler
        metadata = list(handler_call_details.invocation_metadata or ())
        if self._authority.check(role, metadata) is not None:
            return handler
        return _refusal(handler, f"{method.rsplit('/', 1)[-1]}: needs a valid {role} token (authorization: Bearer …)")


def _refusal(handler: grpc.RpcMethodHandler[Any, Any], message: str) -> grpc.RpcMethodHandler[Any, Any]:
    async def deny(request: Any, context: aio.ServicerContext[Any, Any]) -> Any:
        if handler.request_streaming:
            # Take the first message before refusing: aborting while the client is still writing it
            # sometimes reaches the client as INTERNAL "Internal error from Core" instead.
            with contextlib.suppress(Exception):
                await asyncio.wait_for(anext(aiter(request)), 1.0)
        await context.abort(grpc.StatusCode.UNAUTHENTICATED, message)

    kinds = {
        (False, False): grpc.unary_unary_rpc_method_handler,
        (False, True): grpc.unary_stream_rpc_method_handler,
        (True, False): grpc.stream_unary_rpc_method_handler,
        (True, True): grpc.stream_stream_rpc_method_handler,
    }
    make = kinds[(bool(handler.request_streaming), bool(handler.response_streaming))]
    return make(
        deny, request_deserializer=handler.request_deserializer, response_serializer=handler.response_serializer
    )


def caller_identity(context: aio.ServicerContext[Any, Any], authority: TokenAuthority, role: str) -> str:
    """Who is calling: the token's name, else the client certificate's common name, else ""
    (anonymous: no credential was asked for)."""
    name = authority.check(role, list(context.invocation_metadata() or ()))
    if name:
        return f"token:{name}"
    names = list(context.auth_context().get("x509_common_name", ()))
    if names:
        return "cert:" + bytes(names[0]).decode(errors="replace")
    return ""


@functools.lru_cache(maxsize=1024)
def certificate_fields(pem: bytes) -> tuple[str, str]:
    """(common name, DRVS role or "") of a PEM certificate; a role is an OU naming one of ROLES."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    try:
        cert = x509.load_pem_x509_certificate(pem)
    except ValueError:
        return "", ""
    cns = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    units = [str(a.value) for a in cert.subject.get_attributes_for_oid(NameOID.ORGANIZATIONAL_UNIT_NAME)]
    roles = [u for u in units if u in ROLES]
    return (str(cns[0].value) if cns else ""), (roles[0] if len(roles) == 1 else "")


def client_certificate(context: aio.ServicerContext[Any, Any]) -> tuple[str, str] | None:
    """The verified client certificate's (common name, role), or None without one."""
    auth = context.auth_context()
    pems = list(auth.get("x509_pem_cert", ()))
    if pems:
        return certificate_fields(bytes(pems[0]))
    names = list(auth.get("x509_common_name", ()))
    return (bytes(names[0]).decode(errors="replace"), "") if names else None


def camera_identity(
    context: aio.ServicerContext[Any, Any], authority: TokenAuthority, client_auth: bool, method: str
) -> str:
    """Who is registering a camera: `token:NAME`, or `cert:CN` for a client certificate with the
    camera role, or "" (anonymous). Only mutual TLS proves a certificate: TLS without client
    authentication gives no identity. A certificate made for another role may not act for a camera."""
    name = authority.check(CAMERA, list(context.invocation_metadata() or ()))
    if name:
        return f"token:{name}"
    if not client_auth:
        return ""
    cert = client_certificate(context)
    if cert is None:
        return ""
    common_name, role = cert
    if role == CAMERA:
        return f"cert:{common_name}"
    if role:
        raise PermissionDenied(
            f"{method}: the client certificate {common_name!r} has the role {role} (OU={role}); "
            "cameras register with a certificate whose role is camera (OU=camera)"
        )
    return ""
