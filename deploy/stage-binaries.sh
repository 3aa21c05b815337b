#!/usr/bin/env bash
# Stages what the images need from a release build: the stripped binaries in OUT/bin and, in
# OUT/lib, every shared library the learner resolves outside the system's own directories
# (libtorch and what it links: libgomp, and the CUDA runtime stubs that the PyPI build
# references). Used by build-images.sh on the host and by the Dockerfile's source stage, so
# both paths put the same files in the images.
# Usage: deploy/stage-binaries.sh RELEASE_DIR OUT
set -euo pipefail
release="${1:?usage: stage-binaries.sh RELEASE_DIR OUT}"
out="${2:?usage: stage-binaries.sh RELEASE_DIR OUT}"
rm -rf "$out/bin" "$out/lib"
mkdir -p "$out/bin" "$out/lib"
for binary in actor learner eval average pick plot render; do
    cp "$release/$binary" "$out/bin/"
    strip "$out/bin/$binary"
done
ldd "$release/learner" | awk '$3 ~ /^\// && $3 !~ /^\/(usr\/)?lib/ {print $3}' |
    while read -r library; do cp -L "$library" "$out/lib/"; done
if [[ -z "$(ls "$out/lib")" ]]; then
    echo "stage-binaries: ldd found no libtorch for $release/learner; was it built against scripts/install-libtorch-cpu.sh's install?" >&2
    exit 1
fi
