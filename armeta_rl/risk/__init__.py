"""Risk principles: where tasks come from and how per-task losses become the leader's objective."""

from armeta_rl.risk.adversarial import AdversarialPrinciple
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.erm import ERMPrinciple
from armeta_rl.risk.groups import GroupDROPrinciple, WorstCasePrinciple
from armeta_rl.risk.tail import TailRiskPrinciple

__all__ = ["AdversarialPrinciple", "ERMPrinciple", "GroupDROPrinciple", "RiskPrinciple",
           "TailRiskPrinciple", "WorstCasePrinciple"]
