#!/usr/bin/env bash
# The GPU check (benchmarks/gpu_check.py, whose docstring says what it assumes of the machine;
# its workloads are the lines under gpu_check in benchmarks/workloads.yaml): it writes the GPU section of
# docs/benchmarks.md and everything else under ${OUT:-/tmp/gpu_check}. This wrapper puts the
# repository root and benchmarks/ on PYTHONPATH (in front of what is there, e.g. the carried
# wheels' --target directory), runs one thread and bounds the whole run: --budget seconds
# (default 430) for the parts and a hard stop 40 s later (under 8 minutes by default). Extra
# arguments go to `gpu_check.py run` (e.g. --budget 300, --only point_nav, --dry-run).
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export OUT="${OUT:-/tmp/gpu_check}" OMP_NUM_THREADS=1 WANDB_MODE=offline WANDB_SILENT=true HYDRA_FULL_ERROR=1
export PYTHONPATH="$ROOT:$ROOT/benchmarks${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
mkdir -p "$OUT" && cd "$ROOT" || exit 1
LIMIT=470
for ((i = 1; i < $#; i++)); do
    if [ "${!i}" = "--budget" ]; then j=$((i + 1)); LIMIT=$(( ${!j%.*} + 40 )); fi
done
timeout -k 10 "$LIMIT" "${PYTHON:-python}" benchmarks/gpu_check.py run --out "$OUT" \
    --command-line "benchmarks/gpu_check.sh $*" "$@"
code=$?
[ "$code" -eq 0 ] || echo "gpu_check: exit code $code (124: the hard stop at $LIMIT s)" \
    | tee -a "$OUT/summary.txt"
exit "$code"
