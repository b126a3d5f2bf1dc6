"""Prometheus metrics and JSON logs from real server and camera processes: the numbers move with
real requests, and one request id runs through every hop's log."""

from __future__ import annotations

import json

from drvs.robot import DrvsClient
from drvs.sim.scene import RecordedCamera
from drvs.tools.launch import ManagedProcess, start_camera, start_server
from tests.helpers import CAM1_REGION, MAX_RANGE, YELLOW, metrics_port, scrape

OBSERVE = ("--metrics-port", "0", "--log-format", "json", "--log-level", "DEBUG")


def json_lines(proc: ManagedProcess) -> list[dict[str, object]]:
    out = []
    for line in proc.lines:
        if line.startswith("{"):
            out.append(json.loads(line))
    return out


async def test_metrics_and_json_logs_follow_a_request(recorded: dict[str, RecordedCamera]) -> None:
    procs: list[ManagedProcess] = []
    try:
        server, address = await start_server(*OBSERVE)
        procs.append(server)
        rec = recorded["cam1"]
        camera = await start_camera("cam1", rec.video, rec.homography_file, address, "--max-range", MAX_RANGE, *OBSERVE)
        procs.append(camera)
        # The server's metrics answer once it has said where (the line comes after the port is bound).
        await server.wait_for_line(r"metrics on http://")
        await camera.wait_for_line(r"metrics on http://")
        before = await scrape(metrics_port(server))
        assert before["drvs_cameras_registered"] == 1.0
        async with DrvsClient(address, robot_id="observer", listen="127.0.0.1:0") as robot:
            results = [await robot.detect(YELLOW, CAM1_REGION, timeout_s=10) for _ in range(3)]
        assert all(r.complete for r in results)
        request_id = results[0].request_id
        after = await scrape(metrics_port(server))
        dispatched = 'drvs_requests_total{outcome="dispatched"}'
        assert after[dispatched] - before.get(dispatched, 0.0) == 3.0
        assert after['drvs_requests_routed_total{outcome="ok"}'] >= 3.0
        assert after['drvs_stage_seconds_count{stage="route"}'] >= 3.0
        cam = await scrape(metrics_port(camera))
        assert cam['drvs_reports_sent_total{outcome="sent"}'] == 3.0
        assert cam["drvs_detections_sent_total"] == 6.0  # two yellow objects in cam1's view, three times
        assert cam['drvs_stage_seconds_count{stage="detect"}'] == 3.0
        assert cam["drvs_report_bytes_sent_total"] > 0
        # One JSON object per line, and the request's id on the server's and the camera's lines.
        for proc in (server, camera):
            entries = json_lines(proc)
            assert entries and all({"ts", "level", "logger", "msg"} <= set(e) for e in entries)
            assert any(e.get("request_id") == request_id for e in entries), proc.output()
    finally:
        for p in reversed(procs):
            await p.stop()
