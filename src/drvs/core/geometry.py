"""Floor geometry: regions, homographies, fields of view. Pure logic, no gRPC.

World frame: metres, right-handed, floor = x-y plane, z up. Homographies map image pixels
(u, v, 1) to floor points (x, y, 1).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import ArrayLike, NDArray
from shapely.geometry import Point, Polygon, box

from drvs.core.errors import InvalidArgument

#: Coordinates beyond this many metres are refused: no building is that large, and it keeps
#: floating-point geometry well-conditioned.
MAX_COORDINATE_M = 1.0e6
#: Default clip of a camera's field of view, metres from the nearest floor point it sees.
DEFAULT_MAX_RANGE_M = 15.0
#: Image rows closer to the horizon than this fraction of the bottom row's projective scale are
#: dropped: near the horizon one pixel spans metres and detections are meaningless.
HORIZON_MARGIN = 0.05
_MIN_AREA_M2 = 1e-9
MAX_CONDITION = 1e15
#: A region's polygon may have at most this many points: a room or a corridor needs tens, and every
#: point costs the server (and every camera the region reaches) time and memory on every request.
MAX_REGION_VERTICES = 1000


def _finite(value: float, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InvalidArgument(f"{name}: {str(value)[:40]!r} is not a number") from None
    if not math.isfinite(v):
        raise InvalidArgument(f"{name}: {v} is not finite")
    if abs(v) > MAX_COORDINATE_M:
        raise InvalidArgument(f"{name}: {v} is beyond ±{MAX_COORDINATE_M:g} m")
    return v


def box_region(x_lower: float, y_lower: float, x_upper: float, y_upper: float, name: str = "region") -> Polygon:
    """The paper's box as a polygon; lower must be below upper on both axes."""
    x0 = _finite(x_lower, f"{name}.box.x_lower")
    y0 = _finite(y_lower, f"{name}.box.y_lower")
    x1 = _finite(x_upper, f"{name}.box.x_upper")
    y1 = _finite(y_upper, f"{name}.box.y_upper")
    if not x0 < x1:
        raise InvalidArgument(f"{name}.box: x_lower {x0:g} must be less than x_upper {x1:g}")
    if not y0 < y1:
        raise InvalidArgument(f"{name}.box: y_lower {y0:g} must be less than y_upper {y1:g}")
    return shapely.box(x0, y0, x1, y1)  # the fast constructor: this runs for every request


def polygon_region(points: Iterable[Sequence[float]], name: str = "region.polygon") -> Polygon:
    """A simple polygon with positive area from its exterior ring (closing point optional)."""
    coords = []
    for i, p in enumerate(points):
        if i >= MAX_REGION_VERTICES:
            raise InvalidArgument(f"{name}: more than {MAX_REGION_VERTICES} points; simplify the region")
        if len(p) != 2:
            raise InvalidArgument(f"{name}.points[{i}]: expected [x, y], got {len(p)} values")
        coords.append((_finite(p[0], f"{name}.points[{i}].x"), _finite(p[1], f"{name}.points[{i}].y")))
    if len(coords) >= 2 and coords[0] == coords[-1]:
        coords.pop()
    if len(coords) < 3:
        raise InvalidArgument(f"{name}: needs at least 3 distinct points, got {len(coords)}")
    poly = Polygon(coords)
    if not poly.is_valid:
        reason = shapely.is_valid_reason(poly)
        raise InvalidArgument(f"{name}: not a simple polygon ({reason})")
    if poly.area <= _MIN_AREA_M2:
        raise InvalidArgument(f"{name}: has zero area")
    return poly


