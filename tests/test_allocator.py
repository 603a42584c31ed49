"""``trainer.keep_freed_memory``: glibc keeps freed blocks, which changes where memory comes from
and no value of a run. Each check runs in its own process, since the setting is process-wide."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")

ROOT = Path(__file__).resolve().parents[1]
TRAIN = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]

FAULTS = """
import resource, sys, torch
from armeta_rl.allocator import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):  # glibc's own thresholds adapt to the first blocks freed
    torch.ones(12 << 20).sum()
before = faults()
for _ in range(20):
    torch.ones(12 << 20).sum()  # 48 MiB, allocated, written and freed
print(faults() - before)
"""


def page_faults(mode: str) -> int:
    """Minor page faults of 20 allocations of a 48 MiB tensor, after 3 warm-up allocations."""
    result = subprocess.run([sys.executable, "-c", FAULTS, mode], capture_output=True, text=True,
                            check=True)
    return int(result.stdout)


def test_freed_blocks_are_reused_instead_of_faulted_in_again():
    """Relative, so that it holds whatever page size the kernel faults in (transparent huge
    pages make both counts smaller). Memory pressure from other processes (a second test suite
    on the machine) can fault kept pages in again, never fewer: the least of up to three runs
    measures the allocator."""
    returned = page_faults("default")
    assert returned > 0  # glibc's defaults hand each block back to the kernel
    kept = page_faults("keep")
    for _ in range(2):
        if kept * 4 < returned:
            break
        kept = min(kept, page_faults("keep"))
    assert kept * 4 < returned


PEAK = """
import resource, torch
from benchmarks.timing import as_trained, trimmed_above
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def peak():  # 384 MiB held at once, then freed at once, as an iteration's peak is
    blocks = [torch.ones(12 << 20) for _ in range(8)]
    return sum(b[0] for b in blocks)
def rounds(fn):  # after three warm-up rounds: the heap grows to the peak over the first
    for _ in range(3):
        fn()
    before = faults()
    for _ in range(5):
        fn()
    return faults() - before
as_trained()  # keep_freed_memory(), as armeta-train sets it
print(rounds(trimmed_above(peak, 256 << 20)), rounds(peak))
"""


def test_a_peak_freed_at_once_is_kept_and_a_harness_row_trims_it_for_its_own_calls():
    """An iteration's peak freed at once (384 MiB): a finite trim threshold below it (256 MiB, a
    benchmark row's ``trim_threshold``, ``timing.trimmed_above``) hands the excess back to the
    kernel and faults it in again at every round, while :func:`keep_freed_memory`'s default
    keeps it, in the calls after that row's too. Minor page faults of 5 rounds after three
    warm-up rounds, in a process of its own; relative, and run again up to twice while memory
    pressure from other processes blurs it, as above."""
    for _ in range(3):
        result = subprocess.run([sys.executable, "-c", PEAK], capture_output=True, text=True,
                                check=True, cwd=ROOT)
        trimmed, kept = map(int, result.stdout.split())
        if kept * 4 < trimmed:
            break
    assert kept * 4 < trimmed


def test_a_seeded_run_is_the_same_with_and_without_it(tmp_path):
    def evaluation(keep: bool) -> dict:
        out = tmp_path / str(keep)
        subprocess.run(
            [*TRAIN, "benchmark=point_nav", "trainer.iterations=2", "trainer.meta_batch=2",
             "benchmark.collector.episodes=2", "benchmark.collector.max_steps=10",
             "eval.n_tasks=2", "trainer.progress=false", "trainer.density_every=0", "seed=7",
             "logger=none", f"trainer.keep_freed_memory={str(keep).lower()}",
             f"hydra.run.dir={out}"],
            capture_output=True, text=True, check=True, timeout=300,
        )
        return json.loads((out / "eval.json").read_text())

    assert evaluation(True) == evaluation(False)
