#!/usr/bin/env bash
# Build a Debian base image with Python from scratch, without any registry: debootstrap a root filesystem
# and `docker import` it. For air-gapped build hosts and for tests/deploy/test_compose.py; elsewhere the
# Dockerfiles' default base (python:3.11-slim) is simpler.
#
#   sudo deploy/make-base-image.sh swimm-base:bookworm [SUITE] [MIRROR]
#   docker build -f deploy/Dockerfile.sim --build-arg BASE_IMAGE=swimm-base:bookworm -t swimm-sim .
#
# Needs root, debootstrap and a Debian mirror: by default the one this host's apt already uses (its first
# Debian source), so a host behind a local mirror or proxy builds the same way; pass another as MIRROR.
# Debian bookworm's python3 is 3.11, the version swimm is tested with.
set -euo pipefail

tag=${1:?usage: make-base-image.sh TAG [SUITE] [MIRROR]}
suite=${2:-bookworm}

# The first Debian archive URI in this host's apt sources (deb822 .sources files or one-line .list files).
host_mirror() {
  cat /etc/apt/sources.list.d/*.sources 2>/dev/null | sed -n 's/^URIs:[[:space:]]*\([^[:space:]]*\).*/\1/p' | grep -v security | head -n 1 || true
  cat /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null | awk '$1 == "deb" && $2 !~ /security/ {print $2; exit}' || true
}
mirror=${3:-$(host_mirror | head -n 1)}
[ -n "$mirror" ] || { echo "no Debian mirror in this host's apt sources: pass one as MIRROR" >&2; exit 2; }

root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT
debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
  "$suite" "$root" "$mirror" >/dev/null
# Package lists and caches only make the image bigger; Dockerfiles run apt-get update themselves.
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/archives/*.deb
tar -C "$root" -c . | docker import \
  --change 'ENV LANG=C.UTF-8' \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'CMD ["python3"]' \
  - "$tag" >/dev/null
echo "built $tag ($suite from $mirror)"
