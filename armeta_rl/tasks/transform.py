"""Tasks as a TorchRL transform: identifiers drawn at every reset, in any env, collector or batch.

:class:`TaskTransform` sits in a ``TransformedEnv`` next to an env that takes its identifiers under
:data:`~armeta_rl.tasks.TASK_KEY` (any of the package's envs, a MuJoCo env with
``PhysicsTaskTransform``, a batched env of them). At every reset it draws the identifiers of the
entries being reset from its task source and hands them to the env, so a TorchRL ``Collector``
(``MultiSyncCollector`` too) trains on the source's tasks with no manual reset: one task per
episode. A source is anything with ``sample(n)`` or ``propose(n)`` returning tasks
(``{TASK_KEY: [n, d], ...}`` or the identifiers ``[n, d]``): p0 (``BoxUniform``,
``TruncatedNormal``), the flow adversary p_φ, a :class:`~armeta_rl.adversary.TaskSampler`, a
risk principle; or a tensor of identifiers (one task ``[d]``, or one per entry ``[*batch, d]``),
e.g. a fixed shift to evaluate on. Without a source it requires the identifiers at every full
reset and refuses a reset without them: behind transforms, identifiers under any other key never
reach the env (``TransformedEnv`` forwards only reset and state-spec keys), so a misspelled key is
refused there instead of leaving the env on its old tasks.

The episodes' losses go back to a learning source through the data: every step reports its task
under ``TASK_KEY``, ``torchrl.envs.RewardSum`` sums each episode's return, and
:func:`finished_episodes` collects the tasks and returns of the episodes that end in a batch, for
``sampler.update(episodes, -episodes["return"])``.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor, nn
from torchrl.data import Composite
from torchrl.envs import EnvBase, Transform

from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.tasks.protocol import TASK_KEY, IdentifierCheck


def draw_identifiers(source: Any, n: int) -> Tensor:
    """``n`` identifiers ``[n, d]`` from a task source: its ``sample(n)`` or ``propose(n)``
    (tasks under :data:`TASK_KEY`, or identifiers); a tensor ``[d]`` is one task, repeated."""
    if isinstance(source, Tensor):
        return source.expand(n, source.shape[-1])
    draw = getattr(source, "sample", None) or getattr(source, "propose", None)
    if draw is None:
        raise ConfigError("tasks", type(source).__name__,
                          "a task source: a tensor of identifiers or an object with sample(n) "
                          "or propose(n)")
    tasks = draw(n)
    return tasks.get(TASK_KEY) if isinstance(tasks, TensorDictBase) else tasks


class TaskTransform(Transform):
    """Task identifiers at every reset, drawn from ``tasks`` (or required from the reset).

    Args:
        tasks: the task source (see the module docstring): a distribution or sampler with
            ``sample(n)`` / ``propose(n)``, or identifiers ``[d]`` or ``[*batch, d]``. ``None``:
            the identifiers come with every full reset under the key, and a full reset without
            them is refused (a partial reset, ``"_reset"``, keeps each entry's task).
        key: the key the env reads its identifiers under.

    With a source, the transform provides the key: it leaves the env's state spec (a reset needs
    nothing from outside), and at each reset the entries being reset (all, or those of
    ``"_reset"``) get fresh draws, one task per episode; the other entries keep theirs. The env
    reports its identifiers in every output as before, so ``ExcludeTransform(key)`` after this
    transform drops them from the data with consistent specs.

    Examples:
        >>> import torch
        >>> from torchrl.envs import Compose, StepCounter, TransformedEnv
        >>> from armeta_rl.envs import PointNavigationEnv
        >>> from armeta_rl.tasks import TASK_KEY, TaskTransform
        >>> _ = torch.manual_seed(0)
        >>> env = PointNavigationEnv(batch_size=(1,), seed=0)  # the point starts at (0, 0)
        >>> env = TransformedEnv(env, Compose(TaskTransform(env.p0), StepCounter(2)))
        >>> still = lambda td: td.set("action", torch.zeros(1, 2))
        >>> steps = env.rollout(4, still, break_when_any_done=False)  # two 2-step episodes
        >>> steps[TASK_KEY][0]  # a goal from p0 at each reset, kept over its episode
        tensor([[ 0.4701,  0.2078],
                [ 0.4701,  0.2078],
                [-0.0406,  0.4207],
                [-0.0406,  0.4207]])
        >>> steps["next", "reward"].flatten()  # the env's reward for that goal: -‖g‖
        tensor([-0.5139, -0.5139, -0.4227, -0.4227])
    """

    def __init__(self, tasks: Any = None, key: str = TASK_KEY) -> None:
        super().__init__(in_keys=[], out_keys=[])
        self.tasks, self.key = tasks, key
        self._identifiers: Tensor | None = None

    def clone(self) -> TaskTransform:
        """A copy drawing from the same source object (a deep copy would leave the caller's
        sampler learning while the env draws from a frozen copy)."""
        return type(self)(self.tasks, key=self.key)

    def set_container(self, container: Transform | EnvBase) -> None:
        """Attach to ``container`` and check that the env below takes identifiers under the
        key (declared in its state spec, as every env of the package does)."""
        super().set_container(container)
        parent = self.parent
        if parent is None:
            return
        spec = parent.state_spec.get(self.key, None)
        if spec is None or isinstance(spec, Composite) or spec.ndim != len(parent.batch_size) + 1:
            raise ConfigError("env", type(getattr(parent, "base_env", parent)).__name__,
                              f"takes no task identifiers [*batch, d] under '{self.key}' at reset "
                              "(its state spec has no such entry), so TaskTransform has nothing "
                              "to set")

    def extend_identifier_check(self, base: IdentifierCheck | None) -> IdentifierCheck | None:
        """The reset contract of the env with this transform: none with a source (it provides
        the identifiers), else the base env's with every full reset required to carry them."""
        if self.tasks is not None or base is None:
            return None
        return base.requiring()

    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        parent = self.parent
        if tensordict is None:
            tensordict = TensorDict({}, parent.batch_size, device=parent.device)
        reset = tensordict.get("_reset", None)
        if self.tasks is None:
            if reset is None and self.key not in tensordict:
                raise IdentifierError(
                    self.key, "missing", "task identifiers are required at every full reset "
                    "(TaskTransform without a source); identifiers under another key never "
                    "reach the env behind transforms")
            return tensordict
        spec = parent.state_spec[self.key]
        if reset is None or self._identifiers is None:
            new = self._draw(spec.shape, None)
        else:
            mask = reset.reshape(spec.shape[:-1])
            new = self._identifiers.clone()
            if mask.any():
                new[mask] = self._draw(spec.shape, mask)
        return tensordict.set(self.key, new.to(spec.device, spec.dtype))

    def _draw(self, shape: torch.Size, mask: Tensor | None) -> Tensor:
        """Identifiers ``shape`` = ``[*batch, d]`` from the source, or ``[n, d]`` for the ``n``
        entries of ``mask``."""
        if isinstance(self.tasks, Tensor) and self.tasks.dim() > 1:
            try:
                per_entry = self.tasks.expand(shape)
            except RuntimeError:
                raise ConfigError("tasks", f"shape {tuple(self.tasks.shape)}",
                                  f"identifiers [d] or [*batch, d] = {list(shape)}") from None
            return per_entry if mask is None else per_entry[mask]
        n = shape[:-1].numel() if mask is None else int(mask.sum())
        identifiers = draw_identifiers(self.tasks, n)
        return identifiers.reshape(*shape[:-1], -1) if mask is None else identifiers

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
               ) -> TensorDictBase:
        """Keep the identifiers the env reports, so that a partial reset redraws only its
        entries."""
        if self.tasks is not None:
            self._identifiers = tensordict_reset.get(self.key).clone()
        return tensordict_reset

    def source_modules(self) -> list[nn.Module]:
        """The modules whose tensors make the source's draws: the source itself if it is one
        (p0, p_φ) and its module attributes (a TaskSampler's adversary)."""
        source = self.tasks
        candidates = [source, *vars(source).values()] if source is not None else []
        return [m for m in candidates if isinstance(m, nn.Module)]

    def get_extra_state(self) -> dict[str, Tensor]:
        """The source's parameters and buffers, moved to shared memory (in place: the source
        keeps learning on them). ``EnvCreator`` hands this state to every worker of a
        multi-process collector, whose copy of the source then draws from the same, current
        tensors (:meth:`set_extra_state`)."""
        state = {}
        for i, module in enumerate(self.source_modules()):
            for name, tensor in TensorDict.from_module(module).flatten_keys(".").items():
                state[f"{i}/{name}"] = tensor.share_memory_()
        return state

    def set_extra_state(self, state: dict[str, Tensor]) -> None:
        """Make the source's modules use the tensors of ``state`` (:meth:`get_extra_state`),
        shared with the process that made it."""
        for i, module in enumerate(self.source_modules()):
            prefix = f"{i}/"
            tensors = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
            if tensors:
                TensorDict(tensors).unflatten_keys(".").to_module(module)

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        if self.tasks is not None:
            state = input_spec["full_state_spec"]
            if self.key in state:
                del state[self.key]
        return input_spec


