"""Builds a run's players from a composed Hydra config.

Leaders and risk principles are looked up by the names a method config gives
(``method.learner``, ``method.risk``) in :data:`LEARNERS` and :data:`PRINCIPLES`; each builder reads
its own section (``learner.<name>``, ``risk.<name>``) and the model's sizes from the collector, so
adding a player is one function and one entry here. Every builder takes the run's ``device``
(:func:`armeta_rl.devices.resolve_device`) as an argument and builds its player there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.devices import CPU
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


def build_initial(
    cfg: DictConfig, space: TaskSpace, device: torch.device = CPU
) -> TaskDistribution:
    """The benchmark's initial task distribution p0, on ``device``."""
    initial = _section(cfg, "benchmark.initial")
    return make_initial(
        space, initial.get("kind", "uniform"), initial.get("loc"), initial.get("scale")
    ).to(device)


def build_collector(
    cfg: DictConfig, key: str = "benchmark.collector", device: torch.device = CPU
) -> TaskCollector:
    """Instantiate the collector described at ``key`` (a Hydra ``_target_`` node) with its data on
    ``device`` (every collector takes a ``device`` argument); a collector with a ``check_space``
    method is handed the benchmark's box, so a box its env cannot take
    (other identifier names or width, values outside the env's range) fails before training."""
    node = OmegaConf.select(cfg, key)
    if node is None or "_target_" not in node:
        raise ConfigError(
            key,
            None if node is None else OmegaConf.to_container(node),
            "needs a collector with a '_target_'",
        )
    try:
        collector = instantiate(node, device=str(device))
    except InstantiationException as error:
        # A collector's own ConfigError, not Hydra's wrapper around it, is what the CLI reports.
        if isinstance(error.__cause__, ConfigError):
            raise error.__cause__ from None
        raise
    check_space = getattr(collector, "check_space", None)
    if check_space is not None:
        check_space(build_space(cfg))
    return collector


OLD_SIZE_KEYS = ("benchmark.model.in_features", "benchmark.model.out_features")
"""Where configs saved before sizes came from the collector state them."""


def sizes(cfg: DictConfig, collector: TaskCollector, stated: tuple[str, str]) -> tuple[int, int]:
    """The leader's input and output sizes, as the collector defines them (``in_features`` and
    ``out_features``: x and y, or the env's observation and action). A config saved before sizes
    came from the collector states them at the keys ``stated``: such a value is accepted when it
    is the collector's, so old runs load, and refused otherwise."""
    defined = int(collector.in_features), int(collector.out_features)
    for key, size in zip(stated, defined):
        value = OmegaConf.select(cfg, key, default=None)
        if value is not None and value != size:
            raise ConfigError(key, value, f"is defined by the collector: {size}")
    return defined


def _maml(cfg: DictConfig, collector: TaskCollector, device: torch.device) -> Leader:
    from armeta_rl.learners.maml import MAMLLeader
    from armeta_rl.learners.mlp import make_mlp

    opts = _section(cfg, "learner.maml")
    head = OmegaConf.select(cfg, "benchmark.model.head", default="none")
    target = OmegaConf.select(cfg, "benchmark.collector.target", default=None)
    if head == "tied_angle" and target != "next":
        raise ConfigError("benchmark.model.head", head,
                          f"predicts the next observation: needs benchmark.collector.target=next, "
                          f"not {target}")
    model = make_mlp(*sizes(cfg, collector, OLD_SIZE_KEYS), opts.pop("hidden", (128, 128, 128)),
                     head).to(device)
    return MAMLLeader(model, collector, **opts)


def _cnp(cfg: DictConfig, collector: TaskCollector, device: torch.device) -> Leader:
    from armeta_rl.learners.cnp import CNPLeader

    head = OmegaConf.select(cfg, "benchmark.model.head", default="none")
    if head != "none":
        raise ConfigError("benchmark.model.head", head, "the CNP leader has no heads: use none")
    return CNPLeader(*sizes(cfg, collector, OLD_SIZE_KEYS), collector,
                     **_section(cfg, "learner.cnp"), device=device)


