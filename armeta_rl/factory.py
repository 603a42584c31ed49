"""Builds a run's players from its typed config sections.

Leaders and risk principles are looked up by the names a method config gives
(``method.learner``, ``method.risk``) in :data:`LEARNERS` and :data:`PRINCIPLES`; each builder
receives its own options (the ``learner.<name>`` or ``risk.<name>`` section its module declares
and registers), and takes the model's sizes from the collector. A learner's builder and options
live in its module, so adding one is that module, one entry in :data:`LEARNERS` and its line in
``configs/train.yaml``. Every builder takes the run's ``torch.device``
(:func:`armeta_rl.devices.resolve_device`) as an argument and builds its player there.
Importing this module registers every learner's and principle's section in Hydra's ConfigStore.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.options import ArOptions
from armeta_rl.collectors.base import TaskCollector
from armeta_rl.config import InitialConfig, MethodConfig, SpaceConfig
from armeta_rl.devices import CPU
from armeta_rl.errors import ConfigError
from armeta_rl.learners.anil import build_anil
from armeta_rl.learners.base import Leader
from armeta_rl.learners.cnp import build_cnp
from armeta_rl.learners.maml import build_maml
from armeta_rl.learners.maml_ppo import build_maml_ppo
from armeta_rl.learners.maml_trpo import build_maml_trpo
from armeta_rl.risk.adversarial import AdversarialPrinciple
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.erm import ERMPrinciple
from armeta_rl.risk.groups import GroupDROPrinciple, WorstCasePrinciple
from armeta_rl.risk.mpts import MPTSPrinciple
from armeta_rl.risk.pdts import PDTSPrinciple
from armeta_rl.risk.tail import TailRiskPrinciple
from armeta_rl.tasks import TaskDistribution, TaskSpace, make_initial


def build_space(space: SpaceConfig) -> TaskSpace:
    """The benchmark's identifier box."""
    return TaskSpace(list(space.names), list(space.low), list(space.high))


def build_initial(initial: InitialConfig, space: TaskSpace, device: torch.device = CPU
                  ) -> TaskDistribution:
    """The benchmark's initial task distribution p0, on ``device``."""
    return make_initial(space, initial.kind, initial.loc, initial.scale).to(device)


def build_collector(node: Mapping[str, Any], key: str, space: TaskSpace,
                    device: torch.device = CPU) -> TaskCollector:
    """Instantiate the collector of the Hydra ``_target_`` node ``node`` (the config's ``key``)
    with its data on ``device`` (every collector takes a ``device`` argument); a collector with a
    ``check_space`` method is handed the benchmark's box, so a box its env cannot take
    (other identifier names or width, values outside the env's range) fails before training."""
    if "_target_" not in node:
        raise ConfigError(key, dict(node), "needs a collector with a '_target_'")
    try:
        collector = instantiate(node, device=device)
    except InstantiationException as error:
        # A collector's own ConfigError, not Hydra's wrapper around it, is what the CLI reports.
        if isinstance(error.__cause__, ConfigError):
            raise error.__cause__ from None
        raise
    check_space = getattr(collector, "check_space", None)
    if check_space is not None:
        check_space(space)
    return collector


Builder = Callable[[Any, TaskCollector, torch.device, Mapping[str, Any]], Leader]
"""Builds a learner from its options, with its model's sizes from the collector and the
benchmark's model choices (``benchmark.model``: a head), on the run's device."""


@dataclass(frozen=True)
class RLForm:
    """A learner's meta-RL form on episode data: its own config section ``learner.<section>``
    and its builder."""

    section: str
    build: Builder


@dataclass(frozen=True)
class Learner:
    """A registered meta-learner: its builder on regression and system-identification data
    (``build``, handed the options of its ``learner.<name>`` section; ``None``: it learns from
    episodes only, as MAML-PPO), and its meta-RL form on episode data (``rl``; ``None``: it has
    none)."""

    build: Builder | None
    rl: RLForm | None = None


LEARNERS: dict[str, Learner] = {
    "maml": Learner(build_maml, rl=RLForm("maml_trpo", build_maml_trpo)),
    "cnp": Learner(build_cnp),
    "anil": Learner(build_anil),
    "maml_ppo": Learner(None, rl=RLForm("maml_ppo", build_maml_ppo)),
}
"""Every meta-learner ``method.learner`` may name; adding one is a module and an entry here
(docs/adding-a-learner.md)."""


