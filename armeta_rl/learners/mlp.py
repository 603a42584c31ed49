"""The paper's regression network (appendix "Neural Architectures & Optimization")."""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn

from armeta_rl.errors import ConfigError


def make_mlp(
    in_features: int,
    out_features: int,
    hidden: Sequence[int] = (128, 128, 128),
    activation: type[nn.Module] = nn.ReLU,
) -> nn.Sequential:
    """MLP ``in → hidden… → out`` with ``activation`` between layers (paper: 3×128, ReLU)."""
    if not hidden or any(int(h) < 1 for h in hidden):
        raise ConfigError("learner.maml.hidden", list(hidden), "needs one or more sizes >= 1")
    sizes = [in_features, *map(int, hidden)]
    layers: list[nn.Module] = []
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(fan_in, fan_out), activation()]
    layers.append(nn.Linear(sizes[-1], out_features))
    return nn.Sequential(*layers)
