"""The task protocol: the one TensorDict key under which task identifiers travel.

Every task distribution (p0, the flow adversary p_φ) returns its samples under :data:`TASK_KEY`,
every collector reads the identifiers of its tasks there, and every env takes them under the same
key in its reset TensorDict (declared in its state spec, so TorchRL transforms, batched envs and
collectors forward it) and reports them there with every step.

:func:`read_identifiers` is the one check every env applies to a reset TensorDict:

* a key that looks like task identifiers but is not :data:`TASK_KEY` — one of
  :data:`MISPLACED_TASK_KEYS` or one of the env's own identifier names (``"m"``, ``"goal_x"``) —
  is refused rather than ignored;
* the identifiers must have the env's width ``d`` in their last dimension and broadcast to its
  batch size;
* every value must be finite and inside the env's allowed interval.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from torch import Tensor

from armeta_rl.errors import IdentifierError

if TYPE_CHECKING:
    from torchrl.envs import EnvBase

TASK_KEY = "params"
"""TensorDict key of the task identifiers, a float tensor ``[..., task_dim]``."""
FORWARD_REWARD = "reward_forward"
"""The key under which a task env may report, after every step, the task's own term of its
reward (the references' ``info["reward_forward"]``; the locomotion families'), read by the MPTS
authors' meta-RL label (``risk.mpts.label=last_step``)."""

MISPLACED_TASK_KEYS = ("goal", "goals", "task", "tasks", "task_params", "identifiers")
"""Keys under which identifiers are commonly (and here wrongly) passed; an env refuses them."""


def interval(low: float, high: float, open_low: bool = False) -> str:
    """``[low, high]`` (or ``(low, high]``) as text; infinite ends print as ``inf``."""
    return f"{'(' if open_low else '['}{low:g}, {high:g}{')' if math.isinf(high) else ']'}"


def read_identifiers(
    tensordict: TensorDictBase | None,
    names: Sequence[str],
    low: float,
    high: float,
    batch_size: torch.Size,
    open_low: bool = False,
) -> Tensor | None:
    """The identifiers ``[*batch_size, d]`` under :data:`TASK_KEY` of a reset TensorDict (expanded
    to the batch), or ``None`` when it has none; :class:`~armeta_rl.errors.IdentifierError` for a
    misplaced key, a wrong width or batch shape, or a value outside ``[low, high]`` (``(low,
    high]`` with ``open_low``) or not finite. ``names`` are the env's identifier names in order."""
    if tensordict is None:
        return None
    d, allowed_range = len(names), interval(low, high, open_low)
    spelled = f"{d} value{'s' if d > 1 else ''} ({', '.join(names)})"
    for key in tensordict.keys(include_nested=False):
        if key != TASK_KEY and (key in MISPLACED_TASK_KEYS or key in names):
            raise IdentifierError(
                key, _describe(tensordict.get(key)),
                f"task identifiers go under '{TASK_KEY}': {spelled} per batch entry",
            )
    params = tensordict.get(TASK_KEY, None)
    if params is None:
        return None
    if not torch.is_floating_point(params) or params.shape[-1:] != (d,):
        raise IdentifierError(TASK_KEY, _describe(params),
                              f"a float tensor [..., {d}]: {spelled} per batch entry")
    try:
        params = params.expand(*batch_size, d)
    except RuntimeError:
        raise IdentifierError(TASK_KEY, _describe(params),
                              f"needs a shape that broadcasts to {[*batch_size, d]}") from None
    above = params > low if open_low else params >= low
    bad = ~(above & (params <= high) & params.isfinite()).all(-1)
    if bad.any():
        raise IdentifierError(TASK_KEY, params[bad][0].tolist(),
                              f"every identifier ({', '.join(names)}) must be finite and in "
                              f"{allowed_range}")
    return params


def repeat_tasks(tasks: TensorDictBase, times: int) -> TensorDictBase:
    """``tasks`` ``[K]`` repeated ``times`` times, rollout-major ``[times·K]`` (entry ``r·K + k``
    is task ``k``'s ``r``-th copy), so one batched collection gives every task ``times``
    independent rollouts; ``times = 1`` returns ``tasks`` itself."""
    if times == 1:
        return tasks
    n_tasks = tasks.batch_size[0]
    return tasks.expand(times, n_tasks).reshape(times * n_tasks)


def per_rollout(values: Tensor, times: int) -> Tensor:
    """Per-task values ``[times·K]`` of tasks repeated by :func:`repeat_tasks` as
    ``[times, K]``."""
    return values.reshape(times, -1)


def _describe(value: object) -> object:
    """A short stand-in for a tensor in an error message: its shape and dtype."""
    if isinstance(value, Tensor):
        return f"tensor of shape {list(value.shape)}, {value.dtype}"
    return value


def reset_with_identifiers(env: EnvBase, tensordict: TensorDictBase) -> TensorDictBase:
    """``env.reset(tensordict)`` for a reset TensorDict carrying identifiers under
    :data:`TASK_KEY`, with ``set_state=True`` where the env takes a state at reset.

    The identifiers are entries of the env's state spec (so that ``TransformedEnv`` and batched
    envs forward them), so torchrl counts such a reset as one carrying a state: a batched env of
    the system-identification envs honors it in torchrl 0.14 with a ``FutureWarning`` that from
    0.15 a reset not asking for its state ignores it, which would silently keep the old tasks.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import PendulumEnv
        >>> from armeta_rl.tasks import TASK_KEY, reset_with_identifiers
        >>> env = PendulumEnv(batch_size=(2, 3), seed=0)
        >>> identifiers = torch.tensor([0.5, 1.5]).expand(2, 3, 2)
        >>> start = reset_with_identifiers(env, TensorDict({TASK_KEY: identifiers}, [2, 3]))
        >>> bool((start[TASK_KEY] == identifiers).all())
        True
    """
    if env._supports_set_state:
        return env.reset(tensordict, set_state=True)
    return env.reset(tensordict)
