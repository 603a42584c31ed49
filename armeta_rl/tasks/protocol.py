"""The task protocol: the one TensorDict key under which task identifiers travel.

Every task distribution (p0, the flow adversary p_φ) returns its samples under :data:`TASK_KEY`,
every collector reads the identifiers of its tasks there, and every env takes them under the same
key in its reset TensorDict (declared in its state spec, so TorchRL transforms, batched envs and
collectors forward it) and reports them there with every step.

:class:`IdentifierCheck` is the one check every env applies to a reset TensorDict, its reset
contract (``env.identifier_check``), the same bare, behind transforms and in batched envs:

* a key that looks like task identifiers but is not :data:`TASK_KEY` — one of
  :data:`MISPLACED_TASK_KEYS`, a near-spelling of :data:`TASK_KEY` (``"param"``) or one of the
  env's own identifier names (``"m"``, ``"goal_x"``) — is refused rather than ignored;
* a full reset (no ``"_reset"``) handed a TensorDict without identifiers is refused unless it
  carries another key the env reads at reset (a start ``"state"``): behind a ``TransformedEnv``,
  which forwards only ``"_reset"`` and state-spec keys, that is what a reset carrying its
  identifiers under another key leaves, so an unrelated key is refused bare as it is there
  (``env.reset()`` without a TensorDict keeps the stored identifiers; a partial reset keeps the
  tasks of the entries it resets);
* an env built with ``require_identifiers=True`` refuses every full reset without them;
* identifiers nested by name (``TensorDict({"m": ..., "l": ...})``, as TorchRL's pendulum
  tutorial nests its parameters) are taken in the env's order, and refused unless the names are
  exactly the env's;
* the identifiers must have the env's width ``d`` in their last dimension and broadcast to its
  batch size;
* every value must be finite and inside its allowed interval.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from tensordict import TensorDictBase
from torch import Tensor

from armeta_rl.errors import IdentifierError

TASK_KEY = "params"
"""TensorDict key of the task identifiers, a float tensor ``[..., task_dim]``."""
FORWARD_REWARD = "reward_forward"
"""The key under which a task env may report, after every step, the task's own term of its
reward (the references' ``info["reward_forward"]``; the locomotion families'), read by the MPTS
authors' meta-RL label (``risk.mpts.label=last_step``)."""

MISPLACED_TASK_KEYS = ("goal", "goals", "task", "tasks", "task_params", "identifiers",
                       "parameters", "task_id")
"""Keys under which identifiers are commonly (and here wrongly) passed; an env refuses them."""


def _interval(low: float, high: float, open_low: bool = False) -> str:
    """``[low, high]`` (or ``(low, high]``) as text; infinite ends print as ``inf``."""
    return f"{'(' if open_low else '['}{low:g}, {high:g}{')' if math.isinf(high) else ']'}"


def _misplaced(key: str, names: Sequence[str]) -> bool:
    """Whether reset key ``key`` looks like task identifiers under another key than
    :data:`TASK_KEY`: one of :data:`MISPLACED_TASK_KEYS`, an identifier name of the env, or a
    near-spelling of :data:`TASK_KEY` (``"param"``, ``"Params"``)."""
    if key == TASK_KEY:
        return False
    return (key in MISPLACED_TASK_KEYS or key in names
            or bool(difflib.get_close_matches(key.lower(), [TASK_KEY], cutoff=0.8)))


