"""Each speed switch against the readable default it replaces, per AR-MAML meta-iteration: the
``bench_speed_options`` comparison under ``turns`` in ``benchmarks/workloads.yaml``
(``timing.compare_in_turns``).

A switch stays in the code only while this benchmark shows it saving at least 10 % of a
meta-iteration of the benchmark it is meant for (docs/speed-options.md). For every switch two
trainers of ``method=ar_maml`` on its benchmark, one with the switch and one without, run their
warm-up iterations (which compile, for the compile switches), then take turns.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_speed_options.py [--rounds 9] [--calls 10]
[--no-compile]``; it writes its table to its section of docs/benchmarks.md and of
docs/speed-options.md.
"""

from timing import compare_in_turns

if __name__ == "__main__":
    compare_in_turns("bench_speed_options")
