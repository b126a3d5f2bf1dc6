#!/usr/bin/env bash
# Build the simulated office's images (compose.yaml) without an image registry or an index in the
# containers: a local Debian base image (scripts/docker-base-image.sh), the pinned runtime wheels
# (services/requirements.txt; services/requirements-sim.txt, the sim extra's) downloaded on the host
# into services/wheelhouse/ for the base image's Python and platform, then `docker compose build`
# with --no-index. Unchanged inputs rebuild nothing.
#
#   scripts/docker-build.sh          # base image if missing, wheels if missing, images
#   scripts/docker-build.sh --pin    # only rewrite services/requirements*.txt from the set-up .venv
#
# Environment: DRVS_BASE_IMAGE (default drvs-python:bookworm; python:3.11-slim where a registry can be
# reached), DRVS_PIP_ARGS (default --no-index), PYTHON (the host Python whose pip downloads the
# wheels; default .venv/bin/python, set up by ./run setup when missing).
set -euo pipefail
cd "$(dirname "$0")/.."

say() { echo "docker-build: $*" >&2; }
die() { say "ERROR: $*"; exit 1; }

export DRVS_BASE_IMAGE=${DRVS_BASE_IMAGE:-drvs-python:bookworm}
export DRVS_PIP_ARGS=${DRVS_PIP_ARGS---no-index}
WHEELHOUSE=services/wheelhouse
REQUIREMENTS=services/requirements.txt
REQUIREMENTS_SIM=services/requirements-sim.txt
REQUIREMENTS_ETCD=services/requirements-etcd.txt
REQUIREMENTS_LIVE=services/requirements-live.txt

host_python() {
  if [ -n "${PYTHON:-}" ]; then echo "$PYTHON"; return; fi
  [ -x .venv/bin/python ] || ./run setup >&2
  echo .venv/bin/python
}

pin() {
  local py
  py=$(host_python)
  "$py" - "$REQUIREMENTS" "$REQUIREMENTS_SIM" "$REQUIREMENTS_ETCD" "$REQUIREMENTS_LIVE" <<'PY'
"""The installed versions of drvs's runtime dependencies and theirs: the pins. The first file gets
the base package's (every image), the second what the sim extra adds (the simulator's images)."""
import importlib.metadata as md
import sys
from pathlib import Path

from packaging.requirements import Requirement


def closure(extra: str) -> dict[str, str]:
    pins: dict[str, str] = {}
    todo = [(Requirement(r), extra) for r in md.requires("drvs") or []]
    while todo:
        req, wanted = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": wanted}):
            continue
        if req.name == "drvs":  # an extra that includes others (sim includes live): theirs too
            todo += [(Requirement(r), inner) for inner in req.extras for r in md.requires("drvs") or []]
            continue
        dist = md.distribution(req.name)
        name = dist.metadata["Name"]
        if name.lower() in {p.lower() for p in pins}:
            continue
        pins[name] = dist.version
        todo += [(Requirement(r), "") for r in dist.requires or []]
    return pins


def write(path: Path, pins: dict[str, str]) -> None:
    header = [line for line in path.read_text().splitlines() if line.startswith("#")] if path.exists() else []
    body = [f"{name}=={version}" for name, version in sorted(pins.items(), key=lambda kv: kv[0].lower())]
    path.write_text("\n".join(header + body) + "\n")
    print(f"{path}: {len(body)} pins", file=sys.stderr)


base = closure("")
write(Path(sys.argv[1]), base)
base_names = {name.lower() for name in base}
write(Path(sys.argv[2]), {n: v for n, v in closure("sim").items() if n.lower() not in base_names})
write(Path(sys.argv[3]), {n: v for n, v in closure("etcd").items() if n.lower() not in base_names})
write(Path(sys.argv[4]), {n: v for n, v in closure("live").items() if n.lower() not in base_names})
PY
}

if [ "${1:-}" = "--pin" ]; then pin; exit 0; fi
[ $# -eq 0 ] || die "usage: $0 [--pin]"

docker info >/dev/null 2>&1 || die "no Docker daemon answers (start dockerd, or run scripts/docker-office-test.sh)"
docker compose version >/dev/null 2>&1 || die "'docker compose' (the v2 plugin) is missing"

if [ "$DRVS_BASE_IMAGE" = drvs-python:bookworm ]; then
  scripts/docker-base-image.sh
fi

if [ "$DRVS_PIP_ARGS" = --no-index ]; then
  # The base image's Python and platform decide which wheels fit.
  read -r pyver glibc arch < <(docker run --rm --network none "$DRVS_BASE_IMAGE" python3 -c \
    'import platform, sys; print("%d.%d" % sys.version_info[:2], platform.libc_ver()[1], platform.machine())')
  [ -n "${arch:-}" ] || die "cannot read Python, glibc and machine from $DRVS_BASE_IMAGE"
  platforms=()
  for ((minor = ${glibc#*.}; minor >= 17; minor--)); do platforms+=(--platform "manylinux_2_${minor}_${arch}"); done
  platforms+=(--platform "manylinux2014_${arch}")
  py=$(host_python)
  say "wheels for Python $pyver, glibc $glibc, $arch into $WHEELHOUSE/"
  start=$(date +%s)
  log=$(mktemp)
  if ! "$py" -m pip download --disable-pip-version-check --dest "$WHEELHOUSE" \
    --only-binary :all: --python-version "$pyver" --implementation cp --abi "cp${pyver/./}" "${platforms[@]}" \
    -r "$REQUIREMENTS" -r "$REQUIREMENTS_SIM" -r "$REQUIREMENTS_ETCD" -r "$REQUIREMENTS_LIVE" "setuptools>=77" wheel >"$log" 2>&1; then
    tail -20 "$log" >&2
    rm -f "$log"
    die "pip download failed (is PyPI reachable from this host?)"
  fi
  rm -f "$log"
  say "$(find "$WHEELHOUSE" -name '*.whl' | wc -l) wheels, $(du -sm "$WHEELHOUSE" | cut -f1) MB, in $(($(date +%s) - start)) s"
fi

# compose.yaml's ha profile runs Debian's etcd: the host's binary (./run installs etcd-server),
# which needs only libc, goes into the image.
etcd_bin=$(command -v etcd || true)
if [ -n "$etcd_bin" ]; then
  install -m 0755 "$etcd_bin" "$WHEELHOUSE/etcd"
else
  say "no etcd on this host: the etcd image installs Debian's etcd-server with apt"
  rm -f "$WHEELHOUSE/etcd"
fi

# Without buildx (Debian's docker.io has none) compose warns that it cannot use bake, and builds
# through the engine's own BuildKit: the same result.
say "docker compose build (base $DRVS_BASE_IMAGE${DRVS_PIP_ARGS:+, pip $DRVS_PIP_ARGS})"
start=$(date +%s)
docker compose --profile ha build
say "images built in $(($(date +%s) - start)) s:"
docker images --format '{{.Repository}}:{{.Tag}}\t{{.Size}}' | grep -E '^drvs-' | sort >&2
