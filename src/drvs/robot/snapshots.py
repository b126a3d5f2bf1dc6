"""A fused Snapshot as JSON and as a table: drvs-robot track / detect --fuse print these, and the
simulator and the benchmarks write the same JSON (one renderer, so the keys cannot drift)."""

from __future__ import annotations

from typing import Any

from shapely.geometry import Polygon

from drvs.core.model import Snapshot, WorldObject


def _r(value: float, digits: int) -> float:
    return round(float(value), digits)


def world_object_json(o: WorldObject) -> dict[str, Any]:
    """One WorldObject as JSON: `track_id`; `centroid` [x, y], `bounds` [x0, y0, x1, y1] and
    `uncertainty_m` in metres; `velocity` [vx, vy] in m/s; `heading_deg` (course_deg: direction of motion,
    degrees counter-clockwise from +x, null when not moving); `cameras` (ids, sorted; empty when
    predicted); `marker_id` (null unless a marker); `label`; `last_seen` (seconds since the Unix
    epoch); `score` in [0, 1]; `area_m2`."""
    return {
        "track_id": o.track_id,
        "centroid": [_r(o.centroid_xy[0], 4), _r(o.centroid_xy[1], 4)],
        "bounds": [_r(v, 4) for v in o.bounds],
        "velocity": [_r(o.velocity_xy[0], 4), _r(o.velocity_xy[1], 4)],
        "heading_deg": None if o.course_deg is None else _r(o.course_deg, 2),
        "uncertainty_m": _r(o.uncertainty_m, 4),
        "cameras": list(o.camera_ids),
        "marker_id": o.marker_id,
        "label": o.label,
        "last_seen": o.last_seen,
        "score": _r(o.score, 3),
        "area_m2": _r(o.area_m2, 5),
    }


def snapshot_json(snapshot: Snapshot) -> dict[str, Any]:
    """A Snapshot as the JSON object drvs-robot track --json prints (one per line):
    `time` (seconds since the Unix epoch), `sequence` (0, 1, ...), `final`, `objects` (see
    world_object_json), `missing_cameras` ([{camera_id, code, message}], code a gRPC status name),
    `cameras` (the cameras whose reports were merged) and `uncovered` (the parts of the region no
    camera asked sees: polygons, [[x, y], ...] each, metres)."""
    return {
        "time": snapshot.time,
        "sequence": snapshot.sequence,
        "final": snapshot.final,
        "objects": [world_object_json(o) for o in snapshot.objects],
        "missing_cameras": [
            {"camera_id": m.camera_id, "code": m.code, "message": m.message} for m in snapshot.camera_errors.values()
        ],
        "cameras": list(snapshot.camera_ids),
        "uncovered": [polygon_json(p) for p in snapshot.uncovered],
    }


def polygon_json(polygon: Polygon) -> list[list[float]]:
    """A polygon's outer ring as [[x, y], ...] (metres, 4 decimals; not closed)."""
    return [[round(x, 4), round(y, 4)] for x, y in list(polygon.exterior.coords)[:-1]]


_COLUMNS = ("track", "x m", "y m", "vx m/s", "vy m/s", "± m", "type", "cameras")


def _kind(o: WorldObject) -> str:
    if o.marker_id is not None:
        return f"marker {o.marker_id}"
    return o.label or "-"


def snapshot_table(snapshot: Snapshot) -> list[str]:
    """A Snapshot as readable lines: a heading (sequence, time, cameras, missing cameras), then one
    aligned row per object (metres, m/s)."""
    head = f"snapshot #{snapshot.sequence}{' final' if snapshot.final else ''} at {snapshot.time:.3f}: "
    head += f"{len(snapshot.objects)} object(s) from {', '.join(snapshot.camera_ids) or 'no camera'}"
    lines = [head]
    for m in snapshot.camera_errors.values():
        lines.append(f"  missing {m.camera_id}: {m.code} {m.message}")
    if not snapshot.objects:
        return lines
    rows = [list(_COLUMNS)] + [
        [
            str(o.track_id),
            f"{o.centroid_xy[0]:.3f}",
            f"{o.centroid_xy[1]:.3f}",
            f"{o.velocity_xy[0]:.2f}",
            f"{o.velocity_xy[1]:.2f}",
            f"{o.uncertainty_m:.3f}",
            _kind(o),
            ",".join(o.camera_ids) or "(predicted)",
        ]
        for o in snapshot.objects
    ]
    widths = [max(len(row[i]) for row in rows) for i in range(len(_COLUMNS))]
    for row in rows:
        cells = [
            cell.rjust(w) if 0 < i < 6 else cell.ljust(w) for i, (cell, w) in enumerate(zip(row, widths, strict=True))
        ]
        lines.append("  " + "  ".join(cells).rstrip())
    return lines
