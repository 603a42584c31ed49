"""Any MuJoCo env as a task family: adversarial (or uniform) domain randomization of its physics.

A task family maps each dimension of the task identifier τ ∈ R^d onto a named parameter of the
env's ``mujoco.MjModel``. The kinds of parameter, all relative to the model's nominal (compiled)
values except gravity:

    body_mass_scale      body_mass[b] ← v · nominal, and body_inertia[b] ← v · nominal: the body's
                         density scales, its shape stays (the usual domain-randomization choice;
                         scaling the mass alone would change the body's radius of gyration)
    body_mass_only_scale body_mass[b] ← v · nominal, inertia unchanged: MPTS's mass scale
                         (HalfCheetah-MassVel, Walker2d-MassVel: ``model.body_mass[:] =
                         m_scale · original``)
    geom_friction_scale  sliding friction geom_friction[g, 0] ← v · nominal
    joint_damping_scale  dof_damping of every degree of freedom of the joint ← v · nominal
    actuator_gear_scale  actuator_gear[a, 0] ← v · nominal (the actuator's force per control)
    gravity_z            opt.gravity[2] ← v (m/s², e.g. -9.81); no target

``target`` names the body, geom, joint or actuator, or is ``all`` for every one of them. MuJoCo
combines the frictions of two touching geoms by their maximum, so scaling the floor's friction
alone cannot make contacts more slippery than the other geom allows: "ground friction" scales all
geoms (``target: all``), which scales the friction of every contact by v.

After writing the parameters, ``mj_setConst`` recomputes the constants the compiler derives from
them (subtree masses, the inverse weights the constraint solver's regularization uses), as
MuJoCo's documentation prescribes for a model edited after compilation; so an identified env steps
exactly as a hand-edited model on which ``mj_setConst`` was called.

:class:`PhysicsTaskTransform` is the TorchRL component: identifiers arrive under ``"params"``
(:data:`~armeta_rl.tasks.TASK_KEY`, ``[*batch, d]``) in the reset TensorDict; the transform writes
them into the model(s) before the base env resets, and emits them with every observation.
``"params"`` is declared in the state and observation specs, so ``TransformedEnv``,
SerialEnv/ParallelEnv, automatic resets and ``Collector`` carry them; a reset without ``"params"``
keeps the current physics. On an env with identifiers of its own under ``"params"`` (AntGoalEnv's
goal), the physics identifiers follow them: ``"params"`` is ``[goal_x, goal_y, *physics]``, one
task box of goal × physics, and the base env sees its own columns only. Supported base
envs: a TorchRL ``GymEnv`` of a gymnasium MuJoCo env (one simulation, batch ``[]``), a
``SerialEnv`` of them (one task per sub-env, batch ``[n]``), and any env that steps a
:class:`mujoco.batch.Batch` under ``env.sim`` with its model under ``env.model`` (our
:class:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv` envs: one task per simulation,
batch ``[tasks, episodes]``), on the CPU or as MuJoCo Warp worlds
(:class:`~armeta_rl.envs.warp_physics.WarpBatch`, whose per-world model fields are MuJoCo Warp's
batched fields and whose ``set_const`` is ``mjw.set_const``). To run tasks in parallel
processes, put one transform inside each worker's env
(``ParallelEnv(n, lambda: TransformedEnv(GymEnv(...), PhysicsTaskTransform(...)))``).

Task families are written in YAML (``configs/task_family/``)::

    env: HalfCheetah-v5
    parameters:
      - {name: torso_mass, kind: body_mass_scale, target: torso, low: 0.5, high: 1.5}
      - {name: friction, kind: geom_friction_scale, target: all, low: 0.3, high: 1.5}

and the ranges form the task box (:class:`~armeta_rl.tasks.TaskSpace`).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import mujoco
import numpy as np
import torch
from mujoco.batch import Batch
from omegaconf import DictConfig, ListConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase, GymEnv, SerialEnv, StepCounter, Transform, TransformedEnv

from armeta_rl.envs.task_env import TaskTransformedEnv, identifier_check
from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks.protocol import TASK_KEY, IdentifierCheck
from armeta_rl.tasks.space import TaskSpace

ALL = "all"
KEY = "task_family.parameters"

# kind → (object type of the target or None, the model fields it writes, column of each field's
# row it writes or None for the whole row, whether the value scales the nominal one)
_KINDS: dict[str, tuple[str | None, tuple[tuple[str, int | None], ...], bool]] = {
    "body_mass_scale": ("body", (("body_mass", None), ("body_inertia", None)), True),
    "body_mass_only_scale": ("body", (("body_mass", None),), True),
    "geom_friction_scale": ("geom", (("geom_friction", 0),), True),
    "joint_damping_scale": ("joint", (("dof_damping", None),), True),
    "actuator_gear_scale": ("actuator", (("actuator_gear", 0),), True),
    "gravity_z": (None, (("opt.gravity", None),), False),
}
_COUNTS = {"body": "nbody", "geom": "ngeom", "joint": "njnt", "actuator": "nu"}
_OBJECTS = {
    "body": mujoco.mjtObj.mjOBJ_BODY,
    "geom": mujoco.mjtObj.mjOBJ_GEOM,
    "joint": mujoco.mjtObj.mjOBJ_JOINT,
    "actuator": mujoco.mjtObj.mjOBJ_ACTUATOR,
}


@dataclass(frozen=True)
class PhysicsParameter:
    """One identifier dimension: the model parameter ``kind`` of ``target``, ranging in
    ``[low, high]`` (see the module docstring for the kinds).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs import TransformedEnv
        >>> from armeta_rl.envs.mujoco_tasks import PhysicsParameter, PhysicsTaskTransform, gym_env
        >>> from armeta_rl.tasks import TASK_KEY
        >>> g = PhysicsParameter("g", "gravity_z", target=None, low=-10.0, high=0.0)
        >>> env = TransformedEnv(gym_env("InvertedPendulum-v5"), PhysicsTaskTransform([g]))
        >>> def steps_up(gravity):  # the steps before the unpushed pole tilts past 0.2 rad
        ...     _ = env.set_seed(0)  # the same start, tilted 0.008 rad
        ...     start = env.reset(TensorDict({TASK_KEY: torch.tensor([gravity])}, []))
        ...     still = lambda td: td.set("action", torch.zeros(1))
        ...     return len(env.rollout(100, still, tensordict=start, auto_reset=False))
        >>> # θ ≈ θ0 cosh(√(3|g|/2L) t), L = 0.6 m: 0.2 rad at t ≈ 0.8 s, the 20th step of 0.04 s
        >>> steps_up(0.0), steps_up(-9.81)
        (100, 20)
    """

    name: str
    kind: str
    target: str | None
    low: float
    high: float


def parse_parameters(
    entries: Sequence[Mapping[str, Any]], key: str = KEY
) -> list[PhysicsParameter]:
    """The parameters of a YAML mapping list ``[{name, kind, target, low, high}, ...]``.

    Raises:
        ConfigError: an unknown kind or field, a missing target, a target given to ``gravity_z``,
            or a range that is not ``low < high`` (finite).

    Examples:
        >>> from armeta_rl.envs.mujoco_tasks import parse_parameters
        >>> parse_parameters([{"name": "g", "kind": "gravity_z", "low": -12.0, "high": -8.0}])
        [PhysicsParameter(name='g', kind='gravity_z', target=None, low=-12.0, high=-8.0)]
        >>> parse_parameters([{"kind": "body_mass_scale", "low": 0.5, "high": 2.0}])
        Traceback (most recent call last):
        ...
        armeta_rl.errors.ConfigError: config key 'task_family.parameters[0].target' = None: ...
    """
    if not entries:
        raise ConfigError(key, list(entries), "needs at least one {name, kind, target, low, high}")
    parameters = []
    for i, entry in enumerate(entries):
        where = f"{key}[{i}]"
        entry = dict(entry)
        unknown = set(entry) - {"name", "kind", "target", "low", "high"}
        if unknown:
            raise ConfigError(f"{where}", sorted(unknown), "allowed fields: name, kind, target, "
                              "low, high")
        kind = entry.get("kind")
        if kind not in _KINDS:
            raise ConfigError(f"{where}.kind", kind, "allowed: " + ", ".join(_KINDS))
        target = entry.get("target")
        needs_target = _KINDS[kind][0] is not None
        if needs_target and not isinstance(target, str):
            raise ConfigError(f"{where}.target", target,
                              f"a {_KINDS[kind][0]} name of the model, or '{ALL}'")
        if not needs_target and target is not None:
            raise ConfigError(f"{where}.target", target, f"{kind} takes no target")
        low, high = entry.get("low"), entry.get("high")
        try:
            low, high = float(low), float(high)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}.low", [low, high], "low and high must be numbers") from None
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ConfigError(f"{where}.low", [low, high], "finite numbers with low < high")
        name = str(entry.get("name") or f"{kind}:{target}")
        if name in [p.name for p in parameters]:
            raise ConfigError(f"{where}.name", name, "names must differ")
        parameters.append(PhysicsParameter(name, kind, target, low, high))
    return parameters


def task_space(parameters: Sequence[PhysicsParameter]) -> TaskSpace:
    """The task box of the parameters' ranges.

    Examples:
        >>> from armeta_rl.envs.mujoco_tasks import parse_parameters, task_space
        >>> gravity = {"name": "g", "kind": "gravity_z", "low": -12, "high": -8}
        >>> task_space(parse_parameters([gravity]))
        TaskSpace(names=('g',), low=(-12.0,), high=(-8.0,))
    """
    return TaskSpace([p.name for p in parameters], [p.low for p in parameters],
                     [p.high for p in parameters])


@dataclass(frozen=True)
class TaskFamily:
    """A task family read from YAML: the gymnasium env id (or ``None``), its parameters and box.

    Examples:
        >>> from armeta_rl.config_files import config_files
        >>> from armeta_rl.envs.mujoco_tasks import load_task_family
        >>> family = load_task_family(config_files() / "task_family" / "hopper.yaml")
        >>> [(p.name, p.kind, p.target) for p in family.parameters]
        [('torso_mass', 'body_mass_scale', 'torso'), ('friction', 'geom_friction_scale', 'all')]
        >>> family.env, family.space.low, family.space.high  # one box side per parameter
        ('Hopper-v5', (0.5, 0.2), (2.0, 1.5))
    """

    env: str | None
    parameters: tuple[PhysicsParameter, ...]
    space: TaskSpace


def load_task_family(source: str | os.PathLike | Mapping[str, Any]) -> TaskFamily:
    """Read a task family (``{env, parameters}``) from a YAML file or a mapping.

    Examples:
        >>> from armeta_rl.envs.mujoco_tasks import load_task_family
        >>> pole = {"name": "pole_mass", "kind": "body_mass_scale", "target": "pole",
        ...         "low": 0.5, "high": 2}
        >>> family = load_task_family({"env": "InvertedPendulum-v5", "parameters": [pole]})
        >>> family.space
        TaskSpace(names=('pole_mass',), low=(0.5,), high=(2.0,))
    """
    if isinstance(source, Mapping):
        config = dict(source)
    else:
        config = OmegaConf.to_container(OmegaConf.load(source), resolve=True)
        if not isinstance(config, dict):
            raise ConfigError("task_family", config, "a mapping with 'env' and 'parameters'")
    unknown = set(config) - {"env", "parameters"}
    if unknown:
        raise ConfigError("task_family", sorted(unknown), "allowed keys: env, parameters")
    parameters = tuple(parse_parameters(config.get("parameters") or []))
    return TaskFamily(config.get("env"), parameters, task_space(parameters))


@dataclass(frozen=True)
class _Edit:
    """Where one identifier dimension writes: flat indices into a model field, their nominal
    values, and whether the identifier scales them (else it replaces them)."""

    field: str
    index: np.ndarray
    nominal: np.ndarray
    scale: bool


def _field(model: mujoco.MjModel, field: str) -> np.ndarray:
    """A model field as a flat writable view (``opt.<name>`` for an option)."""
    array = getattr(model.opt, field[4:]) if field.startswith("opt.") else getattr(model, field)
    return array.reshape(-1)


def _resolve(
    model: mujoco.MjModel, parameters: Sequence[PhysicsParameter], key: str = KEY
) -> list[list[_Edit]]:
    """For each parameter, the edits it makes on ``model`` (``key``: the parameters' config key,
    for errors).

    Raises:
        ConfigError: a target the model does not have, or one that another parameter writes too.
    """
    edits: list[list[_Edit]] = []
    written: dict[str, dict[int, int]] = {}  # field → flat index → the parameter writing it
    for i, parameter in enumerate(parameters):
        objtype, fields, scale = _KINDS[parameter.kind]
        if objtype is None:
            ids = np.zeros(1, dtype=np.int64)
        elif parameter.target == ALL:
            ids = np.arange(getattr(model, _COUNTS[objtype]))
        else:
            found = mujoco.mj_name2id(model, _OBJECTS[objtype], parameter.target)
            if found < 0:
                count = getattr(model, _COUNTS[objtype])
                names = [mujoco.mj_id2name(model, _OBJECTS[objtype], j) for j in range(count)]
                raise ConfigError(f"{key}[{i}].target", parameter.target,
                                  f"allowed {objtype} names: "
                                  + ", ".join(n for n in names if n) + f", or '{ALL}'")
            ids = np.array([found])
        parameter_edits = []
        for field, column in fields:
            flat = _field(model, field)
            if field == "opt.gravity":
                index = np.array([2])
            elif field == "dof_damping":
                index = np.flatnonzero(np.isin(model.dof_jntid, ids))
            else:
                width = flat.size // max(1, getattr(model, field).shape[0])
                columns = np.arange(width) if column is None else np.array([column])
                index = (ids[:, None] * width + columns[None, :]).reshape(-1)
            owners = written.setdefault(field, {})
            for j in {owners[k] for k in index.tolist() if k in owners}:
                raise ConfigError(f"{key}[{i}].target", parameter.target,
                                  f"{key}[{j}] ({parameters[j].name}) writes the same {field} "
                                  "entries; each entry may follow one identifier")
            owners.update(dict.fromkeys(index.tolist(), i))
            parameter_edits.append(_Edit(field, index, flat[index].copy(), scale))
        edits.append(parameter_edits)
    return edits


def _nominal_params(edits: Sequence[Sequence[_Edit]]) -> list[float]:
    """The identifier that leaves the model as compiled: 1 for a scale, the nominal value of a
    replaced parameter (its first entry)."""
    return [1.0 if e[0].scale else float(e[0].nominal[0]) for e in edits]


def _new_values(edit: _Edit, value: np.ndarray) -> np.ndarray:
    """The values ``[n, len(index)]`` the edit writes for identifiers ``value [n]``."""
    if edit.scale:
        return edit.nominal[None, :] * value[:, None]
    return np.broadcast_to(value[:, None], (len(value), len(edit.index)))


class _ModelList:
    """Simulations that each own an MjModel and MjData (gymnasium envs)."""

    def __init__(self, models: list[mujoco.MjModel], datas: list[mujoco.MjData]) -> None:
        self.models, self.datas = models, datas
        self.model = models[0]

    def write(self, rows: np.ndarray, edits: Sequence[Sequence[_Edit]], params: np.ndarray) -> None:
        for row in rows:
            model = self.models[row]
            for j, parameter_edits in enumerate(edits):
                for edit in parameter_edits:
                    values = _new_values(edit, params[row, j : j + 1])[0]
                    _field(model, edit.field)[edit.index] = values
            mujoco.mj_setConst(model, self.datas[row])


class _BatchSims:
    """The simulations of one :class:`mujoco.batch.Batch`, or of a batch with its ``expand``,
    ``set_const`` and ``nsim`` whose expanded fields are torch tensors (MuJoCo Warp's worlds,
    :class:`~armeta_rl.envs.warp_physics.WarpBatch`), with per-simulation model fields."""

    def __init__(self, sim: Any, model: mujoco.MjModel) -> None:
        self.sim, self.model = sim, model

    def write(self, rows: np.ndarray, edits: Sequence[Sequence[_Edit]], params: np.ndarray) -> None:
        for j, parameter_edits in enumerate(edits):
            for edit in parameter_edits:
                field = self.sim.expand(edit.field).reshape(self.sim.nsim, -1)
                values = _new_values(edit, params[rows, j])
                if isinstance(field, torch.Tensor):
                    at = (torch.as_tensor(rows, device=field.device)[:, None],
                          torch.as_tensor(edit.index, device=field.device)[None, :])
                    field[at] = torch.tensor(np.array(values), dtype=field.dtype).to(field.device)
                else:
                    field[rows[:, None], edit.index[None, :]] = values
        self.sim.set_const(rows.astype(np.int32))


def _is_batch(sim: Any) -> bool:
    """Whether ``sim`` steps a batch of simulations with per-simulation model fields: a
    :class:`mujoco.batch.Batch`, or a batch with the same ``expand`` and ``set_const``
    (:class:`~armeta_rl.envs.warp_physics.WarpBatch`)."""
    return isinstance(sim, Batch) or all(
        callable(getattr(sim, name, None)) for name in ("expand", "set_const", "bind"))


def _gym_model(env: GymEnv) -> tuple[mujoco.MjModel, mujoco.MjData]:
    unwrapped = env._env.unwrapped
    if not isinstance(getattr(unwrapped, "model", None), mujoco.MjModel):
        raise ConfigError("env", env, "a gymnasium MuJoCo env (its unwrapped env has an MjModel)")
    return unwrapped.model, unwrapped.data


def _simulations(env: EnvBase) -> _ModelList | _BatchSims:
    """The MuJoCo simulations behind ``env``, one per element of its batch."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    if isinstance(env, SerialEnv):
        if env.is_closed:
            env.start()
        subs = [_simulations(sub) for sub in env._envs]
        if all(isinstance(s, _ModelList) and len(s.models) == 1 for s in subs):
            return _ModelList([s.models[0] for s in subs], [s.datas[0] for s in subs])
    elif isinstance(env, GymEnv):
        if env.batch_size == torch.Size([]):
            model, data = _gym_model(env)
            return _ModelList([model], [data])
    elif _is_batch(env.__dict__.get("sim")) and isinstance(env.__dict__.get("model"),
                                                           mujoco.MjModel):
        return _BatchSims(env.sim, env.model)
    raise ConfigError(
        "env", type(env).__name__,
        "a GymEnv of a gymnasium MuJoCo env, a SerialEnv of them, or an env with a "
        "mujoco.batch.Batch (or MuJoCo Warp WarpBatch) 'sim' and its 'model' (AntGoalEnv); for "
        "a ParallelEnv put a "
        "PhysicsTaskTransform inside each worker's env",
    )


