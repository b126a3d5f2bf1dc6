"""Domain errors: what DRVS raises on purpose, never a raw gRPC error.

Every error has `.code`, the name of the gRPC status it stands for (``"UNAVAILABLE"``,
``"INVALID_ARGUMENT"`` ...; the same name a failed call or a camera's failed report carries), and
`.camera_id`, the camera whose failure it reports, or None when it is not one camera's (the
server's, the robot's own input, the network). drvs.wire._grpc maps these names to status codes.

    try:
        result = await drvs.detect(...)
    except Unavailable as exc:        # or: except DrvsError as exc: if exc.code == "UNAVAILABLE"
        print(exc.code, exc.camera_id, exc)
"""

from __future__ import annotations


class DrvsError(Exception):
    """Base of every error DRVS raises on purpose.

    `code`: the gRPC status name (str, e.g. ``"UNAVAILABLE"``; ``"UNKNOWN"`` on this base class).
    `camera_id`: the camera whose failure this is (str), or None when it is not one camera's.
    """

    code: str = "UNKNOWN"

    def __init__(self, message: str = "", *, camera_id: str | None = None) -> None:
        super().__init__(message)
        self.camera_id = camera_id


class InvalidArgument(DrvsError):
    """The caller sent something malformed; nothing was changed (INVALID_ARGUMENT)."""

    code = "INVALID_ARGUMENT"


def expect_str(value: object, name: str, example: str = "") -> str:
    """`value` if it is a str, else InvalidArgument naming `name` and the type given (`name: expected
    a string EXAMPLE, got int`): code's Python, before anything calls a string method on it."""
    if not isinstance(value, str):
        raise InvalidArgument(
            f"{name}: expected a string{' ' + example if example else ''}, got {type(value).__name__}"
        )
    return value


class NotFound(DrvsError):
    """The named thing (a camera, a request) is not known (NOT_FOUND)."""

    code = "NOT_FOUND"


class Unavailable(DrvsError):
    """A peer (the server, a camera) could not be reached; retrying later may work (UNAVAILABLE)."""

    code = "UNAVAILABLE"


class DeadlineExceeded(DrvsError):
    """A peer did not answer in time (DEADLINE_EXCEEDED)."""

    code = "DEADLINE_EXCEEDED"


class FailedPrecondition(DrvsError):
    """The system is not in a state to do this, e.g. a camera has no frame yet (FAILED_PRECONDITION)."""

    code = "FAILED_PRECONDITION"


class ResourceExhausted(DrvsError):
    """A bound was hit (too many concurrent requests, a busy camera, a server past its capacity);
    retry later (RESOURCE_EXHAUSTED).

    `retry_after_s`: how long the refuser asks the caller to wait before sending more (seconds; 0
    when it gave no hint). DrvsClient waits that long by itself: requests sent sooner are refused
    at once, on the robot, without reaching the server."""

    code = "RESOURCE_EXHAUSTED"

    def __init__(self, message: str = "", *, camera_id: str | None = None, retry_after_s: float = 0.0) -> None:
        super().__init__(message, camera_id=camera_id)
        self.retry_after_s = retry_after_s


class PermissionDenied(DrvsError):
    """The caller may not do this, e.g. send reports to somebody else's address (PERMISSION_DENIED)."""

    code = "PERMISSION_DENIED"


class Unauthenticated(DrvsError):
    """The call carried no valid credential (token or certificate) for what it asked (UNAUTHENTICATED)."""

    code = "UNAUTHENTICATED"


#: Every error class by its status name.
BY_CODE: dict[str, type[DrvsError]] = {
    cls.code: cls
    for cls in (
        InvalidArgument,
        NotFound,
        Unavailable,
        DeadlineExceeded,
        FailedPrecondition,
        ResourceExhausted,
        PermissionDenied,
        Unauthenticated,
    )
}


def error_for(code: str, message: str, *, camera_id: str | None = None, retry_after_s: float = 0.0) -> DrvsError:
    """The error of status name `code` (an unknown name gives a plain DrvsError whose code is
    ``"UNKNOWN"``), with `message` and `camera_id` (and, for ResourceExhausted, `retry_after_s`)."""
    if code == ResourceExhausted.code:
        return ResourceExhausted(message or code, camera_id=camera_id, retry_after_s=retry_after_s)
    return BY_CODE.get(code, DrvsError)(message or code, camera_id=camera_id)
