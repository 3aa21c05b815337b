#!/usr/bin/env bash
# Installs a CPU-only libtorch 2.13.0 (the version tch =0.26.0 binds) from PyPI's torch wheel,
# then points the project's `.libtorch` symlink at it, which `.cargo/config.toml` hands to
# torch-sys as LIBTORCH. Idempotent: a finished install is reused.
#
# Why a wheel: PyPI is the one registry every machine of ours reaches. The wheel is a CUDA build,
# but we keep only the CPU libraries plus the two small CUDA runtime libraries that
# libtorch_cpu.so lists as DT_NEEDED (they load without a GPU or a driver).
#
# Usage: scripts/install-libtorch-cpu.sh [PREFIX]   (default: $HOME/.cache/tch-libtorch-2.13.0)
set -euo pipefail
TORCH_VERSION=2.13.0
PREFIX="${1:-$HOME/.cache/tch-libtorch-$TORCH_VERSION}"
repo_root="$(cd "$(dirname "$0")/.." && pwd)"

link_into_repo() {
  ln -sfn "$PREFIX" "$repo_root/.libtorch"
  echo "libtorch: $repo_root/.libtorch -> $PREFIX" >&2
}

if [ -f "$PREFIX/.complete" ]; then
  echo "libtorch $TORCH_VERSION already installed at $PREFIX" >&2
  link_into_repo
  exit 0
fi

command -v python3 >/dev/null || { echo "error: python3 with pip is needed to fetch the torch wheel" >&2; exit 1; }

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
# Exact wheels, pinned by hash. The cp311 tag is forced so the result does not depend on the
# host's python: only the C++ libraries are used. --no-deps skips ~2 GB of other nvidia wheels.
cat > "$tmp/requirements.txt" <<REQ
torch==$TORCH_VERSION --hash=sha256:60fcdcb2f3876e21146cb4524ef06397d727ca9ad5f020818547e25075fe3cb7
nvidia-cuda-runtime==13.0.96 --hash=sha256:7f82250d7782aa23b6cfe765ecc7db554bd3c2870c43f3d1821f1d18aebf0548
nvidia-cuda-cupti==13.0.85 --hash=sha256:4eb01c08e859bf924d222250d2e8f8b8ff6d3db4721288cf35d14252a4d933c8
REQ
echo "libtorch: downloading torch $TORCH_VERSION wheel (about 1 GB, once)" >&2
python3 -m pip download --quiet --no-deps --no-cache-dir --only-binary=:all: --require-hashes \
  --python-version 3.11 --implementation cp --abi cp311 \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_25_x86_64 --platform manylinux_2_17_x86_64 \
  -d "$tmp/wheels" -r "$tmp/requirements.txt"

rm -rf "$PREFIX.partial"
mkdir -p "$PREFIX.partial"
python3 - "$tmp/wheels" "$PREFIX.partial" <<'PY'
import glob, os, sys, zipfile
src, dst = sys.argv[1], sys.argv[2]
keep = {
    "torch/lib/libc10.so", "torch/lib/libtorch_cpu.so", "torch/lib/libgomp.so.1",
    "nvidia/cu13/lib/libcudart.so.13", "nvidia/cu13/lib/libcupti.so.13",
}
count = 0
for wheel in glob.glob(os.path.join(src, "*.whl")):
    with zipfile.ZipFile(wheel) as archive:
        for member in archive.infolist():
            header = member.filename.startswith("torch/include/") and not member.is_dir()
            if member.filename in keep or header:
                archive.extract(member, dst)
                count += 1
missing = sorted(f for f in keep if not os.path.exists(os.path.join(dst, f)))
if missing:
    sys.exit(f"error: the wheels lack {missing}; was the pinned version changed?")
print(f"libtorch: extracted {count} files", file=sys.stderr)
PY
# tch's build script always links -ltorch. The wheel's libtorch.so is a stub that pulls in
# libtorch_cuda.so and ~15 nvidia libraries, so point -ltorch at the CPU library instead.
ln -s libtorch_cpu.so "$PREFIX.partial/torch/lib/libtorch.so"
# torch-sys reads this file to check the version.
echo "$TORCH_VERSION" > "$PREFIX.partial/torch/build-version"
# libtorch_cpu.so carries RPATH $ORIGIN/../../nvidia/cu13/lib, so this layout resolves
# libcudart/libcupti with no LD_LIBRARY_PATH entry.
touch "$PREFIX.partial/.complete"
rm -rf "$PREFIX"
mv "$PREFIX.partial" "$PREFIX"
echo "libtorch: installed at $PREFIX ($(du -sh "$PREFIX" | cut -f1))" >&2
link_into_repo
