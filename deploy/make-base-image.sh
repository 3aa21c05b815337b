#!/usr/bin/env bash
# Builds a minimal Debian bookworm base image locally, for machines that cannot pull one:
# debootstrap (minbase) into a temporary directory, pruned of documentation, locales and apt
# caches, then `docker import`ed. Elsewhere, use a standard Debian slim image instead
# (BASE_IMAGE in build-images.sh).
# Usage: deploy/make-base-image.sh [TAG]   (default crawler-base:bookworm)
set -euo pipefail
tag="${1:-crawler-base:bookworm}"
if docker image inspect "$tag" >/dev/null 2>&1; then
    echo "base image: $tag exists" >&2
    exit 0
fi
if ! command -v debootstrap >/dev/null; then
    echo "base image: installing debootstrap" >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap >&2 ||
        { echo "base image: debootstrap is missing and could not be installed (apt-get install debootstrap)" >&2; exit 1; }
fi
rootfs="$(mktemp -d)"
trap 'rm -rf "$rootfs"' EXIT
echo "base image: debootstrap bookworm into $rootfs" >&2
debootstrap --variant=minbase bookworm "$rootfs" >&2
rm -rf "$rootfs"/usr/share/{doc,man,info,locale}/* "$rootfs"/var/cache/apt/* "$rootfs"/var/lib/apt/lists/* \
    "$rootfs"/var/log/*
tar -C "$rootfs" -c . | docker import --change 'CMD ["/bin/bash"]' - "$tag" >/dev/null
echo "base image: $tag ($(docker image inspect "$tag" --format '{{.Size}}' | awk '{printf "%.1f MB", $1/1e6}'))" >&2
