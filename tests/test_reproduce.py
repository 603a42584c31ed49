"""armeta-reproduce: table1 end to end at the tiny profile (the other experiments:
``tests/test_reproduce_experiments.py``), the aggregation against hand-computed cases, skipping and
resuming of finished runs, a Ray-launched sweep on a local head, and bad input (one line, exit
code 2)."""

import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import armeta_rl.reproduce.plan as plan_module
from armeta_rl.cli.compose import config_dir
from armeta_rl.config import validate
from armeta_rl.devices import machine_name
from armeta_rl.errors import ConfigError
from armeta_rl.reproduce.aggregate import (
    collect,
    curve_over_seeds,
    cvar_curve,
    over_seeds,
    train_seconds,
    write_csv,
)
from armeta_rl.reproduce.cli import (
    MANIFEST,
    SweepClock,
    check_runs,
    main,
    reproduce,
    save_manifest,
)
from armeta_rl.reproduce.plan import PROFILES_FILE, experiment_names, make_plan
from armeta_rl.reproduce.reports import paired, table
from armeta_rl.trainers.run_dir import CSV_LOG_DIR

ROOT = Path(__file__).resolve().parents[1]
REPRODUCE = [sys.executable, "-c", "from armeta_rl.reproduce.cli import main; main()"]


@pytest.fixture(scope="module")
def table1_dir(tmp_path_factory) -> Path:
    """table1's tiny profile on Sinusoid-U, run once for the tests that read it."""
    results = tmp_path_factory.mktemp("table1")
    code = reproduce("table1", "tiny", results, launcher="basic",
                     benchmarks=("sinusoid_uniform",))
    assert code == 0
    return results


def _eval_files(results: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(results.glob("runs/**/eval*.json"))}


def test_table1_runs_end_to_end_and_aggregates(table1_dir):
    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    # 42 evaluations on the three adversaries, 14 on the shift suite (table1.yaml: shifts: all)
    assert len(plan.runs) == 14 and len(plan.attacks) == 2 and len(plan.evals) == 56
    for run in plan.runs:
        report = json.loads((table1_dir / run.subdir / "eval.json").read_text())
        assert report["method"] == run.method and report["benchmark"] == run.benchmark
    # The attack on MAML: an AR-MAML run whose learner is MAML's of the same seed, never trained.
    attack = table1_dir / "runs/sinusoid_uniform/ar_maml-vs-maml/seed1"
    target = table1_dir / "runs/sinusoid_uniform/maml/seed1"
    assert f"frozen_leader: {target}\n" in (attack / "config.yaml").read_text()
    assert (json.loads((attack / "eval.json").read_text())["initial"]
            == json.loads((target / "eval.json").read_text())["initial"])
    attacked = json.loads((table1_dir / "runs/sinusoid_uniform/dr_maml/seed1/eval_vs_maml.json")
                          .read_text())
    assert attacked["adversary"] == str(attack)
    same = json.loads((table1_dir / "runs/sinusoid_uniform/maml/seed1/eval_vs_same_seed.json")
                      .read_text())
    assert same["adversary"].endswith("runs/sinusoid_uniform/ar_maml/seed1")
    shifted = json.loads((table1_dir / "runs/sinusoid_uniform/maml/seed1/eval_vs_next_seed.json")
                         .read_text())
    assert shifted["adversary"].endswith("runs/sinusoid_uniform/ar_maml/seed0")
    # Scored on its own adversary with armeta-eval, AR-MAML gets its eval.json's numbers.
    own = json.loads((table1_dir / "runs/sinusoid_uniform/ar_maml/seed0/eval.json").read_text())
    again = json.loads((table1_dir / "runs/sinusoid_uniform/ar_maml/seed0/eval_vs_same_seed.json")
                       .read_text())
    assert again["adversarial"]["mean"] == own["adversarial"]["mean"]
    text = (table1_dir / "table1.md").read_text()
    assert ("complete: 16/16 training runs (attack runs 2/2) and 56/56 evaluations"
            in text)
    assert "0.499 ± 0.01" in text  # the paper's MAML average beside ours
    assert "| Adversarial (p_φ trained against MAML) |" in text
    machine = machine_name(torch.device("cpu"))
    # the learners' 14 runs and the 2 attack runs
    assert f" Training machines: {machine} (16 runs).\n" in text
    rows = (table1_dir / "table1.csv").read_text().splitlines()
    # p0 of every run, three adversaries and the 7 shifts of the sinusoid suite of every run
    assert len(rows) == 1 + 14 + 42 + 98
    shifted = json.loads((table1_dir / "runs/sinusoid_uniform/maml/seed0/eval_shifts.json")
                         .read_text())
    assert "initial" not in shifted and len([k for k in shifted if k.startswith("shift/")]) == 7


def test_a_sweep_run_equals_the_same_armeta_train_run(table1_dir, tmp_path):
    from armeta_rl.job import Job
    from armeta_rl.trainers.training import run_training
    from conftest import train_config

    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    run = next(r for r in plan.runs if r.method == "ar_maml" and r.seed == 1)
    report = run_training(Job(train_config(*run.command()), tmp_path / "by_hand"), progress=False)
    swept = json.loads((table1_dir / run.subdir / "eval.json").read_text())
    assert json.loads(json.dumps(report)) == swept


@pytest.mark.parametrize("experiment", ["cvar_curves", "scatter"])
def test_experiments_sharing_table1s_runs_only_aggregate(table1_dir, experiment):
    before = _eval_files(table1_dir)
    assert reproduce(experiment, "tiny", table1_dir, launcher="basic",
                     benchmarks=("sinusoid_uniform",)) == 0
    assert _eval_files(table1_dir) == before
    assert (table1_dir / f"{experiment}.png").stat().st_size > 0
    assert "complete" in (table1_dir / f"{experiment}.md").read_text()


