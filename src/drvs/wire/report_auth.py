"""Who may report to a robot: keys that prove a report stream belongs to a dispatched camera.

Anyone who can reach a robot's callback listener can open a report stream and write reports in
any camera's name. So the robot gives the server a secret of its own (once per request stream);
for each camera it dispatches a request to, the server derives that camera's key from the secret
and the camera id, and hands it to that camera only, with the request. The camera presents the key
on its first report on a stream; the robot, which can derive the same key, then takes that
camera's reports on that stream and on no other. A camera learns only its own key, so it cannot
report in another camera's name, and nobody the server never dispatched to can report at all; the
server's reply says which cameras a request went to, and the robot takes a request's reports only
from those. The key is per robot and camera, not per request, so it costs nothing per request once
a camera's stream to the robot is open. Pure logic.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import secrets

#: Bytes of a robot's report secret (it may send up to MAX_SECRET_BYTES).
SECRET_BYTES = 16
MAX_SECRET_BYTES = 64
#: Bytes of a report key: 64 bits cannot be guessed online; it travels once per report stream.
KEY_BYTES = 8


def new_secret() -> bytes:
    return secrets.token_bytes(SECRET_BYTES)


#: Secrets and cameras whose keys are kept: a robot's secret lasts its stream, so the server derives
#: the same few keys for every request it forwards (an HMAC each, per camera, before this).
KEYS_CACHED = 256


@functools.lru_cache(maxsize=KEYS_CACHED)
def report_key(secret: bytes, camera_id: str) -> bytes:
    """The key camera `camera_id` presents to the robot whose secret this is; empty without one."""
    if not secret:
        return b""
    return hmac.digest(secret, b"drvs-report-key\0" + camera_id.encode(), hashlib.sha256)[:KEY_BYTES]


def key_matches(secret: bytes, camera_id: str, key: bytes) -> bool:
    return bool(key) and hmac.compare_digest(report_key(secret, camera_id), key)
