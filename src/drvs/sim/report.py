"""map.png: the floor plan, fields of view, detections, planned and driven paths (the paper's
Figs. 5-8), and one frame from each camera with its detections drawn."""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Polygon as MplPolygon
from shapely.geometry import Polygon

from drvs.core.geometry import FieldOfView
from drvs.sim.render import CameraRenderer
from drvs.sim.scenario import Scenario


def _patch(poly: Polygon, **kw: Any) -> MplPolygon:
    return MplPolygon(np.asarray(poly.exterior.coords), closed=True, **kw)


def draw_map(scenario: Scenario, result: dict[str, Any], path: Path, seed: int = 0) -> Path:
    cams = scenario.cameras
    fig = plt.figure(figsize=(14, 7 + 3.2 * math.ceil(len(cams) / 3)), dpi=90)
    grid = fig.add_gridspec(1 + math.ceil(len(cams) / 3), 3, height_ratios=[2.2] + [1] * math.ceil(len(cams) / 3))
    ax = fig.add_subplot(grid[0, :])
    x0, y0, x1, y1 = scenario.bounds
    ax.set_xlim(x0 - 0.3, x1 + 0.3)
    ax.set_ylim(y0 - 0.3, y1 + 0.3)
    ax.set_aspect("equal")
    ax.add_patch(MplPolygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], closed=True, fill=False, edgecolor="black"))
    for wall in scenario.walls:
        ax.add_patch(_patch(wall, facecolor="0.55", edgecolor="0.3"))
    for cam in cams:
        fov = cam.field_of_view.floor
        ax.add_patch(_patch(fov, facecolor="tab:cyan", alpha=0.12, edgecolor="tab:cyan", lw=1))
        cx, cy, _ = cam.position
        yaw = math.radians(cam.yaw_deg)
        ax.annotate("", xy=(cx + 0.8 * math.cos(yaw), cy + 0.8 * math.sin(yaw)), xytext=(cx, cy),
                    arrowprops={"arrowstyle": "->", "lw": 2})  # fmt: skip
        ax.plot([cx], [cy], "ks", ms=8)
        ax.text(cx, cy - 0.45 if cy > y0 + 1 else cy + 0.3, cam.id, fontsize=8, ha="center")
    for scout in scenario.scouts:  # its path, and its camera's view where it starts (dashed)
        line = np.asarray(scout.path)
        ax.plot(line[:, 0], line[:, 1], "-.", color="tab:green", lw=1.2)
        view = FieldOfView.compute(scout.homography_at(0.0), scout.resolution, scout.max_range_m).floor
        ax.add_patch(_patch(view, facecolor="tab:green", alpha=0.08, edgecolor="tab:green", ls="--", lw=1))
        ax.add_patch(_patch(scout.body_at(0.0), facecolor="0.3", edgecolor="tab:green"))
        sx, sy = scout.path[0]
        ax.text(sx, sy + 0.3, f"{scout.id} (mobile camera)", fontsize=8, ha="center", color="tab:green")
    for obj in scenario.objects:
        if obj.aruco is not None and obj.kind == "marker":
            ax.add_patch(_patch(obj.shape, facecolor="black", edgecolor="white", lw=0.8))
            mx, my = obj.shape.centroid.x, obj.shape.centroid.y
            ax.text(mx, my, str(obj.aruco.id), color="white", fontsize=6, ha="center", va="center")
            continue
        if obj.paint is None:
            ax.add_patch(_patch(obj.shape, fill=False, edgecolor="tab:purple", ls=":", lw=1.5))
            continue
        b, g, r = obj.paint
        if obj.moving:  # its path, where it started (outlined) and where it was at the end (filled)
            line = np.asarray(obj.path)
            ax.plot(line[:, 0], line[:, 1], ":", color=(r / 255, g / 255, b / 255), lw=1.5)
            ax.add_patch(_patch(obj.shape, fill=False, edgecolor=(r / 255, g / 255, b / 255), ls="--", lw=1))
            end = obj.shape_at(float(result.get("world_time_s", 0.0)))
            ax.add_patch(_patch(end, facecolor=(r / 255, g / 255, b / 255), alpha=0.45, edgecolor="none"))
            continue
        ax.add_patch(_patch(obj.shape, facecolor=(r / 255, g / 255, b / 255), alpha=0.45, edgecolor="none"))
    for d in result.get("detections", []):
        ax.add_patch(MplPolygon(d["outline"], closed=True, fill=False, edgecolor="red", lw=1.4))
    for t in result.get("tracks", []):  # moving tracks the robot followed: where first and last seen
        if str(t.get("used_as", "")).startswith("moving"):
            ax.annotate("", xy=tuple(t["last"]), xytext=tuple(t["first"]),
                        arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.2, "ls": "--"})  # fmt: skip
    for c in result.get("contacts", []):
        centre = np.mean(np.asarray(c), axis=0)
        ax.plot([centre[0]], [centre[1]], "rx", ms=12, mew=3)
    plans = result.get("planned_paths", [])
    for i, plan in enumerate(plans):
        p = np.asarray(plan)
        if len(p):
            last = i == len(plans) - 1
            ax.plot(p[:, 0], p[:, 1], "--", color="tab:orange", lw=1.6 if last else 0.8, alpha=1.0 if last else 0.5)
    driven = np.asarray(result.get("path", []))
    if len(driven):
        ax.plot(driven[:, 0], driven[:, 1], "-", color="tab:blue", lw=2.5, label="driven")
        ax.plot([driven[0, 0]], [driven[0, 1]], "go", ms=9, label="start")
    if scenario.robot.goal:
        ax.plot([scenario.robot.goal[0]], [scenario.robot.goal[1]], "r*", ms=14, label="goal")
    if result.get("charging_station"):
        sx, sy = result["charging_station"]
        ax.plot([sx], [sy], "P", color="tab:purple", ms=13, label="station found")
    ax.plot([], [], "--", color="tab:orange", label="planned (last bold)")
    ax.plot([], [], "-", color="red", label="DRVS detections")
    ax.plot([], [], "rx", label="collision")
    if any(str(t.get("used_as", "")).startswith("moving") for t in result.get("tracks", [])):
        ax.plot([], [], "--", color="tab:red", lw=1.2, label="moving track (first to last seen)")
    ax.legend(loc="upper left", fontsize=8, ncol=3, framealpha=0.9)
    mode = "with DRVS" if result.get("drvs") else "without DRVS (baseline)"
    outcome = "reached goal" if result.get("reached_goal") else "did not reach goal"
    ax.set_title(
        f"{scenario.name}: {result.get('mission')} {mode}: {outcome}, "
        f"{result.get('collisions', 0)} collision(s), {result.get('replans', 0)} re-plan(s)"
    )
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")

    final = tuple(result["path"][-1]) if result.get("path") else scenario.robot.start
    moves = [(b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(result.get("path", []))]
    moves = [m for m in moves if m != (0, 0)]
    heading = math.atan2(moves[-1][1], moves[-1][0]) if moves else 0.0  # as the robot drove its last step
    for i, cam in enumerate(cams):
        sub = fig.add_subplot(grid[1 + i // 3, i % 3])
        frame = CameraRenderer(scenario, cam, seed=seed).render(
            final, len(result.get("path", [])), heading, float(result.get("world_time_s", 0.0))
        )
        to_image = cam.homography.inverse()
        for d in result.get("detections", []):
            if d["camera_id"] == cam.id:
                pts = to_image.apply(np.asarray(d["outline"]))
                cv2.polylines(frame, [np.round(pts).astype(np.int32)], True, (0, 0, 255), 2)
        sub.imshow(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        sub.set_title(cam.id, fontsize=9)
        sub.axis("off")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
