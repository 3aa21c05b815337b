#!/usr/bin/env bash
# Builds the crawler images offline: release binaries with cargo here, staged with the
# libtorch libraries the learner links, then `docker build` on a base image.
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

context=deploy/.context
rm -rf "$context"
mkdir -p "$context/bin" "$context/lib"
for binary in actor learner eval plot render; do
    cp "$CARGO_TARGET_DIR/release/$binary" "$context/bin/"
    strip "$context/bin/$binary"
done
# Every shared library the learner resolves outside the system's own directories: libtorch
# and what it links (libgomp, and the CUDA runtime stubs the PyPI build references).
ldd "$CARGO_TARGET_DIR/release/learner" | awk '$3 ~ /^\// && $3 !~ /^\/(usr\/)?lib/ {print $3}' |
    while read -r library; do cp -L "$library" "$context/lib/"; done
cp -r configs "$context/configs"
cp deploy/learner-entrypoint.sh "$context/"

for image in actor learner; do
    docker build --quiet --build-arg BASE_IMAGE="$BASE_IMAGE" -f "deploy/Dockerfile.$image" \
        -t "crawler-$image:$tag" "$context" >/dev/null
    size=$(docker image inspect "crawler-$image:$tag" --format '{{.Size}}')
    echo "crawler-$image:$tag $(awk -v s="$size" 'BEGIN {printf "%.1f MB", s/1e6}') (base $BASE_IMAGE)"
done
