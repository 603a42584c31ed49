#!/usr/bin/env bash
# The GPU check, for a lent GPU machine: the CUDA and MuJoCo Warp tests, beside the GPU
# comparisons of benchmarks/workloads.yaml (gpu_meta: meta-iterations on the CPU and on CUDA;
# gpu_warp: the MuJoCo Warp families), each in its own process under its own time limit, so that
# a hang or a crash loses only its own part (a comparison writes its docs/benchmarks.md section
# after every benchmark). Logs and the summary go to ${OUT:-/tmp/gpu_check}. Extra arguments go to
# both comparisons (e.g. --tiny --cuda-as cpu: a dry run on any machine; --benchmarks point_nav).
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export OUT="${OUT:-/tmp/gpu_check}" OMP_NUM_THREADS=1 WANDB_MODE=offline WANDB_SILENT=true
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
PYTHON="${PYTHON:-python}"
mkdir -p "$OUT" && cd "$ROOT" || exit 1
WARP_CACHE_PATH="$(mktemp -d)" timeout -k 5 "${TESTS_LIMIT:-240}" "$PYTHON" -m pytest -rfEs \
    -p no:cacheprovider tests/test_ant_goal_warp.py tests/test_warp_families.py \
    tests/test_devices.py >"$OUT/tests.log" 2>&1 &
tests=$!
: >"$OUT/summary.txt"
failed=0
for entry in gpu_meta gpu_warp; do
    timeout -k 5 "${ENTRY_LIMIT:-300}" "$PYTHON" -m benchmarks.timing "$entry" "$@" \
        >>"$OUT/timing.log" 2>&1
    code=$?
    [ "$code" -eq 0 ] || failed=1
    [ "$code" -eq 124 ] && code="124, stopped at its time limit"
    echo "$entry: exit code $code" | tee -a "$OUT/summary.txt"
done
wait "$tests" || failed=1
echo "tests: $(tail -n 1 "$OUT/tests.log")" | tee -a "$OUT/summary.txt"
cp docs/benchmarks.md "$OUT/"
exit "$failed"