def _erm(options: None, space: TaskSpace, initial: TaskDistribution, iterations: int
         ) -> RiskPrinciple:
    return ERMPrinciple(initial)


def _ar(options: ArOptions, space: TaskSpace, initial: TaskDistribution, iterations: int,
        reference_loss: Callable[[torch.Tensor], torch.Tensor] | None = None) -> RiskPrinciple:
    adversary = FlowAdversary(space, initial, options.flow, **options.flow_kwargs)
    total_updates = max(1, iterations // options.update_every)
    return AdversarialPrinciple(adversary, options, total_updates=total_updates,
                                reference_loss=reference_loss)


def _on_p0(principle: Callable[[TaskDistribution, Any], RiskPrinciple]) -> PrincipleBuilder:
    """The builder of a principle made from p0 and its options alone (DR, TR, DRO, MPTS,
    PDTS)."""

    def build(options: Any, space: TaskSpace, initial: TaskDistribution, iterations: int
              ) -> RiskPrinciple:
        return principle(initial, options)

    return build


PrincipleBuilder = Callable[[Any, TaskSpace, TaskDistribution, int], RiskPrinciple]
"""Builds a risk principle from its options (``None`` where it has no section, as ERM), the
identifier box, p0 and the run's number of iterations."""

PRINCIPLES: dict[str, PrincipleBuilder] = {
    "erm": _erm, "ar": _ar, "dr": _on_p0(TailRiskPrinciple), "tr": _on_p0(WorstCasePrinciple),
    "dro": _on_p0(GroupDROPrinciple), "mpts": _on_p0(MPTSPrinciple),
    "pdts": _on_p0(PDTSPrinciple),
}
"""Every risk principle ``method.risk`` may name."""

TAKES_REFERENCE = frozenset({"ar"})
"""The principles whose builder also takes ``reference_loss=``, the benchmark's reference loss
L*(τ) (the collector's ``reference_loss``, or ``None``): ``risk.ar.signal=regret`` ascends
L − L*."""


def check_method(method: MethodConfig) -> None:
    """``method.learner`` and ``method.risk`` name a registered learner and risk principle."""
    if method.learner not in LEARNERS:
        raise ConfigError("method.learner", method.learner, f"allowed: {', '.join(LEARNERS)}")
    if method.risk not in PRINCIPLES:
        raise ConfigError("method.risk", method.risk, f"allowed: {', '.join(PRINCIPLES)}")


def build_leader(method: MethodConfig, sections: Mapping[str, Any], collector: TaskCollector,
                 model: Mapping[str, Any], device: torch.device = CPU) -> Leader:
    """The learner ``method.learner`` with its options from ``sections`` (the config's
    ``learner:``), in its meta-RL form when the collector gathers episodes (MAML is MAML-TRPO
    there; CNP has no meta-RL form), on ``device``."""
    from armeta_rl.collectors.episodes import EpisodeCollector

    check_method(method)
    learner = LEARNERS[method.learner]
    if isinstance(collector, EpisodeCollector):
        if learner.rl is None:
            with_rl = [name for name, entry in LEARNERS.items() if entry.rl is not None]
            raise ConfigError("method", method.name,
                              f"the benchmark gathers episodes: it supports methods whose "
                              f"learner is one of: {', '.join(with_rl)}")
        build, section = learner.rl.build, learner.rl.section
    elif learner.build is None:
        raise ConfigError("method.learner", method.learner, "learns from episodes: this "
                          "benchmark has none (point_nav, ant_goal have)")
    else:
        build, section = learner.build, method.learner
    return build(sections[section], collector, device, model)


def build_principle(method: MethodConfig, sections: Mapping[str, Any], space: TaskSpace,
                    initial: TaskDistribution, iterations: int, device: torch.device = CPU,
                    collector: TaskCollector | None = None) -> RiskPrinciple:
    """The risk principle ``method.risk`` with its options from ``sections`` (the config's
    ``risk:``), on ``device`` (its task distributions, e.g. the flow adversary, and its state
    such as group weights); ``iterations`` plans the adversary's learning-rate schedule. A
    principle of :data:`TAKES_REFERENCE` gets ``collector``'s ``reference_loss`` (``None`` if it
    has none)."""
    check_method(method)
    options = sections.get(method.risk)
    build = PRINCIPLES[method.risk]
    if method.risk in TAKES_REFERENCE:
        reference = getattr(collector, "reference_loss", None)
        return build(options, space, initial, iterations, reference_loss=reference).to(device)
    return build(options, space, initial, iterations).to(device)
