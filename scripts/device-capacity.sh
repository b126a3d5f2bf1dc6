#!/usr/bin/env bash
# The capacity runs a 2-core machine cannot show, prepared as one short job for a lent many-core
# machine (the workplace's `device` tool: 16 cores, no registry, Python 3.12, a bare copy of this
# repository, at most 10 minutes a command and 8 files back).
#
#   scripts/device-capacity.sh prepare      here: the wheels and Debian's etcd-server the runs need,
#                                           into .whl/ (in .gitignore; about 26 MB)
#   scripts/device-capacity.sh run [DIR]    there (or here, to try it: DRVS_DEVICE_LOCAL=1 uses this
#                                           machine's .venv and etcd): every run below, each under its
#                                           own time limit, results packed into DIR (default $OUT)
#   scripts/device-capacity.sh ros2 [DIR]   there, in a call of its own: drvs-bench ros2 (issue 30's
#                                           0.5 ms a snapshot, which this 2-core virtual machine cannot
#                                           judge: its DDS floor alone is 0.3 to 0.5 ms), --quick first
#
# The device call: carry [".whl"], command `bash scripts/device-capacity.sh run` (or `... ros2`),
# timeout_s 600. What comes back: capacity.tgz (every JSON the runs wrote) and capacity.log.
#
# The runs, in order of what they answer (docs/benchmarks.md, "Capacity"):
#   1. drvs-bench load --sweep, per camera then fused: robots at 30 Hz with zero loss on these cores;
#   2. drvs-bench load --overload 2,4 at the per-camera capacity found: goodput, p99 and refusals;
#   3. drvs-bench load --robots 100: the fleet that once collapsed, as first measured;
#   4. drvs-bench cluster --parts throughput --workers-list 1,2,4,8: what --workers gains;
#   5. drvs-bench load --delivery fused-unary --overload 2,4 at the fused capacity found: the issue's
#      own measurement (unary fused calls, a connection a robot) with --max-pending-calls' default;
#   6. drvs-bench service --quick (routing over the bare proxy), if time is left.
# (Server CPU per request, drvs-bench fusion --parts cost, is measured on 2 cores as well.)
# Each step's limit is its run's time on 16 cores with room; all of them end inside DEADLINE_S.
set -uo pipefail
cd "$(dirname "$0")/.."

#: Pinned as this repository's .venv has them (pyproject.toml's bounds), for CPython 3.12 on x86-64.
WHEELS=(
  grpcio==1.85.3 grpcio-health-checking==1.81.1 grpcio-reflection==1.81.1 grpcio-tools==1.80.0
  protobuf==6.33.6 shapely==2.2.0 cryptography==50.0.2 cffi==2.1.1 pycparser==2.23 aetcd==1.0.0
  # the ros2 job: Cyclone DDS (its CLI's rich-click is not needed) and rosbags with what it needs
  cyclonedds==11.0.1 rosbags==0.11.9 apsw==3.54.1.0 backports.zstd==1.8.0 lz4==4.4.5 ruamel.yaml==0.19.1
)
#: The runs end by then (seconds from the start of `run`), inside the device's 600 s a command.
DEADLINE_S=${DRVS_DEVICE_DEADLINE_S:-570}
PLATFORMS=(manylinux_2_34_x86_64 manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64
  manylinux2014_x86_64 manylinux1_x86_64)

