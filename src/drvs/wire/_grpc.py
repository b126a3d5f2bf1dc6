"""gRPC plumbing shared by every role: the one place domain errors map to status codes."""

from __future__ import annotations

import functools
import logging
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import grpc
from grpc import aio

from drvs.core import errors

log = logging.getLogger(__name__)

_TO_STATUS: dict[type[errors.DrvsError], grpc.StatusCode] = {
    cls: grpc.StatusCode[code] for code, cls in errors.BY_CODE.items()
}
_FROM_STATUS = {code: cls for cls, code in _TO_STATUS.items()}

#: Bound every message: reports and requests are small; anything near this is an attack or a bug.
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
#: The least time one connection attempt gets to open TCP and hear the peer's HTTP/2 SETTINGS.
CONNECT_ATTEMPT_S = 2.0
CHANNEL_OPTIONS: list[tuple[str, Any]] = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    # Reconnect quickly after a peer restarts: the default backoff grows to two minutes.
    ("grpc.initial_reconnect_backoff_ms", 200),
    ("grpc.max_reconnect_backoff_ms", 2000),
    # Despite its name, gRPC's minimum *connect timeout*: how long one attempt may take to open
    # TCP and receive the peer's HTTP/2 SETTINGS (gRPC's default: 20 s). At 200 ms, a first
    # connection to a camera on a loaded host or a slow link failed at once as UNAVAILABLE, and
    # the server skipped that camera until its next heartbeat. The backoff above is unchanged: a
    # refused connection still fails at once and is retried after 200 ms.
    ("grpc.min_reconnect_backoff_ms", round(CONNECT_ATTEMPT_S * 1000)),
    # DRVS messages are small: bandwidth-delay probing cost a PING and its ack per burst of them
    # (a tenth of a robot's bytes) and gained nothing.
    ("grpc.http2.bdp_probe", 0),
    # Every channel its own connection: a robot is one connection to the server (per-robot limits
    # count connections when there are no credentials), not a share of one pooled by the process.
    ("grpc.use_local_subchannel_pool", 1),
]
SERVER_OPTIONS: list[tuple[str, Any]] = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.so_reuseport", 0),
    ("grpc.http2.bdp_probe", 0),
]

#: Server-wide connection limits of the DRVS server (drvs-server flags of the same names).
DEFAULT_MAX_STREAMS_PER_CONNECTION = 100
#: Calls of one method that may wait to be taken in (see ConnectionLimits.max_pending_calls).
DEFAULT_MAX_PENDING_CALLS = 64
#: gRPC's "no limit" for the pending calls (a C int).
_NO_PENDING_LIMIT = 2**31 - 1
DEFAULT_MAX_CONNECTION_IDLE_S = 300.0
DEFAULT_MAX_CONNECTION_AGE_S = 3600.0
DEFAULT_MAX_CONNECTION_AGE_GRACE_S = 60.0


