"""The paper's regression network (appendix "Neural Architectures & Optimization")."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from armeta_rl.errors import ConfigError


class MLP(nn.Module):
    """ReLU MLP ``in → hidden… → out`` whose layers compute ``x @ W + b`` with ``W`` stored
    ``[fan_in, fan_out]``.

    Storing the weights input-major (``nn.Linear`` stores ``[fan_out, fan_in]`` and multiplies by
    ``Wᵀ``) matters for batched MAML: the per-task weight gradients of ``vmap(grad(...))`` and of
    the outer backward then come out in ``W``'s own memory layout, so θ − γ∇L and the sum of
    per-task meta-gradients over tasks run on matching, contiguous strides instead of mixing a
    transposed layout with a plain one (much slower per elementwise op on the CPU).

    Parameters are drawn exactly as ``nn.Linear`` draws them, so a seed gives the same function.
    """

    def __init__(self, sizes: Sequence[int]) -> None:
        super().__init__()
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            layer = nn.Linear(fan_in, fan_out)
            self.weights.append(nn.Parameter(layer.weight.detach().t().contiguous()))
            self.biases.append(nn.Parameter(layer.bias.detach()))

    def forward(self, x: Tensor) -> Tensor:
        """Network output ``[..., out]`` for inputs ``[..., in]``."""
        last = len(self.weights) - 1
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = x @ weight + bias
            if index < last:
                x = relu(x)
        return x

    def layers(self, params: dict[str, Tensor] | None = None) -> list[tuple[Tensor, Tensor]]:
        """``(W [fan_in, fan_out], b [fan_out])`` of every layer, in order, from ``params`` (named
        as ``named_parameters()`` names them) or from the module's own parameters."""
        params = dict(self.named_parameters()) if params is None else params
        return [(params[f"weights.{i}"], params[f"biases.{i}"]) for i in range(len(self.weights))]


def relu(x: Tensor) -> Tensor:
    """max(x, 0): ``torch.relu`` eagerly and, while ``torch.compile`` traces (the
    ``learner.maml.compile`` switch), the same function written (x + |x|) / 2.

    relu's backward keeps a boolean mask of the active units, and inductor's CPU code stores
    boolean masks far more slowly than the ReLU itself: with ``torch.relu`` the compiled
    system-identification MAML step is slower than the eager one (docs/speed-options.md). The
    (x + |x|) / 2 form keeps a float tensor instead. Its values equal relu's exactly (x + x = 2x
    and x + (−x) = 0 are exact in floating point); only the gradient at exactly x = 0 differs (1/2
    instead of 0).
    """
    if torch.compiler.is_compiling():
        return (x + x.abs()) * 0.5
    return torch.relu(x)


class TiedAngleHead(nn.Module):
    """The output head of the paper's system-identification network (its listing's
    ``Meta_Learner.forward`` for ``task_type`` ``'pendulum'`` and ``'acrobot'``).

    The observation of both systems is k (cos, sin) pairs of angles followed by k angular
    velocities (pendulum k = 1, acrobot k = 2). The body MLP outputs one value a_i per angle and
    the head returns ``(cos a_1, sin a_1, …, cos a_k, sin a_k, a_1, …, a_k)``: each predicted
    velocity is the predicted angle itself. The next observation's velocities are not its angles,
    so no network with this head fits the data exactly; on the paper's data (one 200-step
    random-policy episode per task, targets the next observation) the best value of a per
    transition leaves a mean squared error of about 0.50 on the pendulum and 0.22 on the acrobot
    (docs/protocol.md), the scale of the paper's Table 1 rows. It is offered to reproduce those
    rows (``benchmark.model.head=tied_angle``), not as a model to use.

    The paper's body has 2k outputs, of which the head reads the first k; this one has k (the
    same function class; only the initial draw of the unused weights differs).
    """

    def __init__(self, body: MLP) -> None:
        super().__init__()
        self.body = body

    def forward(self, x: Tensor) -> Tensor:
        """Predicted next observation ``[..., 3k]`` for inputs ``[..., in]``."""
        angles = self.body(x)
        pairs = torch.stack([angles.cos(), angles.sin()], -1).flatten(-2)
        return torch.cat([pairs, angles], -1)


HEADS = ("none", "tied_angle")


def make_mlp(in_features: int, out_features: int, hidden: Sequence[int] = (128, 128, 128),
             head: str = "none") -> MLP | TiedAngleHead:
    """MLP ``in → hidden… → out`` with ReLU between layers (paper: 3×128, ReLU); with
    ``head="tied_angle"`` the paper's system-identification head on an MLP with ``out / 3``
    outputs (:class:`TiedAngleHead`).

    Examples:
        >>> import torch
        >>> from armeta_rl.learners import make_mlp
        >>> net = make_mlp(2, 1, hidden=[3, 3])
        >>> [tuple(weight.shape) for weight, _ in net.layers()]  # W stored [fan_in, fan_out]
        [(2, 3), (3, 3), (3, 1)]
        >>> for weight, bias in net.layers():  # every weight 1, every bias 0
        ...     _ = weight.data.fill_(1.0), bias.data.zero_()
        >>> net(torch.tensor([[1.0, 2.0], [-1.0, -2.0]]))  # 3 units of 3, then 3 of 9; ReLU cuts -3
        tensor([[27.],
                [ 0.]], grad_fn=<AddBackward0>)
    """
    if not hidden or any(int(h) < 1 for h in hidden):
        raise ConfigError("learner.maml.hidden", list(hidden), "needs one or more sizes >= 1")
    if head not in HEADS:
        raise ConfigError("benchmark.model.head", head, f"allowed: {', '.join(HEADS)}")
    if head == "none":
        return MLP([int(in_features), *map(int, hidden), int(out_features)])
    if int(out_features) % 3:
        raise ConfigError("benchmark.model.head", head,
                          f"needs out_features divisible by 3 (k cos/sin pairs and k velocities), "
                          f"got {out_features}")
    return TiedAngleHead(MLP([int(in_features), *map(int, hidden), int(out_features) // 3]))
