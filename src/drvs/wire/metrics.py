"""Prometheus metrics of the server and camera nodes (prometheus-client), served over HTTP with
--metrics-port. Names are documented in docs/operations.md; every one starts with drvs_."""

from __future__ import annotations

import logging

from prometheus_client import Counter, Gauge, Histogram, start_http_server

from drvs.core.errors import InvalidArgument
from drvs.core.net import parse_address

log = logging.getLogger(__name__)

#: Request-path stages are milliseconds long; detection can take tens of milliseconds.
_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)

REQUESTS = Counter(
    "drvs_requests_total", "Detection requests the server answered, by outcome (dispatched or refused)", ["outcome"]
)
ROUTED = Counter(
    "drvs_requests_routed_total", "Forwards of a request to a camera, by outcome (ok or failed)", ["outcome"]
)
FORWARDED_BYTES = Counter(
    "drvs_forwarded_bytes_total",
    "Serialised bytes of the requests the server forwarded to cameras (a request's size times its cameras)",
)
CAMERAS = Gauge("drvs_cameras_registered", "Cameras in the server's routing table")
DETECTIONS = Counter("drvs_detections_sent_total", "Detections a camera node sent to robots")
DETECTOR_RUNS = Counter(
    "drvs_detector_runs_total",
    "Searches of a frame a camera node ran, by detector (one serves every request on it)",
    ["detector"],
)
DETECTOR_SECONDS = Counter(
    "drvs_detector_seconds_total", "Seconds a camera node spent searching frames, by detector", ["detector"]
)
DETECTOR_AVAILABLE = Gauge(
    "drvs_detector_available",
    "A camera node's configured detectors: 1 ready (its object types are served and registered), 0 unavailable "
    "(a backend it needs is not installed, or a file it needs is absent; the start log says which and why)",
    ["detector"],
)
REPORTS = Counter(
    "drvs_reports_sent_total", "Reports a camera node sent to robots, by outcome (sent or dropped)", ["outcome"]
)
REPORT_BYTES = Counter("drvs_report_bytes_sent_total", "Serialised bytes of the reports a camera node sent")
FUSION_REPORTS = Counter(
    "drvs_fusion_reports_total",
    "Camera reports the server received for fused requests, by outcome: accepted, late (its request had "
    "ended), or rejected (no fused request in flight dispatched to that camera with the key presented)",
    ["outcome"],
)
FUSION_SNAPSHOTS = Counter(
    "drvs_fusion_snapshots_total",
    "Fused snapshots the server made, by outcome: sent, or dropped (the robot was not reading its stream)",
    ["outcome"],
)
POSE_UPDATES = Counter(
    "drvs_pose_updates_total",
    "Mobile cameras' pose updates the server received, by outcome (ok, or the refusal's status)",
    ["outcome"],
)
LIVEVIEW_FRAMES = Counter(
    "drvs_liveview_frames_total",
    "A camera's live view, per turn (at most --foxglove-fps a second): published (a frame encoded and sent), "
    "unwatched (nobody subscribed: no frame read or encoded), unchanged (no frame newer than the last sent)",
    ["outcome"],
)
LIVEVIEW_BYTES = Counter("drvs_liveview_bytes_total", "JPEG bytes a camera's live view sent")
MOBILE_PICKUPS = Counter(
    "drvs_mobile_pickups_total",
    "Continuous fused requests a mobile camera joined after their dispatch, its field of view having entered "
    "their region (it was asked for the rest of the request)",
)
FUSION_SESSIONS = Gauge("drvs_fusion_sessions", "Fused requests in flight in the server")
ADMISSION_REFUSED = Counter(
    "drvs_admission_refused_total",
    "Requests the server refused at its door, RESOURCE_EXHAUSTED before forwarding anything, by whose "
    "queue stood: the server's own loop, a camera link's, fused delivery's, or a camera link already at its bound",
    ["by"],
).labels
REGISTRY_SKIPPED = Counter(
    "drvs_registry_records_skipped_total",
    "Values under DRVS's prefix in the shared registry (etcd) that the server skipped, by kind (camera or pose): "
    "not JSON, too large, nested too deeply, a field of the wrong type, or not applicable here",
    ["kind"],
)
REGISTRY_WATCH_RESTARTS = Counter(
    "drvs_registry_watch_restarts_total",
    "Times the server's watch of the shared registry failed for a reason other than etcd being unreachable "
    "and was restarted (registrations refused, health NOT_SERVING for them, until it was back)",
)
REGISTRY_WRITES_REFUSED = Counter(
    "drvs_registry_writes_refused_total",
    "Registrations and pose updates refused RESOURCE_EXHAUSTED because their identity wrote to the shared "
    "registry faster than --registration-rate or --pose-write-rate allow, by kind (registration or pose)",
    ["kind"],
)
STAGE = Histogram(
    "drvs_stage_seconds",
    "Time per stage: route (server: validate, check, route, dispatch), forward (server: until the camera "
    "accepts), detect (camera: one detection on a frame), report (camera: handing one report to the robot's stream)",
    ["stage"],
    buckets=_BUCKETS,
)


#: Where /metrics listens unless the operator says otherwise: this host only. The metrics say how
#: busy the service is and which requests fail; publish them to the network on purpose.
DEFAULT_METRICS_HOST = "127.0.0.1"


def parse_metrics_address(value: str, name: str, host: str = DEFAULT_METRICS_HOST) -> tuple[str, int] | None:
    """`PORT` (on `host`), `HOST:PORT`, or a negative number (off: None). 0 picks a free port."""
    text = value.strip()
    if text.lstrip("-").isdecimal():
        port = int(text)
        if port < 0:
            return None
        if port > 65535:
            raise InvalidArgument(f"{name}: {port} is not a port number (0 picks a free one)")
        return host, port
    return parse_address(text, name, allow_port_zero=True)


def serve_metrics(port: int | None, host: str = DEFAULT_METRICS_HOST) -> int | None:
    """Serve /metrics on host:port (0: any free port; None: not at all); returns the bound port."""
    if port is None:
        return None
    server, _thread = start_http_server(port, addr=host)
    bound = int(server.server_port)
    log.info("metrics on http://%s:%d/metrics", host, bound)
    return bound


# Label children bound once: .labels() on every request was a visible share of the server's time.
DISPATCHED = REQUESTS.labels("dispatched")
REFUSED = REQUESTS.labels("refused")
ROUTED_OK = ROUTED.labels("ok")
ROUTED_FAILED = ROUTED.labels("failed")
REPORTS_SENT = REPORTS.labels("sent")
REPORTS_DROPPED = REPORTS.labels("dropped")
FUSION_REPORTS_ACCEPTED = FUSION_REPORTS.labels("accepted")
FUSION_REPORTS_LATE = FUSION_REPORTS.labels("late")
FUSION_REPORTS_REJECTED = FUSION_REPORTS.labels("rejected")
FUSION_SNAPSHOTS_SENT = FUSION_SNAPSHOTS.labels("sent")
FUSION_SNAPSHOTS_DROPPED = FUSION_SNAPSHOTS.labels("dropped")
STAGE_ROUTE = STAGE.labels("route")
STAGE_FORWARD = STAGE.labels("forward")
STAGE_DETECT = STAGE.labels("detect")
STAGE_REPORT = STAGE.labels("report")
