#!/usr/bin/env bash
# The GPU rows of docs/benchmarks.md in one run (issue 8), sized for ~8 minutes on one H100/H200:
#   1. model_bench at V = 6,890, T = 3: the dense fp32 reference, ours eager and ours compiled
#      (cuDNN attention preferred), with MFU, error vs fp32 and the attention op really run;
#   2. full resolution (Anny `notoes`, 12,272 v) compiled with activation checkpointing: T = 3 at
#      batch 8 and T = 8 at batch 2;
#   3. the memory model against torch.cuda.max_memory_allocated (bench/memory_calibration.py).
# Usage: bash bench/gpu_check.sh [OUT_DIR]   (each section's table also goes to OUT_DIR/*.md)
# Needs torch (CUDA), einops, numpy, pyyaml and trimesh; on a machine without trimesh (pure Python),
# put its wheel in .whl/ first (`pip download --no-deps trimesh==5.2.0 -d .whl`): it is installed
# from there into /tmp/site.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-bench/results/gpu}"
mkdir -p "$out"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONUNBUFFERED=1
python3 - <<'PY'
import torch
print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(), torch.cuda.get_device_capability())
PY
# Dense bf16 peak of the card (H100/H200 SXM: 989 TFLOP/s; A100: 312; V100: 125 in fp16).
peak=$(python3 -c "import torch; n=torch.cuda.get_device_name(); print(989 if ('H100' in n or 'H200' in n) else 312 if 'A100' in n else 125)")
kernels=(--attention-kernels cudnn flash efficient)
python3 bench/model_bench.py --device cuda --vertices 6890 --batch 1 --impl dense-fp32 --peak-tflops "$peak" | tee "$out/reference.md"
python3 bench/model_bench.py --device cuda --vertices 6890 --batch 16 --impl ours ours-compiled --peak-tflops "$peak" \
    "${kernels[@]}" | tee "$out/ours.md"
python3 bench/model_bench.py --device cuda --vertices 12272 --batch 8 --impl ours-compiled --activation-checkpointing \
    --peak-tflops "$peak" "${kernels[@]}" | tee "$out/full_resolution_t3.md"
python3 bench/model_bench.py --device cuda --vertices 12272 --window 8 --batch 2 --impl ours-compiled \
    --activation-checkpointing --peak-tflops "$peak" "${kernels[@]}" | tee "$out/full_resolution_t8.md"
python3 bench/memory_calibration.py --device cuda --steps 3 | tee "$out/memory.md"
