"""How failed calls become domain errors."""

from __future__ import annotations

import grpc
from grpc import aio

from drvs.core import errors
from drvs.wire import _grpc


def rpc_error(code: grpc.StatusCode, details: str) -> aio.AioRpcError:
    return aio.AioRpcError(code, aio.Metadata(), aio.Metadata(), details=details)


def test_a_connection_broken_under_a_call_is_unavailable_not_a_fault_of_the_peer() -> None:
    broke = _grpc.from_rpc_error(rpc_error(grpc.StatusCode.INTERNAL, _grpc.CORE_BREAK), "server a:1")
    assert type(broke) is errors.Unavailable and str(broke).startswith("server a:1: ")
    # Any other INTERNAL is the peer's fault, and says so.
    other = _grpc.from_rpc_error(rpc_error(grpc.StatusCode.INTERNAL, "DetectStream: internal error"), "server a:1")
    assert type(other) is errors.DrvsError and str(other) == "server a:1: DetectStream: internal error"


#: The contract, written out here rather than read from the module under test: a wrong or missing
#: row in drvs.wire._grpc fails this test.
EXPECTED_STATUS: dict[type[errors.DrvsError], grpc.StatusCode] = {
    errors.InvalidArgument: grpc.StatusCode.INVALID_ARGUMENT,
    errors.NotFound: grpc.StatusCode.NOT_FOUND,
    errors.Unavailable: grpc.StatusCode.UNAVAILABLE,
    errors.DeadlineExceeded: grpc.StatusCode.DEADLINE_EXCEEDED,
    errors.FailedPrecondition: grpc.StatusCode.FAILED_PRECONDITION,
    errors.ResourceExhausted: grpc.StatusCode.RESOURCE_EXHAUSTED,
    errors.PermissionDenied: grpc.StatusCode.PERMISSION_DENIED,
    errors.Unauthenticated: grpc.StatusCode.UNAUTHENTICATED,
}


def test_statuses_map_to_their_domain_errors_and_back() -> None:
    # Every public error class has its row (a new class without a status is caught here).
    public = {c for c in vars(errors).values() if isinstance(c, type) and issubclass(c, errors.DrvsError)}
    assert public - {errors.DrvsError} == set(EXPECTED_STATUS)
    for cls, code in EXPECTED_STATUS.items():
        error = _grpc.from_rpc_error(rpc_error(code, "why"), "peer")
        assert type(error) is cls and str(error) == "peer: why"
        assert _grpc.status_of(error) == code
        assert type(_grpc.error_from_code(code.name, "why")) is cls
    # A status with no domain error of its own is the base error, both ways.
    unknown = _grpc.from_rpc_error(rpc_error(grpc.StatusCode.ABORTED, "why"), "peer")
    assert type(unknown) is errors.DrvsError and _grpc.status_of(unknown) == grpc.StatusCode.UNKNOWN
