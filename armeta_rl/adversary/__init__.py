"""The distribution adversary p_φ: box-preserving normalizing flows with an exact density."""

from armeta_rl.adversary.flow_adversary import FlowAdversary
from armeta_rl.adversary.flows import PlanarBoxFlow, SplineBoxFlow, make_box_flow
from armeta_rl.adversary.objective import adversary_surrogate
from armeta_rl.adversary.sampler import TaskSampler

__all__ = ["FlowAdversary", "PlanarBoxFlow", "SplineBoxFlow", "TaskSampler",
           "adversary_surrogate", "make_box_flow"]