def _maml_trpo(cfg: DictConfig, collector: TaskCollector, device: torch.device) -> Leader:
    from armeta_rl.learners.maml_trpo import MAMLTRPOLeader

    old_keys = ("learner.maml_trpo.obs_dim", "learner.maml_trpo.action_dim")
    obs_dim, action_dim = sizes(cfg, collector, old_keys)
    opts = {k: v for k, v in _section(cfg, "learner.maml_trpo").items()
            if f"learner.maml_trpo.{k}" not in old_keys}
    return MAMLTRPOLeader(collector, obs_dim=obs_dim, action_dim=action_dim, **opts,
                          device=device)


def _anil(cfg: DictConfig, collector: TaskCollector, device: torch.device) -> Leader:
    from armeta_rl.learners.anil import ANILLeader, BodyHead

    opts = _section(cfg, "learner.anil")
    model = BodyHead(*sizes(cfg, collector, OLD_SIZE_KEYS), opts.pop("hidden")).to(device)
    return ANILLeader(model, collector, **opts)


@dataclass(frozen=True)
class Learner:
    """A registered meta-learner: its builder on regression and system-identification data
    (``build``), and the builder of its meta-RL form on episode data (``rl``; ``None``: it has
    none). A builder reads its own ``learner.<name>`` section (defaults in
    ``configs/train.yaml``, types and ranges in :mod:`armeta_rl.config`) and takes the model's
    sizes from the collector (:func:`sizes`) and builds it on the run's device."""

    build: Callable[[DictConfig, TaskCollector, torch.device], Leader]
    rl: Callable[[DictConfig, TaskCollector, torch.device], Leader] | None = None


LEARNERS: dict[str, Learner] = {
    "maml": Learner(_maml, rl=_maml_trpo),
    "cnp": Learner(_cnp),
    "anil": Learner(_anil),
}
"""Every meta-learner ``method.learner`` may name; adding one is a module and an entry here
(docs/adding-a-learner.md)."""


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


PRINCIPLES: dict[str, Callable[[DictConfig, TaskSpace, TaskDistribution], RiskPrinciple]] = {
    "erm": _erm,
    "ar": _ar,
    "dr": _dr,
    "tr": _tr,
    "dro": _dro,
}


def build_leader(cfg: DictConfig, collector: TaskCollector, device: torch.device = CPU) -> Leader:
    """The learner named by ``method.learner``, in its meta-RL form when the collector gathers
    episodes (MAML is MAML-TRPO there; CNP has no meta-RL form), on ``device``."""
    from armeta_rl.collectors.episodes import EpisodeCollector

    name = cfg.method.learner
    if name not in LEARNERS:
        raise ConfigError("method.learner", name, f"allowed: {', '.join(LEARNERS)}")
    if not isinstance(collector, EpisodeCollector):
        return LEARNERS[name].build(cfg, collector, device)
    build = LEARNERS[name].rl
    if build is None:
        with_rl = [learner for learner, entry in LEARNERS.items() if entry.rl is not None]
        raise ConfigError("method", cfg.method.name,
                          f"benchmark {cfg.benchmark.name} gathers episodes: it supports methods "
                          f"whose learner is one of: {', '.join(with_rl)}")
    return build(cfg, collector, device)


def build_principle(
    cfg: DictConfig, space: TaskSpace, initial: TaskDistribution, device: torch.device = CPU
) -> RiskPrinciple:
    """The risk principle named by ``method.risk``, on ``device`` (its task distributions, e.g.
    the flow adversary, and its state such as group weights)."""
    name = cfg.method.risk
    if name not in PRINCIPLES:
        raise ConfigError("method.risk", name, f"allowed: {', '.join(PRINCIPLES)}")
    return PRINCIPLES[name](cfg, space, initial).to(device)
