"""Each speed switch against the readable default it replaces, per AR-MAML meta-iteration.

A switch stays in the code only while this benchmark shows it saving at least 10 % of a
meta-iteration of the benchmark it is meant for (docs/speed-options.md). For every switch the
script builds two trainers of ``method=ar_maml`` on that benchmark, one with the switch and one
without, runs the warm-up iterations (which compile, for the compile switches), then times them
taking turns: ``--turns`` rounds of ``--calls`` iterations of each, so that a shared machine's slow
spells fall on both alike. It reports the median over the rounds of the switch's time as a
fraction of the default's, and the range over the rounds.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_speed_options.py [--no-compile]``; it prints the
table and writes it to its section of docs/benchmarks.md and of docs/speed-options.md.
"""

from __future__ import annotations

import argparse
import statistics

import torch
from timing import (
    DOCS,
    in_turns,
    markdown_table,
    trainer_for,
    turn_medians,
    wall_times,
    write_section,
)

SWITCHES = (
    ("learner.maml.adaptation=low_rank", "sinusoid_uniform", "learner.maml.adaptation=vmap",
     False),
    ("risk.ar.compile=true", "sinusoid_uniform", "risk.ar.compile=false", True),
    ("learner.maml.compile=true", "sinusoid_uniform", "learner.maml.compile=false", True),
    ("learner.maml.compile=true", "pendulum_uniform", "learner.maml.compile=false", True),
    ("benchmark.collector.compile=true", "acrobot_uniform_paper",
     "benchmark.collector.compile=false", True),
)
"""(switch, benchmark, the default it replaces, whether it compiles)."""
WARMUP = 5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--turns", type=int, default=9, help="rounds of alternation")
    parser.add_argument("--calls", type=int, default=10, help="iterations per turn")
    parser.add_argument("--no-compile", action="store_true",
                        help="skip the compile switches (inductor takes minutes to compile)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    rows = []
    for switch, benchmark, default, compiles in SWITCHES:
        if compiles and args.no_compile:
            continue
        reference, _ = trainer_for("method=ar_maml", f"benchmark={benchmark}", default)
        variant, _ = trainer_for("method=ar_maml", f"benchmark={benchmark}", switch)
        warmup = sum(wall_times(variant.train_iteration, WARMUP, warmup=0))
        wall_times(reference.train_iteration, 0, warmup=WARMUP)
        turns, _ = in_turns({"default": reference.train_iteration,
                             "switch": variant.train_iteration}, args.calls, args.turns)
        ref, var = turn_medians(turns["default"]), turn_medians(turns["switch"])
        ratios = [v / r for r, v in zip(ref, var, strict=True)]
        ratio = statistics.median(ratios)
        rows.append((f"`{switch}`", benchmark, f"{1000 * statistics.median(ref):.1f}",
                     f"{1000 * statistics.median(var):.1f}", f"{ratio:.2f}",
                     f"{min(ratios):.2f}–{max(ratios):.2f}", f"{100 * (1 - ratio):.0f} %",
                     f"{warmup:.0f}"))
        print(rows[-1], flush=True)
    body = (f"AR-MAML meta-iterations with each switch against the default, taking turns "
            f"({args.turns} rounds of {args.calls} iterations each, after {WARMUP} warm-up "
            f"iterations, whose time includes the compile, short when torch's on-disk compile "
            f"cache already holds the graphs; the ms columns are medians over the rounds of each "
            f"turn's median; the ratio is the switch's turn over the default's turn of the same "
            f"round):\n\n"
            + markdown_table(("switch", "benchmark", "default ms", "with switch ms",
                              "time ratio (median)", "ratio range", "saved",
                              f"first {WARMUP} iterations s"), rows))
    print(body)
    title = "Speed switches against the default (bench_speed_options.py)"
    write_section("bench_speed_options", title, body)
    write_section("bench_speed_options", title, body, DOCS / "speed-options.md")


if __name__ == "__main__":
    main()
