"""The task-collector protocol: how a batch of tasks becomes data (docs/architecture.md, "plug-in
seams"). Named ``TaskCollector`` so it does not shadow :class:`torchrl.collectors.Collector`."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from tensordict import TensorDict


@runtime_checkable
class TaskCollector(Protocol):
    """Turns ``K`` task identifiers into data with a leading task dimension.

    ``tasks`` is a TensorDict ``[K]`` with ``"params"`` ``[K, d]``. Regression and system
    identification return ``{"support": {"x", "y"}, "query": {"x", "y"}}`` with batch ``[K]`` and
    tensors ``[K, points, features]``; episode collectors return trajectories ``[K, episodes, T]``
    gathered with ``policy_params`` (per-task parameters with a leading ``K``, or shared ones) and
    also take the policy network as a ``policy=`` keyword.

    A collector is built with a ``device`` keyword (the run's ``device``, passed by
    :func:`armeta_rl.factory.build_collector`) and returns its data there.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.collectors import TaskCollector
        >>> class LineCollector:  # lines y = a x: support at x = 0, 1, query at x = 2
        ...     def collect(self, tasks, policy_params=None):
        ...         x = torch.arange(3.0).expand(len(tasks), 3).unsqueeze(-1)
        ...         y = tasks["params"][:, None, :1] * x
        ...         return TensorDict({"support": {"x": x[:, :2], "y": y[:, :2]},
        ...                            "query": {"x": x[:, 2:], "y": y[:, 2:]}}, [len(tasks)])
        >>> isinstance(LineCollector(), TaskCollector)  # anything with collect(tasks)
        True
        >>> tasks = TensorDict({"params": torch.tensor([[2.0], [-1.0]])}, [2])  # a = 2, a = -1
        >>> LineCollector().collect(tasks)["query", "y"].flatten()  # a · 2
        tensor([ 4., -2.])
    """

    def collect(self, tasks: TensorDict, policy_params: TensorDict | None = None) -> TensorDict:
        """Data for every task, batched over the task dimension."""
        ...
