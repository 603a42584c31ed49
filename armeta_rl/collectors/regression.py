"""Few-shot sinusoid regression data (paper, appendix "Sinusoid Regression"; Finn et al. 2017)."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from armeta_rl.devices import CPU
from armeta_rl.errors import ConfigError
from armeta_rl.tasks.protocol import TASK_KEY


class SinusoidCollector:
    """Draws ``n_support + n_query`` points per task from y = a·sin(x − b), x ~ U[x_low, x_high].

    ``tasks[TASK_KEY]`` is ``[K, 2]`` with columns (amplitude a, phase b). Returns a TensorDict
    ``[K]`` ``{"support": {"x", "y"}, "query": {"x", "y"}}`` of shapes ``[K, points, 1]`` on
    ``device``. All K tasks are drawn in one batched call from torch's global generator of that
    device.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> _ = torch.manual_seed(0)
        >>> tasks = TensorDict({"params": torch.tensor([[2.0, 0.0]])}, [1])  # a = 2, b = 0
        >>> data = SinusoidCollector(n_support=3, n_query=10).collect(tasks)
        >>> data["support", "x"].flatten()  # x ~ U[-5, 5]
        tensor([-0.0374,  2.6822, -4.1152])
        >>> data["support", "y"].flatten()  # y = a sin(x + b): 2 sin(2.6822) = 0.8868
        tensor([-0.0749,  0.8868,  1.6539])
    """

    def __init__(
        self, n_support: int = 5, n_query: int = 5, x_low: float = -5.0, x_high: float = 5.0,
        device: torch.device = CPU,
    ) -> None:
        for key, value in (("n_support", n_support), ("n_query", n_query)):
            if int(value) != value or value < 1:
                raise ConfigError(f"benchmark.collector.{key}", value, "must be an integer >= 1")
        if not x_low < x_high:
            raise ConfigError("benchmark.collector.x_low", x_low, f"must be < x_high ({x_high})")
        self.n_support, self.n_query = int(n_support), int(n_query)
        self.x_low, self.x_high = float(x_low), float(x_high)
        self.device = device

    in_features = 1
    """Size of ``x``."""
    out_features = 1
    """Size of ``y``."""

    def collect(self, tasks: TensorDict, policy_params: TensorDict | None = None) -> TensorDict:
        """Support and query points for every task (``policy_params`` is unused here)."""
        params = tasks[TASK_KEY].to(self.device)
        k, n = params.shape[0], self.n_support + self.n_query
        amplitude, phase = params[:, 0, None, None], params[:, 1, None, None]
        x = self.x_low + (self.x_high - self.x_low) * torch.rand(
            k, n, 1, dtype=params.dtype, device=params.device
        )
        y = amplitude * torch.sin(x - phase)
        s = self.n_support
        return TensorDict(
            {
                "support": {"x": x[:, :s], "y": y[:, :s]},
                "query": {"x": x[:, s:], "y": y[:, s:]},
            },
            batch_size=[k],
        )


class NoisySupport:
    """Wraps a regression collector and adds N(0, σ²) noise to the support labels only.

    The paper's "Random Perturbation Robustness" test (σ = 0.1): adaptation sees noisy labels, the
    query set that scores it stays clean.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors import NoisySupport, SinusoidCollector
        >>> _ = torch.manual_seed(0)
        >>> tasks = TensorDict({"params": torch.tensor([[1.0, 0.0]])}, [1])  # y = sin x
        >>> data = NoisySupport(SinusoidCollector(n_support=1000), sigma=0.1).collect(tasks)
        >>> (data["support", "y"] - torch.sin(data["support", "x"])).std()  # ≈ sigma
        tensor(0.0998)
        >>> (data["query", "y"] - torch.sin(data["query", "x"])).abs().max()  # clean labels
        tensor(0.)
    """

    def __init__(self, collector, sigma: float) -> None:
        if not sigma >= 0:
            raise ConfigError("eval.support_noise", sigma, "must be a number >= 0")
        self.collector, self.sigma = collector, float(sigma)

    def collect(self, tasks: TensorDict, policy_params: TensorDict | None = None) -> TensorDict:
        """The wrapped collector's data with noisy support labels."""
        data = self.collector.collect(tasks, policy_params)
        labels = data["support", "y"]
        data["support", "y"] = labels + self.sigma * torch.randn_like(labels)
        return data
