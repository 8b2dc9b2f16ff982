#!/usr/bin/env bash
# The GPU rows of docs/benchmarks.md in one run of about 12 minutes on one H100/H200 (issue 8; the
# 2026-11-26 H100 run of a shorter first version took 6 minutes). The last section gets what is left
# of SECONDS (default 700): give more where the lease allows.
#   1. the dense fp32 reference at V = 6,890, T = 3, B = 1 and 2, also with TF32 matmuls (bench/model_bench.py);
#   2. ours eager at B = 16: cuDNN attention preferred, torch's own preference, and
#      activation checkpointing (memory per sample);
#   3. ours compiled at B = 16 with the faster of the two kernel preferences, with the paper's 8 heads
#      in every stage and with head dim 128 in every stage (heads 8 4 4 2: the kernels' fastest);
#   4. full resolution (Anny `notoes`, 12,272 v) with activation checkpointing: T = 3 at batch 8
#      eager and compiled, T = 8 at batch 8 eager;
#   5. the memory model against torch.cuda.max_memory_allocated (bench/memory_calibration.py);
#   6. compiled with activation checkpointing at B = 16, in whatever time is left.
# Every model_bench row comes with the warm-up (compile) time and the top kernels of a train step.
# Each section has a time limit, so that a slow compile cannot starve the rest; a failed or
# timed-out section is reported and the next one runs.
# Usage: bash bench/gpu_check.sh [OUT_DIR] [SECONDS]   (everything is also appended to OUT_DIR/gpu_check.md)
# Needs torch (CUDA), einops, numpy, pyyaml and trimesh; on a machine without trimesh (pure Python),
# put its wheel in .whl/ first (`pip download --no-deps trimesh==5.2.0 -d .whl`): it is installed
# from there into /tmp/site.
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-bench/results/gpu}"
budget="${2:-700}"
mkdir -p "$out"
log="$out/gpu_check.md"
: >"$log"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONUNBUFFERED=1

section() {  # section TITLE SECONDS COMMAND...: run COMMAND for at most SECONDS, log it under TITLE
  local title=$1 limit=$2
  shift 2
  if [ "$limit" -le 10 ]; then
    echo -e "\n## $title: skipped, out of time" | tee -a "$log"
    return
  fi
  echo -e "\n## $title ($(date -u +%T), limit ${limit} s)\n" | tee -a "$log"
  timeout "$limit" "$@" 2>&1 | tee -a "$log"
  local rc=${PIPESTATUS[0]}
  [ "$rc" -eq 0 ] || echo "exit $rc$([ "$rc" -eq 124 ] && echo ': timed out')" | tee -a "$log"
}

train_ms() {  # the train-step-per-sample cell of the first row of impl $1 in the table on stdin; inf if none
  awk -F'|' -v impl="$1" '$2 ~ "^ *" impl " *$" { v = $9 + 0; print (v > 0 ? v : "inf"); found = 1; exit }
    END { if (!found) print "inf" }'
}

section environment 30 bash -c 'nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv
  python3 -c "import torch; print(torch.__version__, torch.version.cuda, torch.backends.cudnn.version(), torch.cuda.get_device_name(), torch.cuda.get_device_capability())"'
# Dense bf16 peak of the card, for MFU (H100/H200 SXM: 989 TFLOP/s; A100: 312; V100: 125 in fp16).
peak=$(python3 -c "import torch; n=torch.cuda.get_device_name(); print(989 if ('H100' in n or 'H200' in n) else 312 if 'A100' in n else 125)")
model_bench=(python3 bench/model_bench.py --device cuda --peak-tflops "$peak")
bench=("${model_bench[@]}" --vertices 6890)

section "reference: dense fp32 and TF32, V=6890" 120 "${bench[@]}" --impl dense-fp32 dense-tf32 --batch 1 2 --steps 5
section "ours eager, cuDNN attention preferred" 45 "${bench[@]}" --impl ours --batch 16 --steps 5 \
  --attention-kernels cudnn flash efficient
section "ours eager, torch's kernel preference" 45 "${bench[@]}" --impl ours --batch 16 --steps 5
cudnn_ms=$(sed -n '/^## ours eager, cuDNN/,/^## ours eager, torch/p' "$log" | train_ms ours)
default_ms=$(sed -n '/^## ours eager, torch/,$p' "$log" | train_ms ours)
kernels=()
choice="torch's preference"
if python3 -c "import sys; sys.exit(not float('$cudnn_ms') < float('$default_ms'))"; then
  kernels=(--attention-kernels cudnn flash efficient)
  choice="cuDNN preferred"
fi
echo -e "\ntrain step per sample: cuDNN preferred $cudnn_ms ms, torch's preference $default_ms ms; from here on: $choice" \
  | tee -a "$log"
section "ours eager, activation checkpointing" 45 "${bench[@]}" --impl ours --batch 16 --steps 5 \
  --activation-checkpointing "${kernels[@]}"
section "ours compiled" 200 "${bench[@]}" --impl ours-compiled --batch 16 "${kernels[@]}"
section "ours compiled, head dim 128 (heads 8 4 4 2)" 200 "${bench[@]}" --impl ours-compiled --batch 16 \
  --heads 8 4 4 2 "${kernels[@]}"
section "full resolution, eager, activation checkpointing" 80 \
  "${model_bench[@]}" --vertices 12272 --window 3 --batch 8 --steps 3 --impl ours \
  --activation-checkpointing "${kernels[@]}"
section "full resolution, compiled, activation checkpointing" 120 \
  "${model_bench[@]}" --vertices 12272 --window 3 --batch 8 --steps 3 --impl ours-compiled \
  --activation-checkpointing "${kernels[@]}"
section "full resolution T=8, eager, activation checkpointing" 60 \
  "${model_bench[@]}" --vertices 12272 --window 8 --batch 8 --steps 3 --impl ours \
  --activation-checkpointing "${kernels[@]}"
section "memory model vs max_memory_allocated" 110 python3 bench/memory_calibration.py --device cuda --steps 2
section "ours compiled, activation checkpointing" $((budget - SECONDS)) "${bench[@]}" --impl ours-compiled \
  --batch 16 --activation-checkpointing "${kernels[@]}"
echo -e "\ndone in $SECONDS s" | tee -a "$log"
