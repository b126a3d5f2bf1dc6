"""The robot client's defaults and its checks of the numbers robot code passes (seconds, queue
sizes, fusion options): a bad one raises InvalidArgument before anything is sent."""

from __future__ import annotations

import math

from drvs.core.errors import InvalidArgument
from drvs.core.model import FusionOptions

#: Seconds to wait, beyond a request's own duration, for every camera's final report (`timeout_s`).
DEFAULT_TIMEOUT_S = 5.0
#: Seconds one attempt of one call waits for the server's reply (`rpc_timeout_s`).
DEFAULT_RPC_TIMEOUT_S = 5.0
#: Seconds one attempt to reach the server may take in DrvsClient.connect (`connect_timeout_s`).
DEFAULT_CONNECT_TIMEOUT_S = 5.0
#: Unread reports a continuous request keeps (the newest; older ones are dropped and counted).
MAX_QUEUED_REPORTS = 1024
#: Unread snapshots a track keeps (the newest; older ones are dropped and counted): 6.4 s at 10 Hz.
MAX_QUEUED_SNAPSHOTS = 64
#: Snapshots a second DrvsClient.track asks for unless told.
DEFAULT_TRACK_RATE_HZ = 10.0
#: The longest wait between retries, seconds (RetryPolicy's default max_backoff_s).
MAX_BACKOFF_S = 5.0


def seconds(value: float, name: str, limit: float) -> float:
    """`value` as seconds in (0, limit], or InvalidArgument naming `name`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0 < value <= limit):
        raise InvalidArgument(f"{name}: {value!r} must be a number of seconds in (0, {limit:g}]")
    return float(value)


def check_timeout(timeout_s: float) -> None:
    if isinstance(timeout_s, bool) or not (
        isinstance(timeout_s, (int, float)) and math.isfinite(timeout_s) and timeout_s >= 0
    ):
        raise InvalidArgument(f"timeout_s: {timeout_s!r} must be a finite number of seconds >= 0")


def check_queue(max_queued: int, what: str) -> None:
    if isinstance(max_queued, bool) or not isinstance(max_queued, int) or max_queued < 1:
        raise InvalidArgument(f"max_queued: {max_queued!r} must be a whole number of {what} >= 1")


def fusion_options(deadline_s: float | None, drop_after_s: float | None) -> FusionOptions:
    """FusionOptions from a fused call's arguments (None: 0, the server's default), checked."""
    values = []
    for name, value in (("deadline_s", deadline_s), ("drop_after_s", drop_after_s)):
        if value is None:
            value = 0.0
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InvalidArgument(f"{name}: {value!r} must be a number of seconds, or None for the server's default")
        values.append(float(value))
    fusion = FusionOptions(deadline_s=values[0], drop_after_s=values[1])
    fusion.validate()
    return fusion
