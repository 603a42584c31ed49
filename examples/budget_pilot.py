"""Choose a meta-RL budget from a pilot: does the learner adapt, and from which iteration?

One MAML run is trained in stages (``trainer.stop_at``, then ``resume=``: bit-identical to an
uninterrupted run), and after each stage ``armeta-eval`` scores it on p0, which reports the
adaptation gain (return after the inner step − before, paired on the same episodes) with its
standard error over tasks. The pilot's table (gain, its ratio to its standard error, the adapted
return per stage), its training curve and a figure go into ``--out``.

Run (the HalfCheetah-Vel pilot of docs/meta-rl.md, about 15 minutes on one core)::

    OMP_NUM_THREADS=1 python examples/budget_pilot.py --run runs/pilot --out docs/results/pilot \\
        --stages 150 200 250 300 400 500 -- benchmark=half_cheetah_vel method=maml seed=100 \\
        trainer.meta_batch=20 benchmark.collector.episodes=10 benchmark.collector.max_steps=100 \\
        benchmark.collector.make_env.threads=1 learner.maml_trpo.hvp_episodes=5 \\
        eval.n_tasks=50 eval.rollouts=4 trainer.checkpoint_every=25

``--report-only`` rebuilds the outputs from the run directory's ``eval_at_<iteration>.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from armeta_rl.cli import evaluate, train
from armeta_rl.reproduce.curves import run_curve, write_curves
from armeta_rl.trainers.evaluation import adapts, read_report


def train_in_stages(run: Path, stages: list[int], overrides: list[str]) -> int:
    """Train to each stage and score p0 there (``eval_at_<stage>.json``), skipping stages done,
    with ``armeta-train`` and ``armeta-eval``; their exit code (0 when all went well)."""
    for stage in stages:
        report = run / f"eval_at_{stage}.json"
        if report.is_file():
            continue
        start = ([f"resume={run}"] if (run / "config.yaml").is_file()
                 else [*overrides, f"hydra.run.dir={run}"])
        code = train([*start, f"trainer.iterations={stages[-1]}", f"trainer.stop_at={stage}",
                      "trainer.progress=false"])
        code = code or evaluate([f"learner={run}", f"out={report}"])
        if code:
            return code
    return 0


def stage_rows(run: Path) -> list[dict]:
    """Per scored stage: iteration, adapted return and its s.e., gain and its s.e."""
    rows = []
    for path in run.glob("eval_at_*.json"):
        section = read_report(path, below=run)["initial"]
        adaptation = section["adaptation"]
        rows.append({"iteration": int(path.stem.rsplit("_", 1)[1]), "adapted": section["mean"],
                     "adapted_sem": section["sem"], "gain": adaptation["gain"],
                     "gain_sem": adaptation["gain_sem"], "improved": adaptation["improved"],
                     "tasks": section["n_tasks"]})
    return sorted(rows, key=lambda r: r["iteration"])


def report(run: Path, out: Path) -> str:
    """The pilot's table (Markdown), its training curve (``pilot_curves.csv.gz``) and figure
    (``pilot.png``) into ``out``; returns the table."""
    out.mkdir(parents=True, exist_ok=True)
    rows = stage_rows(run)
    curve = [{"benchmark": "pilot", "run": "maml", "seed": 0, "iteration": i, **values}
             for i, values in sorted(run_curve(run).items())]
    write_curves(curve, out / "pilot_curves.csv.gz")
    figure = Figure(figsize=(9, 3.4), layout="constrained")
    FigureCanvasAgg(figure)
    gain_ax, return_ax = figure.subplots(1, 2)
    window = 10
    points = [(r["iteration"], r["gain"]) for r in curve if r.get("gain") is not None]
    means = [(points[i + window - 1][0], sum(g for _, g in points[i:i + window]) / window)
             for i in range(0, len(points) - window + 1, window)]
    gain_ax.plot(*zip(*means), label=f"training tasks ({window}-iteration means)")
    gain_ax.errorbar([r["iteration"] for r in rows], [r["gain"] for r in rows],
                     yerr=[2 * r["gain_sem"] for r in rows], fmt="o", capsize=3,
                     label="p0 evaluation ± 2 s.e.")
    gain_ax.axhline(0.0, color="black", linewidth=0.6)
    gain_ax.set_title("adaptation gain (return after − before the inner step)", fontsize=9)
    return_ax.errorbar([r["iteration"] for r in rows], [r["adapted"] for r in rows],
                       yerr=[2 * r["adapted_sem"] for r in rows], fmt="o-", capsize=3)
    return_ax.set_title("p0 return after adaptation ± 2 s.e.", fontsize=9)
    for ax in (gain_ax, return_ax):
        ax.set_xlabel("meta-iteration")
    gain_ax.legend(fontsize=7)
    figure.savefig(out / "pilot.png", dpi=90)
    lines = ["| iteration | p0 return after adaptation | p0 gain ± s.e. | gain / s.e. | "
             "tasks improved | adapts |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['iteration']} | {r['adapted']:.1f} ± {r['adapted_sem']:.1f} | "
              f"{r['gain']:+.1f} ± {r['gain_sem']:.1f} | {r['gain'] / r['gain_sem']:.1f} | "
              f"{r['improved']}/{r['tasks']} | {_yes(adapts(r['gain'], r['gain_sem']))} |"
              for r in rows]
    table = "\n".join(lines)
    (out / "pilot.md").write_text(
        f"# Budget pilot: `{run.name}`\n\nOne MAML run trained in stages and scored on p0 after "
        "each (`examples/budget_pilot.py`): the adaptation gain (return after the inner step − "
        "before, on the same episodes) ± its standard error over tasks, and the return after "
        "adaptation. A stage adapts when its gain is beyond twice its standard error. The run's "
        "training curve, every iteration, is in `pilot_curves.csv.gz`.\n\n"
        f"{table}\n\n![the pilot](pilot.png)\n\nLeft: the gain on the training tasks (means "
        "of 10 iterations of 20 tasks) and on p0's evaluation tasks (± 2 standard errors; the "
        "same 50 tasks at every stage). Right: p0's return after adaptation.\n")
    return table


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="the pilot's run directory")
    parser.add_argument("--out", type=Path, required=True, help="where its report goes")
    parser.add_argument("--stages", type=int, nargs="+", default=[150, 200, 250, 300, 400, 500])
    parser.add_argument("--report-only", action="store_true")
    args, overrides = parser.parse_known_args(argv)
    if not args.report_only:
        code = train_in_stages(args.run, sorted(args.stages),
                               [o for o in overrides if o != "--"])
        if code:
            return code
    print(report(args.run, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