@dataclass(frozen=True)
class ConnectionLimits:
    """What one client connection may hold: streams open at once (more wait on the client), how
    long it may stay without a call before the server closes it, and how long it may live at all
    (after which the server asks the client to reconnect, and ends its calls `age_grace_s` later).
    0 means no limit. Without these a client can hold connections and streams open forever.

    `max_pending_calls`, server-wide: the calls of one method that may wait in gRPC's core for the
    server to take them in (grpc.aio takes in one call a few passes of its event loop, so a
    server busy with work it has taken takes in new calls slowly). Past it gRPC's core drops new
    calls at once, at random beyond `max_pending_calls` and every one at twice it: the caller gets
    CANCELLED. Without it (gRPC's own 1000 and 3000) unary calls queue there for seconds, unseen by
    the server's admission (drvs.server.admission), and most end at their deadline. (gRPC 1.85's core
    applies these limits under its experiment optimization_04, on by default; tests/behaviour/
    test_exhaustion.py fails if a gRPC release stops applying them.)"""

    max_streams: int = DEFAULT_MAX_STREAMS_PER_CONNECTION
    max_idle_s: float = DEFAULT_MAX_CONNECTION_IDLE_S
    max_age_s: float = DEFAULT_MAX_CONNECTION_AGE_S
    age_grace_s: float = DEFAULT_MAX_CONNECTION_AGE_GRACE_S
    max_pending_calls: int = DEFAULT_MAX_PENDING_CALLS

    def __post_init__(self) -> None:
        for name in ("max_streams", "max_idle_s", "max_age_s", "age_grace_s", "max_pending_calls"):
            value = getattr(self, name)
            if not (value >= 0 and value <= 1e9):
                raise errors.InvalidArgument(f"{name}: {value} must be a number in [0, 1e9] (0: no limit)")

    def options(self) -> list[tuple[str, Any]]:
        out: list[tuple[str, Any]] = []
        if self.max_streams:
            out.append(("grpc.max_concurrent_streams", int(self.max_streams)))
        if self.max_idle_s:
            out.append(("grpc.max_connection_idle_ms", round(self.max_idle_s * 1000)))
        if self.max_age_s:
            out.append(("grpc.max_connection_age_ms", round(self.max_age_s * 1000)))
            out.append(("grpc.max_connection_age_grace_ms", round(self.age_grace_s * 1000)))
        pending = int(self.max_pending_calls) or _NO_PENDING_LIMIT
        out.append(("grpc.server.max_pending_requests", pending))
        out.append(("grpc.server.max_pending_requests_hard_limit", min(2 * pending, _NO_PENDING_LIMIT)))
        return out


T = TypeVar("T")
Handler = Callable[..., Awaitable[T]]


def status_of(exc: errors.DrvsError) -> grpc.StatusCode:
    for cls in type(exc).__mro__:
        if cls in _TO_STATUS:
            return _TO_STATUS[cls]
    return grpc.StatusCode.UNKNOWN


#: What grpc.aio says when an operation hits a call whose connection has just failed (the peer
#: went away): not a fault of the peer but a broken link, which callers retry as Unavailable.
CORE_BREAK = "Internal error from Core"
#: How gRPC says the peer refused a call before reading it: HTTP/2 REFUSED_STREAM (error code 7,
#: "closed prior to any processing", RFC 9113 8.7) comes as UNAVAILABLE with this in its details
#: (a loaded server counts calls it has answered and not yet released against its limit of calls
#: open on one connection); and a call that gRPC's core dropped while it waited to be taken in
#: (ConnectionLimits.max_pending_calls) ends CANCELLED with these details and nothing else.
REFUSED_STREAM = "RST_STREAM with error code 7"
DROPPED_PENDING = "CANCELLED"
#: The wait asked of a caller after either (no hint travels with them): the door's shortest.
REFUSED_RETRY_S = 0.1


def from_rpc_error(exc: grpc.RpcError, what: str) -> errors.DrvsError:
    """Turn a failed call into the domain error robot code sees (never a raw grpc.RpcError)."""
    code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNKNOWN
    details = exc.details() if hasattr(exc, "details") else str(exc)
    if code == grpc.StatusCode.INTERNAL and details == CORE_BREAK:
        return errors.Unavailable(f"{what}: the connection broke during the call")
    if code == grpc.StatusCode.RESOURCE_EXHAUSTED:
        return errors.ResourceExhausted(f"{what}: {details or code.name}", retry_after_s=retry_hint(exc))
    # Refused before the peer's code saw the call, for load: a refusal as the door's are (so a
    # robot's throttle backs off), not a dead server (UNAVAILABLE) or an unknown failure.
    if refused_before_read(exc):
        why = (
            "refused before it was read (HTTP/2 REFUSED_STREAM: the peer is at its limit of calls open on this "
            "connection)"
            if code == grpc.StatusCode.UNAVAILABLE
            else "dropped before it was taken in (CANCELLED: the peer's queue of calls waiting to be taken in was "
            "full, or it was stopping)"
        )
        return errors.ResourceExhausted(
            f"{what}: {why}; retry in {REFUSED_RETRY_S * 1000:.0f} ms", retry_after_s=REFUSED_RETRY_S
        )
    cls = _FROM_STATUS.get(code, errors.DrvsError)
    return cls(f"{what}: {details or code.name}")


