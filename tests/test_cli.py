"""The command line: bad input gets one clear line and exit code 2; wandb runs offline."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from armeta_rl.cli import evaluate, train
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, cross_evaluate, in_process, refusal, train_config

TRAIN = [sys.executable, "-c", "import sys; from armeta_rl.cli import train; sys.exit(train())"]
EVAL = [sys.executable, "-c",
        "import sys; from armeta_rl.cli import evaluate; sys.exit(evaluate())"]


@pytest.mark.parametrize(
    "override,key,allowed",
    [
        ("benchmark=sinusoid_square", "benchmark", "sinusoid_uniform"),
        ("method=super_maml", "method", "ar_maml"),
        ("logger=tensorbored", "logger", "tensorboard"),
        ("benchmark.space.low=[5.0,0.0]", "benchmark.space.low", "must be <"),
        ("risk.ar.lam=-0.5", "risk.ar.lam", ">= 0"),
        ("eval.alphas=[0.5,1.2]", "eval.alphas", "(0, 1)"),
        ("trainer.meta_batch=0", "trainer.meta_batch", ">= 1"),
        ("trainer.iterations=-3", "trainer.iterations", ">= 1"),
        ("eval.n_tasks=0", "eval.n_tasks", ">= 1"),
        ("eval.rollouts=0", "eval.rollouts", ">= 1"),
        ("benchmark=point_nav trainer.follower_rollouts=0", "trainer.follower_rollouts", ">= 1"),
        ("risk.ar.signal=advantage", "risk.ar.signal", "allowed: loss, regret"),
        ("trainer.follower_rollouts=2", "trainer.follower_rollouts", "must be 1 on sinusoid"),
        ("trainer.follower_at=later", "trainer.follower_at", "allowed: next, step"),
        ("benchmark=point_nav trainer.follower_rollouts=2 trainer.follower_at=step",
         "trainer.follower_rollouts", "must be 1 with trainer.follower_at=step"),
        ("method=mpts_maml risk.mpts.reconstruction=exact", "risk.mpts.reconstruction",
         "allowed: expected, mean_prediction"),
        ("method=pdts_maml risk.pdts.label_scale=0", "risk.pdts.label_scale", "must be > 0"),
        ("method=mpts_maml risk.mpts.label=last_step", "risk.mpts.label",
         "needs an env that reports its forward reward"),
        ("risk.ar.signal=regret", "risk.ar.signal", "needs a benchmark that knows a reference"),
        ("risk.ar.compile=fast", "risk.ar.compile", "a backend (inductor"),
        ("method=mpts_maml risk.mpts.candidate_ratio=0.5", "risk.mpts.candidate_ratio",
         "must be >= 1 (the candidate pool holds at least the batch)"),
        ("method=pdts_maml risk.pdts.distance=manhattan", "risk.pdts.distance",
         "allowed: identifier, unit"),
        ("trainer.iteratons=5", "trainer.iteratons", "did you mean 'trainer.iterations'?"),
        ("method.learner=reptile", "method.learner", "allowed: maml, cnp, anil"),
        ("risk.ar.flow_kwargs.activation=leaky_relu", "risk.ar.flow_kwargs.activation",
         "+risk.ar.flow_kwargs.activation=leaky_relu"),
        ("benchmark=pendulum_uniform benchmark.collector.target=state",
         "benchmark.collector.target", "allowed: delta, next"),
        ("benchmark=pendulum_uniform benchmark.space.low=[0.0,0.4]", "benchmark.space.low",
         "must be > 0"),
        ("benchmark=ant_goal_smoke trainer.progress=false benchmark.space.names=[x,y,z] "
         "benchmark.space.low=[0,0,0] benchmark.space.high=[1,1,1]", "benchmark.space",
         "AntGoalEnv refuses it: tensordict key 'params'"),
    ],
)
def test_bad_input_gets_one_line_and_exit_code_2(tmp_path, capsys, override, key, allowed):
    """``override``: one or more space-separated overrides (``armeta-train`` in this process;
    the program's own exit code and stderr: the next test)."""
    line = refusal(train, [*override.split(), f"hydra.run.dir={tmp_path}"], capsys)
    assert f"'{key}'" in line and allowed in line


def test_support_noise_on_an_rl_benchmark_is_refused_before_training(tmp_path):
    result = subprocess.run(
        [*TRAIN, "benchmark=point_nav_plain", "eval.support_noise=0.1",
         f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert "'eval.support_noise'" in result.stderr and "no support labels" in result.stderr
    assert not (tmp_path / "checkpoints").exists() and not (tmp_path / "config.yaml").exists()


def test_unknown_choice_inside_a_sweep_is_rejected(tmp_path):
    result = subprocess.run(
        [*TRAIN, "-m", "method=maml,ar_mam"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert result.returncode == 2 and "'ar_mam'" in result.stderr


def test_override_keys_are_checked_for_the_chosen_benchmark_and_sweep(tmp_path, monkeypatch,
                                                                      capsys):
    monkeypatch.chdir(tmp_path)

    def run(*args: str) -> tuple[int, str, str]:
        return in_process(train, list(args), capsys)

    code, out, _ = run("benchmark=pendulum_uniform", "benchmark.collector.episodes=10",
                       "--cfg", "job")
    assert code == 0 and "episodes: 10" in out
    code, _, err = run("-m", "benchmark=point_nav,sinusoid_uniform",
                       "benchmark.collector.max_steps=50")
    assert code == 2
    assert "'benchmark.collector.max_steps'" in err and "benchmark=sinusoid_uniform" in err
    code, out, _ = run("risk.ar.flow=planar", "+risk.ar.flow_kwargs.activation=leaky_relu",
                       "--cfg", "job")
    assert code == 0 and "activation: leaky_relu" in out
    assert "'trainer.iterations=['" in refusal(train, ["trainer.iterations=["], capsys)


def test_resume_and_eval_of_a_non_run_directory_are_rejected(tmp_path, capsys):
    assert "'resume'" in refusal(train, [f"resume={tmp_path}"], capsys)
    assert "'learner'" in refusal(evaluate, [f"learner={tmp_path}"], capsys)


def test_eval_scores_a_saved_learner_on_another_runs_adversary(tmp_path):
    run_training(Job(train_config(*SMALL_RUN, "method=maml"), tmp_path / "maml"))
    run_training(Job(train_config(*SMALL_RUN, "method=ar_maml"), tmp_path / "ar"))
    result = subprocess.run(
        [*EVAL, f"learner={tmp_path / 'maml'}", f"adversary={tmp_path / 'ar'}", "eval.n_tasks=30"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "adversarial" in result.stdout
    report = json.loads((tmp_path / "maml" / "eval_vs_ar.json").read_text())
    # the CLI scores what the runs' own players score, in process, on the same seeded tasks
    reference = cross_evaluate(tmp_path / "maml", tmp_path / "ar", {"n_tasks": 30})
    for section in ("initial", "adversarial"):
        assert report[section]["n_tasks"] == 30
        assert report[section]["mean"] == reference[section]["mean"]
        assert report[section]["cvar"] == reference[section]["cvar"]
    assert report["adversarial"]["mean"] != report["initial"]["mean"]


def test_a_checkpoint_of_another_config_gets_one_line(tmp_path):
    """A config.yaml edited after the run (another flow) no longer describes the run its
    checkpoint records: one line naming the learner's directory."""
    run_training(Job(train_config(*SMALL_RUN, "+risk.ar.flow_kwargs.layers=2"), tmp_path / "ar"))
    config = tmp_path / "ar" / "config.yaml"
    text = config.read_text()
    config.write_text(text.replace("flow_kwargs:\n      layers: 2", "flow_kwargs: {}"))
    assert config.read_text() != text
    result = subprocess.run(
        [*EVAL, f"learner={tmp_path / 'ar'}"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert "'learner'" in result.stderr and "is another run's: config_sha256" in result.stderr


def test_wandb_offline_runs_in_one_process_each_write_their_own_files(tmp_path, monkeypatch):
    # two runs in one process, as the jobs of an in-process sweep: each gets its own wandb run
    # (a run left open would be handed back to the second job, which would log into it)
    monkeypatch.setenv("WANDB_MODE", "offline")
    for run_dir in (tmp_path / "first", tmp_path / "second"):
        run_training(Job(train_config(*SMALL_RUN, "logger=wandb", "trainer.density_every=3"),
                         run_dir))
        runs = list((run_dir / "wandb").glob("offline-run-*"))
        assert len(runs) == 1
        assert list(runs[0].glob("run-*.wandb"))
        # the density frames of iterations 0, 3 and 6 and the final density.png, as wandb images
        images = list((runs[0] / "files" / "media" / "images" / "adversary").glob("density_*.png"))
        assert len(images) == 4


def test_a_run_prints_its_directory_writes_a_job_log_and_releases_its_lock(tmp_path):
    run_dir = tmp_path / "run"
    result = subprocess.run([*TRAIN, *SMALL_RUN, "trainer.iterations=4", "trainer.log_every=2",
                             f"hydra.run.dir={run_dir}"], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    assert f"run directory: {run_dir}" in result.stdout.splitlines()
    log = (run_dir / "armeta-train.log").read_text()
    assert f"run directory: {run_dir}" in log
    assert "iteration 2: train/leader_loss=" in log and "iteration 4: " in log
    assert "adversarial" in log and "cvar_0.5" in log  # the evaluation table
    assert not (run_dir / "run.lock").exists()


def test_the_lock_file_names_its_holder_and_is_removed_when_the_lock_is_released(tmp_path):
    """The lock file holds this process's pid while the lock is held; a second lock of the same
    directory is refused naming that pid, even from this process (a run locks its directory
    once), and leaves the lock held; releasing removes the file."""
    import os

    from armeta_rl.trainers.run_dir import LOCK_FILE, run_lock

    with run_lock(tmp_path, "hydra.run.dir"):
        assert (tmp_path / LOCK_FILE).read_text().strip() == str(os.getpid())
        with pytest.raises(ConfigError, match=f"in use by another run \\(pid {os.getpid()}\\)"), \
                run_lock(tmp_path, "hydra.run.dir"):
            pass
        assert (tmp_path / LOCK_FILE).read_text().strip() == str(os.getpid())
    assert not (tmp_path / LOCK_FILE).exists()


def test_help_lists_the_groups_a_command_line_chooses_from_and_exits_0(capsys):
    from armeta_rl.cli import evaluate, train

    assert train(["--help"]) == 0
    text = capsys.readouterr().out
    groups = text.split("Configuration groups (group=option):\n")[1].split("\n\n")[0]
    assert [line.split(":")[0].strip() for line in groups.splitlines()] == [
        "benchmark", "method", "logger"]
    assert "sinusoid_uniform" in groups and "armeta-train [overrides] --cfg job" in text
    assert evaluate(["--help"]) == 0
    assert "armeta-eval learner=<run dir>" in capsys.readouterr().out


def test_help_lists_every_key_with_its_type_default_range_and_doc_from_its_dataclass(capsys):
    """The keys of ``armeta-train --help`` are the dataclasses' fields: every field of
    ``TrainerConfig`` has its line, with its default, its range and the comment written with
    it; a learner's section is listed when a word names it, and then only what is under it."""
    import dataclasses

    from armeta_rl.cli import train
    from armeta_rl.config import TrainerConfig

    assert train(["--help"]) == 0
    keys = capsys.readouterr().out.split("Keys (")[1].split("\n\n")[0].splitlines()[1:]
    names = [line.split(" = ")[0].strip() for line in keys if " = " in line]
    assert [n for n in names if n.startswith("trainer.")] == [
        f"trainer.{spec.name}" for spec in dataclasses.fields(TrainerConfig)]
    assert "  trainer.meta_batch = 25: an integer, must be >= 1" in keys
    assert ("  trainer.stop_at = null: an integer, must be >= 1. stop (with a checkpoint) after "
            "this iteration; resume later") in keys
    assert "  logger.kind = csv: a string, allowed: csv, wandb, tensorboard, mlflow, none" in keys
    assert not any(n.startswith("learner.maml") for n in names)
    assert train(["--help", "learner.maml"]) == 0
    keys = capsys.readouterr().out.split("Keys (")[1].split("\n\n")[0].splitlines()[1:]
    assert keys and all(line.startswith("  learner.maml.") for line in keys)
    assert any(line.startswith("  learner.maml.inner_lr = 0.01: a number, must be > 0.")
               for line in keys)


@pytest.mark.parametrize("script", ["armeta-train", "armeta-eval", "armeta-reproduce"])
def test_help_imports_neither_torch_nor_mujoco_nor_ray(script):
    """--help of each console script (its entry point, as installed) answers from the config
    folder alone: torch, TorchRL, MuJoCo and Ray stay unimported (its seconds:
    docs/notes/speed-measurements.md)."""
    probe = ("import sys; from importlib.metadata import entry_points; "
             f"(e,) = [e for e in entry_points(group='console_scripts') if e.name == '{script}']; "
             f"sys.argv = ['{script}', '--help']\n"
             "try:\n    e.load()()\nexcept SystemExit as stop:\n    assert not stop.code\n"
             "print(sorted({m.split('.')[0] for m in sys.modules} "
             "& {'torch', 'torchrl', 'mujoco', 'ray'}))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=120, check=True)
    assert "usage" in done.stdout or "--cfg job" in done.stdout
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_reproduce_help_and_shell_completion_exit_0():
    helped = subprocess.run([sys.executable, "-c", "from armeta_rl.reproduce.cli import main; "
                             "main()", "--help"], capture_output=True, text=True, timeout=120)
    assert helped.returncode == 0 and "experiments: " in helped.stdout
    completion = subprocess.run([*TRAIN, "-sc", "install=bash"], capture_output=True, text=True,
                                timeout=120)
    assert completion.returncode == 0, completion.stderr
    assert "hydra_bash_completion" in completion.stdout


def wandb_records(path: Path) -> list[bytes]:
    """The records of a wandb transaction log (``run-*.wandb``): a 7-byte wandb header, then the
    LevelDB log format wandb writes (32 KiB blocks of chunks, each with a 7-byte header: CRC,
    length, type FULL=1, FIRST=2, MIDDLE=3, LAST=4)."""
    data, block, records, pending = path.read_bytes(), 32768, [], b""
    assert data[:4] == b":W&B"
    offset = 7
    while offset + 7 <= len(data):
        if block - offset % block < 7:  # a block's tail too short for a header is padding
            offset += block - offset % block
            continue
        length, kind = int.from_bytes(data[offset + 4:offset + 6], "little"), data[offset + 6]
        chunk = data[offset + 7:offset + 7 + length]
        offset += 7 + length
        if kind == 0:
            break
        pending = chunk if kind in (1, 2) else pending + chunk
        if kind in (1, 4):
            records.append(pending)
    return records


def wandb_history(run: Path) -> list[dict]:
    """The history rows an offline wandb run wrote, parsed with wandb's own protobuf record."""
    import json

    from wandb.proto import wandb_internal_pb2

    rows = []
    for data in wandb_records(next(run.glob("run-*.wandb"))):
        record = wandb_internal_pb2.Record()
        record.ParseFromString(data)
        if record.WhichOneof("record_type") == "history":
            rows.append({"/".join(item.nested_key) or item.key: json.loads(item.value_json)
                         for item in record.history.item})
    return rows


def test_an_offline_rl_run_logs_the_density_animation_and_the_adaptation(tmp_path, monkeypatch):
    """A MAML-TRPO run on the point robot with wandb: the density animation as a video, the
    pre- and post-adaptation returns and their gain every logged iteration, and the frames and
    the final density.png (titled) as images."""
    monkeypatch.setenv("WANDB_MODE", "offline")
    run_dir = tmp_path / "run"
    run_training(Job(train_config("benchmark=point_nav", "method=ar_maml", "trainer.iterations=4",
                               "trainer.log_every=1", "trainer.meta_batch=2",
                               "trainer.checkpoint_every=2", "trainer.density_every=2",
                               "benchmark.collector.episodes=2",
                               "benchmark.collector.max_steps=8", "eval.n_tasks=2",
                               "trainer.progress=false", "logger=wandb"), run_dir))
    (run,) = (run_dir / "wandb").glob("offline-run-*")
    rows = wandb_history(run)
    gains = [r["train/gain"] for r in rows if "train/gain" in r]
    assert len(gains) == 4
    for row in rows:
        if "train/gain" in row:
            assert row["train/gain"] == pytest.approx(
                row["train/return_post"] - row["train/return_pre"], abs=1e-4)
    (video,) = [r for r in rows if "adversary/density_animation/_type" in r]
    assert video["adversary/density_animation/_type"] == "video-file"
    path = video["adversary/density_animation/path"]
    assert path.endswith(".gif") and (run / "files" / path).stat().st_size > 0
    images = list((run / "files" / "media" / "images" / "adversary").glob("density_*.png"))
    assert len(images) == 4  # iterations 0, 2 and 4, and the final density.png