def finished_episodes(
    batch: TensorDictBase, return_key: Any = ("next", "episode_reward"), key: str = TASK_KEY
) -> TensorDict:
    """The episodes that end in a collector batch: their task identifiers ``[n, d]`` under
    ``key`` and their returns ``[n]`` under ``"return"``.

    An episode ends at a step whose ``("next", "done")`` is set; there the data's identifiers are
    the episode's task and ``return_key`` (what ``torchrl.envs.RewardSum`` writes) its return.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.tasks import finished_episodes
        >>> # 2 envs × 3 steps: env 0's episode on task 1 ends at step 1 and one on task 3
        >>> # starts; env 1's episode on task 2 ends at step 2
        >>> batch = TensorDict({
        ...     "params": torch.tensor([[[1.0], [1.0], [3.0]], [[2.0], [2.0], [2.0]]]),
        ...     "next": {"done": torch.tensor([[False, True, False],
        ...                                    [False, False, True]]).unsqueeze(-1),
        ...              "episode_reward": torch.tensor([[-0.2, -0.5, -0.1],
        ...                                              [-0.3, -0.6, -0.9]]).unsqueeze(-1)},
        ... }, [2, 3])
        >>> episodes = finished_episodes(batch)  # the running sums at the done steps
        >>> episodes["params"].flatten(), episodes["return"]
        (tensor([1., 2.]), tensor([-0.5000, -0.9000]))
    """
    done = batch.get(("next", "done")).squeeze(-1)
    returns = batch.get(return_key)[done].squeeze(-1)
    return TensorDict({key: batch.get(key)[done], "return": returns}, batch_size=[len(returns)])
