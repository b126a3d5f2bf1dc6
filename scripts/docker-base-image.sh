#!/usr/bin/env bash
# Make a local Python base image from Debian with debootstrap, for machines that cannot pull one:
# Debian bookworm (minbase) + python3, python3-venv and ca-certificates, no apt lists or docs.
# The service Dockerfiles take it as BASE_IMAGE (their default, python:3.11-slim, needs a registry).
#
#   scripts/docker-base-image.sh            # build drvs-python:bookworm unless it exists
#   scripts/docker-base-image.sh --force    # build it again
#
# Environment: DRVS_BASE_IMAGE (tag, default drvs-python:bookworm), DRVS_DEBIAN_MIRROR (default: the
# Debian mirror apt uses on this host, else http://deb.debian.org/debian). Needs root, debootstrap
# (installed through apt when missing) and a running Docker daemon.
set -euo pipefail

TAG=${DRVS_BASE_IMAGE:-drvs-python:bookworm}
SUITE=bookworm
force=0
case "${1:-}" in
  --force) force=1 ;;
  "") ;;
  *) echo "usage: $0 [--force]" >&2; exit 2 ;;
esac

say() { echo "docker-base-image: $*" >&2; }
die() { say "ERROR: $*"; exit 1; }

docker info >/dev/null 2>&1 || die "no Docker daemon answers (start dockerd first)"
if [ "$force" = 0 ] && docker image inspect "$TAG" >/dev/null 2>&1; then
  say "$TAG exists; nothing to do (--force builds it again)"
  exit 0
fi
[ "$(id -u)" = 0 ] || die "debootstrap needs root"

# The mirror apt already uses here (deb822 .sources or one-line sources.list), so no other host is needed.
mirror=${DRVS_DEBIAN_MIRROR:-}
if [ -z "$mirror" ]; then
  mirror=$(cat /etc/apt/sources.list.d/*.sources 2>/dev/null |
    awk '/^URIs:/ {u=$2} /^Suites:/ && / '"$SUITE"'( |$)/ && u ~ /debian\/?$/ {print u; exit}' || true)
fi
if [ -z "$mirror" ]; then
  mirror=$(grep -hsE '^deb +(\[[^]]*\] +)?https?://[^ ]+ +'"$SUITE"' ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list |
    awk '{for (i = 2; i <= NF; i++) if ($i ~ /^https?:/) {print $i; exit}}' || true)
fi
mirror=${mirror:-http://deb.debian.org/debian}
mirror=${mirror%/}

if ! command -v debootstrap >/dev/null; then
  say "installing debootstrap"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap >/dev/null
fi

work=$(mktemp -d /var/tmp/drvs-rootfs.XXXXXX)
cleanup() {
  # debootstrap mounts proc/sys inside the target; never delete through a live mount.
  for m in proc sys dev/pts dev; do
    mountpoint -q "$work/rootfs/$m" 2>/dev/null && umount -l "$work/rootfs/$m" || true
  done
  rm -rf --one-file-system "$work"
}
trap cleanup EXIT

rootfs=$work/rootfs
start=$(date +%s)
say "debootstrap $SUITE (minbase + python3) from $mirror"
if ! debootstrap --variant=minbase --components=main \
  --include=python3,python3-venv,ca-certificates \
  "$SUITE" "$rootfs" "$mirror" >"$work/debootstrap.log" 2>&1; then
  tail -30 "$work/debootstrap.log" >&2
  die "debootstrap failed"
fi

# Keep it small: no apt lists or caches, no docs, man pages or translations (copyright files stay),
# and tell dpkg not to install them in later layers either.
cat >"$rootfs/etc/dpkg/dpkg.cfg.d/01-docker-minimal" <<'EOF'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
EOF
cat >"$rootfs/etc/apt/apt.conf.d/01-docker-clean" <<'EOF'
APT::Install-Recommends "false";
APT::Install-Suggests "false";
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/*.bin || true"; };
EOF
cat >"$rootfs/etc/apt/sources.list" <<EOF
deb $mirror $SUITE main
deb $mirror $SUITE-updates main
deb http://deb.debian.org/debian-security $SUITE-security main
EOF
rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/* "$rootfs"/var/cache/debconf/*-old \
  "$rootfs"/var/log/* "$rootfs"/tmp/* "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/*
find "$rootfs/usr/share/doc" -mindepth 1 -not -name copyright -not -type d -delete 2>/dev/null || true
find "$rootfs/usr/share/doc" -mindepth 1 -type d -empty -delete 2>/dev/null || true
find "$rootfs/usr/share/locale" -mindepth 1 -maxdepth 1 -not -name locale.alias -exec rm -rf {} + 2>/dev/null || true
# The image's hostname and resolver come from Docker.
: >"$rootfs/etc/hostname"
rm -f "$rootfs/etc/resolv.conf"

python_version=$(chroot "$rootfs" python3 -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])')
tar --numeric-owner -C "$rootfs" -c . | docker import \
  --change 'ENV LANG=C.UTF-8' \
  --change 'CMD ["python3"]' \
  --change "LABEL org.opencontainers.image.description=\"Debian $SUITE minbase + python3 $python_version, made by scripts/docker-base-image.sh\"" \
  - "$TAG" >/dev/null
size=$(docker image inspect -f '{{.Size}}' "$TAG")
say "$TAG: Debian $SUITE, python $python_version, $((size / 1000000)) MB, in $(($(date +%s) - start)) s"
