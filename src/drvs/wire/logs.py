"""Logging for every role: plain lines, or one JSON object per line (--log-format json) carrying
the request id of whatever request the code is serving, on every hop (server, camera, robot)."""

from __future__ import annotations

import contextvars
import json
import logging
import time
from typing import TextIO

#: The request being served; asyncio tasks copy it when they are created, so work a request
#: spawns (forwards, report streams) logs the same id.
request_id: contextvars.ContextVar[str] = contextvars.ContextVar("drvs_request_id", default="")

FORMATS = ("text", "json")


class _RequestId(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if not getattr(record, "request_id", ""):
            record.request_id = request_id.get()
        return True


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": round(record.created, 6),
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        rid = getattr(record, "request_id", "")
        if rid:
            entry["request_id"] = rid
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False)


def configure(level: str, fmt: str, stream: TextIO) -> None:
    if fmt not in FORMATS:
        raise ValueError(f"log format: {fmt!r} is not one of {', '.join(FORMATS)}")
    handler = logging.StreamHandler(stream)
    handler.addFilter(_RequestId())
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s"))
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)
