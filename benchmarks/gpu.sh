#!/usr/bin/env bash
# torch-frontend on a CUDA machine: the fused CUDA kernels against the CPU kernels and cv2, the CUDA
# tests, then the pipeline benchmark for
# B in {1, 16, 64, 256} (eager = the capturable CUDA path, and one compiled row with CUDA graphs).
# Writes benchmarks/results/pipeline_cuda.{json,md} (temp + rename). Budget: under 8 minutes on an
# H100-class GPU (tests ~2 min, eager rows ~2 min, the compiled row's graph build ~2-3 min).
#
#   bash benchmarks/gpu.sh            # from the repository root; PY=... to choose the interpreter
#   GPU_COMPILE=0 bash benchmarks/gpu.sh   # skip the compiled row
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-}
if [ -z "$PY" ]; then
  if [ -x .venv/bin/python ]; then PY=.venv/bin/python; else PY=python3; fi
fi
"$PY" - <<'PYEOF'
import sys, torch
if not torch.cuda.is_available():
    sys.exit(f"benchmarks/gpu.sh: no CUDA device visible to torch {torch.__version__}")
print(f"torch {torch.__version__}, {torch.cuda.get_device_name(0)}")
PYEOF
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
start=$(date +%s)
# first: the fused CUDA kernels against the CPU kernels, cv2 and the tensor LK on real pairs (with the
# run-time self-check); benchmarks/results/fused_cuda.json
"$PY" benchmarks/fused_cuda_check.py --device cuda || { echo "gpu.sh: the fused CUDA kernels differ"; exit 1; }
echo "gpu.sh: fused CUDA check $(( $(date +%s) - start )) s"
# every test parametrized over the device has 'cuda' in its id; -x: the first failure stops the run
"$PY" -m pytest -q -x -p no:cacheprovider -k cuda tests/ || { echo "gpu.sh: CUDA tests failed"; exit 1; }
echo "gpu.sh: CUDA tests $(( $(date +%s) - start )) s"
args=(--device cuda --batches 1 16 64 256 --threads 1 --out-name pipeline_cuda)
if [ "${GPU_COMPILE:-1}" != "0" ]; then args+=(--compile); fi
"$PY" benchmarks/bench_pipeline.py "${args[@]}"
echo "gpu.sh: total $(( $(date +%s) - start )) s; results in benchmarks/results/pipeline_cuda.{json,md}"
# the modelled figures of this same tree beside the measured ones (roofline.py runs on a simulated
# device, so it needs no GPU time: skipped where ../shared/tools/cuda_sim is absent)
if [ -f ../shared/tools/cuda_sim/roofline.py ]; then
  "$PY" benchmarks/roofline_report.py run --B 1 16 64 256 --out benchmarks/results/roofline_modelled.json
  "$PY" benchmarks/roofline_report.py beside --measured benchmarks/results/pipeline_cuda.json \
    --modelled benchmarks/results/roofline_modelled.json --out benchmarks/results/pipeline_cuda_vs_model.md
  echo "gpu.sh: measured beside modelled in benchmarks/results/pipeline_cuda_vs_model.md"
else
  echo "gpu.sh: ../shared/tools/cuda_sim/roofline.py not found: no modelled figures beside the measured ones"
fi
