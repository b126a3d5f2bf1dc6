"""Who may report to a robot: keys that prove a report stream belongs to a dispatched camera.

Anyone who can reach a robot's callback listener can open a report stream and write reports in
any camera's name. So the robot gives the server a secret of its own (once per request stream);
for each camera a request is dispatched to, the server derives a key from that secret, the request
id and the camera id, and hands it to that camera only. The camera presents the key on its first
report of the request on a stream; the robot, which can derive the same key, then accepts the
request's reports for that camera on that stream and on no other. A camera learns only its own
keys, so it cannot report in another camera's name, and nobody who was not dispatched can report
at all. Pure logic.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

#: Bytes of a robot's report secret (it may send up to MAX_SECRET_BYTES).
SECRET_BYTES = 16
MAX_SECRET_BYTES = 64
#: Bytes of a report key: 64 bits, guessed online against a live request, is out of reach, and the
#: key travels once per request and camera, so the first report pays 10 bytes.
KEY_BYTES = 8


def new_secret() -> bytes:
    return secrets.token_bytes(SECRET_BYTES)


def report_key(secret: bytes, request_id: str, camera_id: str) -> bytes:
    """The key a camera presents for `request_id`; empty when the robot gave no secret."""
    if not secret:
        return b""
    message = f"{request_id}\0{camera_id}".encode()
    return hmac.digest(secret, message, hashlib.sha256)[:KEY_BYTES]


def key_matches(secret: bytes, request_id: str, camera_id: str, key: bytes) -> bool:
    return bool(key) and hmac.compare_digest(report_key(secret, request_id, camera_id), key)