@dataclass(frozen=True)
class Homography:
    """A 3x3 image -> floor homography, scaled so that its largest entry has magnitude 1."""

    matrix: NDArray[np.float64]

    @classmethod
    def from_values(cls, values: ArrayLike, name: str = "homography") -> Homography:
        try:
            m = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise InvalidArgument(f"{name}: expected 9 numbers (3x3 row-major)") from None
        if m.size != 9:
            raise InvalidArgument(f"{name}: expected 9 numbers (3x3 row-major), got {m.size}")
        m = m.reshape(3, 3)
        if not np.all(np.isfinite(m)):
            raise InvalidArgument(f"{name}: contains NaN or infinite values")
        scale = float(np.max(np.abs(m)))
        if scale == 0.0:
            raise InvalidArgument(f"{name}: all zeros")
        m = m / scale
        # Singular or numerically so. The condition number is scale-invariant, but it grows with the
        # distance of the camera from the world origin (about 1e14 at the 1e6 m coordinate limit),
        # so the limit sits near float64 precision rather than at a small determinant.
        cond = float(np.linalg.cond(m))
        if not math.isfinite(cond) or cond > MAX_CONDITION:
            raise InvalidArgument(f"{name}: singular (condition number {cond:.3g}); it cannot map an image to a floor")
        return cls(m)

    def inverse(self) -> Homography:
        return Homography(np.asarray(np.linalg.inv(self.matrix), dtype=np.float64))

    def apply(self, points: ArrayLike) -> NDArray[np.float64]:
        """Map an (N, 2) array of points; returns (N, 2). A point on the horizon maps to inf.

        Not cv2.perspectiveTransform: it silently maps points whose scale is below its epsilon
        to (0, 0), which would put such detections at the world origin.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        mapped = pts @ self.matrix[:, :2].T + self.matrix[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return mapped[:, :2] / mapped[:, 2:3]

    def projective_scale(self, points: ArrayLike) -> NDArray[np.float64]:
        """The third homogeneous coordinate w of each mapped point (0 on the horizon)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return pts @ self.matrix[2, :2] + self.matrix[2, 2]  # type: ignore[no-any-return]

    def to_list(self) -> list[float]:
        return [float(v) for v in self.matrix.reshape(-1)]


@dataclass(frozen=True)
class FieldOfView:
    """The floor polygon a camera sees, and the image polygon it comes from."""

    floor: Polygon
    image: Polygon

    @classmethod
    def compute(
        cls,
        homography: Homography,
        image_size: tuple[int, int],
        max_range_m: float = DEFAULT_MAX_RANGE_M,
        name: str = "field_of_view",
    ) -> FieldOfView:
        """The image below the horizon (with a margin), mapped to the floor, clipped to max_range_m.

        Which side of the horizon is floor does not depend on the matrix's arbitrary scale: a real
        camera (image v pointing down, right-handed floor frame) maps the floor in front of it with
        reversed orientation, and the Jacobian determinant of a homography at a point is
        det(H) / w³, so floor pixels are those where w·det(H) < 0. A camera looking above the
        horizon, or a mirrored homography, sees no floor. The range is measured from the nearest
        floor point in view (the bottom centre of the image when it shows floor).
        """
        width, height = image_size
        if not (0 < width <= 100_000 and 0 < height <= 100_000):
            raise InvalidArgument(f"{name}: image size {width}x{height} is not a real image size")
        max_range = float(max_range_m)
        if not (math.isfinite(max_range) and 0 < max_range <= 10_000):
            raise InvalidArgument(f"{name}: max_range_m {max_range_m} must be in (0, 10000]")
        sign = -1.0 if np.linalg.det(homography.matrix) > 0 else 1.0
        rect = box(0.0, 0.0, float(width), float(height))
        corners = np.asarray(rect.exterior.coords)[:-1]
        nearest_scale = float(np.max(sign * homography.projective_scale(corners)))
        if nearest_scale <= 0:
            raise InvalidArgument(
                f"{name}: the whole image is above the horizon; the camera sees no floor "
                "(is it pitched up, or is the homography mirrored?)"
            )
        # Keep s*w >= margin * (s*w of the nearest corner): near the horizon one pixel spans metres.
        a, b, c = (homography.matrix[2] * sign).tolist()
        image_poly = _clip_half_plane(rect, a, b, c - HORIZON_MARGIN * nearest_scale)
        if image_poly.is_empty or image_poly.area < 1.0:
            raise InvalidArgument(f"{name}: no part of the image is below the horizon; the camera sees no floor")
        bottom = np.array([[width / 2.0, height - 0.5]])
        if sign * float(homography.projective_scale(bottom)[0]) > 0:
            near_px = bottom
        else:
            near_px = corners[int(np.argmax(sign * homography.projective_scale(corners)))].reshape(1, 2)
        near = Point(homography.apply(near_px)[0])
        if not (math.isfinite(near.x) and math.isfinite(near.y)) or max(abs(near.x), abs(near.y)) > MAX_COORDINATE_M:
            raise InvalidArgument(
                f"{name}: the field of view lies beyond ±{MAX_COORDINATE_M:g} m; check the homography"
            )
        ring = np.asarray(image_poly.exterior.coords)[:-1]
        floor_pts = homography.apply(ring)
        floor = Polygon(floor_pts)
        if not floor.is_valid:
            floor = shapely.make_valid(floor)
        floor = floor.intersection(near.buffer(max_range, quad_segs=16))
        floor = _largest_polygon(floor)
        if floor is None or floor.area <= _MIN_AREA_M2:
            raise InvalidArgument(f"{name}: the camera sees no floor (empty field of view)")
        coords = np.asarray(floor.exterior.coords)
        if not np.all(np.isfinite(coords)):
            raise InvalidArgument(f"{name}: field of view is not finite")
        if np.max(np.abs(coords)) > MAX_COORDINATE_M:
            raise InvalidArgument(
                f"{name}: the field of view lies beyond ±{MAX_COORDINATE_M:g} m; check the homography"
            )
        # The image polygon that maps into the clipped floor polygon (for masking detections).
        image_clip = Polygon(homography.inverse().apply(np.asarray(floor.exterior.coords)[:-1]))
        if not image_clip.is_valid:
            image_clip = _largest_polygon(shapely.make_valid(image_clip)) or image_poly
        image_clip = _largest_polygon(image_clip.intersection(rect)) or image_poly
        return cls(floor=floor, image=image_clip)


