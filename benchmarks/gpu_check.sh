#!/usr/bin/env bash
# The GPU check of issue 37 (and issue 36 item 6): tests on CUDA and MuJoCo Warp, meta-iterations
# of every benchmark family on the CPU and on CUDA, Ant with MuJoCo Warp; it writes the GPU section
# of docs/benchmarks.md. Everything is in benchmarks/gpu_check.py (its docstring says what each
# part does); this wrapper only sets up the environment and bounds the whole run.
#
# Device-side assumptions, explicit:
#   * run from anywhere; it works in the repository root, which is NOT pip-installed: the root
#     (armeta_rl, hydra_plugins) and benchmarks/ are put on PYTHONPATH in front of what PYTHONPATH
#     already holds (e.g. the `pip install --target DIR` directory of the carried wheels: torchrl,
#     tensordict, normflows, hydra-core, omegaconf, gymnasium, mujoco, mujoco-warp, warp-lang);
#     no console scripts are used (python -m ..., python -c "from armeta_rl.cli import train; train()");
#   * torch with CUDA is preinstalled; pytest, tqdm and matplotlib must be importable as well (the
#     first part, preflight, names any module that is missing);
#   * no network; results go to ${OUT:-/tmp/gpu_check}: gpu_check.log, tests.log, results.jsonl,
#     summary.txt and benchmarks.md (a copy of docs/benchmarks.md with the GPU section);
#   * the whole check is bounded: --budget seconds (default 320) for the parts, each with its own
#     time limit, and a hard stop at 360 s for the lot (past --budget + 40 s if one is given).
#     Extra arguments go to
#     `gpu_check.py run` (e.g. --budget 300, --benchmarks point_nav).
# Without CUDA the CUDA parts are skipped with that reason and the rest runs.
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${OUT:-/tmp/gpu_check}"
mkdir -p "$OUT"
cd "$ROOT" || exit 1
export OUT
export PYTHONPATH="$ROOT:$ROOT/benchmarks${PYTHONPATH:+:$PYTHONPATH}"
export OMP_NUM_THREADS=1 WANDB_MODE=offline WANDB_SILENT=true PYTHONUNBUFFERED=1
PYTHON="${PYTHON:-python}"
echo "gpu_check: repo $ROOT, out $OUT, python $(command -v "$PYTHON"), PYTHONPATH=$PYTHONPATH"
LIMIT=360
for ((i = 1; i <= $#; i++)); do
    if [ "${!i}" = "--budget" ]; then j=$((i + 1)); LIMIT=$(( ${!j%.*} + 40 )); fi
done
timeout -k 10 "$LIMIT" "$PYTHON" benchmarks/gpu_check.py run --out "$OUT" \
    --command-line "benchmarks/gpu_check.sh $*" "$@"
code=$?
if [ "$code" -ne 0 ]; then
    echo "gpu_check: the driver ended with exit code $code (124: the hard stop at $LIMIT s)" \
        | tee -a "$OUT/summary.txt"
fi
exit "$code"