class PhysicsTaskTransform(Transform):
    """A TorchRL transform that makes a MuJoCo env a family of tasks over its physics.

    At reset, the identifiers ``"params"`` (``[*batch, d]``, one task per simulation) of the
    simulations being reset are checked against the box and written into their models before the
    base env resets; a reset without ``"params"`` keeps the current ones (the nominal physics
    until the first one). ``"params"`` is emitted with every reset and step output. If the base
    env has identifiers of its own under the key (width w), the key holds ``w + d`` columns: the
    base env's, handed to it at reset, then the physics.

    Args:
        parameters: the identifier dimensions, as :class:`PhysicsParameter` or YAML mappings.
        key: the TensorDict key of the identifiers: ``"params"``, the package's one task key;
            another only to stack this family on an env that already reads ``"params"``.
        config_key: the config key of ``parameters``, named by configuration errors.

    Raises:
        ConfigError (a ValueError): a bad parameter list, a target the model lacks (when the
            transform first meets its env), or an env whose MjModel it cannot reach.
        IdentifierError (a ValueError): identifiers of the wrong width or batch shape,
            non-finite, or outside the box.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs import TransformedEnv
        >>> from armeta_rl.envs.mujoco_tasks import PhysicsTaskTransform, gym_env
        >>> from armeta_rl.tasks import TASK_KEY
        >>> gravity = {"name": "g", "kind": "gravity_z", "low": -12.0, "high": -8.0}
        >>> env = TransformedEnv(gym_env("InvertedPendulum-v5"), PhysicsTaskTransform([gravity]))
        >>> start = env.reset(TensorDict({TASK_KEY: torch.tensor([-9.0])}, []))
        >>> env.rollout(3, tensordict=start, auto_reset=False)[TASK_KEY].squeeze(-1)
        tensor([-9., -9., -9.])
    """

    def __init__(
        self,
        parameters: Sequence[PhysicsParameter | Mapping[str, Any]],
        key: str = TASK_KEY,
        config_key: str = KEY,
    ) -> None:
        super().__init__(in_keys=[], out_keys=[key])
        self.key, self.config_key = key, config_key
        if all(isinstance(p, PhysicsParameter) for p in parameters):
            parameters = list(parameters)
            if not parameters:
                raise ConfigError(config_key, [], "needs at least one parameter")
        else:
            parameters = parse_parameters(parameters, config_key)
        self.parameters = tuple(parameters)
        self.space = task_space(self.parameters)
        self._sims: _ModelList | _BatchSims | None = None
        self._edits: list[list[_Edit]] = []
        self._params: torch.Tensor | None = None
        self._base_width = 0

    def clone(self) -> PhysicsTaskTransform:
        """A fresh copy, not yet bound to any env (it finds its models in its next parent)."""
        return type(self)(self.parameters, key=self.key, config_key=self.config_key)

    def set_container(self, container: Transform | EnvBase) -> None:
        """Attach to ``container``; inside a TransformedEnv, find the models at once, so that a
        target the model lacks is reported when the env is built."""
        super().set_container(container)
        if isinstance(container, TransformedEnv):
            self._bind()

    def _bind(self) -> None:
        """Find the simulations of the parent env, the model entries each parameter writes and the
        width of the parent's own identifiers under the key."""
        if self._sims is not None:
            return
        parent = self.parent
        if parent is None:
            raise ConfigError("env", None, "PhysicsTaskTransform must be inside a TransformedEnv")
        sims = _simulations(parent)
        self._edits = _resolve(sims.model, self.parameters, self.config_key)
        base = parent.state_spec.get(self.key, None)
        self._base_width = 0 if base is None else base.shape[-1]
        nominal = torch.tensor(_nominal_params(self._edits), dtype=torch.get_default_dtype())
        self._params = nominal.expand(*parent.batch_size, self.space.dim).clone()
        self._sims = sims

    def extend_task_space(self, base: TaskSpace | None) -> TaskSpace:
        """The box of the env with this transform: the base env's own identifiers (if any), then
        the physics (:func:`~armeta_rl.envs.task_env.task_space`)."""
        if base is None:
            return self.space
        return TaskSpace(base.names + self.space.names, base.low + self.space.low,
                         base.high + self.space.high)

    def extend_identifier_check(self, base: IdentifierCheck | None) -> IdentifierCheck:
        """The reset contract of the env with this transform: the base env's, then the physics
        identifiers, each in its range of the box."""
        base = base or IdentifierCheck((), (), (), ())
        return base.then(self.space.names, self.space.low, self.space.high)

    def check_params(self, params: torch.Tensor) -> torch.Tensor:
        """The physics identifiers of ``params`` (its last ``d`` columns, after the base env's
        own) as float64 rows ``[n, d]``; an IdentifierError naming the value and what is
        allowed."""
        width, dim = self._base_width + self.space.dim, self.space.dim
        names = [*(["<env's own>"] * self._base_width), *self.space.names]
        if not torch.is_floating_point(params) or params.shape[-1:] != (width,):
            raise IdentifierError(self.key, f"shape {tuple(params.shape)}",
                                  f"a float tensor [..., {width}]: {', '.join(names)}")
        rows = params[..., self._base_width :].detach().to("cpu", torch.float64)
        rows = rows.reshape(-1, dim)
        low, high = self.space.bounds(torch.float64)
        outside = ~(torch.isfinite(rows).all(-1) & ((rows >= low) & (rows <= high)).all(-1))
        if outside.any():
            box = ", ".join(f"{n} in [{lo:g}, {hi:g}]"
                            for n, lo, hi in zip(self.space.names, self.space.low, self.space.high))
            raise IdentifierError(self.key, rows[outside][0].tolist(),
                                  f"outside the task box ({box})")
        return rows

    def _reset_env_preprocess(self, tensordict: TensorDictBase | None) -> TensorDictBase | None:
        """Write the identifiers of the simulations being reset into their models, and hand the
        base env its own identifiers (the leading columns) only."""
        self._bind()
        params = None if tensordict is None else tensordict.get(self.key, None)
        if params is None:
            return tensordict
        if isinstance(params, TensorDictBase):  # by name
            params = self.extend_identifier_check(identifier_check(self.parent)).flat(params)
        shape = self._params.shape
        rows = self.check_params(params)
        if rows.shape[0] != math.prod(shape[:-1]):
            raise IdentifierError(self.key, f"shape {tuple(params.shape)}",
                                  f"needs {[*shape[:-1], self._base_width + shape[-1]]}, one "
                                  "task per simulation")
        reset = tensordict.get("_reset", None)
        mask = (torch.ones(rows.shape[0], dtype=torch.bool) if reset is None
                else reset.reshape(rows.shape[0], -1).any(-1).cpu())
        ids = np.flatnonzero(mask.numpy())
        if ids.size:
            self._sims.write(ids, self._edits, rows.numpy())
            new = rows.to(self._params.dtype).reshape(shape)
            self._params = torch.where(mask.reshape(*shape[:-1], 1), new, self._params)
        if self._base_width:
            tensordict.set(self.key, params[..., : self._base_width])
            return tensordict
        del tensordict[self.key]
        # the key was all the reset carried for this transform: the base env keeps its own
        # identifiers, as on a reset that names none (an empty TensorDict it would refuse)
        return None if tensordict.is_empty() else tensordict

    def identifiers(self, base: torch.Tensor | None, device: torch.device | None
                    ) -> torch.Tensor:
        """The key's value ``[*batch, w + d]``: the base env's identifiers ``base`` (if any)
        followed by the physics ones (a new tensor)."""
        physics = self._params.to(device)
        if self._base_width:
            physics = torch.cat([base, physics.to(base)], -1)
        return physics.clone()

    def _with_physics(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Set the key to the base env's identifiers (if any) followed by the physics ones."""
        return tensordict.set(self.key, self.identifiers(tensordict.get(self.key, None),
                                                         tensordict.device))

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        self._bind()
        return self._with_physics(tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._with_physics(next_tensordict)

    def _params_spec(self, spec: Composite) -> TensorSpec:
        """The key's spec: the base env's identifiers (if any) followed by the physics box."""
        low, high = self.space.bounds()
        shape, dim = spec.shape, self.space.dim
        base = spec.get(self.key, None)
        if base is not None:
            if not isinstance(base, Bounded):
                return Unbounded(shape=(*shape, base.shape[-1] + dim), dtype=base.dtype,
                                 device=spec.device)
            low = torch.cat([base.space.low, low.to(base.dtype).expand(*shape, dim)], -1)
            high = torch.cat([base.space.high, high.to(base.dtype).expand(*shape, dim)], -1)
            dim = low.shape[-1]
        return Bounded(low.expand(*shape, dim), high.expand(*shape, dim), shape=(*shape, dim),
                       dtype=torch.get_default_dtype() if base is None else base.dtype,
                       device=spec.device)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec[self.key] = self._params_spec(observation_spec)
        return observation_spec

    def transform_state_spec(self, state_spec: Composite) -> Composite:
        state_spec[self.key] = self._params_spec(state_spec)
        return state_spec


class MujocoWarning(UserWarning):
    """A warning MuJoCo's C library raised (through ``mju_warning``), e.g. the compiler's
    deprecation of ``settotalmass`` in gymnasium's HalfCheetah model.

    Silence it with ``warnings.simplefilter("ignore", MujocoWarning)``.

    Examples:
        >>> import subprocess
        >>> import sys
        >>> code = "from armeta_rl.envs.mujoco_tasks import gym_env; gym_env('HalfCheetah-v5')"
        >>> print(subprocess.run([sys.executable, "-c", code], capture_output=True,
        ...                      text=True).stderr)  # what a new process shows on stderr
        <string>:1: MujocoWarning: compiler attribute 'settotalmass' is deprecated ... model
        <BLANKLINE>
    """


_ISSUED: set[str] = set()
"""The MuJoCo warnings :func:`gym_env` has issued in this process. Python's own memory of shown
warnings cannot serve: TorchRL's ``GymEnv`` enters ``warnings.catch_warnings`` at every env it
builds, which clears it, so every env would show the warning again."""


def gym_env(env_id: str, **gym_kwargs: Any) -> GymEnv:
    """``GymEnv(env_id, **gym_kwargs)`` with the warnings MuJoCo raises while compiling its model
    issued as :class:`MujocoWarning`: MuJoCo prints each one to stdout at every compilation (24
    times for the 24 envs of the PPO example); each is issued once per process. They are
    collected during construction (TorchRL's ``GymEnv`` records and drops
    the Python warnings raised inside ``gym.make``) and issued after it; MuJoCo's own handler is
    restored.

    Examples:
        >>> import torch
        >>> from armeta_rl.envs.mujoco_tasks import gym_env
        >>> env = gym_env("InvertedPendulum-v5")  # TorchRL's GymEnv of gymnasium's env
        >>> _ = env.set_seed(0)
        >>> still = lambda td: td.set("action", torch.zeros(1))
        >>> env.rollout(3, still)["next", "reward"].flatten()  # 1 a step while the pole is up
        tensor([1., 1., 1.])
    """
    messages: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(messages.append)
    try:
        env = GymEnv(env_id, **gym_kwargs)
    finally:
        mujoco.set_mju_user_warning(previous)
    for message in messages:
        if message not in _ISSUED:
            _ISSUED.add(message)
            warnings.warn(message, MujocoWarning, stacklevel=2)
    return env


def make_gym_task_env(
    family: TaskFamily,
    num_tasks: int | None = None,
    max_steps: int | None = None,
    **gym_kwargs: Any,
) -> TaskTransformedEnv:
    """A TorchRL env of the family's gymnasium env whose physics follow ``"params"``: one
    ``GymEnv`` (batch ``[]``) if ``num_tasks`` is ``None``, else a ``SerialEnv`` of ``num_tasks``
    of them (batch ``[num_tasks]``, one task each). ``max_steps`` adds a ``StepCounter`` that
    truncates episodes after that many steps.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs.mujoco_tasks import load_task_family, make_gym_task_env
        >>> from armeta_rl.tasks import TASK_KEY
        >>> gear = {"name": "gear", "kind": "actuator_gear_scale", "target": "all",
        ...         "low": 0.5, "high": 2.0}  # the cart motor's force per unit of action
        >>> family = load_task_family({"env": "InvertedPendulum-v5", "parameters": [gear]})
        >>> env = make_gym_task_env(family, num_tasks=2, max_steps=50)  # a SerialEnv, one task each
        >>> _ = env.set_seed(0)
        >>> start = env.reset(TensorDict({TASK_KEY: torch.tensor([[1.0], [2.0]])}, [2]))
        >>> push = lambda td: td.set("action", torch.ones(2, 1))
        >>> after = env.rollout(1, push, tensordict=start, auto_reset=False)["next", "observation"]
        >>> (after[:, 0, 2] - start["observation"][:, 2]).round(decimals=2)  # the cart's speed gain
        tensor([0.3300, 0.6600], dtype=torch.float64)
    """
    if family.env is None:
        raise ConfigError("task_family.env", None, "a gymnasium MuJoCo env id, e.g. HalfCheetah-v5")
    if num_tasks is None:
        base: EnvBase = gym_env(family.env, **gym_kwargs)
    else:
        if num_tasks < 1:
            raise ConfigError("num_tasks", num_tasks, "must be >= 1")
        base = SerialEnv(num_tasks, partial(gym_env, family.env, **gym_kwargs))
    env = TaskTransformedEnv(base, PhysicsTaskTransform(family.parameters))
    if max_steps is not None:
        env.append_transform(StepCounter(max_steps))
    return env


class PhysicsTaskEnv(TaskTransformedEnv):
    """A :class:`~armeta_rl.envs.task_env.TaskTransformedEnv` of an env with
    ``gaussian_transitions`` (a batched MuJoCo env) and its :class:`PhysicsTaskTransform`, which
    rolls out with the base env's own
    ``gaussian_transitions``: the transform changes nothing within a rollout but the identifiers
    it emits (the physics are written at the full reset before, and the automatic resets
    between steps carry no identifiers), so the rollout is ``env.rollout``'s bit for bit
    (``tests/test_locomotion.py``) without TorchRL's per-step machinery.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from armeta_rl.envs import HalfCheetahVelEnv
        >>> from armeta_rl.envs.mujoco_tasks import physics_task_env
        >>> from armeta_rl.rl import GaussianMLP
        >>> from armeta_rl.rl.policy import GaussianActor
        >>> mass = {"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all",
        ...         "low": 0.75, "high": 1.25}
        >>> tasks = torch.tensor([[1.5, 0.8], [0.5, 1.2]])[:, None]  # (velocity, mass) x 2 tasks
        >>> net = GaussianMLP(obs_dim=20, action_dim=6, hidden=(16,))
        >>> def rollout(fast):
        ...     env = physics_task_env(HalfCheetahVelEnv, [mass], batch_size=(2, 1), seed=0)
        ...     torch.manual_seed(0)
        ...     start = env.reset(TensorDict({"params": tasks}, [2, 1]))
        ...     if fast:
        ...         return env.gaussian_transitions(5, net)
        ...     return env.rollout(5, GaussianActor(net), tensordict=start, auto_reset=False,
        ...                        break_when_any_done=False)
        >>> fast, slow = rollout(True), rollout(False)
        >>> fast["next", "params"][:, 0, -1]  # the goal velocity, then the physics
        tensor([[1.5000, 0.8000],
                [0.5000, 1.2000]])
        >>> all(torch.equal(fast[key], slow[key]) for key in fast.keys(True, True))
        True
    """

    def gaussian_transitions(self, steps: int, net: GaussianMLP,
                             params: TensorDictBase | None = None) -> TensorDictBase:
        """The base env's ``gaussian_transitions`` with the key's identifiers of every step
        followed by the physics ones, as the transform emits them."""
        rollout = self.base_env.gaussian_transitions(steps, net, params)
        transform, time = self.transform, len(self.batch_size)
        for key in (transform.key, ("next", transform.key)):
            rollout.set(key, torch.stack([
                transform.identifiers(base, rollout.device)
                for base in rollout.get(key).unbind(time)], time))
        return rollout


def physics_task_env(
    make_env: Callable[..., EnvBase],
    parameters: Sequence[Mapping[str, Any]],
    space: Mapping[str, Any] | None = None,
    config_key: str = "benchmark.collector.make_env.parameters",
    **kwargs: Any,
) -> TaskTransformedEnv:
    """``make_env(**kwargs)`` with a :class:`PhysicsTaskTransform` over ``parameters``: the
    ``make_env`` a collector calls as ``make_env(batch_size=..., max_steps=..., seed=...)``, so a
    benchmark YAML turns an env into a physics family (``configs/benchmark/ant_goal_physics.yaml``).
    An env whose class rolls out a Gaussian policy itself (``gaussian_transitions``: the batched
    MuJoCo envs) comes as a :class:`PhysicsTaskEnv`, which keeps that rollout.

    Args:
        make_env: builds the base env from ``kwargs``.
        parameters: the physics parameters (YAML mappings).
        space: the benchmark's box ``{names, low, high}``; if given, it must be the env's own
            identifiers followed by exactly the physics parameters (names and ranges).
        config_key: the config key of ``parameters``, named by errors.

    Raises:
        ConfigError: bad parameters, or a box that does not match them.

    Examples:
        >>> import torch
        >>> from armeta_rl.envs import AntGoalEnv
        >>> from armeta_rl.envs.mujoco_tasks import physics_task_env
        >>> friction = {"name": "friction", "kind": "geom_friction_scale", "target": "all",
        ...             "low": 0.5, "high": 1.5}
        >>> env = physics_task_env(AntGoalEnv, [friction], batch_size=(2, 3))
        >>> env.task_space.names  # the goal's identifiers, then the friction scale
        ('goal_x', 'goal_y', 'friction')
        >>> env.task_space.low, env.task_space.high  # the goal's ±3 box and the friction's
        ((-3.0, -3.0, 0.5), (3.0, 3.0, 1.5))
    """
    if isinstance(parameters, (DictConfig, ListConfig)):
        parameters = OmegaConf.to_container(parameters, resolve=True)
    transform = PhysicsTaskTransform(parameters, config_key=config_key)
    base = make_env(**kwargs)
    fast = callable(getattr(type(base), "gaussian_transitions", None))
    env = (PhysicsTaskEnv if fast else TaskTransformedEnv)(base, transform)
    if space is not None:
        _check_box(space, transform, env.state_spec[transform.key].shape[-1])
    return env


def _check_box(space: Mapping[str, Any], transform: PhysicsTaskTransform, width: int) -> None:
    """A ConfigError unless the box has ``width`` identifiers whose last ones are the physics
    parameters, with their names and ranges."""
    box = TaskSpace(list(space["names"]), list(space["low"]), list(space["high"]))
    physics = transform.space
    tail = (box.names[-physics.dim :], box.low[-physics.dim :], box.high[-physics.dim :])
    if box.dim != width or tail != (physics.names, physics.low, physics.high):
        wanted = ", ".join(f"{n} in [{lo:g}, {hi:g}]"
                           for n, lo, hi in zip(physics.names, physics.low, physics.high))
        raise ConfigError("benchmark.space", {"names": list(box.names), "low": list(box.low),
                                              "high": list(box.high)},
                          f"{width} identifiers: the env's own {width - physics.dim}, then the "
                          f"physics parameters of {transform.config_key} ({wanted})")
