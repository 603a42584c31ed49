"""Builds a run's players from a composed Hydra config.

Leaders and risk principles are looked up by the names a method config gives
(``method.learner``, ``method.risk``); each builder reads its own section
(``learner.<name>``, ``risk.<name>``), so adding a player is one function and one entry here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.errors import ConfigError
from armeta_rl.learners.base import Leader
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.tasks import TaskDistribution, TaskSpace, make_initial


def _section(cfg: DictConfig, key: str) -> dict[str, Any]:
    node = OmegaConf.select(cfg, key)
    return {} if node is None else OmegaConf.to_container(node, resolve=True)


def build_space(cfg: DictConfig) -> TaskSpace:
    """The benchmark's identifier box."""
    space = cfg.benchmark.space
    return TaskSpace(list(space.names), list(space.low), list(space.high))


def build_initial(cfg: DictConfig, space: TaskSpace) -> TaskDistribution:
    """The benchmark's initial task distribution p0."""
    initial = _section(cfg, "benchmark.initial")
    return make_initial(
        space, initial.get("kind", "uniform"), initial.get("loc"), initial.get("scale")
    )


def build_collector(cfg: DictConfig, key: str = "benchmark.collector") -> TaskCollector:
    """Instantiate the collector described at ``key`` (a Hydra ``_target_`` node); a collector
    with a ``check_space`` method is handed the benchmark's box, so a box its env cannot take
    (other identifier names or width, values outside the env's range) fails before training."""
    node = OmegaConf.select(cfg, key)
    if node is None or "_target_" not in node:
        raise ConfigError(
            key,
            None if node is None else OmegaConf.to_container(node),
            "needs a collector with a '_target_'",
        )
    try:
        collector = instantiate(node)
    except InstantiationException as error:
        # A collector's own ConfigError, not Hydra's wrapper around it, is what the CLI reports.
        if isinstance(error.__cause__, ConfigError):
            raise error.__cause__ from None
        raise
    check_space = getattr(collector, "check_space", None)
    if check_space is not None:
        check_space(build_space(cfg))
    return collector


def _maml(cfg: DictConfig, collector: TaskCollector) -> Leader:
    from armeta_rl.learners.maml import MAMLLeader
    from armeta_rl.learners.mlp import make_mlp

    opts = _section(cfg, "learner.maml")
    head = OmegaConf.select(cfg, "benchmark.model.head", default="none")
    target = OmegaConf.select(cfg, "benchmark.collector.target", default=None)
    if head == "tied_angle" and target != "next":
        raise ConfigError("benchmark.model.head", head,
                          f"predicts the next observation: needs benchmark.collector.target=next, "
                          f"not {target}")
    model = make_mlp(
        cfg.benchmark.model.in_features,
        cfg.benchmark.model.out_features,
        opts.pop("hidden", (128, 128, 128)),
        head,
    )
    return MAMLLeader(model, collector, **opts)


def _cnp(cfg: DictConfig, collector: TaskCollector) -> Leader:
    from armeta_rl.learners.cnp import CNPLeader

    head = OmegaConf.select(cfg, "benchmark.model.head", default="none")
    if head != "none":
        raise ConfigError("benchmark.model.head", head, "the CNP leader has no heads: use none")
    return CNPLeader(
        cfg.benchmark.model.in_features,
        cfg.benchmark.model.out_features,
        collector,
        **_section(cfg, "learner.cnp"),
    )


def _maml_trpo(cfg: DictConfig, collector: TaskCollector) -> Leader:
    from armeta_rl.learners.maml_trpo import MAMLTRPOLeader

    return MAMLTRPOLeader(collector, **_section(cfg, "learner.maml_trpo"))


def _erm(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    from armeta_rl.risk.erm import ERMPrinciple

    return ERMPrinciple(initial)


def _ar(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    from armeta_rl.adversary.flow_adversary import FlowAdversary
    from armeta_rl.risk.adversarial import AdversarialPrinciple

    opts = _section(cfg, "risk.ar")
    adversary = FlowAdversary(
        space, initial, opts.pop("flow", "spline"), **opts.pop("flow_kwargs", {})
    )
    total_updates = max(1, cfg.trainer.iterations // max(1, opts.get("update_every", 1)))
    return AdversarialPrinciple(adversary, total_updates=total_updates, **opts)


def _dr(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    from armeta_rl.risk.tail import TailRiskPrinciple

    return TailRiskPrinciple(initial, **_section(cfg, "risk.dr"))


def _tr(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    from armeta_rl.risk.groups import WorstCasePrinciple

    return WorstCasePrinciple(initial, **_section(cfg, "risk.tr"))


def _dro(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    from armeta_rl.risk.groups import GroupDROPrinciple

    return GroupDROPrinciple(initial, **_section(cfg, "risk.dro"))


LEADERS: dict[str, Callable[[DictConfig, TaskCollector], Leader]] = {
    "maml": _maml,
    "cnp": _cnp,
    "maml_trpo": _maml_trpo,
}
PRINCIPLES: dict[str, Callable[[DictConfig, TaskSpace, TaskDistribution], RiskPrinciple]] = {
    "erm": _erm,
    "ar": _ar,
    "dr": _dr,
    "tr": _tr,
    "dro": _dro,
}


def build_leader(cfg: DictConfig, collector: TaskCollector) -> Leader:
    """The leader named by ``method.learner``, through the benchmark's ``leaders`` map if it has
    one (on RL benchmarks ``maml`` means MAML-TRPO; CNP has no RL form)."""
    name = cfg.method.learner
    leaders = OmegaConf.select(cfg, "benchmark.leaders")
    if leaders is not None:
        if name not in leaders:
            raise ConfigError("method", cfg.method.name,
                              f"benchmark {cfg.benchmark.name} supports methods whose learner is "
                              f"one of: {', '.join(leaders)}")
        name = leaders[name]
    if name not in LEADERS:
        raise ConfigError("method.learner", name, f"allowed: {', '.join(LEADERS)}")
    return LEADERS[name](cfg, collector)


def build_principle(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    """The risk principle named by ``method.risk``."""
    name = cfg.method.risk
    if name not in PRINCIPLES:
        raise ConfigError("method.risk", name, f"allowed: {', '.join(PRINCIPLES)}")
    return PRINCIPLES[name](cfg, space, initial)
