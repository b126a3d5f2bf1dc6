"""Domain errors. Each carries the gRPC status it maps to; the mapping lives in drvs._grpc alone."""

from __future__ import annotations


class DrvsError(Exception):
    """Base of every error DRVS raises on purpose."""


class InvalidArgument(DrvsError):
    """The caller sent something malformed; nothing was changed."""


class NotFound(DrvsError):
    """The named thing (a camera, a request) is not known."""


class Unavailable(DrvsError):
    """A peer could not be reached; retrying later may work."""


class DeadlineExceeded(DrvsError):
    """A peer did not answer in time."""


class FailedPrecondition(DrvsError):
    """The system is not in a state to do this (e.g. a camera has no frame yet)."""


class ResourceExhausted(DrvsError):
    """A bound was hit (too many concurrent requests); retry later."""


class PermissionDenied(DrvsError):
    """The caller may not do this (e.g. send reports to somebody else's address)."""


class Unauthenticated(DrvsError):
    """The call carried no valid credential (token or certificate) for what it asked."""