def _clip_half_plane(poly: Polygon, a: float, b: float, c: float) -> Polygon:
    """poly ∩ {(u, v): a*u + b*v + c >= 0} (Sutherland-Hodgman on a convex ring)."""
    pts = list(poly.exterior.coords)[:-1]
    out: list[tuple[float, float]] = []
    for i, p in enumerate(pts):
        q = pts[(i + 1) % len(pts)]
        fp = a * p[0] + b * p[1] + c
        fq = a * q[0] + b * q[1] + c
        if fp >= 0:
            out.append(p)
        if (fp >= 0) != (fq >= 0):
            t = fp / (fp - fq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    if len(out) < 3:
        return Polygon()
    return Polygon(out)


def _largest_polygon(geom: shapely.Geometry) -> Polygon | None:
    if isinstance(geom, Polygon):
        return None if geom.is_empty else geom
    polys = [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]
    return max(polys, key=lambda g: g.area) if polys else None


def homography_from_pose(
    position: Sequence[float],
    yaw_deg: float,
    pitch_deg: float,
    hfov_deg: float,
    resolution: tuple[int, int],
    camera_matrix: tuple[float, float, float, float] | None = None,
) -> Homography:
    """Image -> floor homography of an ideal pinhole camera (no distortion).

    position: (x, y, z) with z the mounting height; yaw: the optical axis on the floor,
    counter-clockwise from +x; pitch: tilt below horizontal. Intrinsics: square pixels and the
    principal point at the image centre from `hfov_deg`, or `camera_matrix` (fx, fy, cx, cy in
    pixels, OpenCV's K) when given (then hfov_deg is not used).
    """
    width, height = resolution
    cx, cy, cz = (float(v) for v in position)
    if cz <= 0:
        raise InvalidArgument(f"position: camera height {cz} must be above the floor (z > 0)")
    if camera_matrix is None and not 0 < hfov_deg < 180:
        raise InvalidArgument(f"hfov_deg: {hfov_deg} must be in (0, 180)")
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(forward, right)
    rot = np.vstack([right, down, forward])  # world -> camera (OpenCV axes: x right, y down, z forward)
    if camera_matrix is None:
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        k = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    else:
        fx, fy, px, py = (float(v) for v in camera_matrix)
        if not (fx > 0 and fy > 0 and math.isfinite(fx) and math.isfinite(fy)):
            raise InvalidArgument(f"camera_matrix: focal lengths fx={fx:g}, fy={fy:g} must be > 0 pixels")
        if not (math.isfinite(px) and math.isfinite(py)):
            raise InvalidArgument("camera_matrix: the principal point must be finite")
        k = np.array([[fx, 0.0, px], [0.0, fy, py], [0.0, 0.0, 1.0]])
    t = -rot @ np.array([cx, cy, cz])
    world_to_image = k @ np.column_stack([rot[:, 0], rot[:, 1], t])
    return Homography.from_values(np.linalg.inv(world_to_image))


def polygon_coords(poly: Polygon) -> list[tuple[float, float]]:
    """Exterior ring without the closing point."""
    return [(float(x), float(y)) for x, y in list(poly.exterior.coords)[:-1]]
