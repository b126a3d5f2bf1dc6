"""Domain errors: what DRVS raises on purpose, never a raw gRPC error.

Every error has `.code`, the name of the gRPC status it stands for (``"UNAVAILABLE"``,
``"INVALID_ARGUMENT"`` ...; the same name a failed call or a camera's failed report carries), and
`.camera_id`, the camera whose failure it reports, or None when it is not one camera's (the
server's, the robot's own input, the network). drvs._grpc maps these names to status codes.

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
    """A bound was hit (too many concurrent requests, a busy camera); retry later (RESOURCE_EXHAUSTED)."""

    code = "RESOURCE_EXHAUSTED"


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


def error_for(code: str, message: str, *, camera_id: str | None = None) -> DrvsError:
    """The error of status name `code` (an unknown name gives a plain DrvsError whose code is
    ``"UNKNOWN"``), with `message` and `camera_id`."""
    return BY_CODE.get(code, DrvsError)(message or code, camera_id=camera_id)
