"""Every method trains through the CLI; the RL benchmarks train end to end."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from armeta_rl.config import schema, validate
from armeta_rl.config_files import group_choices
from armeta_rl.errors import ConfigError
from armeta_rl.factory import (
    build_collector,
    build_initial,
    build_leader,
    build_principle,
    build_space,
)
from armeta_rl.job import Job
from armeta_rl.trainers.players import saved_run
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, moved_players

METHODS = [
    "maml",
    "dr_maml",
    "tr_maml",
    "dro_maml",
    "ar_maml",
    "cnp",
    "dr_cnp",
    "tr_cnp",
    "dro_cnp",
    "ar_cnp",
    "mpts_maml",
    "pdts_maml",
    "mpts_cnp",
    "pdts_cnp",
]


LEARNED_PRINCIPLES = ("ar_", "tr_", "dro_", "mpts_", "pdts_")
"""Methods whose task source learns as the leader trains: the flow adversary, TR's and DRO's
weights over task groups, the risk model (DR's tail of the batch keeps nothing)."""


@pytest.mark.parametrize("benchmark", ["sinusoid_uniform", "acrobot_normal"])
def test_every_method_trains_a_few_iterations_through_the_cli(tmp_path, benchmark):
    """One ``-m`` sweep of every method: each run's report is its own, and each trained: its
    leader (and, for the learning task sources, its principle) moved from where its seed
    started it."""
    assert sorted(group_choices("method")) == sorted(METHODS)
    command = [
        sys.executable,
        "-c",
        "import sys; from armeta_rl.cli import train; sys.exit(train())",
        "-m",
        f"method={','.join(METHODS)}",
        f"benchmark={benchmark}",
        "trainer.iterations=3",
        "trainer.meta_batch=8",
        "eval.n_tasks=10",
        "logger=none",
        "trainer.progress=false",
        f"hydra.sweep.dir={tmp_path}",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    for job, method in enumerate(METHODS):
        run = tmp_path / f"{job}_{benchmark}_{method}_seed0"
        report = json.loads((run / "eval.json").read_text())
        assert report["method"] == method and report["benchmark"] == benchmark
        assert report["metric"] == "mse" and report["initial"]["n_tasks"] == 10
        assert ("adversarial" in report) == method.startswith("ar_")
        moved = moved_players(saved_run(run, "run"), run)
        assert moved == {"leader": True, "principle": method.startswith(LEARNED_PRINCIPLES)}


@pytest.mark.parametrize("benchmark", ["point_nav", "ant_goal_smoke"])
@pytest.mark.parametrize("method", ["maml", "ar_maml", "dr_maml"])
def test_rl_benchmarks_train_end_to_end(tmp_path, benchmark, method):
    cfg = compose_train(
        *SMALL_RUN,
        f"benchmark={benchmark}",
        f"method={method}",
        "trainer.iterations=2",
        "trainer.meta_batch=3",
        "eval.n_tasks=3",
        "benchmark.collector.episodes=2",
        "benchmark.collector.max_steps=10",
        "logger=csv",
    )
    config = validate(cfg)
    report = run_training(Job(config, tmp_path))
    assert report["metric"] == "return"
    assert ("adversarial" in report) == (method == "ar_maml")
    assert moved_players(config, tmp_path) == {"leader": True, "principle": method == "ar_maml"}
    for curve in ("return_pre", "return_post"):
        assert (tmp_path / "logs" / "scalars" / "train" / f"{curve}.csv").is_file()


def test_cnp_has_no_rl_form():
    cfg = compose_train(*SMALL_RUN, "benchmark=point_nav", "method=cnp")
    with pytest.raises(ConfigError, match="supports methods whose learner is one of: maml"):
        run_training(Job(validate(cfg), Path("/nonexistent")))


@pytest.mark.parametrize(
    "benchmark,method", [("acrobot_uniform", "maml"), ("sinusoid_uniform", "cnp"),
                         ("point_nav_plain", "maml")],
)
def test_model_sizes_come_from_the_collector(benchmark, method):
    """The model's input and output sizes are the data's."""
    config = validate(compose_train(*SMALL_RUN, f"benchmark={benchmark}", f"method={method}"))
    space = build_space(config.benchmark.space)
    collector = build_collector(config.benchmark.collector, "benchmark.collector", space)
    sizes = collector.in_features, collector.out_features
    tasks = build_initial(config.benchmark.initial, space).sample(2)
    leader = build_leader(config.method, config.learner, collector, config.benchmark.model)
    if benchmark == "point_nav_plain":
        episodes = collector.collect(tasks, policy=leader.net)
        assert sizes == (episodes["observation"].shape[-1], episodes["action"].shape[-1])
    else:
        data = collector.collect(tasks)
        assert sizes == (data["support", "x"].shape[-1], data["support", "y"].shape[-1])
        assert leader.evaluate(data).shape == (2,)


def registered(group: str) -> dict[str, type]:
    """The options dataclass of every registered ``<group>.<name>`` section."""
    typed = schema()
    return {name: OmegaConf.get_type(typed[group][name]) for name in typed[group]}


def out_of_range(field: dataclasses.Field) -> object:
    """A value of ``field``'s type that its range refuses."""
    return {"list[int]": [-1], "str": "bogus"}.get(str(field.type), -1)


@pytest.mark.parametrize(("group", "name", "options"), [
    (group, name, options) for group in ("learner", "risk")
    for name, options in registered(group).items()])
def test_options_refuse_a_bad_value_under_their_own_section(group, name, options):
    """A learner's or a risk principle's options built from Python are checked when made,
    naming the key of their own section."""
    for field in dataclasses.fields(options):
        if field.metadata.get("test") is not None:
            with pytest.raises(ConfigError, match=f"'{group}.{name}.{field.name}' = "):
                options(**{field.name: out_of_range(field)})


@pytest.mark.parametrize(("name", "options"), registered("risk").items())
def test_a_principle_built_from_python_has_the_values_of_the_default_run(name, options):
    """The composed ``risk.<name>`` section of the default run is its options' defaults, and the
    builder hands them to the principle: a principle made from Python with ``options()`` (TR's
    and DRO's tuned step sizes included) is the one ``armeta-train method=<name>_maml`` trains."""
    config = validate(compose_train(f"method={name}_maml"))
    assert config.risk[name] == options()
    space = build_space(config.benchmark.space)
    built = build_principle(config.method, config.risk, space,
                            build_initial(config.benchmark.initial, space), 100)
    kept = {spec.name for spec in dataclasses.fields(options)} & set(vars(built))
    assert kept
    for field in kept:
        assert getattr(built, field) == getattr(options(), field), field
