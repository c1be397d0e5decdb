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
# The shipped weights are most of the tree (39 MiB of the 44 tracked; each small model 18 MiB).
# GPU_WEIGHTS="NAME ..." keeps only the named shipped models in the tree for the call and moves
# the others' files to .aside/ (ignored, so they do not travel): a training needs none of them
# (GPU_WEIGHTS=none), the check needs rainbench-yolo11s and the models its paper step evaluates
# (those present). Put them back after the call with `bash bench/gpu_prepare.sh --restore`
# (also done first by every run of this script); until then git shows them as deleted.
#
# Usage:  [GPU_WEIGHTS="rainbench-yolo11s rainbench-yolo11n"] bash bench/gpu_prepare.sh
# Then:   run(command="bash bench/gpu_check.sh", carry=[".whl", ".gl"], timeout_s=600)
#    or:  run(command="bash bench/gpu_train.sh RECIPE", carry=[".whl", ".gl"], timeout_s=600)
# After:  bash bench/gpu_prepare.sh --restore
set -euo pipefail
cd "$(dirname "$0")/.."

weights=eval/weights
restore() {  # the weights set aside by an earlier run back into the tree
    if [[ -d .aside/$weights ]]; then
        find ".aside/$weights" -type f -exec mv -n -t "$weights" {} +
        rmdir ".aside/$weights" 2>/dev/null || true
        echo "gpu_prepare: the weights set aside are back in $weights" \
             "($(git status --short "$weights" | grep -c '^ D' || true) tracked files still missing)"
    fi
}
restore
if [[ "${1:-}" == "--restore" ]]; then
    exit 0
fi

exclude=.git/info/exclude
mkdir -p "$(dirname "$exclude")"
for path in /.whl/ /.gl/ /.aside/; do
    grep -qxF "$path" "$exclude" 2>/dev/null || echo "$path" >> "$exclude"
done

rm -rf .whl .gl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    mujoco==4.0.0 mujoco-core==4.0.0 PyOpenGL==3.1.10 ultralytics-opencv-headless==8.4.190 \
    ultralytics-thop==2.2.3 ultralytics-platform==0.1.99 deflate==0.9.0 isal==1.9.1 \
    pycocotools==2.0.11

mkdir -p .gl /tmp/rainbench-apt/partial
apt_options=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64
             -oDir::State::Lists=/tmp/rainbench-apt)
apt-get "${apt_options[@]}" update -qq
(cd .gl && apt-get "${apt_options[@]}" download -qq libegl1 libglvnd0 libopengl0 libgl1 \
    libglx0 libgles2)

if [[ -n "${GPU_WEIGHTS:-}" ]]; then
    mkdir -p ".aside/$weights"
    for file in "$weights"/*.pt "$weights"/*.onnx; do
        [[ -e "$file" ]] || continue
        name=$(basename "$file"); name=${name%.*}
        [[ " $GPU_WEIGHTS " == *" $name "* ]] || mv "$file" ".aside/$weights/"
    done
    echo "gpu_prepare: weights in the tree: $(cd "$weights" && ls *.pt 2>/dev/null | tr '\n' ' ')" \
         "(the rest in .aside/; bash bench/gpu_prepare.sh --restore puts them back)"
fi
tree_kib=$( (git ls-files -z --cached --others --exclude-standard; find .whl .gl -type f -print0) \
            | while IFS= read -r -d '' file; do [[ -f "$file" ]] && printf '%s\0' "$file"; done \
            | du -ck --files0-from=- | tail -1 | cut -f1)
echo "wheels: $(du -sh .whl | cut -f1), GL: $(du -sh .gl | cut -f1), tree with both: $((tree_kib / 1024)) MiB (limit 64)"
if (( tree_kib > 64 * 1024 )); then
    echo "gpu_prepare: the tree with .whl and .gl is over 64 MiB: the device tool would refuse it" >&2
    exit 1
fi
