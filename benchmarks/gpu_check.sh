#!/usr/bin/env bash
# Issue 27's GPU measurements in one call of a lent GPU machine (the `device` tool: minutes are scarce,
# so everything runs from this one prepared script, each step under its own time limit):
#   0. bench_fold_batch.py --device cuda: a training step of one fold alone and of K = 1, 2, 4, 8 folds
#      batched, on the GPU (wall seconds, operators) -> fold_batch-cuda.json (at most 90 s)
#   1. the Suturing-sized whole LOUO at the defaults with --accelerator cuda (bench_train.py --louo-all:
#      simulated and aligned there, the 8 folds batched in one process) -> train_louo_all-ensemble-cuda.json
#   2. if a jigsaws-dev folder is given: Knot Tying's, then Needle Passing's LOUO at the defaults on the GPU
#      (gestures_jigsaws.py, variant "cuda"; rows saved per task): real accuracy next to the CPU rows, to see
#      that batching and float16 cost none
#   nvidia-smi samples the GPU's load every 2 s throughout (gpu_util.csv).
#
#   bash benchmarks/gpu_check.sh OUT_DIR [JIGSAWS_DEV_DIR] [SECONDS]
#
# Everything lands in OUT_DIR (results JSON, one log with a clock on each line; 7 files, the device tool
# returns 8 at most). SECONDS (default 540) bounds
# the whole script. Needs python3 with torch (CUDA) and midas's runtime packages importable.
set -u
out=${1:?usage: gpu_check.sh OUT_DIR [JIGSAWS_DEV_DIR] [SECONDS]}
data=${2:-}
budget=${3:-540}
mkdir -p "$out"
export MIDAS_BENCH_RESULTS=$out PYTHONUNBUFFERED=1
start=$(date +%s)
left() { echo $(( budget - ($(date +%s) - start) )); }
stamp() { while IFS= read -r line; do printf '%s %s\n' "$(date +%H:%M:%S)" "$line"; done; }

nvidia-smi -L
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name(0))" || exit 1
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 2 >"$out/gpu_util.csv" 2>&1 &
smi=$!
trap 'kill $smi 2>/dev/null' EXIT

echo "== batched folds, a step on the GPU (limit 90 s)"
timeout 90 python3 benchmarks/bench_fold_batch.py --device cuda 2>&1 | stamp | tee -a "$out/gpu_check.log" | tail -n 12
echo "== fold_batch exit: ${PIPESTATUS[0]}, $(left) s left"

echo "== Suturing-sized LOUO, --accelerator cuda (limit $(( $(left) * 6 / 10 )) s)"
timeout $(( $(left) * 6 / 10 )) python3 benchmarks/bench_train.py --louo-all --accelerator cuda --prep-jobs 16 2>&1 \
    | stamp | tee -a "$out/gpu_check.log" | tail -n 60
rc=${PIPESTATUS[0]}
echo "== louo-all exit: $rc, $(left) s left"

if [ -n "$data" ] && [ "$(left)" -gt 60 ]; then
    echo "== Knot Tying, Needle Passing LOUO on the GPU (limit $(left) s)"
    timeout "$(left)" python3 benchmarks/gestures_jigsaws.py "$data" --work /tmp/midas-jigsaws-dev --tasks knot_tying,needle_passing \
        --models ensemble --variant cuda --train-args "--accelerator cuda" --jobs 8 \
        --note "ensemble --accelerator cuda: one process, the 8 folds batched (gpu_check.sh)" 2>&1 | stamp | tee -a "$out/gpu_check.log" | tail -n 30
    rc=${PIPESTATUS[0]}
    echo "== jigsaws exit: $rc, $(left) s left"
    rm -f "$out/gestures_jigsaws.md"  # the device returns 8 files at most; the rows are in the JSON
    for task in knot_tying needle_passing; do
        cp /tmp/midas-jigsaws-dev/runs/$task/ensemble--cuda/cv.json "$out/${task}_cuda_cv.json" 2>/dev/null
    done
fi
