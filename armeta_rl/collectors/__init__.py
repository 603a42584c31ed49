"""Collectors: the one protocol that regression, system identification and RL data share."""

from armeta_rl.collectors.base import Collector

__all__ = ["Collector"]
