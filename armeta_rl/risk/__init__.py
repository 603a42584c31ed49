"""Risk principles: where tasks come from and how per-task losses become the leader's objective."""

from armeta_rl.risk.adversarial import AdversarialPrinciple
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.risk.erm import ERMPrinciple
from armeta_rl.risk.groups import GroupDROPrinciple, WorstCasePrinciple
from armeta_rl.risk.mpts import MPTSPrinciple
from armeta_rl.risk.pdts import PDTSPrinciple
from armeta_rl.risk.sampling import PrincipleSampler
from armeta_rl.risk.tail import TailRiskPrinciple

__all__ = ["AdversarialPrinciple", "ERMPrinciple", "GroupDROPrinciple", "MPTSPrinciple",
           "PDTSPrinciple", "PrincipleSampler", "RiskPrinciple", "TailRiskPrinciple",
           "WorstCasePrinciple"]
