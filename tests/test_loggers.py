"""Every logger of ``logger=`` gets the same keys, offline: CSV, TensorBoard
and MLflow (a SQLite store in the run directory) through TorchRL's loggers, with the adversary's
density pictures where the backend takes media (TensorBoard's images, MLflow's artifacts)."""

from __future__ import annotations

from pathlib import Path

import pytest

from armeta_rl.job import Job
from armeta_rl.trainers.training import run_training
from conftest import refusal, train_config

RUN = ("benchmark=point_nav", "method=ar_maml", "trainer.iterations=2", "trainer.log_every=1",
       "trainer.meta_batch=2", "trainer.checkpoint_every=2", "trainer.density_every=1",
       "benchmark.collector.episodes=2", "benchmark.collector.max_steps=8", "eval.n_tasks=2",
       "trainer.progress=false")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The same seeded run logged by each backend."""
    made = {}
    for kind in ("csv", "tensorboard", "mlflow"):
        made[kind] = tmp_path_factory.mktemp(kind) / "run"
        run_training(Job(train_config(*RUN, f"logger={kind}"), made[kind]))
    return made


def csv_keys(run: Path) -> set[str]:
    scalars = run / "logs" / "scalars"
    return {str(path.relative_to(scalars).with_suffix("")) for path in scalars.rglob("*.csv")}


def test_tensorboard_gets_the_csv_keys_and_the_density_pictures(runs):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(runs["tensorboard"] / "tensorboard"),
                              size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    tags = events.Tags()
    keys = csv_keys(runs["csv"])
    assert set(tags["scalars"]) == keys and {"train/gain", "eval/initial/after_3_steps"} <= keys
    csv_gain = (runs["csv"] / "logs" / "scalars" / "train" / "gain.csv").read_text().split()
    assert [round(e.value, 4) for e in events.Scalars("train/gain")] == [
        round(float(line.split(",")[1]), 4) for line in csv_gain]
    # a frame at iterations 0, 1 and 2, and the final picture
    assert tags["images"] == ["adversary/density"]
    assert len(events.Images("adversary/density")) == 4


def test_mlflow_gets_the_csv_keys_the_config_and_the_pictures_as_artifacts(runs):
    from mlflow import MlflowClient

    run_dir = runs["mlflow"]
    client = MlflowClient(f"sqlite:///{run_dir / 'mlflow.db'}")
    (experiment,) = [e for e in client.search_experiments() if e.name == run_dir.name]
    (run,) = client.search_runs([experiment.experiment_id])
    assert run.info.status == "FINISHED"
    assert set(run.data.metrics) == csv_keys(runs["csv"])
    assert run.data.params["benchmark.name"] == "point_nav"
    frames = [a.path for a in client.list_artifacts(run.info.run_id, "adversary/density")]
    assert sorted(Path(f).name for f in frames) == [
        "density.png", "iter_000000.png", "iter_000001.png", "iter_000002.png"]
    (animation,) = client.list_artifacts(run.info.run_id, "adversary/density_animation")
    assert animation.path.endswith("density.gif")


def test_an_unknown_logger_is_refused_in_one_line(capsys):
    from armeta_rl.cli import train

    line = refusal(train, ["logger=tensorbored"], capsys)
    assert "tensorboard" in line and "mlflow" in line
