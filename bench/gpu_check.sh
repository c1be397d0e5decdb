#!/usr/bin/env bash
# Issue 17's measurements on a lent GPU machine, in one call of the device tool (under its
# 10-minute limit), after `bash bench/gpu_prepare.sh` here:
#
#   run(command="bash bench/gpu_check.sh", carry=[".whl", ".gl"], timeout_s=600)
#
# Steps, in this order (GPU_CHECK_STEPS picks some; each is cut at its own cap, and a step is
# skipped once fewer than 30 s are left before GPU_CHECK_SECONDS, default 575, have passed;
# the device tool's limit is 600 s of the command's wall time):
#   env        the GPU, torch, the GL renderer that MuJoCo's EGL context gets, core count, the
#              disk's write speed (1 GiB with fsync in data/ and /tmp), and whether igzip
#              compresses to the development machine's bytes (bench/deflate_identity.py)
#   inference  bench/inference.py: rainbench-yolo11s at 960 px, batch 64, 128 frames (eval
#              images/s, the fp16 forward pass, ultralytics' predict, the shard reader alone in
#              one process and in its worker processes; target >= 800 images/s from shards);
#              ONNX and Darknet, CPU paths, left out; each figure printed as it is measured
#   agreement  bench/backend_agreement.py --fp32 on the paper clip with jeon2022 rain (generated
#              by the step into data/agreement): batched backend against ultralytics' predict,
#              AP@0.5 within 0.002 per class, and the same in fp32 (what fp16 makes of it)
#   paper      `rainbench paper --workers 14` with both shipped models and both rain models,
#              timed (target <= 60 s), each phase's time printed as it ends; its report comes
#              back when it finishes
#   pieces-cpu the paper clip (jeon2022) in 4 and in 8 pieces with the statistics on the CPU
#              (no torch import, no CUDA context a worker), each against its own bare loops
#   dataset    bench/dataset.py end to end: the paper clip, jeon2022 (target <= 3.0x the bare
#              loop) and physical with the weather following the rate (<= 4.0x), one worker
#   profile    bench/generate_profile.py: where one process's generation time goes, stage by
#              stage, wall and CPU (the paper clip with jeon2022, its statistics on the GPU;
#              the same with the statistics on the CPU, and with the shard written to
#              /dev/shm instead of the disk; 40 frames of it with physical, with the default 4
#              and then 8 frames in flight; 13 frames on one thread, as one of 16 pieces), and
#              the clip in 16 pieces from the parent's side (when they were joined, what joining
#              cost); then jeon2022 and physical again with OpenCV on one thread
#              (OPENCV_FOR_THREADS_NUM=1: are its threads inside 16 pool threads oversubscribed?)
#   stats      bench/stats_device.py: one frame's per-rate statistics on the GPU (torch) against
#              the CPU path on every core, in the same run (issue 17, item 3)
#   pieces     the same as dataset with 16 workers: the clip in 16 pieces, each its own GL context
#   scaling    bench/dataset.py scaling: 16 workers on 16 scenes against 1 worker, 50 frames,
#              11 rates (target >= 10x)
#   scaling-cpu  the same with the statistics on the CPU (--device cpu): 5.5x with them on the
#              GPU on 2026-11-27, 16 processes each with its own CUDA context on one GPU
# The third run (2026-11-27, second session) measured everything up to the agreement step, which
# was cut; the paper step has never finished. What that run measured now comes last.
# Everything it prints goes to $OUT/check.log too; JSON and the report go to $OUT (at most 8 files).
# Locally (no install, the project's venv): GPU_CHECK_PYTHON=.venv/bin/python GPU_CHECK_INSTALL=0
set -uo pipefail
cd "$(dirname "$0")/.."
# It installs wheels and GL packages into this machine (bench/gpu_env.sh): only where a GPU is
if [[ ${GPU_CHECK_INSTALL:-1} != 0 ]] && ! nvidia-smi -L > /dev/null 2>&1; then
    echo "gpu_check: skipped: no NVIDIA GPU here (nvidia-smi -L failed) to install for; run it through the device tool, or locally with GPU_CHECK_INSTALL=0"
    exit 0
fi

OUT=${OUT:-results/gpu-check}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/check.log") 2>&1
start=$(date +%s)
deadline=$((start + ${GPU_CHECK_SECONDS:-575}))
steps=${GPU_CHECK_STEPS:-"env inference agreement paper pieces-cpu dataset profile stats pieces scaling scaling-cpu"}
source bench/gpu_env.sh
echo "== installed in $(($(date +%s) - start)) s"

step() {  # step NAME CAP_SECONDS COMMAND...
    local name=$1 cap=$2
    shift 2
    [[ " $steps " == *" $name "* ]] || return 0
    local left=$((deadline - $(date +%s)))
    if ((left < 30)); then
        echo "== $name: skipped, ${left} s left"
        return 0
    fi
    ((cap > left)) && cap=$left
    echo "== $name (at most $cap s)"
    local t0 rc
    t0=$(date +%s.%N)
    timeout "$cap" "$@"
    rc=$?
    echo "== $name: exit $rc after $(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }') s"
}

