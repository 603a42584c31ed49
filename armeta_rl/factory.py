"""Builds a run's players from a composed Hydra config.

Leaders and risk principles are looked up by the names a method config gives
(``method.learner``, ``method.risk``) in :data:`LEARNERS` and :data:`PRINCIPLES`; each builder reads
its own section (``learner.<name>``, ``risk.<name>``) into the options its module declares, and
the model's sizes from the collector. A learner's builder and options live in its module, so adding
one is that module and one entry in :data:`LEARNERS`. Every builder takes the run's ``device``
(:func:`armeta_rl.devices.resolve_device`) as an argument and builds its player there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.collectors.base import TaskCollector
from armeta_rl.devices import CPU
from armeta_rl.errors import ConfigError
from armeta_rl.fields import section
from armeta_rl.learners.anil import AnilOptions, build_anil
from armeta_rl.learners.base import Leader
from armeta_rl.learners.cnp import CnpOptions, build_cnp
from armeta_rl.learners.maml import MamlOptions, build_maml
from armeta_rl.learners.maml_trpo import MamlTrpoOptions, build_maml_trpo
from armeta_rl.risk.adversarial import AdversarialPrinciple, ArOptions
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.erm import ERMPrinciple
from armeta_rl.risk.groups import DroOptions, GroupDROPrinciple, TrOptions, WorstCasePrinciple
from armeta_rl.risk.mpts import MptsOptions, MPTSPrinciple
from armeta_rl.risk.pdts import PdtsOptions, PDTSPrinciple
from armeta_rl.risk.tail import DrOptions, TailRiskPrinciple
from armeta_rl.tasks import TaskDistribution, TaskSpace, make_initial


def build_space(cfg: DictConfig) -> TaskSpace:
    """The benchmark's identifier box."""
    space = cfg.benchmark.space
    return TaskSpace(list(space.names), list(space.low), list(space.high))


def build_initial(
    cfg: DictConfig, space: TaskSpace, device: torch.device = CPU
) -> TaskDistribution:
    """The benchmark's initial task distribution p0, on ``device``."""
    initial = section(cfg, "benchmark.initial")
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


Builder = Callable[[DictConfig, TaskCollector, torch.device], Leader]
"""Builds a learner from a composed config, with its model's sizes from the collector
(:func:`armeta_rl.learners.base.sizes`), on the run's device."""


@dataclass(frozen=True)
class RLForm:
    """A learner's meta-RL form on episode data: its own config section ``learner.<section>``,
    its builder and its options."""

    section: str
    build: Builder
    options: type


@dataclass(frozen=True)
class Learner:
    """A registered meta-learner: its builder on regression and system-identification data
    (``build``), its options (``options``: a dataclass of :mod:`armeta_rl.config` fields, the type,
    range and default value of every key of its ``learner.<name>`` section), and its meta-RL form
    on episode data (``rl``; ``None``: it has none). The composed config's ``learner:`` section and
    its schema are derived from the options (:func:`learner_sections`)."""

    build: Builder
    options: type
    rl: RLForm | None = None


LEARNERS: dict[str, Learner] = {
    "maml": Learner(build_maml, MamlOptions, rl=RLForm("maml_trpo", build_maml_trpo,
                                                       MamlTrpoOptions)),
    "cnp": Learner(build_cnp, CnpOptions),
    "anil": Learner(build_anil, AnilOptions),
}
"""Every meta-learner ``method.learner`` may name; adding one is a module and an entry here
(docs/adding-a-learner.md)."""


def learner_sections() -> dict[str, type]:
    """The options of every ``learner.<name>`` section: each learner's, and its meta-RL form's."""
    sections = {}
    for name, learner in LEARNERS.items():
        sections[name] = learner.options
        if learner.rl is not None:
            sections[learner.rl.section] = learner.rl.options
    return sections


def _erm(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    return ERMPrinciple(initial)


def _ar(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    options = ArOptions(**section(cfg, "risk.ar"))
    adversary = FlowAdversary(space, initial, options.flow, **options.flow_kwargs)
    total_updates = max(1, cfg.trainer.iterations // options.update_every)
    return AdversarialPrinciple(adversary, options, total_updates=total_updates)


def _dr(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    return TailRiskPrinciple(initial, DrOptions(**section(cfg, "risk.dr")))


def _tr(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    return WorstCasePrinciple(initial, TrOptions(**section(cfg, "risk.tr")))


def _dro(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    return GroupDROPrinciple(initial, DroOptions(**section(cfg, "risk.dro")))


def _mpts(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    return MPTSPrinciple(initial, MptsOptions(**section(cfg, "risk.mpts")))


def _pdts(cfg: DictConfig, space: TaskSpace, initial: TaskDistribution) -> RiskPrinciple:
    return PDTSPrinciple(initial, PdtsOptions(**section(cfg, "risk.pdts")))


@dataclass(frozen=True)
class Principle:
    """A registered risk principle: its builder and its options (the type, range and default
    value of every key of its ``risk.<name>`` section; ``None``: it has no section, as ERM). The
    composed config's ``risk:`` section and its schema are derived from the options
    (:func:`risk_sections`)."""

    build: Callable[[DictConfig, TaskSpace, TaskDistribution], RiskPrinciple]
    options: type | None = None


PRINCIPLES: dict[str, Principle] = {
    "erm": Principle(_erm),
    "ar": Principle(_ar, ArOptions),
    "dr": Principle(_dr, DrOptions),
    "tr": Principle(_tr, TrOptions),
    "dro": Principle(_dro, DroOptions),
    "mpts": Principle(_mpts, MptsOptions),
    "pdts": Principle(_pdts, PdtsOptions),
}
"""Every risk principle ``method.risk`` may name."""


def risk_sections() -> dict[str, type]:
    """The options of every ``risk.<name>`` section."""
    return {name: entry.options for name, entry in PRINCIPLES.items() if entry.options is not None}


def build_leader(cfg: DictConfig, collector: TaskCollector, device: torch.device = CPU) -> Leader:
    """The learner named by ``method.learner``, in its meta-RL form when the collector gathers
    episodes (MAML is MAML-TRPO there; CNP has no meta-RL form), on ``device``."""
    from armeta_rl.collectors.episodes import EpisodeCollector

    name = cfg.method.learner
    if name not in LEARNERS:
        raise ConfigError("method.learner", name, f"allowed: {', '.join(LEARNERS)}")
    if not isinstance(collector, EpisodeCollector):
        return LEARNERS[name].build(cfg, collector, device)
    rl = LEARNERS[name].rl
    if rl is None:
        with_rl = [learner for learner, entry in LEARNERS.items() if entry.rl is not None]
        raise ConfigError("method", cfg.method.name,
                          f"benchmark {cfg.benchmark.name} gathers episodes: it supports methods "
                          f"whose learner is one of: {', '.join(with_rl)}")
    return rl.build(cfg, collector, device)


def build_principle(
    cfg: DictConfig, space: TaskSpace, initial: TaskDistribution, device: torch.device = CPU
) -> RiskPrinciple:
    """The risk principle named by ``method.risk``, on ``device`` (its task distributions, e.g.
    the flow adversary, and its state such as group weights)."""
    name = cfg.method.risk
    if name not in PRINCIPLES:
        raise ConfigError("method.risk", name, f"allowed: {', '.join(PRINCIPLES)}")
    return PRINCIPLES[name].build(cfg, space, initial).to(device)
