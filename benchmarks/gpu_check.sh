#!/usr/bin/env bash
# Everything this project wants from a lent GPU, as one command of the device tool (10 minutes per command, 15 per
# session, start-up included). Each step is bounded and writes its log under $OUT (the device tool brings $OUT back);
# the last lines of each are printed too. Run from the repository root with the Python that holds torch, triton,
# transformers and pytest (the GPU image's python3: no network, no [dev] extra):
#
#     OUT=/tmp/gpu benchmarks/gpu_check.sh          # about 9 minutes on an H100 or H200
#
# 1. doctor: every sampling path at full size against its reference (the runbook's first line, docs/gpu.md);
# 2. the GPU tests: tests/test_cuda.py (the fused steps' first-call verification at batch 1, 3 and 8 among them) and
#    the fused kernels' tests on real kernels (tests/test_kernels.py);
# 3. the benchmark: fused steps against the torch path, eager and graph, pi0 and pi0.5, batch 1 and 8, with each row's
#    GPU activities and GPU time; real-time chunking rows;
# 4. the GEMM shapes of a step: cuBLAS against the fused kernels, us and GB/s;
# 5. π0-FAST's decoding at full size: the fused decoded tokens against the modules (eager; last: the step a
#    10-minute command cuts if the others took their whole time).
set -u
OUT="${OUT:-/tmp/pi0-torch-gpu-check}"
PY="${PY:-python3}"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1

step() {  # step NAME SECONDS COMMAND...
    local name="$1" limit="$2"
    shift 2
    printf '\n== %s (at most %s s): %s\n' "$name" "$limit" "$*"
    local start=$SECONDS
    timeout --signal=INT --kill-after=15 "$limit" "$@" > "$OUT/$name.log" 2>&1
    local status=$?
    printf 'exit %s after %s s\n' "$status" "$((SECONDS - start))" | tee -a "$OUT/$name.log"
    tail -n "${TAIL:-45}" "$OUT/$name.log"
}

{ date; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  "$PY" -c "import torch, triton, transformers; print('torch', torch.__version__, 'triton', triton.__version__, 'transformers', transformers.__version__)"
} 2>&1 | tee "$OUT/versions.log"

step doctor 170 "$PY" -m pi0_torch.cli doctor --full --device cuda
step gpu-tests 170 "$PY" -m pytest -q -p no:cacheprovider -m gpu tests/test_cuda.py
# (the shared-memory test compiles for an RTX 4090 on the CPU, as in CI; here the real launches say it)
step kernel-tests 60 "$PY" -m pytest -q -p no:cacheprovider tests/test_kernels.py -k "not shared_memory"
step bench 130 "$PY" -m pi0_torch.cli bench --device cuda --presets pi0,pi05 --dtypes bfloat16 --cameras 3 --batches 1,8 \
    --kernels auto,torch --rtc guidance,conditioning --repeats 10
step gemms 40 "$PY" -m pi0_torch.cli bench --device cuda --skip-generate --gemms --presets pi0 --batches 1,8 --repeats 10
step fast-bench 90 "$PY" -m pi0_torch.cli bench --device cuda --skip-generate --fast --fast-presets pi0_fast --dtypes bfloat16 \
    --batches 1 --kernels auto,torch --repeats 3
printf '\nlogs in %s\n' "$OUT"
