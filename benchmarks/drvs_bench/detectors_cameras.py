"""drvs-bench detectors, the camera processes' part: the CPU of a real drvs-camera serving one
detector, idle and at 10 requests a second, and the peak RSS of a camera with every detector loaded
against one with only hsv (see drvs_bench.detectors for the whole benchmark)."""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from drvs.robot import DrvsClient
from drvs.tools.launch import ManagedProcess, start_camera, start_server

from .common import cpu_seconds, peak_rss_bytes
from .service import CAPACITY_NOT_POLICY
from .stats import check_work, interleaved, publish

if TYPE_CHECKING:
    from .detectors import DetectorInputs

#: The request rate of the camera CPU comparison.
RATE_HZ = 10.0


async def start_detector_camera(
    camera_id: str, inputs: DetectorInputs, address: str, detectors: Sequence[str], config: Mapping[str, Any],
    directory: Path,
) -> ManagedProcess:  # fmt: skip
    """A real drvs-camera on the inputs' video, running `detectors` with `config` (options)."""
    assert inputs.video is not None and inputs.homography_file is not None
    # Cost, not policy: a frame up to 30 s old still serves (the default, 2 s, refuses requests when
    # the shared machine starves the camera's reader thread; a full run failed on it once).
    args = ["--max-range", f"{inputs.max_range_m:g}", "--detectors", ",".join(detectors), "--max-frame-age", "30"]
    if config:
        path = directory / f"{camera_id}.config.yaml"
        path.write_text(yaml.safe_dump(dict(config), sort_keys=False))
        args += ["--config", str(path)]
    return await start_camera(camera_id, inputs.video, inputs.homography_file, address, *args)


async def paced_requests(
    client: DrvsClient, filter_def: str, region: tuple[float, ...], rate: float, seconds: float, camera_ids: set[str],
    what: str,
) -> float:  # fmt: skip
    """Single-shot requests at `rate` for `seconds` (none: an idle wait), each checked to be answered
    in full by exactly `camera_ids`; returns the wall time until the last one was answered."""
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    n = int(rate * seconds)
    if n == 0:
        await asyncio.sleep(seconds)
        return loop.time() - t0
    tasks = []
    for i in range(n):
        delay = t0 + i / rate - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        tasks.append(loop.create_task(client.detect(filter_def, region, timeout_s=600, outlines=False)))
    results = await asyncio.gather(*tasks)
    wall = loop.time() - t0
    got: dict[str, float] = {
        "requests": n,
        "complete": sum(
            1
            for res in results
            if res.complete and set(res.camera_ids) == camera_ids and res.finished_cameras == camera_ids
        ),
        "error_reports": sum(1 for res in results for rep in res.reports if rep.error),
    }
    errors = sorted({rep.error[:200] for res in results for rep in res.reports if rep.error})[:3]
    check_work(what + (f" (errors: {errors})" if errors else ""), {"complete": n, "error_reports": 0}, got)
    return wall


