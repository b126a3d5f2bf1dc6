"""What a robot hears when the server could not hand its request to a camera.

A camera registers its own address, and the server dials it for every request routed there; what
went wrong on that connection (``Connection refused``, ``Trying to connect an http1.x server``, a
timeout, a stranger's gRPC ``Method not found``) would tell whoever registered the address whether
a port is open and what listens on it. So the robot hears one opaque ``UNAVAILABLE`` for every
failure of the hop itself, and the server's log keeps the details, once per camera per
`LOG_EVERY_S`. A camera's own answers about the request (`KEPT`: a bad field, no room, not ready)
reach the robot as they are: they say nothing about the network.
"""

from __future__ import annotations

import logging
import time

from drvs.core.errors import DrvsError
from drvs.wire import _grpc

log = logging.getLogger("drvs.server")

#: The camera's own answers about the request, passed on to the robot as they are.
KEPT = frozenset({"INVALID_ARGUMENT", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION", "NOT_FOUND"})
#: What a robot hears for every other failure to hand a camera its request.
OPAQUE_CODE = "UNAVAILABLE"
OPAQUE_MESSAGE = "the server could not reach it"
#: The details of one camera's failed forwards are logged at most this often.
LOG_EVERY_S = 30.0


class RoutingErrors:
    """`for_robot(camera_id, exc)`: the status name and message a robot may see; the details of
    an opaque one are logged here (WARNING, at most once per camera per `LOG_EVERY_S`; the rest
    are counted and the count said with the next line)."""

    def __init__(self, every_s: float = LOG_EVERY_S) -> None:
        self.every_s = every_s
        self._logged: dict[str, tuple[float, int]] = {}  # camera id -> (last logged, suppressed since)

    def for_robot(self, camera_id: str, exc: DrvsError, request_id: str = "") -> tuple[str, str]:
        code = _grpc.status_of(exc).name
        if code in KEPT:
            return code, str(exc)
        now = time.monotonic()
        last, suppressed = self._logged.get(camera_id, (-self.every_s, 0))
        if now - last >= self.every_s:
            more = f" ({suppressed} more since, not logged)" if suppressed else ""
            log.warning("request %s: camera %s could not be reached: %s %s%s", request_id, camera_id, code, exc, more)
            self._logged[camera_id] = (now, 0)
        else:
            self._logged[camera_id] = (last, suppressed + 1)
        return OPAQUE_CODE, OPAQUE_MESSAGE

    def forget(self, camera_id: str) -> None:
        self._logged.pop(camera_id, None)