prepare() {
  mkdir -p .whl
  local platform_args=()
  for p in "${PLATFORMS[@]}"; do platform_args+=(--platform "$p"); done
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --abi cp312 --abi abi3 --abi none "${platform_args[@]}" -d .whl "${WHEELS[@]}" || exit 1
  # etcd for the shared registry (--workers, the cluster benchmark): Debian's package, unpacked there.
  (cd .whl && apt-get download -q etcd-server >/dev/null) || exit 1
  # The wheels install together for 3.12 (a check of versions and platforms here, nothing installed).
  python3 -m pip install -q --dry-run --no-index --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp "${platform_args[@]}" --target /tmp/drvs-wheel-check .whl/*.whl || exit 1
  du -sh .whl
}

# environment DIR: sets out, work, log, py and started for a job writing into DIR; installs the
# wheels and unpacks etcd on the device.
environment() {
  out=${1:-${OUT:?give DIR or set OUT}}
  mkdir -p "$out"
  work=$(mktemp -d /tmp/drvs-capacity.XXXXXX)
  log="$out/capacity.log"
  if [ "${DRVS_DEVICE_LOCAL:-}" = 1 ]; then
    py=${DRVS_VENV:-.venv}/bin/python
  else
    py=python3
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
      .whl/*.whl >>"$log" 2>&1 || { echo "the wheels did not install" | tee -a "$log"; exit 1; }
    dpkg -x .whl/etcd-server_*.deb /tmp/etcd >>"$log" 2>&1 || { echo "etcd did not unpack" | tee -a "$log"; exit 1; }
    export PATH=/tmp/etcd/usr/bin:$PATH
    export PYTHONPATH=/tmp/site
  fi
  export PYTHONPATH=$PWD/src:$PWD/benchmarks${PYTHONPATH:+:$PYTHONPATH}
  export PYTHONUNBUFFERED=1
  started=$SECONDS
  {
    echo "# $(date -u +%FT%TZ) $(nproc) cores, $(uname -m), $("$py" --version 2>&1)"
    "$py" -c 'import grpc, google.protobuf, numpy, cv2, shapely; print("grpcio", grpc.__version__, "protobuf",
google.protobuf.__version__, "numpy", numpy.__version__, "opencv", cv2.__version__, "shapely", shapely.__version__)'
    command -v etcd && etcd --version | head -1
  } >>"$log" 2>&1
}

# step NAME LIMIT_S ARGS...: one drvs-bench run into $work/NAME, cut at LIMIT_S or where the job's
# DEADLINE_S would pass (the device's command limit is 600 s), results packed after it.
step() {
  local name=$1 limit=$2 left=$((DEADLINE_S - (SECONDS - started)))
  shift 2
  [ "$left" -lt "$limit" ] && limit=$left
  if [ "$limit" -lt 20 ]; then
    echo "## $name: left out, ${left} s left" >>"$log"
    return
  fi
  echo "## $name (limit ${limit} s, at $((SECONDS - started)) s): drvs-bench $*" >>"$log"
  timeout -k 10 "$limit" "$py" -m drvs_bench.cli "$@" --out "$work/$name" >>"$log" 2>&1
  echo "## $name: exit $? after $((SECONDS - started)) s" >>"$log"
  tar czf "$out/capacity.tgz" -C "$work" . 2>>"$log"
}

run() {
  local out work log py started
  environment "$@"
  step sweep-per-camera 150 load --sweep --robots 16 --sweep-max 128 --seconds 6 --warmup 2 --workers 8
  step sweep-fused 130 load --sweep --delivery fused --robots 8 --sweep-max 128 --seconds 6 --warmup 2 --workers 8
  # found DIR: the robots at capacity the sweep in DIR found (nothing if it found none).
  found() {
    "$py" - "$1" <<'EOF'
import json, pathlib, sys
for path in sorted(pathlib.Path(sys.argv[1]).glob("*.json")):
    sweep = json.loads(path.read_text()).get("sweep") or {}
    if sweep.get("capacity_robots"):
        print(sweep["capacity_robots"])
        break
EOF
  }
  local capacity fused
  capacity=$(found "$work/sweep-per-camera")
  fused=$(found "$work/sweep-fused")
  echo "## the capacity found: per camera ${capacity:-none}, fused ${fused:-none} robots" >>"$log"
  step overload-per-camera 80 load --overload 2,4 --robots "${capacity:-25}" --seconds 8 --warmup 2 --workers 12
  step load-100 45 load --robots 100 --seconds 10 --warmup 3 --workers 12
  step cluster-workers 120 cluster --parts throughput --workers-list 1,2,4,8 --rounds 1
  step overload-fused-unary 60 load --delivery fused-unary --overload 2,4 --robots "${fused:-8}" --seconds 8 \
    --warmup 2 --workers 12
  step service 100 service --quick --rounds 1
  echo "# done after $((SECONDS - started)) s" >>"$log"
  rm -rf "$work"
}

# The ROS 2 bridge's CPU a snapshot beside its DDS floor (docs/benchmarks.md, "drvs-bench ros2"):
# paced at 50 Hz, so as long here as anywhere (--quick about 30 s, the full run about 220 s).
ros2() {
  local out work log py started
  environment "$@"
  step ros2-quick 90 ros2 --quick
  step ros2 400 ros2
  echo "# done after $((SECONDS - started)) s" >>"$log"
  rm -rf "$work"
}

case "${1:-}" in
  prepare) prepare ;;
  run) shift; run "$@" ;;
  ros2) shift; ros2 "$@" ;;
  *) echo "usage: scripts/device-capacity.sh prepare | run [DIR] | ros2 [DIR]" >&2; exit 2 ;;
esac
