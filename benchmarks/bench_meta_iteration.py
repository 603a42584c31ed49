"""Milliseconds per meta-iteration of the regression and system-identification games, one thread.

Rows: the full AR-MAML iteration (data collection, leader step, follower losses at θ_{t+1},
adversary update every iteration) with the spline and the planar adversary, and plain MAML with
either batched adaptation (``learner.maml.adaptation``: the benchmark's default is low_rank on the
sinusoid, vmap on system identification), on sinusoid_uniform (25 tasks), pendulum_uniform and
acrobot_uniform (16 tasks × 200 transitions, collection included); and the sinusoid's
second-order meta-gradient computed with a Python loop over tasks instead of ``vmap``.
``--compile`` adds rows with the adversary's flow and/or the leader's loss compiled
(``risk.ar.compile=true``, ``learner.maml.compile=true``). Config overrides may follow on the
command line.

The rows of a benchmark take turns: every row runs ``TURN`` timed iterations, then the next row,
``--turns`` times over. A shared machine runs slower for spells of tens of seconds (up to 1.5x
here); timed one after the other, one row could fall in such a spell and the next one not.
Taking turns spreads the spells over all rows, so rows compare; short turns of consecutive
iterations keep each trainer's data warm in the caches, as in a real run. The yardstick product
is timed between turns, and a turn's yardstick is the mean of the ones before and after it. The
"fast-spell median" is the median iteration of the turns whose yardstick is at most the lower
quartile of the benchmark's turn yardsticks (printed under the table): the code's cost in the
run's fastest spells, steadier than the median of every turn (in a run that is slow throughout,
its fast spells are slow too).

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_meta_iteration.py [--compile] [--turns 10]
[--benchmarks sinusoid_uniform ...]``; it prints the table and writes it to its section of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable

import torch
from hydra import compose, initialize_config_dir
from timing import markdown_table, reference_product_ms, wall_times, write_section

from armeta_rl.allocator import keep_freed_memory
from armeta_rl.cli import config_dir
from armeta_rl.config import TrainerConfig, validate
from armeta_rl.trainers.game import GameTrainer
from armeta_rl.trainers.players import build_players

BENCHMARKS = ("sinusoid_uniform", "pendulum_uniform", "acrobot_uniform")
WARMUP = 10
TURN = 10

Turn = tuple[float, list[float]]
"""One turn of a row: its yardstick in ms and the wall times in seconds of its iterations."""


def summary(turns: list[Turn], fast_yardstick: float
            ) -> tuple[float, float, float, float | None]:
    """Median, interquartile range and minimum in ms of the iterations of every turn, and the
    median of those of the turns whose yardstick is at most ``fast_yardstick`` (``None`` if no
    turn of the row was that fast). On a shared machine the minimum and the fast-spell median are
    the steadiest estimates of the code's own cost."""
    times = [1000 * t for _, turn in turns for t in turn]
    fast = [1000 * t for yardstick, turn in turns if yardstick <= fast_yardstick for t in turn]
    q1, median, q3 = statistics.quantiles(times, n=4)
    return median, q3 - q1, min(times), statistics.median(fast) if fast else None


def taking_turns(rows: dict[str, Callable[[], object]], turns: int) -> dict[str, list[Turn]]:
    """Every row's ``turns`` turns of ``TURN`` calls of its function, the rows taking turns, each
    turn with the mean of the yardsticks measured just before and just after it."""
    turns_of: dict[str, list[Turn]] = {label: [] for label in rows}
    before = reference_product_ms(repeats=5)
    for _ in range(turns):
        for label, fn in rows.items():
            times = wall_times(fn, TURN, warmup=0)
            after = reference_product_ms(repeats=5)
            turns_of[label].append(((before + after) / 2, times))
            before = after
    return turns_of


def trainer_for(method: str, *overrides: str) -> GameTrainer:
    """A trainer for ``method`` on the default benchmark with config ``overrides``."""
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = compose("train", overrides=[f"method={method}", *overrides])
    players = build_players(validate(cfg))
    return GameTrainer(
        players.leader,
        players.principle,
        TrainerConfig(iterations=10**9, meta_batch=cfg.trainer.meta_batch, progress=False),
    )