async def measure_cameras(
    all_inputs: Mapping[str, DetectorInputs], rounds: int, seconds: float, directory: Path, out: dict[str, Any]
) -> None:
    """One camera per detector, idle and at 10 requests a second in turn, every round."""
    procs: list[ManagedProcess] = []
    try:
        server, address = await start_server(*CAPACITY_NOT_POLICY)
        procs.append(server)
        cams: dict[str, ManagedProcess] = {}
        for prefix, inputs in all_inputs.items():
            cams[prefix] = await start_detector_camera(
                f"det-{prefix}", inputs, address, [prefix], inputs.camera_config, directory
            )
            procs.append(cams[prefix])
        modes = [(prefix, rate) for prefix in all_inputs for rate in (0.0, RATE_HZ)]
        per_round: list[dict[tuple[str, float], dict[str, float]]] = [{} for _ in range(rounds)]
        async with DrvsClient(address, listen="127.0.0.1:0") as client:
            for prefix, inputs in all_inputs.items():  # warm-up, not counted: first requests of each type
                await paced_requests(client, inputs.filter_def, inputs.region(), 5.0, 0.6, {f"det-{prefix}"},
                                     f"camera {prefix}: warm-up")  # fmt: skip
            for r, (prefix, rate) in interleaved(modes, rounds):
                inputs, pid = all_inputs[prefix], cams[prefix].pid
                c0 = cpu_seconds(pid)
                wall = await paced_requests(
                    client, inputs.filter_def, inputs.region(), rate, seconds, {f"det-{prefix}"},
                    f"camera {prefix} at {rate:g} requests/s, round {r + 1}",
                )  # fmt: skip
                cpu = cpu_seconds(pid) - c0
                per_round[r][(prefix, rate)] = {"cpu_s": cpu, "wall_s": wall, "requests": rate * seconds}
                print(f"drvs-bench detectors: camera {prefix} at {rate:g}/s, round {r + 1}: {cpu / wall:.3f} cores",
                      file=sys.stderr, flush=True)  # fmt: skip
        for prefix in all_inputs:
            entry = out.setdefault(prefix, {})
            idle = [f[(prefix, 0.0)] for f in per_round]
            busy = [f[(prefix, RATE_HZ)] for f in per_round]
            publish(entry, "camera_cpu_idle_cores", [m["cpu_s"] / m["wall_s"] for m in idle])
            publish(entry, "camera_cpu_10hz_cores", [m["cpu_s"] / m["wall_s"] for m in busy])
            publish(entry, "camera_cpu_10hz_over_idle", [
                (b["cpu_s"] / b["wall_s"]) / (i["cpu_s"] / i["wall_s"]) for b, i in zip(busy, idle, strict=True)
            ])  # fmt: skip
            # Requests answered per second of wall time (until the last answer): under 10, the camera
            # could not keep up and requests queued for its detector threads.
            publish(entry, "camera_answered_per_s", [b["requests"] / b["wall_s"] for b in busy])
            publish(entry, "camera_marginal_cpu_ms_per_request", [
                (b["cpu_s"] - i["cpu_s"] / i["wall_s"] * b["wall_s"]) / b["requests"] * 1000
                for b, i in zip(busy, idle, strict=True)
            ])  # fmt: skip
    finally:
        for p in reversed(procs):
            await p.stop()


async def measure_memory(
    all_inputs: Mapping[str, DetectorInputs], rounds: int, directory: Path, out: dict[str, Any]
) -> None:
    """Peak RSS of a camera with every detector loaded against one with only hsv, side by side: both
    on the office video, both given requests of every type they serve before VmHWM is read."""
    office = all_inputs["hsv"]
    config: dict[str, Any] = {}
    for inputs in all_inputs.values():
        config.update(inputs.camera_config)
    every = list(all_inputs)
    all_rss, hsv_rss = [], []
    for r in range(rounds):
        procs: list[ManagedProcess] = []
        try:
            server, address = await start_server(*CAPACITY_NOT_POLICY)
            procs.append(server)
            hsv_cam = await start_detector_camera("rss-hsv", office, address, ["hsv"], {}, directory)
            procs.append(hsv_cam)
            all_cam = await start_detector_camera("rss-all", office, address, every, config, directory)
            procs.append(all_cam)
            async with DrvsClient(address, listen="127.0.0.1:0") as client:
                for prefix, inputs in all_inputs.items():
                    expected = {"rss-all", "rss-hsv"} if prefix == "hsv" else {"rss-all"}
                    await paced_requests(client, inputs.filter_def, office.region(), 5.0, 1.0, expected,
                                         f"memory: {prefix} requests, round {r + 1}")  # fmt: skip
            all_rss.append(peak_rss_bytes(all_cam.pid))
            hsv_rss.append(peak_rss_bytes(hsv_cam.pid))
        finally:
            for p in reversed(procs):
                await p.stop()
    memory: dict[str, Any] = {"all_detectors": every}
    publish(memory, "camera_peak_rss_bytes_all", all_rss)
    publish(memory, "camera_peak_rss_bytes_hsv", hsv_rss)
    publish(memory, "camera_rss_all_over_hsv", [a / h for a, h in zip(all_rss, hsv_rss, strict=True)])
    out["memory"] = memory