def test_finished_runs_are_skipped_and_an_interrupted_run_resumes(table1_dir, capsys):
    before = _eval_files(table1_dir)
    assert reproduce("table1", "tiny", table1_dir, launcher="basic",
                     benchmarks=("sinusoid_uniform",)) == 0
    assert "(0 to run)" in capsys.readouterr().out
    assert _eval_files(table1_dir) == before
    # An interrupted run: its checkpoint is on disk but not its eval.json (nor the evaluations
    # that need it). The sweep resumes it and gets the same numbers; nothing else runs again.
    run = table1_dir / "runs/sinusoid_uniform/ar_maml/seed1"
    removed = [run / "eval.json", *table1_dir.glob("runs/**/seed*/eval_vs_same_seed.json")]
    removed = [p for p in removed if "seed1" in str(p)]
    for path in removed:
        path.unlink()
    assert reproduce("table1", "tiny", table1_dir, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 1  # aggregates only: incomplete
    assert ("**partial**: 15/16 training runs (attack runs 2/2) and 49/56 evaluations"
            in (table1_dir / "table1.md").read_text())
    assert reproduce("table1", "tiny", table1_dir, launcher="basic",
                     benchmarks=("sinusoid_uniform",)) == 0
    out = capsys.readouterr().out
    assert "(1 to run)" in out
    # Each job's progress line counts the finished jobs of the experiment from their files.
    progress = [line.rsplit(", elapsed", 1)[0] for line in out.splitlines()
                if line.startswith("[table1 train]")]
    assert progress == [
        "[table1 train] start runs/sinusoid_uniform/ar_maml/seed1: 13/14 finished, 1 left",
        "[table1 train] done runs/sinusoid_uniform/ar_maml/seed1: 14/14 finished, 0 left"]
    jobs = (table1_dir / ".sweeps" / "table1-train.yaml").read_text()
    assert f"resume={run}" in jobs and jobs.count("overrides") == 1
    # the resume takes the plan's keys that change no result, and only those
    assert "trainer.progress=false" in jobs and "seed=" not in jobs
    assert _eval_files(table1_dir) == before


def test_a_run_killed_before_its_first_checkpoint_starts_again(table1_dir, tmp_path, capsys):
    """A run killed before it wrote a checkpoint leaves its config and logs behind; the sweep
    starts it again in its directory (``resume=`` with no checkpoint) and gets the numbers of the
    uninterrupted run."""
    results = tmp_path / "table1"
    shutil.copytree(table1_dir, results)
    run = results / "runs/sinusoid_uniform/dr_maml/seed0"
    before = (run / "eval.json").read_bytes()
    (run / "eval.json").unlink()
    shutil.rmtree(run / "checkpoints")
    capsys.readouterr()
    assert reproduce("table1", "tiny", results, launcher="basic",
                     benchmarks=("sinusoid_uniform",)) == 0
    assert "(1 to run)" in capsys.readouterr().out
    assert (run / "eval.json").read_bytes() == before
    assert f"resume={run}" in (results / ".sweeps" / "table1-train.yaml").read_text()


def test_a_failing_job_does_not_stop_the_other_jobs_of_its_sweep(tmp_path, capsys):
    """A job that stops with a user error (here: its directory is held by another live process)
    prints its line; the jobs after it still run, and the sweep exits with the job's code."""
    from armeta_rl.cli import train
    from armeta_rl.reproduce.launch import launch, train_job

    blocked, other = make_plan("noise", "tiny", benchmarks=("sinusoid_uniform",)).runs[:2]
    (tmp_path / blocked.subdir).mkdir(parents=True)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, signal, sys; f = open(sys.argv[1], 'w'); "
         "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); signal.pause()",
         str(tmp_path / blocked.subdir / "run.lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        code = launch(train, [train_job(tmp_path, r) for r in (blocked, other)], tmp_path,
                      "noise train", 0, ())
    finally:
        holder.kill()
        holder.wait()
    assert code == 2
    assert (tmp_path / other.subdir / "eval.json").is_file()
    assert not (tmp_path / blocked.subdir / "eval.json").exists()
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(errors) == 1 and "is in use by another run" in errors[0], errors


def test_a_sweep_restricted_to_another_benchmark_keeps_the_finished_rows(table1_dir, tmp_path):
    results = tmp_path / "table1"
    shutil.copytree(table1_dir, results)
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_normal",)) == 1  # aggregates only: nothing ran
    text = (results / "table1.md").read_text()
    assert "| Sinusoid-U | Initial |" in text
    assert ("**partial**: 16/32 training runs (attack runs 2/4) and 56/112 evaluations"
            in text)
    rows = (results / "table1.csv").read_text().splitlines()
    assert rows == (table1_dir / "table1.csv").read_text().splitlines()


def test_over_seeds_by_hand():
    summary = over_seeds([1.0, 2.0, 3.0, 6.0])
    assert summary.mean == 3.0
    assert math.isclose(summary.std, math.sqrt((4 + 1 + 0 + 9) / 3))
    assert math.isclose(summary.se, summary.std / 2)
    assert summary.format() == "3.000 ± 2.160"
    assert summary.format("se") == "3.000 ± 1.080"
    one = over_seeds([0.25])
    assert one.mean == 0.25 and math.isnan(one.std) and one.format() == "0.250"
    # Small MSEs keep three significant digits, returns one decimal.
    assert over_seeds([0.00123, 0.00127]).format() == "0.00125 ± 0.00003"
    assert over_seeds([-15.3, -14.1]).format() == "-14.7 ± 0.8"


def test_cvar_curves_by_hand():
    # Per-task losses 1..10: CVaR_α is the mean of the worst ceil((1 − α)·10) of them.
    first = {"mean": 5.5, "cvar_0.5": (6 + 7 + 8 + 9 + 10) / 5, "cvar_0.9": 10.0}
    second = {"mean": 6.5, "cvar_0.5": 9.0, "cvar_0.9": 11.0, "cvar_0.7": 10.0}
    assert cvar_curve(first) == ([0.0, 0.5, 0.9], [5.5, 8.0, 10.0])
    alphas, points = curve_over_seeds([{"seed": 0, **first}, {"seed": 1, **second}])
    assert alphas == [0.0, 0.5, 0.9]  # α = 0.7 is not in both runs
    assert [p.mean for p in points] == [6.0, 8.5, 10.5]
    assert all(math.isclose(p.std, math.sqrt(2) / 2) for p in points)
    assert all(math.isclose(p.se, 0.5) for p in points)


HAND_SCORED = ("eval.n_tasks=4", "eval.alphas=[0.5]")
"""The evaluation settings of :func:`_report`'s hand-made reports: a plan whose runs are scored
so (these as ``+train`` overrides) takes them."""


def _report(mean: float, cvar: float, adversarial: tuple[float, float] | None = None) -> dict:
    """A report that passes the schema (check_report): p0's ``mean`` and CVaR_0.5 over 4 tasks
    (sem |cvar - mean|, at least the spread they imply), and an adversary's if given."""
    def section(mean: float, cvar: float) -> dict:
        return {"mean": mean, "sem": abs(cvar - mean), "cvar": {"0.5": cvar}, "n_tasks": 4,
                "entropy": 1.0, "kl_p0": 0.0}

    report = {"metric": "mse", "benchmark": "sinusoid_uniform", "method": "maml",
              "initial": section(mean, cvar)}
    if adversarial is not None:
        report["adversarial"] = section(*adversarial)
    return report


def test_table_cells_are_mean_and_std_over_seeds_by_hand(tmp_path):
    plan = make_plan("cnp_table", "quick", HAND_SCORED)
    numbers = {("cnp", 0): (0.5, 1.0), ("cnp", 1): (0.7, 1.4), ("ar_cnp", 0): (0.4, 0.8),
               ("ar_cnp", 1): (0.6, 1.0)}
    for (method, seed), (mean, cvar) in numbers.items():
        run = tmp_path / f"runs/sinusoid_uniform/{method}/seed{seed}"
        run.mkdir(parents=True)
        (run / "eval.json").write_text(_of(plan, run, _report(mean, cvar)))
        (run / "eval_vs_same_seed.json").write_text(
            _of(plan, run, _report(mean, cvar, adversarial=(2 * mean, 2 * cvar))))
    records = collect(plan, tmp_path, {})
    assert len(records) == 8
    write_csv(records, tmp_path / "t.csv")
    assert (tmp_path / "t.csv").read_text().splitlines()[0].startswith(
        "benchmark,method,variant,seed,distribution,noisy,metric,mean")
    text = table(plan, records, tmp_path)
    initial = next(line for line in text.splitlines() if "| Initial |" in line)
    cells = [c.strip() for c in initial.split("|")[3:-1]]
    # Averages: CNP (0.5, 0.7) → 0.600 ± 0.141, AR-CNP (0.4, 0.6) → 0.500 ± 0.141 (the best,
    # bold); methods without runs show "–". CVaR0.5: CNP (1.0, 1.4), AR-CNP (0.8, 1.0).
    assert cells[0] == "0.600 ± 0.141" and cells[4] == "**0.500 ± 0.141**"
    assert cells[1] == "–"
    assert cells[5] == "1.200 ± 0.283" and cells[9] == "**0.900 ± 0.141**"
    adversarial = next(line for line in text.splitlines() if "same seed) |" in line)
    assert "**1.000 ± 0.283**" in adversarial


def test_each_benchmark_lists_only_its_own_shift_suite(tmp_path):
    """Two benchmarks with different shift suites: a benchmark's rows name its own shifts, not
    the other's (as rows of '–')."""
    plan = make_plan("table1", "quick", HAND_SCORED)
    for benchmark, shift in (("sinusoid_uniform", "shift/high_amplitude"),
                             ("pendulum_uniform", "shift/rim")):
        run = tmp_path / f"runs/{benchmark}/maml/seed0"
        run.mkdir(parents=True)
        (run / "eval.json").write_text(_of(plan, run, _report(0.5, 1.0)))
        shifts = _report(0.5, 1.0)
        shifts[shift] = shifts.pop("initial")
        (run / "eval_shifts.json").write_text(_of(plan, run, shifts))
    text = table(plan, collect(plan, tmp_path, {}), tmp_path)
    shift_rows = [line.split("|")[1:3] for line in text.splitlines() if "| shift: " in line]
    assert [[cell.strip() for cell in row] for row in shift_rows] == [
        ["Sinusoid-U", "shift: high_amplitude"], ["Pendulum-U", "shift: rim"]]


def _of(plan, run_dir: Path, report: dict) -> str:
    """``report`` as JSON, as the plan's run in ``run_dir`` writes it, beside the config.yaml the
    plan gives that run: with its identity (benchmark config, method, seed and the digest of its
    config), as a report is taken only where it is that run's."""
    from armeta_rl.reproduce.plan import composed, run_command, saved_config
    from armeta_rl.trainers.run_dir import write_config

    run = next(r for r in (*plan.runs, *plan.attacks) if run_dir.as_posix().endswith(r.subdir))
    config = run_dir / "config.yaml"
    if not config.exists():
        values = OmegaConf.to_container(composed(run_command(run)), resolve=True)
        write_config({**values, "seed": run.seed}, config)
    return json.dumps({**report, "benchmark": run.config, "method": run.method,
                       "seed": run.seed, "config_sha256": saved_config(config.read_text())[0]})


def _paired_report(per_task: list[float], section: str = "initial", seed: int = 1234) -> dict:
    values = torch.tensor(per_task)
    return {"metric": "return", "benchmark": "point_nav", "method": "maml", section: {
        "mean": float(values.mean()), "sem": float(values.std() / len(per_task) ** 0.5),
        "cvar": {"0.5": float(values.min())}, "cvar_sem": {"0.5": 0.2}, "n_tasks": 2,
        "rollouts": 8, "seed": seed,
        "per_task": per_task, "entropy": 1.0, "kl_p0": 0.0}}


def _write_point_seeds(plan, root: Path, offsets: list[dict[str, tuple[float, float]]]) -> None:
    """Per seed (the list's index) and learner, the point robot's ``eval.json`` on p0 (tasks
    −10, −12) and ``eval_shifts.json`` on the rim (−11, −13), each task shifted by the learner's
    ``(p0, rim)`` offsets."""
    for seed, learners in enumerate(offsets):
        for method, (p0, rim) in learners.items():
            run = root / f"runs/point_nav/{method}/seed{seed}"
            run.mkdir(parents=True)
            (run / "eval.json").write_text(_of(plan, run, _paired_report(
                [-10.0 + p0, -12.0 + p0])))
            (run / "eval_shifts.json").write_text(_of(plan, run, _paired_report(
                [-11.0 + rim, -13.0 + rim], "shift/rim", seed=7)))


def test_paired_differences_over_seeds_by_hand(tmp_path):
    """Per seed, AR-MAML minus MAML on the same tasks, then mean ± std over seeds, the RMS of the
    per-seed paired standard errors over tasks and the seeds where AR-MAML is better."""
    plan = make_plan("meta_rl_point", "paper", ("eval.n_tasks=2", "eval.alphas=[0.5]"))
    scores = {("maml", 0): [-10.0, -12.0], ("ar_maml", 0): [-9.0, -12.0],
              ("maml", 1): [-11.0, -13.0], ("ar_maml", 1): [-10.0, -11.0]}
    for (method, seed), per_task in scores.items():
        run = tmp_path / f"runs/point_nav/{method}/seed{seed}"
        run.mkdir(parents=True)
        (run / "eval.json").write_text(_of(plan, run, _paired_report(per_task)))
        shifted = [v - 1 for v in per_task]
        (run / "eval_shifts.json").write_text(_of(
            plan, run, _paired_report(shifted, "shift/rim", seed=7)))
    records = collect(plan, tmp_path, {})
    assert {r["distribution"] for r in records} == {"initial", "shift/rim"}
    text = paired(plan, records, tmp_path)
    # differences per seed: (1, 0) → mean 0.5, sem 0.5; (1, 2) → mean 1.5, sem 0.5. Over seeds:
    # 1.0 ± 0.707, RMS sem 0.5, 2/2 better; 1.0 is not beyond 2 · 0.5 (the se over seeds): plain.
    # Written with the decimals of the returns compared (MAML's −11.5: one), as the level table.
    initial = next(line for line in text.splitlines()
                   if line.startswith("| point_nav | initial |") and "Δ" not in line
                   and "+1.0 " in line)
    assert "+1.0 ± 0.7 [0.5] (2/2)" in initial
    # CVaR0.5 of two tasks is the lower one: (−12) − (−12) = 0 and (−11) − (−13) = 2; the
    # paired CVaR standard error is 1 at both seeds (influence values −9, −15 against −10, −14;
    # −10, −12 against −11, −15); no difference at seed 0, so 1 of 2 seeds better
    assert "+1.0 ± 1.4 [1.0] (1/2)" in initial
    assert "| point_nav | shift: rim |" in text
    level = next(line for line in text.splitlines() if line.startswith("| point_nav | initial |"))
    assert "-11.5 ± 0.7 [1.0]" in level  # MAML's average: (−11, −12) over seeds, task s.e. 1.0


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*REPRODUCE, *args], capture_output=True, text=True, timeout=120,
                          cwd=cwd, env={**os.environ, "PYTHONPATH": str(ROOT)})