@dataclass(frozen=True)
class IdentifierCheck:
    """An env's reset contract for its identifiers (the module docstring): their names in the
    order of :data:`TASK_KEY`'s columns, each one's allowed interval, whether a full reset must
    carry them, and the other reset keys the env reads (a start ``"state"``).

    Every env of the package checks its resets with its own (``env.identifier_check``), and a
    batched env of them (:class:`~armeta_rl.envs.TaskSerialEnv`,
    :class:`~armeta_rl.envs.TaskParallelEnv`) checks a reset with its workers' in the calling
    process, before any worker sees it.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.tasks.protocol import IdentifierCheck
        >>> check = IdentifierCheck.uniform(("m", "l"), 0.0, float("inf"), open_low=True)
        >>> nested = TensorDict({"params": TensorDict({"l": torch.ones(3), "m": torch.zeros(3) + 2},
        ...                                           [3])}, [3])
        >>> check.read(nested, torch.Size([3]))[0]  # by name, in the env's order (m, l)
        tensor([2., 1.])
    """

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    open_low: tuple[bool, ...]
    required: bool = False
    reads: tuple[str, ...] = ()

    @classmethod
    def uniform(cls, names: Sequence[str], low: float, high: float, open_low: bool = False,
                required: bool = False, reads: Sequence[str] = ()) -> IdentifierCheck:
        """One interval for every identifier."""
        d = len(names)
        return cls(tuple(names), (float(low),) * d, (float(high),) * d, (bool(open_low),) * d,
                   bool(required), tuple(reads))

    def then(self, names: Sequence[str], low: Sequence[float], high: Sequence[float]
             ) -> IdentifierCheck:
        """This check with identifiers ``names`` in ``[low, high]`` after its own (a
        :class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`'s physics columns)."""
        return IdentifierCheck(self.names + tuple(names), self.low + tuple(map(float, low)),
                               self.high + tuple(map(float, high)),
                               self.open_low + (False,) * len(names), self.required, self.reads)

    def requiring(self, required: bool = True) -> IdentifierCheck:
        """This check with every full reset required to carry the identifiers (or not)."""
        return replace(self, required=bool(required))

    def spelled(self) -> str:
        """``2 values (m, l) per batch entry``."""
        d = len(self.names)
        return f"{d} value{'s' if d > 1 else ''} ({', '.join(self.names)}) per batch entry"

    def refuse_misplaced(self, tensordict: TensorDictBase) -> None:
        """An :class:`~armeta_rl.errors.IdentifierError` for the first key of ``tensordict``
        that looks like identifiers under another key than :data:`TASK_KEY`: one of
        :data:`MISPLACED_TASK_KEYS`, one of this check's names, or a near-spelling of
        :data:`TASK_KEY` (``"param"``, ``"Params"``)."""
        for key in tensordict.keys(include_nested=False):
            if _misplaced(key, self.names):
                raise IdentifierError(key, _describe(tensordict.get(key)),
                                      f"task identifiers go under '{TASK_KEY}': {self.spelled()}")

    def flat(self, params: Tensor | TensorDictBase) -> Tensor:
        """Identifiers ``[..., d]`` given as a tensor, or nested by name as TorchRL's pendulum
        tutorial nests its parameters (``TensorDict({"m": [...], "l": [...]})``, one value per
        batch entry each, ``[...]`` or ``[..., 1]``), stacked in this check's order."""
        if not isinstance(params, TensorDictBase):
            return params
        given = sorted(map(str, params.keys(include_nested=True, leaves_only=True)))
        if given != sorted(self.names):
            raise IdentifierError(
                TASK_KEY, f"nested keys {given}",
                f"identifiers by name need exactly ({', '.join(self.names)}), or a float "
                f"tensor [..., {len(self.names)}]")
        columns = []
        for name in self.names:
            value = params.get(name)
            if value.shape[params.batch_dims:] not in ((), (1,)):
                raise IdentifierError(f"{TASK_KEY}.{name}", _describe(value),
                                      "one value per batch entry: "
                                      f"{list(params.batch_size)} or {[*params.batch_size, 1]}")
            columns.append(value.reshape(params.batch_size))
        return torch.stack(columns, -1)

    def read(self, tensordict: TensorDictBase | None, batch_size: torch.Size) -> Tensor | None:
        """The identifiers ``[*batch_size, d]`` of a reset TensorDict (expanded to the batch),
        or ``None`` when it has none and the reset keeps the stored ones; an
        :class:`~armeta_rl.errors.IdentifierError` where the reset breaks the contract: a
        misplaced key; a full reset handed a TensorDict with nothing the env reads (what a
        TransformedEnv or a batched env leaves of a misspelled key), or without identifiers when
        ``required``; nested names that are not the env's; a wrong width or batch shape; a value
        outside its interval or not finite."""
        d = len(self.names)
        if tensordict is None:
            if self.required:
                raise IdentifierError(TASK_KEY, "missing", "this env requires its identifiers "
                                      f"at every full reset: {self.spelled()}")
            return None
        self.refuse_misplaced(tensordict)
        params = tensordict.get(TASK_KEY, None)
        if params is None:
            if "_reset" in tensordict:
                return None
            if self.required:
                raise IdentifierError(TASK_KEY, "missing", "this env requires its identifiers "
                                      f"at every full reset: {self.spelled()}")
            if not any(key in tensordict for key in self.reads):
                others = sorted(map(str, tensordict.keys()))
                raise IdentifierError(
                    TASK_KEY, "missing",
                    "a full reset's TensorDict must carry the identifiers (it has "
                    f"{'only ' + ', '.join(others) if others else 'no entry'}; behind a "
                    "transform only 'params', '_reset' and state keys arrive; env.reset() "
                    f"without a TensorDict keeps the stored ones): {self.spelled()}")
            return None
        params = self.flat(params)
        if not torch.is_floating_point(params) or params.shape[-1:] != (d,):
            raise IdentifierError(TASK_KEY, _describe(params),
                                  f"a float tensor [..., {d}]: {self.spelled()}")
        try:
            params = params.expand(*batch_size, d)
        except RuntimeError:
            raise IdentifierError(TASK_KEY, _describe(params),
                                  f"needs a shape that broadcasts to {[*batch_size, d]}") from None
        low = torch.tensor(self.low, dtype=params.dtype, device=params.device)
        high = torch.tensor(self.high, dtype=params.dtype, device=params.device)
        open_low = torch.tensor(self.open_low, device=params.device)
        above = torch.where(open_low, params > low, params >= low)
        bad = ~(above & (params <= high) & params.isfinite()).all(-1)
        if bad.any():
            raise IdentifierError(TASK_KEY, params[bad][0].tolist(), self._allowed())
        return params

    def _allowed(self) -> str:
        ranges = list(zip(self.low, self.high, self.open_low))
        if len(set(ranges)) == 1:
            return (f"every identifier ({', '.join(self.names)}) must be finite and in "
                    f"{_interval(*ranges[0])}")
        each = ", ".join(f"{name} in {_interval(*r)}" for name, r in zip(self.names, ranges))
        return f"every identifier must be finite and in its interval ({each})"


