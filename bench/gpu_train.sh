#!/usr/bin/env bash
# Train one recipe on a lent GPU machine in one call of the device tool (issue 19's small rain
# models, issue 15's small model), after `bash bench/gpu_prepare.sh` here:
#
#   run(command="bash bench/gpu_train.sh rainbench-yolo11s-rain", carry=[".whl", ".gl"],
#       timeout_s=600)
#
# Runs `rainbench train --recipe RECIPE --workers 14` (cut at GPU_TRAIN_SECONDS, default 540;
# a cut run resumes from its last checkpoint when the same command runs again on the same warm
# machine). What comes back in $OUT: train.log, the model card RECIPE.json, and the weights
# RECIPE.pt split into 15 MiB parts (the tool returns files of at most 16 MiB); put them
# together here with
#   cat <files_at>/RECIPE.pt.part-* > eval/weights/RECIPE.pt
# Once the tree with the wheels is over the tool's 64 MiB (each small model adds 18 MiB), keep
# only the weights the recipe starts from: `GPU_WEIGHTS=rainbench-yolo11s bash
# bench/gpu_prepare.sh` for a twin (its init_weights), `GPU_WEIGHTS=none` for a model trained
# from scratch; `bash bench/gpu_prepare.sh --restore` afterwards.
set -uo pipefail
cd "$(dirname "$0")/.."
recipe=${1:?usage: bash bench/gpu_train.sh RECIPE}
OUT=${OUT:-results/gpu-train}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/train.log") 2>&1
start=$(date +%s)
source bench/gpu_env.sh
echo "== installed in $(($(date +%s) - start)) s"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"

timeout "${GPU_TRAIN_SECONDS:-540}" "$python" -m rainbench.cli train --recipe "$recipe" \
    --out "runs/$recipe" --workers 14
rc=$?
echo "== train: exit $rc after $(($(date +%s) - start)) s"
if [[ -f "runs/$recipe/$recipe.pt" ]]; then
    cp "runs/$recipe/$recipe.json" "$OUT/" 2>/dev/null
    split -b 15M -d "runs/$recipe/$recipe.pt" "$OUT/$recipe.pt.part-"
    sha256sum "runs/$recipe/$recipe.pt"
fi
exit $rc