cat > /tmp/gpu_check_env.py <<'EOF'
import os, platform
import torch, mujoco
from OpenGL import GL
context = mujoco.GLContext(64, 64)
context.make_current()
print("gl renderer:", GL.glGetString(GL.GL_RENDERER).decode())
context.free()
print("python", platform.python_version(), "torch", torch.__version__, "cuda",
      torch.cuda.is_available() and torch.cuda.get_device_name(0), "mujoco", mujoco.__version__,
      "cores", os.cpu_count())
EOF

if [[ " $steps " == *" env "* ]]; then
    { nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null \
          || echo "no nvidia-smi"
      step env 60 "$python" /tmp/gpu_check_env.py
      # igzip (the shard writer) picks its code by CPU features: the same bytes as here?
      step env 30 "$python" bench/deflate_identity.py
      # the paper clip's shard is about 1.5 GB (2 200 deflated images): what writing it costs
      for folder in data /tmp; do
          mkdir -p "$folder"
          echo "disk write, 1 GiB with fsync, in $folder: $(dd if=/dev/zero of="$folder/gpu_check_dd" \
              bs=1M count=1024 conv=fsync 2>&1 | tail -1)"
          rm -f "$folder/gpu_check_dd"
      done
      df -h data /tmp | tail -n +2; } | tee "$OUT/env.txt"
fi
step inference 150 "$python" bench/inference.py --weights rainbench-yolo11s --imgsz 960 \
    --images 128 --batch 64 --repeats 1 --skip onnx,darknet --json "$OUT/inference.json"
step agreement 60 "$python" -m rainbench.cli generate --out data/agreement --rates 0:100:10 \
    --workers 14 --quiet
step agreement 150 "$python" bench/backend_agreement.py --weights rainbench-yolo11s --fp32 \
    --data data/agreement --json "$OUT/agreement.json"
# the paper step's time is the figure of the target (<= 60 s)
step paper 300 "$python" -m rainbench.cli paper --workers 14 --data data/paper --out results/paper
if [[ " $steps " == *" paper "* && -f results/paper/report.md ]]; then
    cp results/paper/report.md "$OUT/paper_report.md"
fi
# one process is GIL-bound (4.8 of 16 cores busy) and each worker with GPU statistics pays torch's
# import and a CUDA context (4 s): a few pieces with the statistics on the CPU instead?
step pieces-cpu 60 "$python" bench/dataset.py --e2e-repeats 1 --skip weather,scaling,reader --workers 4 --device cpu \
    --json "$OUT/dataset_pieces4_cpu.json"
step pieces-cpu 60 "$python" bench/dataset.py --e2e-repeats 1 --skip weather,scaling,reader --workers 8 --device cpu \
    --json "$OUT/dataset_pieces8_cpu.json"
step dataset 150 "$python" bench/dataset.py --e2e-repeats 1 --skip scaling,reader --json "$OUT/dataset.json"
# the profiles' tables are in check.log ($OUT returns at most 8 files)
step profile 60 "$python" bench/generate_profile.py --rain-model jeon2022
step profile 45 "$python" bench/generate_profile.py --rain-model jeon2022 --device cpu
step profile 45 "$python" bench/generate_profile.py --rain-model jeon2022 --out /dev/shm
step profile 60 "$python" bench/generate_profile.py --rain-model physical --frames 40
# each physical frame's weather rain is one thread's serial work: does feeding more frames pay?
step profile 45 "$python" bench/generate_profile.py --rain-model physical --frames 40 --frames-in-flight 8
step profile 30 "$python" bench/generate_profile.py --frames 13 --threads 1  # one of 16 pieces
step profile 60 "$python" bench/generate_profile.py --workers 16  # the 16 pieces, joined
# OpenCV's own threads inside 16 pool threads (oversubscribed?): the same two runs with one each
step profile 45 env OPENCV_FOR_THREADS_NUM=1 "$python" bench/generate_profile.py --rain-model jeon2022
step profile 45 env OPENCV_FOR_THREADS_NUM=1 "$python" bench/generate_profile.py --rain-model physical --frames 40
step stats 40 "$python" bench/stats_device.py --frames 3
step pieces 120 "$python" bench/dataset.py --e2e-repeats 1 --skip scaling,reader --workers 16 --json "$OUT/dataset_pieces.json"
step scaling 200 "$python" bench/dataset.py --skip e2e,weather,reader --scaling-workers 16 \
    --scaling-frames 50 --scaling-rates 0:100:10 --json "$OUT/scaling.json"
# the same with the statistics on the CPU: do 16 CUDA contexts on one GPU hold the workers back?
step scaling-cpu 200 "$python" bench/dataset.py --skip e2e,weather,reader --scaling-workers 16 \
    --scaling-frames 50 --scaling-rates 0:100:10 --scaling-device cpu --json "$OUT/scaling_cpu.json"
echo "== done in $(($(date +%s) - start)) s"