def repeat_tasks(tasks: TensorDictBase, times: int) -> TensorDictBase:
    """``tasks`` ``[K]`` repeated ``times`` times, rollout-major ``[times·K]`` (entry ``r·K + k``
    is task ``k``'s ``r``-th copy), so one batched collection gives every task ``times``
    independent rollouts; ``times = 1`` returns ``tasks`` itself. :func:`per_rollout` groups
    the per-entry values of the collection back by task.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.tasks.protocol import repeat_tasks
        >>> tasks = TensorDict({"params": torch.tensor([[0.5], [2.0]])}, [2])  # K = 2 tasks
        >>> repeat_tasks(tasks, 3)["params"].squeeze(-1)  # 3 rollouts each, one batch of 6
        tensor([0.5000, 2.0000, 0.5000, 2.0000, 0.5000, 2.0000])
    """
    if times == 1:
        return tasks
    n_tasks = tasks.batch_size[0]
    return tasks.expand(times, n_tasks).reshape(times * n_tasks)


def per_rollout(values: Tensor, times: int) -> Tensor:
    """Per-task values ``[times·K]`` of tasks repeated by :func:`repeat_tasks` as
    ``[times, K]``: row ``r`` holds every task's ``r``-th rollout, so ``.mean(0)`` is each task's
    score over its rollouts.

    Examples:
        >>> import torch
        >>> from armeta_rl.tasks.protocol import per_rollout
        >>> losses = torch.tensor([1.0, 10.0, 3.0, 30.0, 2.0, 20.0])  # tasks 0, 1, 0, 1, 0, 1
        >>> per_rollout(losses, 3)
        tensor([[ 1., 10.],
                [ 3., 30.],
                [ 2., 20.]])
        >>> per_rollout(losses, 3).mean(0)  # each task's mean over its 3 rollouts
        tensor([ 2., 20.])
    """
    return values.reshape(times, -1)


def _describe(value: object) -> object:
    """A short stand-in for a tensor in an error message: its shape and dtype."""
    if isinstance(value, Tensor):
        return f"tensor of shape {list(value.shape)}, {value.dtype}"
    return value
