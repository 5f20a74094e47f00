#!/usr/bin/env bash
# Everything this project wants from a lent GPU, as one command of the device tool (10 minutes per command, 15 per
# session, start-up included). Each step is bounded and writes its log under $OUT (the device tool brings back 8
# files: this writes 8); the last lines of each are printed too. Run from the repository root with the Python that
# holds torch, triton, transformers and pytest (the GPU image's python3: no network, no [dev] extra):
#
#     OUT=/tmp/gpu benchmarks/gpu_check.sh          # at most 9.0 minutes (the steps' limits) on an H100 or H200
#     SKIP="bench doctor" OUT=/tmp/gpu benchmarks/gpu_check.sh   # leave steps out (default: SKIP=tilings)
#     SKIP= OUT=/tmp/gpu benchmarks/gpu_check.sh    # everything, the kernels' tilings too (about 10.5 minutes)
#
# Timings run alone on the GPU; the checks run side by side (correctness does not mind sharing the GPU):
# 1. alone: the benchmark, "auto" against the torch path, eager and graph, π0 and π0.5, batch 1, 2 and 8 (eager "auto"
#    runs the persistent launch at batch 1 and 2, five fused launches per layer elsewhere), with each row's GPU
#    activities, GPU time and its 30 longest kinds of kernel, and the host's side of it (its time to the last launch
#    and its waits on the device before that: where eager's host time goes);
# 2. together: doctor (every sampling path at full size against its reference, sampling_kernels="persistent" too),
#    the GPU tests (tests/test_cuda.py), the fused kernels' tests on real kernels (tests/test_kernels.py, the persistent
#    launch's sampling included), and issue 37's persistent experiments against their references (which compiles what
#    step 3 times into triton's disk cache; with tilings, every tiling too);
# 3. alone: the step GEMMs against cuBLAS (GB/s); an Euler step's 18 layers as one persistent launch against today's
#    90 (benchmarks/persistent_layers.py: its tilings, then where one launch's time went, phase by phase, from the
#    timeline its tiles stamp); π0's benchmark again with sampling_kernels="triton" and "persistent" (five launches per
#    layer against one per step, eager and graph, batch 1, 2 and 3: "auto" takes the persistent launch eagerly up to
#    PERSISTENT_EAGER_BATCH = 2, and batch 3 says whether that cut is right; the MLP half alone,
#    benchmarks/persistent_mlp.py, is left out); with tilings, the kernels' tilings (benchmarks/kernel_sweep.py: every
#    candidate timed and checked against the reference, the fastest written to $OUT/tilings.json, then π0 and π0.5
#    sampled with them; measured on an H200 on 2026-11-27); and π0-FAST's decoding, fused against the modules,
#    eager and replayed as hand-captured CUDA graphs. (benchmarks/eager_host.py, eager's host time, is left out.)
set -u
OUT="${OUT:-/tmp/pi0-torch-gpu-check}"
PY="${PY:-python3}"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"  # (benchmarks/*.py import pi0_torch)

step() {  # step NAME SECONDS COMMAND...: appends to $OUT/NAME.log (nothing where $SKIP names it)
    local name="$1" limit="$2"
    shift 2
    case " ${SKIP-tilings} " in *" $name "*) return ;; esac
    local start=$SECONDS
    printf '\n== %s (at most %s s): %s\n' "$name" "$limit" "$*" >> "$OUT/$name.log"
    timeout --signal=INT --kill-after=10 "$limit" "$@" >> "$OUT/$name.log" 2>&1
    printf 'exit %s after %s s: %s\n' "$?" "$((SECONDS - start))" "$*" | tee -a "$OUT/$name.log"
}

show() {  # show NAME: the end of its log
    [ -f "$OUT/$1.log" ] || return 0
    printf '\n---- %s\n' "$1"
    tail -n "${TAIL:-40}" "$OUT/$1.log"
}

{ date; nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv,noheader
  "$PY" -c "import torch, triton, transformers; print('torch', torch.__version__, 'triton', triton.__version__, 'transformers', transformers.__version__)"
} 2>&1 | tee "$OUT/bench.log"  # (the versions head the benchmark's log: 8 files come back, no more)

# 1. alone
step bench 150 "$PY" -m pi0_torch.cli bench --device cuda --presets pi0,pi05 --dtypes bfloat16 --cameras 3 --batches 1,2,8 \
    --kernels auto,torch --repeats 10 --kernel-table 30
[ -f "$OUT/bench.log" ] && grep -v '^      ' "$OUT/bench.log" | tail -n 25

# 2. together
step doctor 200 "$PY" -m pi0_torch.cli doctor --full --device cuda &
step gpu-tests 200 "$PY" -m pytest -q -s -p no:cacheprovider -m gpu tests/test_cuda.py &
# (the shared-memory and direct-launch tests compile for an RTX 4090 on the CPU, as in CI; here the real launches say it;
#  the persistent experiments' test is their --check below)
step kernel-tests 200 "$PY" -m pytest -q -p no:cacheprovider tests/test_kernels.py \
    -k "not shared_memory and not direct_launches and not persistent_experiments" &
for shard in 0 1 2 3 4 5 6 7; do
    step tilings 190 "$PY" benchmarks/kernel_sweep.py --compile-only --shard "$shard/8" &
done
step persistent-check 190 "$PY" benchmarks/persistent_mlp.py --check &
step persistent-check 190 "$PY" benchmarks/persistent_layers.py --check &
wait
show doctor
show gpu-tests
TAIL=8 show kernel-tests
grep -h "against the reference\|outputs NaN\|^exit" "$OUT/persistent-check.log"

# 3. alone
step sweep 20 "$PY" -m pi0_torch.cli bench --device cuda --skip-generate --gemms --presets pi0 --batches 1,8 --repeats 10
step sweep 50 "$PY" benchmarks/persistent_layers.py --bench
step bench 75 "$PY" -m pi0_torch.cli bench --device cuda --presets pi0 --dtypes bfloat16 --cameras 3 --batches 1,2,3 \
    --kernels triton,persistent --repeats 10 --kernel-table 15
step tilings 100 "$PY" benchmarks/kernel_sweep.py --write "$OUT/tilings.json" --bench
step fast-bench 45 "$PY" -m pi0_torch.cli bench --device cuda --skip-generate --fast --fast-presets pi0_fast \
    --dtypes bfloat16 --batches 1 --kernels auto,torch --repeats 3
TAIL=70 show sweep
printf '\n---- bench, sampling_kernels="triton" and "persistent"\n'
grep -v '^      ' "$OUT/bench.log" | tail -n 14
TAIL=40 show tilings
TAIL=8 show fast-bench
printf '\nlogs in %s\n' "$OUT"
