#!/usr/bin/env bash
# Prepare, on this machine, what a lent GPU machine needs to run bench/gpu_check.sh (issue 17).
#
# The GPU machine has python3 3.12 with torch, h5py, numpy, OpenCV, onnxruntime, matplotlib and
# tqdm, and no package registry. This downloads the rest as cp312 manylinux x86-64 wheels into
# .whl/ and the GL dispatch libraries (libglvnd's EGL and OpenGL) as Debian packages into .gl/,
# both ignored by git through .git/info/exclude. Left out, to keep the copied tree under the
# tool's 64 MiB: mujoco-studio and glfw (not imported with MUJOCO_GL=egl), h5py (the image has
# one) and polars (ultralytics imports it only to read back a training run's results.csv).
#
# Usage:  bash bench/gpu_prepare.sh
# Then:   run(command="bash bench/gpu_check.sh", carry=[".whl", ".gl"], timeout_s=600)
#    or:  run(command="bash bench/gpu_train.sh RECIPE", carry=[".whl", ".gl"], timeout_s=600)
set -euo pipefail
cd "$(dirname "$0")/.."

exclude=.git/info/exclude
mkdir -p "$(dirname "$exclude")"
for path in /.whl/ /.gl/; do
    grep -qxF "$path" "$exclude" 2>/dev/null || echo "$path" >> "$exclude"
done

rm -rf .whl .gl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    mujoco==4.0.0 mujoco-core==4.0.0 PyOpenGL==3.1.10 ultralytics-opencv-headless==8.4.190 \
    ultralytics-thop==2.2.3 ultralytics-platform==0.1.99 deflate==0.9.0 pycocotools==2.0.11

mkdir -p .gl /tmp/rainbench-apt/partial
apt_options=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64
             -oDir::State::Lists=/tmp/rainbench-apt)
apt-get "${apt_options[@]}" update -qq
(cd .gl && apt-get "${apt_options[@]}" download -qq libegl1 libglvnd0 libopengl0 libgl1 \
    libglx0 libgles2)

tree_kib=$( (git ls-files -z --cached --others --exclude-standard; find .whl .gl -type f -print0) \
            | du -ck --files0-from=- | tail -1 | cut -f1)
echo "wheels: $(du -sh .whl | cut -f1), GL: $(du -sh .gl | cut -f1), tree with both: $((tree_kib / 1024)) MiB (limit 64)"
if (( tree_kib > 64 * 1024 )); then
    echo "gpu_prepare: the tree with .whl and .gl is over 64 MiB: the device tool would refuse it" >&2
    exit 1
fi
