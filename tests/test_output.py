"""Output a person reads: every job of a ``-m`` sweep labels its progress bar
and its end-of-run table with its run's name; the end of a run says what the columns are once
and repeats the run directory with the report and the density picture; an unknown group value
is refused before torch is imported."""

from __future__ import annotations

import subprocess
import sys

from armeta_rl.cli import train
from conftest import in_process

SMALL = ("benchmark=point_nav_plain", "trainer.iterations=2", "trainer.meta_batch=2",
         "benchmark.collector.episodes=2", "benchmark.collector.max_steps=8", "eval.n_tasks=2",
         "logger=none", "trainer.density_every=0")


def test_each_job_of_a_sweep_labels_its_bar_and_its_table(tmp_path, capsys):
    code, out, err = in_process(train, ["-m", "method=ar_maml,maml", *SMALL,
                                        f"hydra.sweep.dir={tmp_path}"], capsys)
    assert code == 0, err
    jobs = sorted(path.name for path in tmp_path.iterdir() if path.is_dir())
    assert jobs == ["0_point_nav_plain_ar_maml_seed0", "1_point_nav_plain_maml_seed0"]
    for job, method in zip(jobs, ("ar_maml", "maml")):
        assert f"{job}: {method} on point_nav_plain, seed 0\nmetric: return" in out
        assert f"{job}: 100%" in err  # its progress bar, under its name
    bars = [line for line in err.replace("\r", "\n").splitlines() if "it/s" in line]
    assert bars and all(line.startswith(tuple(jobs)) for line in bars)
    assert out.count("R: rollouts per task") == 2  # once under each job's table


def test_the_end_of_a_run_names_its_directory_report_and_picture(tmp_path, capsys):
    run_dir = tmp_path / "run"
    code, out, err = in_process(train, ["method=ar_maml", *SMALL, "trainer.progress=false",
                                        f"hydra.run.dir={run_dir}"], capsys)
    assert code == 0, err
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"run directory: {run_dir} (report: eval.json")
    assert f"{run_dir / 'density.png'}" in last and (run_dir / "density.png").is_file()
    assert "adversary objective=" not in out  # the bar is off: nothing but the table printed


def test_an_unknown_benchmark_is_refused_before_torch_is_imported():
    program = ("import sys; from armeta_rl.cli import train; code = train(sys.argv[1:]); "
               "assert 'torch' not in sys.modules, 'torch imported'; sys.exit(code)")
    done = subprocess.run([sys.executable, "-c", program, "benchmark=half_cheetah_vell"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert "config key 'benchmark' = 'half_cheetah_vell': allowed:" in line
    assert "half_cheetah_vel," in line
