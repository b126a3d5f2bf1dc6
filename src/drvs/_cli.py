"""What every entry point shares: logging set-up, and SIGINT/SIGTERM turned into one shutdown event."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys

#: Log level for every role, e.g. DEBUG; --log-level overrides it.
ENV_LOG_LEVEL = "DRVS_LOG_LEVEL"


def env(name: str, default: str | None = None) -> str | None:
    """A DRVS_* environment variable, or the default (flags override both)."""
    value = os.environ.get(name)
    return value if value not in (None, "") else default


def setup_logging(level: str | None) -> None:
    logging.basicConfig(
        level=(level or env(ENV_LOG_LEVEL, "INFO") or "INFO").upper(),
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )


def shutdown_event() -> asyncio.Event:
    """An event set by the first SIGINT or SIGTERM (containers send SIGTERM)."""
    event = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, event.set)
    return event


def join_negative_values(argv: list[str], options: tuple[str, ...]) -> list[str]:
    """Let `--roi -50,0,750,900` work: argparse would read a value starting with '-' as an option."""
    out: list[str] = []
    it = iter(argv)
    for arg in it:
        if arg in options:
            value = next(it, None)
            out.append(arg if value is None else f"{arg}={value}")
        else:
            out.append(arg)
    return out
