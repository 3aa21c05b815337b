#!/usr/bin/env bash
# Builds the crawler images offline: release binaries with cargo here, staged with the
# libtorch libraries the learner links (stage-binaries.sh), then deploy/Dockerfile's `actor`
# and `learner` targets with BINARIES=prebuilt. Where images can be pulled,
# `docker compose build` builds the same targets from source instead (deploy/README.md).
#   BASE_IMAGE   the base (default: debian:bookworm-slim when it is present locally, else a
#                local debootstrap image made by make-base-image.sh). The binaries link this
#                machine's glibc: use a base at least as new (bookworm: 2.36).
#   TAG          image tag (default latest): crawler-learner:$TAG, crawler-actor:$TAG
# Prints each image's size.
set -euo pipefail
cd "$(dirname "$0")/.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/crawler-target}"
tag="${TAG:-latest}"
if [[ -z "${BASE_IMAGE:-}" ]]; then
    if docker image inspect debian:bookworm-slim >/dev/null 2>&1; then
        BASE_IMAGE=debian:bookworm-slim
    else
        deploy/make-base-image.sh crawler-base:bookworm
        BASE_IMAGE=crawler-base:bookworm
    fi
fi

scripts/install-libtorch-cpu.sh >&2
cargo build --release --bins >&2

deploy/stage-binaries.sh "$CARGO_TARGET_DIR/release" deploy/prebuilt

for image in actor learner; do
    # BUILDER_IMAGE too is the local base: a legacy builder enters the source stage (which
    # does nothing for prebuilt binaries) and must not pull a Rust image for it.
    docker build --quiet --target "$image" --build-arg BINARIES=prebuilt \
        --build-arg BUILDER_IMAGE="$BASE_IMAGE" --build-arg RUNTIME_IMAGE="$BASE_IMAGE" \
        -f deploy/Dockerfile -t "crawler-$image:$tag" . >/dev/null
    size=$(docker image inspect "crawler-$image:$tag" --format '{{.Size}}')
    echo "crawler-$image:$tag $(awk -v s="$size" 'BEGIN {printf "%.1f MB", s/1e6}') (base $BASE_IMAGE)"
done