def refused_before_read(exc: grpc.RpcError) -> bool:
    """Whether the peer refused or dropped the call before its code read it (REFUSED_STREAM, or
    CANCELLED by gRPC's core while the call waited to be taken in): busy, not gone."""
    code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNKNOWN
    details = (exc.details() if hasattr(exc, "details") else "") or ""
    return (code == grpc.StatusCode.UNAVAILABLE and REFUSED_STREAM in details) or (
        code == grpc.StatusCode.CANCELLED and details == DROPPED_PENDING
    )


#: The trailer a refusal's retry hint travels in on a unary call: gRPC's own name for it (its
#: retry policy honours it), in whole milliseconds.
RETRY_PUSHBACK = "grpc-retry-pushback-ms"


def retry_hint(exc: grpc.RpcError) -> float:
    """The seconds a failed call's trailers ask the caller to wait (0: no hint)."""
    trailers: Any = exc.trailing_metadata() if hasattr(exc, "trailing_metadata") else None
    for key, value in trailers or ():
        if key == RETRY_PUSHBACK:
            try:
                return max(0.0, int(value) / 1000)
            except (TypeError, ValueError):
                return 0.0
    return 0.0


def error_from_code(code_name: str, message: str, retry_after_s: float = 0.0) -> errors.DrvsError:
    """The domain error for a status code sent by name (a refused request on a stream)."""
    return errors.error_for(code_name, message, retry_after_s=retry_after_s)


def servicer_method(method: Handler[T]) -> Handler[T]:
    """Map DrvsError to its status; log and hide anything unexpected as INTERNAL."""

    @functools.wraps(method)
    async def wrapper(self: Any, request: Any, context: aio.ServicerContext[Any, Any]) -> T:
        try:
            return await method(self, request, context)
        except errors.DrvsError as exc:
            hint = getattr(exc, "retry_after_s", 0.0)
            trailers = ((RETRY_PUSHBACK, str(max(1, round(hint * 1000)))),) if hint > 0 else ()
            await context.abort(status_of(exc), str(exc), trailing_metadata=trailers)
        except aio.AbortError:
            raise
        except Exception:
            log.exception("%s failed", method.__qualname__)
            await context.abort(grpc.StatusCode.INTERNAL, f"{method.__name__}: internal error")
        raise AssertionError("unreachable")  # context.abort always raises

    return wrapper


def insecure_channel(address: str) -> aio.Channel:
    return aio.insecure_channel(address, options=CHANNEL_OPTIONS)


def new_server(
    interceptors: Sequence[aio.ServerInterceptor] = (), options: Sequence[tuple[str, Any]] = ()
) -> aio.Server:
    merged = dict(SERVER_OPTIONS)
    merged.update(options)  # the caller's win (gRPC would take the first of two with one name)
    return aio.server(options=list(merged.items()), interceptors=list(interceptors) or None)


def bind(server: aio.Server, address: str, credentials: grpc.ServerCredentials | None = None) -> int:
    """Bind `address` (port 0 = any free port), with TLS when given credentials; returns the bound
    port or raises OSError."""
    try:
        if credentials is None:
            port = server.add_insecure_port(address)
        else:
            port = server.add_secure_port(address, credentials)
    except RuntimeError as exc:
        raise OSError(f"cannot listen on {address}: {exc}") from exc
    if port == 0:
        raise OSError(f"cannot listen on {address}")
    return port
