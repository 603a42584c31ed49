"""Shared fixtures: one torch thread, Hydra configs composed as the CLI composes them, and the
benchmark harness as a module."""

from __future__ import annotations

import importlib.util
import logging
import os
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import mujoco
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from armeta_rl.cli.compose import config_dir
from armeta_rl.config import TrainConfig, validate

torch.set_num_threads(1)
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")
# Ray nodes started by the tests listen on the loopback only: Ray otherwise advertises this
# machine's network address even for a single-machine instance.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")

SMALL_RUN = (
    "trainer.iterations=6",
    "trainer.checkpoint_every=3",
    "trainer.log_every=2",
    "trainer.progress=false",
    "eval.n_tasks=20",
    "logger=none",
    "trainer.density_every=0",
)
"""Overrides that make any benchmark/method run in a couple of seconds."""


@pytest.fixture(autouse=True)
def _no_log_file_left_open():
    """After each test, the log files a Hydra job run in this process attached to the root logger
    (``armeta-train.log``) are detached and closed, so that no later test's garbage collection
    finds one open. Only file handlers: restoring the whole logging state here, as
    :func:`in_process` does around one command, would also restore pytest's own capture handlers
    of the setup phase into the teardown phase."""
    yield
    root = logging.getLogger()
    for handler in root.handlers[:]:
        if isinstance(handler, logging.FileHandler):
            root.removeHandler(handler)
            handler.close()


def compose_train(*overrides: str) -> DictConfig:
    """The ``armeta-train`` config for ``overrides``."""
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        return compose("train", overrides=list(overrides))


def train_config(*overrides: str) -> TrainConfig:
    """The ``armeta-train`` config for ``overrides``, validated as the CLI validates it."""
    return validate(compose_train(*overrides))


def in_process(command: Callable[[list[str]], int], args: list[str],
               capsys: pytest.CaptureFixture) -> tuple[int, str, str]:
    """``command`` (:func:`armeta_rl.cli.train` or ``evaluate``) run in this process on the
    command line ``args``: its exit code, stdout and stderr. A process of its own costs a second
    or more of imports per case; the tests that run the programs as processes check that their
    exit codes and streams are these. A command that got as far as Hydra's job set up logging to
    the captured streams, which close with the test, and to the run's log file: the loggers are
    restored as they were, so that a later test's logs do not go to a closed stream, and the
    handlers the job attached are closed, so that no log file is left open."""
    known = logging.Logger.manager.loggerDict.values()
    loggers = [logging.getLogger(), *(lg for lg in known if isinstance(lg, logging.Logger))]
    saved = [(logger, logger.handlers[:], logger.level, logger.propagate) for logger in loggers]
    try:
        code = command(list(args))
    finally:
        for logger, handlers, level, propagate in saved:
            for attached in set(logger.handlers) - set(handlers):
                attached.close()
            logger.handlers[:] = handlers
            logger.setLevel(level)
            logger.propagate = propagate
    out, err = capsys.readouterr()
    return code, out, err


def refusal(command: Callable[[list[str]], int], args: list[str],
            capsys: pytest.CaptureFixture) -> str:
    """The one line :func:`in_process` ``command`` writes to stderr when it refuses ``args``
    with exit code 2."""
    code, _, err = in_process(command, args, capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def raw_mjdata(model: mujoco.MjModel, sim) -> list[mujoco.MjData]:
    """One MjData of ``model`` per simulation of the ``mujoco.batch.Batch`` ``sim``, at that
    simulation's state (qpos, qvel): the raw references the batched MuJoCo envs are checked
    against."""
    datas = []
    for qpos, qvel in zip(sim.bind("qpos"), sim.bind("qvel")):
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = qpos, qvel
        datas.append(data)
    return datas


def collector_of(cfg: DictConfig, key: str = "collector"):
    """The collector ``benchmark.<key>`` of the composed ``cfg``, on the CPU."""
    from armeta_rl.factory import build_collector, build_space

    benchmark = validate(cfg).benchmark
    return build_collector(getattr(benchmark, key), f"benchmark.{key}",
                           build_space(benchmark.space))


def players_of(cfg: DictConfig):
    """The players of the composed ``cfg`` (:func:`armeta_rl.trainers.players.build_players`)."""
    from armeta_rl.trainers.players import build_players

    return build_players(validate(cfg))


@pytest.fixture
def sinusoid_cfg() -> DictConfig:
    return compose_train(*SMALL_RUN)


def cross_evaluate(learner_dir, adversary_dir, eval_overrides=None, device="cpu", shifts=None,
                   initial=True) -> dict:
    """What ``armeta-eval learner=… adversary=…`` scores, from Python: the saved runs' configs
    (``eval_overrides`` replacing the learner's ``eval.*``) loaded onto ``device``, then
    :func:`~armeta_rl.trainers.report.evaluate_runs`."""
    from armeta_rl.trainers.players import saved_run
    from armeta_rl.trainers.report import evaluate_runs

    learner = saved_run(learner_dir, "learner", device, {"eval": eval_overrides or {}})
    adversary = None if adversary_dir is None else saved_run(adversary_dir, "adversary", device)
    return evaluate_runs(learner_dir, learner, adversary_dir, adversary, shifts, initial)


def _tensors(state, path: tuple = ()) -> dict[tuple, torch.Tensor]:
    """Every tensor of a (nested) state dict, by its path."""
    if isinstance(state, torch.Tensor):
        return {path: state}
    items = (state.items() if isinstance(state, dict)
             else enumerate(state) if isinstance(state, (list, tuple)) else ())
    return {found: tensor for key, value in items
            for found, tensor in _tensors(value, (*path, key)).items()}


def moved_players(config: TrainConfig, run_dir) -> dict[str, bool]:
    """Which players of the finished run in ``run_dir`` differ from those its seed builds (the
    run's starting point): per ``leader`` and ``principle`` (the adversary, the risk model),
    whether any tensor of its initial state dict changed (an optimizer's state, which training
    adds, is not compared). Training that updates nothing leaves both ``False``; a principle
    without parameters (MAML's p0) stays ``False``."""
    from armeta_rl.trainers.players import build_players, restore_players

    start, end = build_players(config), restore_players(run_dir, "run", config)
    moved = {}
    for name in ("leader", "principle"):
        before = _tensors(getattr(start, name).state_dict())
        after = _tensors(getattr(end, name).state_dict())
        moved[name] = any(not torch.equal(tensor, after[path])
                          for path, tensor in before.items() if path in after)
    return moved


@pytest.fixture(scope="module")
def timing() -> ModuleType:
    """``benchmarks/timing.py``, the benchmark harness (a script folder, not a package), loaded
    as a module for the tests of what it measures and writes."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "timing.py"
    spec = importlib.util.spec_from_file_location("timing", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