def _refusal(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    """``armeta-reproduce args`` in this process: its exit code and what it wrote to stderr."""
    monkeypatch.setattr(sys, "argv", ["armeta-reproduce", *args])
    with pytest.raises(SystemExit) as exit_:
        main()
    return exit_.value.code, capsys.readouterr().err


@pytest.mark.parametrize(
    "args,expected",
    [
        (["table2"], "'experiment' = 'table2': allowed: ant_pos, cnp_table"),
        (["table1", "profile=huge"],
         "'profile' = 'huge': allowed: quick, paper, paper_ray, paper_warp, tiny"),
        (["table1", "launcher=mpi"], "'launcher' = 'mpi': allowed: local"),
        (["table1", "benchmarks=point_nav"], "'benchmarks' = 'point_nav': table1 has:"),
        (["table1", "seeds=7"], "'seeds' = 7: table1 at profile quick has: 0, 1"),
        (["table1", "iterations=3"], "'iterations' = '3': no such option"),
        (["profile=quick"], "name an experiment first"),
    ],
)
def test_bad_input_gets_one_line_and_exit_code_2(tmp_path, monkeypatch, capsys, args, expected):
    code, err = _refusal(monkeypatch, capsys, *args, f"results={tmp_path / 'r'}")
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert expected in err
    assert not (tmp_path / "r").exists()


def test_a_refusal_is_one_line_and_exit_code_2_from_the_command_itself(tmp_path):
    result = _run("table2", f"results={tmp_path / 'r'}", cwd=tmp_path)
    assert (result.returncode, result.stdout) == (2, ""), result.stderr
    assert result.stderr == ("armeta-reproduce: error: config key 'experiment' = 'table2': "
                             f"allowed: {', '.join(experiment_names())}\n")


def test_a_pack_value_other_than_true_or_false_gets_one_line_and_exit_code_2(capsys):
    from armeta_rl.reproduce.cli import parse

    assert parse(["table1", "pack=true"])["pack"] is True
    with pytest.raises(SystemExit) as exit_:
        parse(["table1", "pack=yes"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err == ("armeta-reproduce: error: config key 'pack' = 'yes': "
                                       "allowed: true, false\n")


def test_a_results_directory_is_claimed_whatever_its_runs_checkpointing(tmp_path):
    """A results directory swept with ``+train.trainer.checkpoint_every=50`` (a key that changes
    no result) is claimed by the same command without it, and its manifest keeps the record;
    one swept with a key that changes results is refused without that key."""
    from armeta_rl.errors import ConfigError
    from armeta_rl.reproduce.cli import MANIFEST, claim
    from armeta_rl.reproduce.plan import make_plan

    plan = make_plan("table1", "tiny")
    for train, claimed in ((["trainer.checkpoint_every=50"], True),
                           (["trainer.iterations=3"], False)):
        results = tmp_path / train[0]
        results.mkdir()
        (results / MANIFEST).write_text(
            f"experiment: table1\nprofile: tiny\ntrain: {train}\nwall_seconds: {{}}\n")
        if claimed:
            assert claim(results, plan, ())["train"] == train
        else:
            with pytest.raises(ConfigError, match="with \\+train overrides"):
                claim(results, plan, ())


def test_a_results_directory_of_another_experiment_is_refused(table1_dir, tmp_path, monkeypatch,
                                                              capsys):
    code, err = _refusal(monkeypatch, capsys, "cnp_table", "profile=tiny", f"results={table1_dir}")
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert "holds the runs of experiment table1, not cnp_table" in err
    code, err = _refusal(monkeypatch, capsys, "table1", "profile=quick", f"results={table1_dir}")
    assert code == 2 and "holds profile tiny" in err
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "a.txt").write_text("mine")
    code, err = _refusal(monkeypatch, capsys, "table1", "profile=tiny",
                         f"results={tmp_path / 'notes'}")
    assert code == 2 and "not an armeta-reproduce results" in err


def test_a_seed_restriction_keeps_the_evaluations_that_involve_its_seeds():
    whole = make_plan("table1", "paper", benchmarks=("sinusoid_uniform",))
    part = make_plan("table1", "paper", benchmarks=("sinusoid_uniform",), seeds=(1,))
    assert {run.seed for run in part.runs} == {1} and len(part.runs) == 7
    assert set(part.runs) < set(whole.runs) and set(part.evals) < set(whole.evals)
    assert [run.subdir for run in part.attacks] == ["runs/sinusoid_uniform/ar_maml-vs-maml/seed1"]
    # Same seed: learner seed 1 on adversary seed 1; next seed: seed 0 on 1 and seed 1 on 2;
    # the attack on MAML: seed 1 on seed 1; the shift suite: seed 1's learners.
    pairs = {(job.name, job.learner.seed, job.adversary and job.adversary.seed)
             for job in part.evals}
    assert pairs == {("same_seed", 1, 1), ("next_seed", 0, 1), ("next_seed", 1, 2),
                     ("maml", 1, 1), ("shifts", 1, None)}
    assert len(part.evals) == 35


def test_run_wall_times_come_from_the_manifest_before_file_times(tmp_path):
    """A run's wall time is measured once from its files (config.yaml written as it starts,
    eval.json as it ends) and then kept in the manifest: a checkout resets file times."""
    plan = make_plan("cnp_table", "quick")
    first, second = plan.runs[0].subdir, plan.runs[1].subdir
    for subdir, (start, end) in ((first, (1000.0, 1030.0)), (second, (2000.0, 2012.5))):
        run = tmp_path / subdir
        run.mkdir(parents=True)
        (run / "config.yaml").write_text("seed: 0\n")
        (run / "eval.json").write_text("{}")
        os.utime(run / "config.yaml", (start, start))
        os.utime(run / "eval.json", (end, end))
    assert train_seconds(plan, tmp_path, {}) == {first: 30.0, second: 12.5}
    assert train_seconds(plan, tmp_path, {first: 7.0}) == {first: 7.0, second: 12.5}


def test_a_resumed_runs_wall_time_is_its_logged_iterations_without_its_pause(tmp_path):
    """A run stopped after iteration 2 and resumed an hour later: its files span the hour, its
    CSV log's iteration times (iteration 2 logged twice, by a run killed before its checkpoint
    and by the resumed one: the last counts) do not, and they win over the manifest's value;
    a log that misses an iteration (``log_every`` > 1) is no measure of the run."""
    plan = make_plan("cnp_table", "quick")
    first, second = plan.runs[0].subdir, plan.runs[1].subdir
    for subdir, rows in ((first, "1,1000\n2,9999\n2,2000\n3,4000\n"),
                         (second, "2,1000\n4,1000\n")):
        run = tmp_path / subdir
        (run / CSV_LOG_DIR / "scalars" / "time").mkdir(parents=True)
        (run / CSV_LOG_DIR / "scalars" / "time" / "iteration_ms.csv").write_text(rows)
        (run / "config.yaml").write_text("seed: 0\n")
        (run / "eval.json").write_text("{}")
        os.utime(run / "config.yaml", (1000.0, 1000.0))
        os.utime(run / "eval.json", (4600.0, 4600.0))
    assert train_seconds(plan, tmp_path, {first: 3600.0}) == {first: 7.0, second: 3600.0}


def test_a_killed_sweep_keeps_its_wall_time_up_to_the_clocks_last_write(tmp_path):
    """While a sweep runs, the manifest on disk (what a kill would leave) holds the wall time
    from before plus the time so far; the caller's manifest is not touched. The wait for the
    clock's first write is bounded by this machine's own pace: 100 of the clock's periods, each
    with the time one manifest write and read takes here."""
    manifest = {"experiment": "table1", "profile": "tiny", "train": [],
                "wall_seconds": {"table1": 5.0}}
    def written(results: Path = tmp_path) -> float:
        """The wall time the manifest on disk holds (0 before the clock's first write)."""
        if not (results / MANIFEST).is_file():
            return 0.0
        return OmegaConf.load(results / MANIFEST).wall_seconds.table1

    reference = tmp_path / "reference"
    reference.mkdir()
    start = time.monotonic()
    save_manifest(reference, manifest)
    assert written(reference) == 5.0
    pace = time.monotonic() - start
    with SweepClock(tmp_path, manifest, "table1", every=0.05) as clock:
        while written() < 5.0 + 0.05 and clock.seconds < 100 * (clock.every + pace):
            time.sleep(0.01)
        left = OmegaConf.load(tmp_path / MANIFEST)
        assert 5.0 + 0.05 <= left.wall_seconds.table1 <= 5.0 + clock.seconds
        assert left.experiment == "table1" and left.profile == "tiny"
    assert manifest["wall_seconds"] == {"table1": 5.0}
    seconds = clock.seconds
    time.sleep(0.02)
    assert clock.seconds == seconds >= 0.05  # frozen at the block's end


def test_a_profile_entry_may_train_another_config_for_a_row(tmp_path):
    """``{config: sinusoid_normal_paper, overrides: [...]}`` under ``sinusoid_normal``: the runs
    train that config, while the row's name keys their directories and the paper's numbers."""
    plan = make_plan("table1", "paper", HAND_SCORED, benchmarks=("sinusoid_normal",))
    run = next(r for r in plan.runs if r.method == "maml" and r.seed == 0)
    assert run.benchmark == "sinusoid_normal" and run.config == "sinusoid_normal_paper"
    assert run.subdir == "runs/sinusoid_normal/maml/seed0"
    assert run.command()[:3] == ["benchmark=sinusoid_normal_paper", "method=maml", "seed=0"]
    assert "risk.ar.lr=0.000125" in run.overrides
    # A list entry trains the row's own config.
    plain = make_plan("table1", "paper", benchmarks=("sinusoid_uniform",)).runs[0]
    assert plain.config == plain.benchmark == "sinusoid_uniform"
    (tmp_path / run.subdir).mkdir(parents=True)
    (tmp_path / run.subdir / "eval.json").write_text(
        _of(plan, tmp_path / run.subdir, _report(0.5, 0.9)))
    text = table(plan, collect(plan, tmp_path, {}), tmp_path)
    ours = next(line for line in text.splitlines() if line.startswith("| Sinusoid-N | Initial"))
    assert "**0.500**" not in ours and "0.500" in ours  # one method: nothing to bold
    assert "0.578 ± 0.03" in text  # the paper's Sinusoid-N MAML average beneath


def test_every_experiment_plans_at_every_profile():
    for experiment in experiment_names():
        for profile in ("paper", "quick", "tiny"):
            plan = make_plan(experiment, profile)
            assert plan.runs and len(set(plan.runs)) == len(plan.runs)
    cnp = make_plan("cnp_table", "paper").runs[0].overrides
    # The experiment's own paper settings come after the shared ones, so they win.
    assert cnp[-2:] == ("trainer.iterations=15000", f"risk.ar.lr={0.5 / 15000}")


def test_the_quick_profile_trains_the_paper_profiles_configs():
    """quick is the paper's protocol shortened: every row of every experiment trains the same
    benchmark config at both profiles (the authors' p0 and data, not the package's own)."""
    for experiment in experiment_names():
        configs = [{run.benchmark: run.config for run in make_plan(experiment, profile).runs}
                   for profile in ("quick", "paper")]
        assert configs[0] == configs[1], experiment


@pytest.mark.parametrize("profile,config", [("paper_ray", "ant_goal_ray"),
                                            ("paper_warp", "ant_goal_warp")])
def test_the_ant_experiment_plans_for_bigger_hardware_and_others_refuse_it(profile, config):
    """ant_pos at the Ray and Warp profiles trains those configs in the ``ant_goal`` rows (5
    seeds, 40 tasks a batch); the Ray workers divide the meta-batch and the evaluation
    tasks (the Warp runs ask for CUDA, which the config check wants present). An experiment
    without Ant has no settings there: one line."""
    plan = make_plan("ant_pos", profile)
    assert {run.config for run in plan.runs} == {config}
    assert {run.benchmark for run in plan.runs} == {"ant_goal"}
    assert sorted({run.seed for run in plan.runs}) == [0, 1, 2, 3, 4]
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = compose("train", overrides=list(plan.runs[0].command()))
    assert cfg.benchmark.name == config
    if profile == "paper_ray":
        validate(cfg)
    with pytest.raises(ConfigError, match=f"'{profile}.benchmarks' = 'sinusoid_uniform'"):
        make_plan("table1", profile)


def _packaged_copy(tmp_path: Path, profiles_text: str) -> Path:
    """The package as a wheel installs it (its configs inside it), with ``profiles_text`` as
    its ``configs/reproduce/profiles.yaml``; the directory to put on ``PYTHONPATH``."""
    root = tmp_path / "site"
    shutil.copytree(ROOT / "armeta_rl", root / "armeta_rl",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "configs", root / "armeta_rl" / "configs")
    (root / "armeta_rl" / "configs" / "reproduce" / PROFILES_FILE).write_text(profiles_text)
    return root


MALFORMED_ENTRIES = [
    ("{config: sinusoid_normal_paper, iterations: 5}",
     "'paper.benchmarks.sinusoid_normal' = {'config': 'sinusoid_normal_paper', "
     "'iterations': 5}: allowed: a list of overrides, or {config: <benchmark>"),
    ("{overrides: [trainer.iterations=5]}",
     "'paper.benchmarks.sinusoid_normal' = {'overrides': ['trainer.iterations=5']}: allowed"),
    ("{config: sinusoid_circle}", "'benchmark' = 'sinusoid_circle': allowed: "),
]
SHOWN_ENTRY = "sinusoid_normal: {config: sinusoid_normal_paper, overrides: [risk.ar.lr=0.000125]}"


def _profiles_with(entry: str) -> str:
    """``profiles.yaml`` with Sinusoid-N's paper entry replaced by ``entry``."""
    profiles = (ROOT / "configs" / "reproduce" / PROFILES_FILE).read_text()
    assert SHOWN_ENTRY in profiles
    return profiles.replace(SHOWN_ENTRY, f"sinusoid_normal: {entry}")


@pytest.mark.parametrize("entry,expected", MALFORMED_ENTRIES)
def test_a_malformed_profile_entry_gets_one_line_and_exit_code_2(tmp_path, monkeypatch, capsys,
                                                                  entry, expected):
    profiles = OmegaConf.to_container(OmegaConf.create(_profiles_with(entry)))
    monkeypatch.setattr(plan_module, "load_profiles", lambda: profiles)
    code, err = _refusal(monkeypatch, capsys, "table1", "profile=paper",
                         f"results={tmp_path / 'r'}")
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert expected in err
    assert not (tmp_path / "r").exists()


def test_an_installed_packages_malformed_profile_entry_gets_one_line(tmp_path):
    entry, expected = MALFORMED_ENTRIES[0]
    site = _packaged_copy(tmp_path, _profiles_with(entry))
    result = subprocess.run(
        [*REPRODUCE, "table1", "profile=paper", f"results={tmp_path / 'r'}"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(site)})
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert expected in result.stderr


@pytest.mark.parametrize(
    "attacks,key,allowed",
    [
        ({"maml": {"method": "ar_maml"}}, "attacks.maml", "allowed: {method: <AR method>"),
        ({"maml": {"method": "ar_maml", "target": "cnp"}}, "attacks.maml.target",
         "allowed: maml, ar_maml"),
        ({"same_seed": {"method": "ar_maml", "target": "maml"}}, "attacks.same_seed",
         "an adversary of the experiment has that name already"),
    ],
)
def test_a_malformed_attack_is_refused(monkeypatch, attacks, key, allowed):
    spec = {"groups": [{"benchmarks": ["sinusoid_uniform"], "methods": ["maml", "ar_maml"]}],
            "adversaries": {"same_seed": {"method": "ar_maml"}}, "attacks": attacks}
    monkeypatch.setattr(plan_module, "load_spec", lambda experiment: spec)
    with pytest.raises(ConfigError, match=f"'{key}'") as error:
        make_plan("table1", "tiny")
    assert allowed in str(error.value)


def test_an_attacks_own_overrides_follow_its_targets(monkeypatch):
    """An attack's ``overrides`` (its adversary's settings) come after its target's, so the
    target's run need not carry them: the target trains as before, the attack with them."""
    spec = {"groups": [{"benchmarks": ["sinusoid_uniform"], "methods": ["maml"]},
                       {"benchmarks": ["sinusoid_uniform"], "methods": ["ar_maml"],
                        "variants": {"": ["risk.ar.step=natural"]}}],
            "attacks": {"maml": {"method": "ar_maml", "target": "maml",
                                 "overrides": ["risk.ar.step=natural"]}}}
    monkeypatch.setattr(plan_module, "load_spec", lambda experiment: spec)
    plan = make_plan("table1", "tiny")
    (maml,) = [run for run in plan.runs if run.method == "maml" and run.seed == 0]
    (attack,) = [run for run in plan.attacks if run.seed == 0]
    assert "risk.ar.step=natural" not in maml.overrides
    assert attack.overrides == (*maml.overrides, "risk.ar.step=natural")
    assert attack.target == maml


def test_an_attack_by_a_method_without_an_adversary_is_refused(monkeypatch):
    spec = {"groups": [{"benchmarks": ["sinusoid_uniform"], "methods": ["maml"]}],
            "attacks": {"maml": {"method": "dr_maml", "target": "maml"}}}
    monkeypatch.setattr(plan_module, "load_spec", lambda experiment: spec)
    with pytest.raises(ConfigError, match="'attacks' = 'dr_maml': an attack trains a flow"):
        check_runs(make_plan("table1", "tiny"))


def test_a_curve_file_written_before_a_column_existed_reads_it_as_empty(tmp_path):
    """A committed curve file whose header predates a column (here the batch's spread) reads
    with that column ``None`` in every row, and is written back with it, empty."""
    import gzip

    from armeta_rl.reproduce.curves import CURVES, KEYS, read_curves, write_curves

    old = [*KEYS, *(c for c in CURVES if c != "task_spread")]
    path = tmp_path / "old_curves.csv.gz"
    path.write_bytes(gzip.compress((",".join(old) + "\nhalf_cheetah_vel,maml,0,1,"
                                    + ",".join(["-1.5"] * (len(old) - 4)) + "\n").encode()))
    (row,) = read_curves(path)
    assert row["task_spread"] is None and row["gain"] == -1.5 and row["iteration"] == 1
    write_curves([row], path)
    assert read_curves(path) == [row]


@pytest.mark.parametrize(("edit", "words"), [
    ("another method", "it is the report of method 'dr_maml', not this run's 'maml'"),
    ("another seed", "it is the report of seed 1, not this run's 0"),
    ("a section that is a string", "'initial' = 'str' is not a distribution's section"),
    ("another config", "it is the report of another config (config_sha256 "),
    ("no identity", "it records no seed or config_sha256: a report that does not say which"),
    ("not the plan's config", "its run's config has trainer.iterations = 2, not the 1 this "
                              "experiment's plan gives it"),
    ("scored otherwise", "it was scored with support_noise 0.1, not the 0.0 the plan gives"),
])
def test_a_report_that_is_not_this_runs_is_unfinished_and_left_out(tmp_path, table1_dir, edit,
                                                                   words):
    """An eval.json copied from another run's directory (another method or seed), with a
    section of the wrong type, without the identity of the run that wrote it (another method's
    relabelled), or whose run's config or scoring is not what the experiment's plan gives it
    (another experiment's or profile's) marks its run unfinished, and the aggregate leaves it
    out."""
    from armeta_rl.reproduce.aggregate import collect
    from armeta_rl.reproduce.plan import report_problem

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    maml = next(r for r in plan.runs if (r.method, r.seed) == ("maml", 0))
    source = {"another method": "dr_maml/seed0", "another seed": "maml/seed1",
              "no identity": "dr_maml/seed0"}.get(edit, "maml/seed0")
    report = json.loads((results / "runs/sinusoid_uniform" / source / "eval.json").read_text())
    if edit == "a section that is a string":
        report["initial"] = "str"
    if edit == "no identity":  # as copied from another method, its identity removed
        report = {**{k: v for k, v in report.items() if k not in ("seed", "config_sha256")},
                  "method": "maml"}
    if edit == "not the plan's config":  # a key the plan sets; iterations are not digested
        config = results / maml.subdir / "config.yaml"
        config.write_text(config.read_text().replace("  iterations: 1\n", "  iterations: 2\n"))
    if edit == "scored otherwise":  # as the noise experiment scores the same training runs
        report["support_noise"] = 0.1
    if edit == "another config":  # as a variant's report: same method and seed, other settings
        config = results / maml.subdir / "config.yaml"
        config.write_text(config.read_text().replace("inner_lr: 0.01", "inner_lr: 0.02"))
    (results / maml.subdir / "eval.json").write_text(json.dumps(report))
    assert report_problem(results, maml).startswith(words)
    records = collect(plan, results, {})
    assert not [r for r in records if (r["method"], r["seed"], r["distribution"]) == (
        "maml", 0, "initial")]


def _run_files(results: Path) -> dict[str, bytes]:
    return {str(p.relative_to(results)): p.read_bytes()
            for p in sorted(results.glob("runs/*/*/*/*"))
            if p.name == "config.yaml" or (p.name.startswith("eval") and p.suffix == ".json")}


def test_packed_runs_hold_every_value_and_rebuild_the_reports_alone(table1_dir, tmp_path):
    """``pack=true`` puts every report and config of the run directories into two compact files
    that give each file back byte for byte (every float bit for bit); with the run directories
    gone, the same command rebuilds the report, its CSV and its figure as they were."""
    from armeta_rl.reproduce.packed import CONFIGS_FILE, REPORTS_FILE, read_packed, unpack

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    files = _run_files(results)
    assert len(files) == 16 + 16 + 56  # every run's config.yaml and eval.json, every evaluation
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",), pack=True) == 0
    aggregated = {name: (results / name).read_bytes()
                  for name in ("table1.md", "table1.csv", "table1.png")}
    packed = read_packed(results)
    for name, data in files.items():
        place = (str(Path(name).parent), Path(name).name)
        if place[1] == "config.yaml":
            assert packed.configs[place[0]] == data.decode()
        else:  # key order and floats' every bit: the JSON texts are equal
            assert json.dumps(packed.reports[place]) == json.dumps(json.loads(data))
    unpack(tmp_path / "unpacked", packed)
    assert _run_files(tmp_path / "unpacked") == files
    size = sum(len(d) for d in files.values())
    assert (results / REPORTS_FILE).stat().st_size + (results / CONFIGS_FILE).stat().st_size \
        < size / 4
    shutil.rmtree(results / "runs")
    for name in aggregated:
        (results / name).unlink()
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 0
    assert {name: (results / name).read_bytes() for name in aggregated} == aggregated


def test_a_run_directorys_report_wins_over_its_packed_copy(table1_dir, tmp_path):
    """A report in its run directory is the one read (a sweep writing into a packed directory
    reads its own reports): another run's report copied there marks the run unfinished although
    its packed copy is its own, and the packed copy counts again once the file is gone."""
    from armeta_rl.reproduce.packed import pack, read_packed
    from armeta_rl.reproduce.plan import finished, packable, report_problem

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    pack(results, packable(results, plan))
    packed = read_packed(results)
    maml = next(r for r in plan.runs if (r.method, r.seed) == ("maml", 0))
    report = results / maml.subdir / "eval.json"
    shutil.copy(results / "runs/sinusoid_uniform/dr_maml/seed0/eval.json", report)
    assert report_problem(results, maml, packed).startswith("it is the report of method")
    shutil.rmtree(results / maml.subdir)
    assert finished(results, maml, packed) and not finished(results, maml)


def test_configs_pack_as_differences_from_the_base_and_read_back_as_written():
    """A config is its differences from the base (each key's most common value); one with its
    keys in another order also keeps that order, one whose keys cannot be dotted keeps its
    text; every text reads back as it was."""
    from armeta_rl.reproduce.packed import config_lines, configs_of

    base = "method:\n  name: maml\n  lr: 0.01\nseed: 0\ntags:\n- a\n- 1\n"
    configs = {"runs/a/seed0": base,
               "runs/a/seed1": base.replace("seed: 0", "seed: 1"),
               "runs/b/seed0": base.replace("lr: 0.01", "lr: 1").replace("tags:\n- a\n- 1\n",
                                                                          "extra: {}\n"),
               "runs/c/seed0": "seed: 0\nmethod:\n  name: maml\n  lr: 0.01\n",
               "runs/d/seed0": base + "cvar:\n  '0.5': 1.0\n"}
    lines = config_lines(configs)
    assert lines[0]["base"] == {"method": {"name": "maml", "lr": 0.01}, "seed": 0,
                                "tags": ["a", 1]}
    by_run = {line["run"]: line for line in lines[1:]}
    assert by_run["runs/a/seed0"] == {"run": "runs/a/seed0", "set": {}, "unset": []}
    assert by_run["runs/a/seed1"]["set"] == {"seed": 1}
    assert by_run["runs/b/seed0"]["set"] == {"method.lr": 1, "extra": {}}  # 1, not 1.0
    assert by_run["runs/b/seed0"]["unset"] == ["tags"]
    assert by_run["runs/c/seed0"]["order"] == ["seed", "method.name", "method.lr"]
    assert by_run["runs/d/seed0"] == {"run": "runs/d/seed0", "text": configs["runs/d/seed0"]}
    assert configs_of(lines) == configs


def test_a_gain_cell_counts_the_seeds_that_adapt_in_the_returns_decimals():
    """Three seeds' gains on returns near −55: one decimal as the returns have (a gain of 7.58
    is not written with three), the root-mean-square standard error over tasks in brackets, and
    the seeds whose gain is beyond twice its error counted."""
    from armeta_rl.reproduce.reports import _gain

    records = [{"method": "maml", "seed": s, "mean": m, "gain": g, "gain_sem": e}
               for s, m, g, e in ((0, -54.0, 7.5, 2.0), (1, -56.0, 3.0, 2.0),
                                  (2, -55.0, 12.24, 2.0))]
    records.append({"method": "dr_maml", "seed": 0, "mean": -60.0, "gain": None})
    text, adapting, seeds = _gain(records, method="maml")
    assert text == "+7.6 ± 4.6 [2.0] (2/3 adapt)" and (adapting, seeds) == (2, 3)
    assert _gain(records, method="dr_maml") == ("–", 0, 0)


def test_a_run_saved_before_a_key_existed_keeps_its_report(tmp_path, table1_dir):
    """A run whose config.yaml was written before a key was added (its default now in the
    schema) and whose report was made after, by a resume under the newer version, is the same
    run: its saved config is read as a resume reads it, merged into the schema."""
    from armeta_rl.reproduce.plan import report_problem

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    maml = next(r for r in plan.runs if (r.method, r.seed) == ("maml", 0))
    config = results / maml.subdir / "config.yaml"
    older = config.read_text().replace("    label_scale: 1.0\n", "")
    assert older != config.read_text()
    config.write_text(older)
    assert report_problem(results, maml) is None


def test_a_report_written_before_a_key_existed_keeps_its_run(tmp_path, table1_dir):
    """A run whose config.yaml lacks a key added since (``risk.ar.max_kl``) and whose report
    recorded the identity of that config as saved (the run's own, written before the key
    existed) is finished; a report recording neither that identity nor today's reading of the
    config is another config's."""
    from armeta_rl.reproduce.plan import report_problem
    from armeta_rl.trainers.checkpoint import identity_as_saved

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    maml = next(r for r in plan.runs if (r.method, r.seed) == ("maml", 0))
    config, report_file = (results / maml.subdir / name for name in ("config.yaml", "eval.json"))
    older = config.read_text().replace("    max_kl: 0.005\n", "", 1)
    assert older != config.read_text()
    config.write_text(older)
    report = json.loads(report_file.read_text())
    for digest, problem in ((identity_as_saved(older)["config_sha256"], None),
                            ("0" * 64, "it is the report of another config")):
        report_file.write_text(json.dumps({**report, "config_sha256": digest}))
        found = report_problem(results, maml)
        assert found is None if problem is None else found.startswith(problem)


def test_what_a_report_check_remembers_is_what_a_fresh_reading_gives(table1_dir):
    """A report check remembers, by their input, each run's composed config, planned values,
    saved config and saved identity (it asks for each several times). After a whole check of a
    sweep, each remembered value equals a fresh computation (no caller changed a shared one); a
    saved identity is a fresh dict each call (a caller's change does not reach the next); texts
    that differ in a result-changing key have different identities, and a refused text has none
    every time it is asked for."""
    import yaml

    from armeta_rl.reproduce.plan import (
        composed,
        planned_values,
        report_problem,
        run_command,
        saved_config,
    )
    from armeta_rl.trainers.checkpoint import identity_as_saved, run_identity

    plan = make_plan("table1", "tiny", benchmarks=("sinusoid_uniform",))
    assert [report_problem(table1_dir, run) for run in plan.runs] == [None] * len(plan.runs)
    texts = {run: (table1_dir / run.subdir / "config.yaml").read_text() for run in plan.runs}
    for run, text in texts.items():
        assert composed(run_command(run)) == composed.__wrapped__(run_command(run))
        assert planned_values(run) == planned_values.__wrapped__(run)
        assert saved_config(text) == saved_config.__wrapped__(text)
        identity = identity_as_saved(text)
        assert identity == run_identity(yaml.safe_load(text))
        identity["seed"] = -1
        assert identity_as_saved(text)["seed"] == run.seed
    digests = {identity_as_saved(text)["config_sha256"] for text in texts.values()}
    assert len(digests) == len(texts)
    text = next(iter(texts.values()))
    assert "  meta_batch: " in text
    batch = text.replace("  meta_batch: ", "  meta_batch: 1", 1)
    assert identity_as_saved(batch)["config_sha256"] not in digests
    aliased = f"{text}alias: &name 1\nagain: *name\n"
    assert [identity_as_saved(aliased) for _ in range(2)] == [None, None]


def test_a_run_checkpointed_otherwise_than_its_plan_says_keeps_its_report(tmp_path, table1_dir):
    """The plan's keys that change no result (``NO_RESULT_KEYS``: how often a run checkpoints
    or logs) do not decide whether a report is the run's: an experiment that checkpoints its
    runs more often keeps the runs it finished before; a key that changes results does."""
    from armeta_rl.reproduce.plan import report_problem

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    for extra, problem in ((("trainer.checkpoint_every=7",), None),
                           (("trainer.meta_batch=7",), "trainer.meta_batch = ")):
        plan = make_plan("table1", "tiny", extra, benchmarks=("sinusoid_uniform",))
        maml = next(r for r in plan.runs if (r.method, r.seed) == ("maml", 0))
        found = report_problem(results, maml)
        assert found is None if problem is None else problem in found


def test_pack_packs_only_the_reports_the_plan_accepts(tmp_path, table1_dir):
    """A report refused (another method's, its identity removed) is not packed, and the packed
    files then hold every other report: pack=true never turns a refused report into a packed
    one the run directories no longer contradict."""
    from armeta_rl.reproduce.packed import read_packed

    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    maml = results / "runs/sinusoid_uniform/maml/seed0"
    report = json.loads((maml.parent.parent / "dr_maml/seed0/eval.json").read_text())
    report = {**{k: v for k, v in report.items() if k not in ("seed", "config_sha256")},
              "method": "maml"}
    (maml / "eval.json").write_text(json.dumps(report))
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",), pack=True) == 1
    packed = read_packed(results)
    assert ("runs/sinusoid_uniform/maml/seed0", "eval.json") not in packed.reports
    assert len(packed.reports) == 16 + 56 - 1


@pytest.fixture(scope="module")
def table1_packed(table1_dir, tmp_path_factory):
    """table1's tiny results packed, its run directories gone: the compact files alone."""
    results = tmp_path_factory.mktemp("packed") / "results"
    shutil.copytree(table1_dir, results)
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",), pack=True) == 0
    shutil.rmtree(results / "runs")
    return results


def test_another_experiments_packed_files_are_refused(tmp_path, table1_packed):
    """Packed files whose reports were scored otherwise than this experiment's plan scores them
    (the noise experiment trains the same runs and scores them with noisy labels too): none of
    their runs is finished here, and the report aggregates none."""
    from armeta_rl.reproduce.packed import Packed, pack, read_packed

    results = tmp_path / "results"
    shutil.copytree(table1_packed, results)
    packed = read_packed(results)
    pack(results, Packed({place: {**report, "support_noise": 0.1}
                          for place, report in packed.reports.items()}, packed.configs))
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 1
    assert "No run finished." in (results / "table1.md").read_text()
    assert len(read_packed(results).reports) == 16 + 56


@pytest.mark.parametrize(("damage", "words"), [
    ("truncated", "its reports.jsonl.gz is cut short (its gzip stream does not end)"),
    ("bit flipped", "its reports.jsonl.gz is damaged"),
    ("a line too long", "its reports.jsonl.gz has a line (1) longer than the 64 bytes"),
    ("not JSON", "its reports.jsonl.gz has a line (1) that is not JSON"),
])
def test_a_damaged_packed_file_is_one_line_naming_it(tmp_path, table1_packed, monkeypatch, damage,
                                                     words):
    import gzip

    import armeta_rl.reproduce.packed as packed_module

    results = tmp_path / "results"
    shutil.copytree(table1_packed, results)
    path = results / "reports.jsonl.gz"
    data = bytearray(path.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    elif damage == "bit flipped":
        data[len(data) // 2] ^= 0x10
    elif damage == "a line too long":
        monkeypatch.setattr(packed_module, "LINE_BYTES", 64)
    else:
        data = bytearray(gzip.compress(b"{not json\n"))
    path.write_bytes(bytes(data))
    with pytest.raises(ConfigError, match=re.escape(f"'results' = '{results}': {words}")):
        reproduce("table1", "tiny", results, launcher="none", benchmarks=("sinusoid_uniform",))


def test_a_partial_sweep_names_on_stderr_what_is_missing_and_why(tmp_path, table1_dir, capsys):
    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    shutil.rmtree(results / "runs/sinusoid_uniform/maml/seed0")
    capsys.readouterr()
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 1
    err = capsys.readouterr().err
    assert ("armeta-reproduce: missing runs/sinusoid_uniform/maml/seed0/eval.json: it does not "
            "exist") in err
    assert ("armeta-reproduce: missing runs/sinusoid_uniform/maml/seed0/eval_vs_same_seed.json: "
            "it waits for runs/sinusoid_uniform/maml/seed0, not finished") in err


def test_an_evaluation_whose_run_lost_its_checkpoints_is_named_as_one_that_cannot_run(
        tmp_path, table1_dir, capsys):
    """A finished run whose checkpoints are gone strands the evaluations still to make from it:
    stderr and the report's first line say they cannot run and which run they need; while the
    run still has a checkpoint, the same missing evaluation is only missing."""
    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    run = results / "runs/sinusoid_uniform/maml/seed0"
    (run / "eval_vs_same_seed.json").unlink()
    capsys.readouterr()
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 1
    assert "cannot run" not in capsys.readouterr().err + (results / "table1.md").read_text()
    shutil.rmtree(run / "checkpoints")
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 1
    assert ("armeta-reproduce: missing runs/sinusoid_uniform/maml/seed0/eval_vs_same_seed.json: "
            "it cannot run: runs/sinusoid_uniform/maml/seed0 finished without a checkpoint to "
            "load") in capsys.readouterr().err
    assert ("and 55/56 evaluations finished (each cell summarizes the seeds finished so far, so "
            "cells may rest on different numbers of seeds). The evaluation left cannot run: "
            "runs/sinusoid_uniform/maml/seed0 finished without a checkpoint to load.") in (
        results / "table1.md").read_text()


def test_the_staging_files_a_killed_process_left_are_removed(tmp_path, table1_dir):
    """A kill while packing leaves ``.reports.jsonl.<pid>.gz``: the next run removes those of
    processes that are gone, and leaves a live process's own."""
    results = tmp_path / "results"
    shutil.copytree(table1_dir, results)
    gone = subprocess.Popen(["true"])
    gone.wait()
    stale = results / f".reports.jsonl.{gone.pid}.gz"
    live = results / f".reports.jsonl.{os.getpid()}.gz"
    for path in (stale, live):
        path.write_bytes(b"half a packed file")
    assert reproduce("table1", "tiny", results, launcher="none",
                     benchmarks=("sinusoid_uniform",)) == 0
    assert not stale.exists() and live.exists()


def test_a_results_directory_that_is_a_link_loop_is_one_line(tmp_path):
    loop = tmp_path / "results"
    loop.symlink_to(loop)
    with pytest.raises(ConfigError, match=f"'results' = '{loop}': cannot be used"):
        reproduce("table1", "tiny", loop, launcher="none", benchmarks=("sinusoid_uniform",))


def test_the_verdict_rule_on_hand_made_differences():
    """The docs' rule: helps when the mean difference is on the better side, beyond twice its
    standard error over seeds, and better on at least 80 % of the seeds; hurts with the sign
    reversed; otherwise does not help."""
    from armeta_rl.reproduce.reports import HELPS, HURTS, NO_HELP, verdict

    assert verdict([2.0, 2.0, 2.0, 2.0, 1.0], higher_better=True) == HELPS
    # beyond twice the error (mean 1.76, se 0.76) but better at 3 of 5 seeds only
    assert verdict([3.0, 3.0, 3.0, -0.1, -0.1], higher_better=True) == NO_HELP
    # worse at 4 of 5 seeds, mean −0.8 beyond 2 · 0.255
    assert verdict([-1.0, -1.2, -0.9, -1.1, 0.2], higher_better=True) == HURTS
    assert verdict([-1.0, -1.2, -0.9, -1.1, 0.2], higher_better=False) == HELPS  # losses
    assert verdict([1.0, 1.1, 0.9, 1.0, 8.0], higher_better=True) == NO_HELP  # within spread
    assert verdict([5.0], higher_better=True) == NO_HELP  # one seed: no standard error
    eight_of_ten = [1.0, 1.1, 0.9, 1.2, 1.0, 0.8, 1.1, 1.0, -0.1, -0.2]
    assert verdict(eight_of_ten, higher_better=True) == HELPS
    assert verdict([*eight_of_ten[:7], -0.1, -0.2, -0.1], higher_better=True) == NO_HELP


def _curve_rows(run: str, seeds: int, iterations: int, **columns) -> list[dict]:
    """Curve-file rows of ``run``: each column a function of (seed, iteration), others empty."""
    from armeta_rl.reproduce.curves import CURVES

    return [{"benchmark": "half_cheetah_vel", "run": run, "seed": seed, "iteration": i,
             **dict.fromkeys(CURVES), **{k: f(seed, i) for k, f in columns.items()}}
            for seed in range(seeds) for i in range(1, iterations + 1)]


def test_the_late_trend_compares_the_last_fifth_of_a_curve_with_the_fifth_before():
    """The change from iterations 301–400 to 401–500 of 500, per seed; rising or falling by the
    verdicts' rule (a rise of 5, 6, 7, 8, 9 over the five seeds: +7 ± 0.707, rising, written
    +7.0 ± 0.7 as the returns it is a change of, about 31), level within the spread, a lone seed
    without a word, and '–' where a run lacks the column."""
    from armeta_rl.reproduce.curves import late_changes, late_means
    from armeta_rl.reproduce.reports import late_trend

    step = {300: 0.0, 400: 1.0, 500: 3.0}  # the curve's value up to each of these iterations
    rows = [
        *_curve_rows("maml", 5, 500,
                     return_post=lambda s, i: (0.05 + 0.01 * s) * i,
                     gain=lambda s, i: (1.0 if i > 400 else 0.0) * (-1) ** s),
        *_curve_rows("ar_maml", 1, 500,
                     return_post=lambda s, i: next(v for end, v in step.items() if i <= end),
                     adversary_kl_p0=lambda s, i: 2.0),
        *_curve_rows("ar_maml-vs-maml", 5, 500, adversary_kl_p0=lambda s, i: -i / (s + 1)),
    ]
    changes = late_changes(late_means(rows, "return_post"))
    assert changes[("half_cheetah_vel", "ar_maml")] == [2.0]
    assert changes[("half_cheetah_vel", "maml")] == pytest.approx([5.0, 6.0, 7.0, 8.0, 9.0])
    assert ("half_cheetah_vel", "ar_maml-vs-maml") not in changes
    labels = {"maml": "MAML", "ar_maml": "AR-MAML", "ar_maml-vs-maml": "attack"}
    lines = late_trend(rows, labels).splitlines()
    assert lines[-5] == ("| Benchmark | Run | return after adaptation | adaptation gain "
                         "| adversary KL(p0 ‖ p_φ) |")
    assert lines[-2:] == [
        "| half_cheetah_vel | AR-MAML | +2.000 (1 seed) | – | +0.000 (1 seed) |",
        "| half_cheetah_vel | attack | – | – | -45.7 ± 14.5 (0/5 up) falling |"]
    maml = lines[-3].split(" | ")
    assert maml[2:] == ["+7.0 ± 0.7 (5/5 up) rising", "+0.200 ± 0.490 (3/5 up) level",
                        "– |"]
    assert "(for 500 iterations: 401–500 against 301–400)" in late_trend(rows, labels)
    shorter = _curve_rows("maml", 2, 400, gain=lambda s, i: float(i))
    assert "(for 400 iterations: 321–400 against 241–320)" in late_trend(shorter, labels)
    assert late_trend(_curve_rows("maml", 2, 500), labels) == ""  # no curve at all

def test_the_reports_verdicts_come_from_its_paired_differences(tmp_path):
    """Five seeds where AR-MAML beats MAML on every task of p0 by 1 to 1.4 and loses on the rim
    at 4 of 5 seeds: the report and the verdicts file say it helps on p0 and hurts on the rim,
    with the differences over seeds (mean ± its standard error, in the decimals of the returns
    compared, −11 and −12: one, two where the error needs them) and the seeds better; DR-MAML,
    level with MAML, does not help anywhere; the option, worse on p0 at every seed but within
    the spread (one seed far off) and level on the rim, does not help, worse at every seed on
    p0."""
    from armeta_rl.reproduce.reports import verdicts_path

    plan = make_plan("meta_rl_point", "paper", ("eval.n_tasks=2", "eval.alphas=[0.5]"))
    _write_point_seeds(plan, tmp_path, [
        {"maml": (0.0, 0.0), "ar_maml": (1.0 + 0.1 * seed, -0.5 - 0.1 * seed if seed else 0.1),
         "dr_maml": (0.1 * (-1) ** seed, 0.1 * (-1) ** seed),
         "ar_maml-best": (-5.0 if seed == 3 else -0.1, 0.0)} for seed in range(5)])
    text = paired(plan, collect(plan, tmp_path, {}), tmp_path)
    lines = verdicts_path(tmp_path, "meta_rl_point").read_text().splitlines()
    assert lines[0] == "- **DR-MAML** (5 seeds): does not help on any of the 2 distributions."
    assert lines[1] == ("- **AR-MAML** (5 seeds): helps on p0 (avg +1.20 ± 0.07, 5/5 seeds "
                        "better; CVaR0.5 +1.20 ± 0.07, 5/5 seeds better); hurts on shift: rim "
                        "(avg -0.6 ± 0.2, 1/5 seeds better; CVaR0.5 -0.6 ± 0.2, 1/5 "
                        "seeds better).")
    assert lines[2] == ("- **AR-MAML (std., λ 0.2)** (5 seeds): does not help on any of the 2 "
                        "distributions, though it is worse than MAML at every seed on p0 (avg "
                        "-1.1 ± 1.0, 0/5 seeds better; CVaR0.5 -1.1 ± 1.0, 0/5 seeds "
                        "better), within the spread.")
    assert all(line in text for line in lines)
    # MAML scored on the rim at seed 0 only: one pair there, no standard error, no verdict
    for seed in range(1, 5):
        (tmp_path / f"runs/point_nav/maml/seed{seed}/eval_shifts.json").unlink()
    paired(plan, collect(plan, tmp_path, {}), tmp_path)
    lines = verdicts_path(tmp_path, "meta_rl_point").read_text().splitlines()
    single = "; no verdict yet on shift: rim, paired at one seed only."
    assert lines[0] == "- **DR-MAML** (5 seeds): does not help on p0" + single
    assert lines[1] == ("- **AR-MAML** (5 seeds): helps on p0 (avg +1.20 ± 0.07, 5/5 seeds "
                        "better; CVaR0.5 +1.20 ± 0.07, 5/5 seeds better)" + single)
    assert lines[2].startswith("- **AR-MAML (std., λ 0.2)** (5 seeds): does not help on p0, "
                               "though it is worse than MAML at every seed on p0 (")
    assert lines[2].endswith("within the spread" + single)
    # the attacks' KL 0.5 and 0.6 against the co-trained 0.2 and 0.3: the check closes the file
    for seed, (attack, cotrained) in enumerate(((0.5, 0.2), (0.6, 0.3))):
        for method, name, kl in (("maml", "maml", attack), ("ar_maml", "same_seed", cotrained)):
            report = _paired_report([-10.0, -12.0], "adversarial", seed=seed)
            report["adversarial"]["kl_p0"] = kl
            run = tmp_path / f"runs/point_nav/{method}/seed{seed}"
            (run / f"eval_vs_{name}.json").write_text(_of(plan, run, report))
    text = paired(plan, collect(plan, tmp_path, {}), tmp_path)
    last = verdicts_path(tmp_path, "meta_rl_point").read_text().splitlines()[-1]
    assert last.startswith("- **The attack against MAML** (p_φ vs MAML, KL 0.55) against the "
                           "co-trained adversary (p_φ same seed, KL 0.25): KL ratio 2.20 ± 0.24")
    assert last[2:] in text


def test_matched_progress_reads_each_learners_p0_gain_against_the_references_per_seed():
    """AR-MAML's p0 gain 1.0 to 1.4 below MAML's at five seeds (−1.2 ± 0.071, 0/5 higher):
    behind, so the comparison is at equal iterations only; DR-MAML's alternately 0.1 above and
    below: level; a seed scored on other tasks pairs with nothing; with AR-MAML level too, the
    comparison is also one at equal gain; fewer than two paired seeds: no line."""
    from armeta_rl.reproduce.reports import progress_line

    plan = make_plan("meta_rl_point", "paper")
    base = {"benchmark": "point_nav", "distribution": "initial", "noisy": False,
            "n_tasks": 2, "mean": -10.0}

    def records(ar_offset):
        out = []
        for seed in range(5):
            out += [{**base, "method": m, "variant": "", "seed": seed, "task_seed": 1234,
                     "gain": 3.0 + seed + offset}
                    for m, offset in (("maml", 0.0), ("dr_maml", 0.1 * (-1) ** seed),
                                      ("ar_maml", ar_offset(seed)))]
        out.append({**base, "method": "ar_maml", "variant": "", "seed": 5, "task_seed": 99,
                    "gain": 50.0})  # MAML has no seed 5 on these tasks
        return out

    line = progress_line(plan, records(lambda seed: -1.0 - 0.1 * seed), ("maml", ""))
    assert line == (
        "- **Matched progress?** The adaptation gain on p0 at the compared iteration, each "
        "learner's minus MAML's per seed on the same tasks (mean ± its standard error over "
        "seeds; *ahead* or *behind* by the rule, else *level*): DR-MAML +0.0 ± 0.0 (3/5 seeds "
        "higher), level; AR-MAML -1.2 ± 0.1 (0/5 seeds higher), behind. AR-MAML is behind, so "
        "for it the comparison is at equal iterations, not at equal gain.")
    level = progress_line(plan, records(lambda seed: 0.2 * (-1) ** seed), ("maml", ""))
    assert level.endswith("AR-MAML +0.0 ± 0.1 (3/5 seeds higher), level. Every learner's "
                          "gain is level with MAML's within the spread, so the learners "
                          "compared at equal iterations are also compared at equal gain.")
    assert progress_line(plan, [r for r in records(lambda seed: 0.0) if r["seed"] == 0],
                         ("maml", "")) == ""


def _strength_records() -> list[dict]:
    """MAML at two seeds: its worst quarter on p0 is 1 (returns −20 and −30), where the attack
    puts 0.6 and 0.7; the co-trained AR-MAML's worst is quarter 3; the attack's KL 0.5 and 0.6
    against the co-trained 0.2 and 0.3; MAML's mean return −12 on p0 and −18 on the attack."""
    base = {"benchmark": "point_nav", "noisy": False, "metric": "return"}
    records = []
    for seed, (attack_kl, cotrained_kl, attack_mass) in enumerate(((0.5, 0.2, 0.6),
                                                                   (0.6, 0.3, 0.7))):
        quarters = {f"quarter_scores_{q}": s for q, s in enumerate((-10.0, -20 - 10 * seed,
                                                                    -5.0, None))}
        p0_mass = {f"quarter_mass_{q}": 0.25 for q in range(4)}
        records += [
            {**base, "method": "maml", "variant": "", "seed": seed, "distribution": "initial",
             "mean": -12.0, **quarters, **p0_mass},
            {**base, "method": "maml", "variant": "", "seed": seed, "distribution": "maml",
             "mean": -18.0, "kl_p0": attack_kl, "kl_p0_sem": 0.01,
             **{f"quarter_mass_{q}": m for q, m in enumerate(
                 (0.1, attack_mass, 0.2, 0.7 - attack_mass))}},
            {**base, "method": "ar_maml", "variant": "", "seed": seed,
             "distribution": "initial", "mean": -13.0,
             **{f"quarter_scores_{q}": s for q, s in enumerate((-1.0, -2.0, -3.0, -9.0))}},
            {**base, "method": "ar_maml", "variant": "", "seed": seed,
             "distribution": "same_seed", "mean": -13.0, "kl_p0": cotrained_kl}]
    return records


def test_the_adversaries_strength_and_the_attack_check_by_hand():
    """p_φ's mass on the learner's worst quarter (0.6 and 0.7 → 0.65 ± 0.07, p0 0.25), the loss
    ratio 18 / 12 = 1.5 and the KL ratio (0.5 + 0.6) / (0.2 + 0.3) = 2.2, whose delta-method
    influence values are ±0.24 (standard error 0.24): the attack moved clearly further. A
    section without masses (an evaluation before they were recorded) shows –."""
    from armeta_rl.reproduce.reports import adversary_section, attack_check, kl_ratio

    plan = make_plan("meta_rl_point", "paper")
    ratio, se = kl_ratio([0.5, 0.6], [0.2, 0.3])
    assert ratio == pytest.approx(2.2) and se == pytest.approx(0.24)
    text = adversary_section(plan, _strength_records())
    row = next(line for line in text.splitlines() if "| p_φ vs MAML |" in line)
    assert row.split(" | ")[2:] == ["MAML (attack)", "0.550 ± 0.071 [0.010]",
                                    "0.65 ± 0.07 (p0: 0.25 ± 0.00)", "1.50 ± 0.00 |"]
    same = next(line for line in text.splitlines() if "| p_φ same seed |" in line)
    assert same.split(" | ")[4] == "–"  # no masses recorded: –, not a crash
    [check] = attack_check(plan, _strength_records(), "point_nav")
    assert "KL ratio 2.20 ± 0.24" in check and "It moved clearly further" in check
    # MAML's loss 18 / 12 = 1.5× on the attack, AR-MAML's 13 / 13 = 1× on its own p_φ
    assert ("raised MAML's loss to 1.50× its loss on p0, the co-trained adversary AR-MAML's to "
            "1.00×: difference +0.500 ± 0.000 (2/2 seeds higher), clearly stronger.") in check
    assert "the learner's answer" not in check  # it moved further: the KL says it already
    cotrained_moved_as_far = [
        {**r, "kl_p0": 0.55} if r["distribution"] == "same_seed" else r
        for r in _strength_records()]
    [check] = attack_check(plan, cotrained_moved_as_far, "point_nav")
    assert "It did not move clearly further" in check and "Adam at 0.5 / iterations" in check
    # natural steps (the fair test's attacks): no step rule to blame
    fair = make_plan("meta_rl_cheetah_fair", "paper")
    cheetah = [{**r, "benchmark": "half_cheetah_vel"} for r in cotrained_moved_as_far]
    [check] = attack_check(fair, cheetah, "half_cheetah_vel")
    assert "It did not move clearly further" in check and "Adam at 0.5" not in check
    assert check.endswith("clearly stronger. Both went equally far from p0, natural steps "
                          "capping neither, and the co-trained adversary is clearly weaker "
                          "against its learner than the attack against a frozen one: the "
                          "learner's answer, not the step rule, is what holds it back.")
    harder = [{**r, "mean": -26.0} if r["distribution"] == "same_seed" else r for r in cheetah]
    [check] = attack_check(fair, harder, "half_cheetah_vel")  # 26 / 13 = 2× against 1.5×
    assert check.endswith("(0/2 seeds higher), clearly weaker.")
    one_seed = [r for r in _strength_records() if r["seed"] == 0]  # 0.5 / 0.2
    assert attack_check(plan, one_seed, "point_nav")[0].endswith(
        "KL ratio 2.50 at one seed: no standard error over seeds, no verdict yet.")
    assert attack_check(plan, _strength_records(), "half_cheetah_vel") == []  # not scored there


def test_the_share_of_the_goal_blind_gap_is_a_column_only_where_recorded():
    from armeta_rl.reproduce.reports import gap_closed_section

    plan = make_plan("meta_rl_point", "paper")
    base = {"benchmark": "point_nav", "noisy": False, "variant": "", "distribution": "initial",
            "goal_oracle": -1.0}
    records = [{**base, "method": "maml", "seed": s, "gap_closed": g, "gap_closed_sem": 0.02}
               for s, g in ((0, 0.64), (1, 0.68))]
    assert gap_closed_section(plan, [{k: v for k, v in r.items() if k != "goal_oracle"}
                                     for r in records]) == ""
    row = next(line for line in gap_closed_section(plan, records).splitlines()
               if line.startswith("| point_nav | initial |"))
    assert row.split(" | ")[2:4] == ["66 ± 3 % [2]", "–"]  # MAML; DR-MAML has no record


def test_a_share_of_the_gap_with_an_error_above_one_is_a_dash_in_a_rebuilt_report():
    """The goal sections of HalfCheetah-Vel's validation seed as its reports carry them
    (evaluated without the rule): MAML's share on the co-trained adversary's p_φ, −407973 %
    with an error of 616 (61610 points; a gap of 0.03 against an achieved −133), reads
    undefined, in the CSV's columns and as "–" in the table, and so does every cell where one
    seed's share is undefined; on the slow shift (−71 %, error 0.12) the share stays."""
    from armeta_rl.reproduce.aggregate import evidence_columns
    from armeta_rl.reproduce.reports import gap_closed_section

    plan = make_plan("meta_rl_cheetah", "paper")
    goals = {"same_seed": {"achieved": -132.63, "blind": -0.0325, "oracle": 0.0,
                           "gap_closed": -4079.73, "gap_closed_sem": 616.10},
             "shift/slow": {"achieved": -23.06, "blind": -13.49, "oracle": 0.0,
                            "gap_closed": -0.7092, "gap_closed_sem": 0.1197}}
    base = {"benchmark": "half_cheetah_vel", "noisy": False, "variant": "", "method": "maml"}
    records = [{**base, "seed": 100, "distribution": d, **evidence_columns({"goal": goal})}
               for d, goal in goals.items()]
    concentrated = next(r for r in records if r["distribution"] == "same_seed")
    assert (concentrated["gap_closed"], concentrated["gap_closed_sem"]) == (None, None)
    assert concentrated["goal_blind"] == -0.0325  # the references stay
    records.append({**records[1], "seed": 101})
    records.append({**base, "seed": 101, "distribution": "initial", "goal_oracle": 0.0,
                    "gap_closed": None, "gap_closed_sem": None})
    records.append({**base, "seed": 100, "distribution": "initial", "goal_oracle": 0.0,
                    "gap_closed": 0.30, "gap_closed_sem": 0.05})
    cells = {line.split(" | ")[1]: line.split(" | ")[2]
             for line in gap_closed_section(plan, records).splitlines()
             if line.startswith("| half_cheetah_vel |")}
    assert cells["shift: slow"] == "-71 ± 0 % [12]"
    assert cells["initial"] == "–"  # seed 101's share undefined: not seed 100's alone
    assert cells["p_φ same seed"] == "–"


def test_the_curve_file_holds_the_natural_steps_kl(tmp_path):
    """The follower's ``adversary/step_kl`` scalar (natural steps) is a column of the curve
    file."""
    from armeta_rl.reproduce.curves import run_curve

    scalars = tmp_path / CSV_LOG_DIR / "scalars" / "adversary"
    scalars.mkdir(parents=True)
    (scalars / "step_kl.csv").write_text("step,value\n1,0.0049\n2,0.0051\n")
    curve = run_curve(tmp_path)
    assert [curve[i]["adversary_step_kl"] for i in (1, 2)] == [0.0049, 0.0051]


def test_a_section_evaluated_before_the_evidence_fields_keeps_its_csv_columns():
    """A section without the KL's error, the quarters or the goal references adds no column (a
    committed CSV rebuilt from old reports is unchanged); a new one adds each."""
    from armeta_rl.reproduce.aggregate import evidence_columns

    assert evidence_columns({"mean": -1.0, "kl_p0": 0.3}) == {}
    goal = {"achieved": -12.0, "blind": -33.0, "oracle": -1.0, "gap_closed": 0.66,
            "gap_closed_sem": 0.02}
    columns = evidence_columns({"kl_p0_sem": None, "quarter_mass": [0.1, 0.2, 0.3, 0.4],
                                "quarter_scores": [-1.0, None, -3.0, -4.0], "goal": goal})
    assert columns == {"kl_p0_sem": None, "quarter_mass_0": 0.1, "quarter_mass_1": 0.2,
                       "quarter_mass_2": 0.3, "quarter_mass_3": 0.4, "quarter_scores_0": -1.0,
                       "quarter_scores_1": None, "quarter_scores_2": -3.0,
                       "quarter_scores_3": -4.0, "goal_achieved": -12.0, "goal_blind": -33.0,
                       "goal_oracle": -1.0, "gap_closed": 0.66, "gap_closed_sem": 0.02}


def test_the_report_counts_the_machines_its_runs_trained_on():
    """One count per machine over the runs (p0's clean record: one per run; the noisy and the
    adversaries' records are the same runs; an attack run's report: one per attack run), runs
    whose reports predate the record counted as such; nothing when no report records one (a
    committed report rebuilt from old runs keeps its text)."""
    from armeta_rl.reproduce.cli import machines

    def run(machine=None, distribution="initial", noisy=False):
        return {"distribution": distribution, "noisy": noisy,
                **({} if machine is None else {"machine": machine})}

    records = [run("A"), run("A", noisy=True), run("A", "adversarial"), run("B"), run(), run("A")]
    assert machines(records) == " Training machines: A (2 runs), B (1 run), not recorded (1 run)."
    assert machines([run(), run(None, "adversarial")]) == ""
    attacks = [{"machine": "B"}, {"machine": "C"}, {}]  # attack runs' reports count alike
    assert machines(records, attacks) == (" Training machines: A (2 runs), B (2 runs), "
                                          "not recorded (2 runs), C (1 run).")


def test_the_precision_target_by_hand(tmp_path):
    """Paired differences over 5 seeds of 1, 3, 1, 3, 2 on p0 (std 1, se 0.45) and 0, 4, 0, 4, 2
    on the rim (std 2, se 0.89) against a target of 0.5: AR-MAML's largest error is the rim's,
    not below it at the plan's 5 seeds, and (2 / 0.5)² = 16 seeds would not be enough but 17
    would; DR-MAML (±0.1) and the option (−0.1 at every seed) are below it. With a seed still to
    come the line says "not yet". A malformed target is refused before anything runs."""
    from dataclasses import replace

    from armeta_rl.reproduce.reports import precision_line

    plan = make_plan("meta_rl_point", "paper", ("eval.n_tasks=2", "eval.alphas=[0.5]"))
    _write_point_seeds(plan, tmp_path, [
        {"maml": (0.0, 0.0), "ar_maml": (step, 2 * step - 2),
         "dr_maml": (0.1 * (-1) ** seed, 0.1 * (-1) ** seed), "ar_maml-best": (-0.1, -0.1)}
        for seed, step in enumerate((1.0, 3.0, 1.0, 3.0, 2.0))])
    records = collect(plan, tmp_path, {})
    target = replace(plan, spec={**plan.spec, "precision": {
        "se_below": 0.5, "distributions": ["initial", "shift/rim"]}})
    assert precision_line(target, records, ("maml", ""), 0.5) == (
        "**Precision**, the protocol's target: the paired standard error over seeds below 0.5 "
        "on p0, shift: rim. DR-MAML: largest 0.05 (p0, avg; 5 seeds), reached; AR-MAML: largest "
        "0.89 (shift: rim, avg; 5 seeds), not met at the planned 5 seeds; at this spread 17 "
        "seeds would reach it; AR-MAML (std., λ 0.2): largest 0.00 (p0, avg; 5 seeds), reached.")
    assert precision_line(plan, records, ("maml", ""), 0.5) == ""  # no target, no line
    four = [r for r in records if r["seed"] != 4]
    assert "0.89 (shift: rim, avg; 5 seeds)" not in precision_line(target, four, ("maml", ""), 0.5)
    assert "seeds), not yet; at this spread" in precision_line(target, four, ("maml", ""), 0.5)
    for bad in (2, {"se_below": 0, "distributions": ["initial"]},
                {"se_below": 2, "distributions": []}, {"se_below": True, "distributions": ["x"]}):
        with pytest.raises(ConfigError, match=r"'precision' = .*allowed: \{se_below"):
            plan_module.precision_target({"precision": bad})