def looped_meta_gradient(trainer: GameTrainer) -> Callable[[], None]:
    """The same meta-gradient with a Python loop over tasks (the pattern vmap replaces)."""
    leader = trainer.leader
    params = dict(leader.model.named_parameters())

    def step() -> None:
        tasks = trainer.principle.propose(trainer.meta_batch)
        data = leader.collect(tasks)
        support, query = data["support"], data["query"]
        losses = torch.stack([
            leader.query_loss(params, support["x"][k], support["y"][k], query["x"][k],
                              query["y"][k])
            for k in range(len(data))
        ])
        leader.optimizer.zero_grad()
        losses.mean().backward()
        leader.optimizer.step()

    return step


LOOPED = "maml, per-task Python loop"
LEADER, ADVERSARY = "learner.maml.compile=true", "risk.ar.compile=true"
ROWS = (
    ("ar_maml, spline adversary", "ar_maml", ("risk.ar.flow=spline",)),
    ("ar_maml, planar adversary", "ar_maml", ("risk.ar.flow=planar",)),
    ("maml (ERM), vmap adaptation", "maml", ("learner.maml.adaptation=vmap",)),
    ("maml (ERM), low_rank adaptation", "maml", ("learner.maml.adaptation=low_rank",)),
)
COMPILED_ROWS = (
    ("ar_maml, spline adversary compiled", "ar_maml", (ADVERSARY,)),
    ("ar_maml, spline adversary and leader compiled", "ar_maml", (ADVERSARY, LEADER)),
    ("maml (ERM), leader compiled", "maml", (LEADER,)),
)


def main() -> None:
    """Print the table; unknown arguments are config overrides (e.g. ``risk.ar.lam=0.1``)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--benchmarks", nargs="+", default=list(BENCHMARKS), choices=BENCHMARKS)
    parser.add_argument("--compile", action="store_true",
                        help="also time the compiled leader and adversary (inductor); the warm-up "
                             "column then holds the compile time")
    parser.add_argument("--turns", type=int, default=10,
                        help=f"turns of {TURN} timed iterations per row")
    args, extra = parser.parse_known_args()
    if args.turns < 1:
        parser.error(f"--turns must be at least 1, got {args.turns}")
    torch.set_num_threads(1)
    keep_freed_memory()  # as armeta-train does (trainer.keep_freed_memory)
    torch.manual_seed(0)
    rows, yardsticks, fast_yardsticks = [], [], {}
    for benchmark in args.benchmarks:
        iterations, warmups = {}, {}
        for label, method, overrides in ROWS + (COMPILED_ROWS if args.compile else ()):
            trainer = trainer_for(method, f"benchmark={benchmark}", *overrides, *extra)
            warmups[label] = sum(wall_times(trainer.train_iteration, WARMUP, warmup=0))
            iterations[label] = trainer.train_iteration
        if benchmark == "sinusoid_uniform":
            looped = looped_meta_gradient(trainer_for("maml", *extra))
            warmups[LOOPED] = sum(wall_times(looped, WARMUP, warmup=0))
            iterations[LOOPED] = looped
        turns_of = taking_turns(iterations, args.turns)
        turn_yardsticks = [yardstick for turns in turns_of.values() for yardstick, _ in turns]
        yardsticks += turn_yardsticks
        fast_yardsticks[benchmark] = statistics.quantiles(turn_yardsticks, n=4)[0]
        for label, turns in turns_of.items():
            summaries = summary(turns, fast_yardsticks[benchmark])
            rows.append((benchmark, label, *summaries, warmups[label]))
    low, middle, high = min(yardsticks), statistics.median(yardsticks), max(yardsticks)
    table = markdown_table(
        ("benchmark", "meta-iteration", "median ms", "IQR ms", "min ms", "fast-spell median ms",
         f"first {WARMUP} iterations s"),
        [(benchmark, label, f"{median:.1f}", f"{iqr:.1f}", f"{least:.1f}",
          "–" if fast is None else f"{fast:.1f}", f"{warmup:.1f}")
         for benchmark, label, median, iqr, least, fast, warmup in rows])
    spells = "; ".join(f"{benchmark}: turns with a yardstick of at most {yardstick:.2f} ms"
                       for benchmark, yardstick in fast_yardsticks.items())
    body = (f"Second-order MAML, {args.turns} turns of {TURN} iterations per row. Machine "
            f"yardstick (`timing.reference_product_ms`) in the timed turns: median {middle:.2f} "
            f"ms, range {low:.2f}–{high:.2f} ms. Fast spells: {spells}.\n\n{table}")
    print(body)
    write_section("bench_meta_iteration", "Meta-iterations (bench_meta_iteration.py)", body)

if __name__ == "__main__":
    main()
