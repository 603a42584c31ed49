"""Collectors: the one protocol that regression, system identification and RL data share."""

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.regression import NoisySupport, SinusoidCollector
from armeta_rl.collectors.sysid import SysIdCollector

__all__ = ["TaskCollector", "NoisySupport", "SinusoidCollector", "SysIdCollector"]
