"""MuJoCo Warp physics for every batched MuJoCo task env: any
:class:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv` subclass (Ant-Pos, Ant-Dir,
HalfCheetah-Vel/Dir, Walker2d-Vel, and the mass-scale families on top of them) steps its
``tasks × episodes`` simulations as the worlds of one ``mujoco_warp`` model on a warp device, a GPU
where there is one, with nothing going through the host between steps.

:class:`WarpBatch` stands in for the :class:`mujoco.batch.Batch` of the CPU envs: the same calls
(``bind``, ``reset``, ``forward``, ``step``, and ``expand``, ``set_const`` for per-simulation
model fields) on ``nsim`` worlds. Its ``bind`` returns torch views of the warp arrays themselves
(``warp.to_torch``: same memory, on the warp device), shaped as the CPU batch binds them, so the
env writes the controls and reads the state and outputs where the physics keeps them.
:class:`WarpSimulation` is the env side: mixed into a task env's class
(``class HalfCheetahVelWarpEnv(WarpSimulation, HalfCheetahVelEnv)``) it makes the bound arrays
float32 torch tensors on the warp device and the array module of the task's code torch
(:attr:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv.xp`), so the family's own observation,
reward, termination, identifiers and resets run unchanged, in torch on that device. The env's
torch device is the warp device's, so an episode collector's policy acts there and the
trajectories stay there (:class:`~armeta_rl.collectors.episodes.EpisodeCollector`).

``step`` runs ``nstep`` ``mjw.step`` then the forward stage the env asks for at the new state:
``mjSTAGE_ACC``, ``mjw.forward`` (whose sensor stage computes the contact forces ``cfrc_ext`` where
the model has an accelerometer, as the Ant's); ``mjSTAGE_POS``, the forward kinematics (body
positions and orientations, all the planar runners read). On CUDA each sequence (hundreds of small
kernels) is captured once into a CUDA graph and replayed at every step, as are resets
(``graphs``; the same kernels on the same arrays, so the same results); torch's and warp's work
are ordered by synchronizing the device between them.

Per-simulation physics (:class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform`, e.g. the
MassVel families' mass scale): ``expand`` gives a model field a world dimension (MuJoCo Warp's
batched model fields: ``body_mass`` of shape ``(nworld, nbody)`` instead of ``(1, nbody)``) and
returns it as a torch view; ``set_const`` runs ``mjw.set_const`` on every world, which recomputes
the constants derived from the masses (subtree masses, the inverse weights of the constraint
solver) per world, as ``mj_setConst`` does per simulation on the CPU.

Reset noise and default identifiers are drawn on the CPU with the env's generator, exactly as the
CPU env draws them, and copied to the device (resets are rare against steps).

MuJoCo Warp computes in float32 (the CPU envs in float64) and solves contacts with its own
parallel solver, so its trajectories equal the CPU dynamics only up to a tolerance, stated and
checked in ``tests/test_ant_goal_warp.py`` and ``tests/test_warp_families.py``. It runs on warp's
``"cpu"`` device too (for checks without a GPU; far slower than the native CPU batch);
``warp_device="cuda"`` needs a CUDA device and fails with a
:class:`~armeta_rl.errors.ConfigError` where there is none.

``mujoco-warp`` is an optional dependency (``pip install 'armeta-rl[gpu]'``).
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from functools import partial
from typing import Any

import mujoco
import numpy as np
import torch

from armeta_rl.errors import ConfigError
from armeta_rl.quiet import native_stderr_silenced

DEVICE_KEY = "benchmark.collector.make_env.warp_device"
STAGE_NONE = mujoco.mjtStage.mjSTAGE_NONE.value
STAGE_POS = mujoco.mjtStage.mjSTAGE_POS.value
STAGE_ACC = mujoco.mjtStage.mjSTAGE_ACC.value
CONSTANTS = ("body_subtreemass", "body_invweight0", "dof_invweight0", "tendon_invweight0",
             "actuator_acc0")
"""The model fields ``mjw.set_const`` derives from the masses and inertias: per world once any
field is (else every world would write its own into the one shared row)."""


def _import_warp(key: str = DEVICE_KEY):
    """``(warp, mujoco_warp)``, started quietly, or a :class:`ConfigError` naming the extra that
    provides them."""
    try:
        import warp
    except ImportError:
        raise ConfigError(key, None, "MuJoCo Warp is not installed: "
                          "pip install 'armeta-rl[gpu]' (mujoco-warp)") from None
    warp.config.log_level = warp.LOG_WARNING  # no start-up banner, no line per module loaded
    with native_stderr_silenced():  # its CUDA warning: find_warp_device says it in one line
        warp.init()
    import mujoco_warp

    return warp, mujoco_warp


def find_warp_device(name: str, key: str = DEVICE_KEY):
    """The warp device ``name`` (``"cuda"``, ``"cuda:N"`` or ``"cpu"``); a :class:`ConfigError`
    naming the config ``key`` when warp has no such device (e.g. ``"cuda"`` on a machine without
    CUDA)."""
    warp, _ = _import_warp(key)
    names = [str(device) for device in warp.get_devices()]
    wanted = "cuda:0" if name == "cuda" else str(name)
    if wanted not in names:
        raise ConfigError(key, name,
                          f"warp has no such device here (it has: {', '.join(names)}); "
                          "'cuda' needs an NVIDIA GPU and driver")
    return warp.get_device(wanted)


def torch_device_of(warp_device) -> torch.device:
    """The torch device of a warp device (``cuda:N`` or ``cpu``)."""
    if warp_device.is_cuda:
        return torch.device("cuda", warp_device.ordinal)
    return torch.device("cpu")


class WarpBatch:
    """``nsim`` simulations of ``model`` on a warp device, with the calls of
    :class:`mujoco.batch.Batch` that the batched MuJoCo envs and
    :class:`~armeta_rl.envs.mujoco_tasks.PhysicsTaskTransform` make, its fields as torch views.

    Args:
        model: the MuJoCo model (copied to the device).
        nsim: number of simulations (warp worlds).
        device: warp device name (:func:`find_warp_device`).
        nconmax: contacts allocated per world (``None``: MuJoCo Warp's default for the model).
        njmax: constraints allocated per world (``None``: MuJoCo Warp's default).
        graphs: replay ``step``, ``forward`` and ``reset`` as CUDA graphs (``None``: on CUDA; a
            capture that fails falls back to launching the kernels, with a warning).
    """

    def __init__(self, model: mujoco.MjModel, nsim: int, device: str = "cuda",
                 nconmax: int | None = None, njmax: int | None = None,
                 graphs: bool | None = None) -> None:
        self.wp, self.mjw = _import_warp()
        self.device = find_warp_device(device)
        self.host_model = model
        with self.wp.ScopedDevice(self.device):
            self.model = self.mjw.put_model(model)
            self.data = self.mjw.make_data(model, nworld=nsim, nconmax=nconmax, njmax=njmax)
            self._reset_mask = self.wp.zeros(nsim, dtype=bool)
        self.nsim = nsim
        self.torch_device = torch_device_of(self.device)
        self.graphs = self.device.is_cuda and (graphs is None or bool(graphs))
        self._graphs: dict[str, Any] = {}
        self._host_data = mujoco.MjData(model)  # the shapes of the fields, as MjData has them
        self._views: dict[str, torch.Tensor] = {}
        self._expanded: dict[str, torch.Tensor] = {}
        self._mask_view = self.wp.to_torch(self._reset_mask)

    def bind(self, name: str) -> torch.Tensor:
        """The live torch view ``(nsim, ...)`` (float32, on the warp device) of MjData field
        ``name``, shaped as :class:`mujoco.batch.Batch` binds it (``xmat``: ``(nsim, nbody, 9)``):
        writes to ``qpos``, ``qvel``, ``ctrl`` are what the next call simulates; the outputs are
        refreshed by every call."""
        if name not in self._views:
            shape = np.shape(getattr(self._host_data, name))
            view = self.wp.to_torch(getattr(self.data, name))
            self._views[name] = view.reshape(self.nsim, *shape)
        return self._views[name]

    def expand(self, name: str) -> torch.Tensor:
        """Give model field ``name`` (as in MjModel; an option as ``"opt.<name>"``) a world
        dimension, one row per simulation, starting from the shared values; its live torch view
        ``(nsim, ...)`` (float32, on the warp device), shaped as :class:`mujoco.batch.Batch`
        expands it. After writing a field that ``mj_setConst`` reads (the masses), call
        :meth:`set_const`."""
        if name not in self._expanded:
            option = name.startswith("opt.")
            field = name[4:] if option else name
            owner, host = ((self.model.opt, self.host_model.opt) if option
                           else (self.model, self.host_model))
            self._per_world(owner, field)
            view = self.wp.to_torch(getattr(owner, field))
            self._expanded[name] = view.reshape(self.nsim, *np.shape(getattr(host, field)))
        return self._expanded[name]

    def _per_world(self, owner: Any, field: str) -> None:
        """Replace ``owner.field`` by an array of one row per world, each a copy of its shared
        row; the kernels read row ``world % rows``, so each world reads its own from then on.
        Captured CUDA graphs read the replaced array and are dropped."""
        array = getattr(owner, field)
        if array.shape[0] == self.nsim:
            return
        rows = np.repeat(array.numpy()[:1], self.nsim, axis=0)
        setattr(owner, field, self.wp.array(rows, dtype=array.dtype, device=self.device))
        self._graphs.clear()

    def set_const(self, ids: np.ndarray | None = None) -> None:
        """Recompute the constants derived from the model fields (``mjw.set_const``, MuJoCo's
        ``mj_setConst``), per world: those of the worlds not in ``ids`` follow from their
        unchanged fields."""
        for field in CONSTANTS:
            self._per_world(self.model, field)
        self._run("set_const", lambda: self.mjw.set_const(self.model, self.data), capture=False)

    def _run(self, name: str, launch: Callable[[], None], capture: bool = True) -> None:
        """Run ``launch`` (warp kernels) after torch's pending work and before torch's next; as a
        CUDA graph captured at its first call when ``graphs`` (and ``capture``). Resets are
        replayed too: some of the batch's worlds end at nearly every step, and mujoco_warp's
        ``reset_data`` builds and hashes its kernels anew at each call, while the replay reads
        the reset mask as the env last wrote it."""
        if self.device.is_cuda:
            torch.cuda.synchronize(self.torch_device)
        with self.wp.ScopedDevice(self.device):
            if capture and self.graphs and name not in self._graphs:
                self._graphs[name] = self._capture(name, launch)
            graph = self._graphs.get(name) if capture else None
            if graph is None:
                launch()
            else:
                self.wp.capture_launch(graph)
            self.wp.synchronize_device(self.device)

    def _capture(self, name: str, launch: Callable[[], None]):
        try:
            with self.wp.ScopedCapture(device=self.device) as capture:
                launch()
            return capture.graph
        except Exception as error:  # any capture failure leaves the kernels launched one by one
            warnings.warn(f"MuJoCo Warp: capturing {name} as a CUDA graph failed ({error}); its "
                          "kernels are launched one by one", RuntimeWarning, stacklevel=3)
            return None

    def _stage(self, stage: int) -> None:
        """The forward stages up to ``stage`` at the current state: ``mjSTAGE_ACC`` the whole
        forward pass (sensors included), ``mjSTAGE_POS`` the forward kinematics, which is what a
        position-stage env reads (body poses)."""
        if stage >= STAGE_ACC:
            self.mjw.forward(self.model, self.data)
        elif stage >= STAGE_POS:
            self.mjw.kinematics(self.model, self.data)

    def reset(self, ids: np.ndarray | None = None, stage: int = STAGE_ACC) -> None:
        """Reset simulations ``ids`` (``None``: all) to the model's defaults, then run the forward
        stages up to ``stage`` (on every world)."""
        mask = self._mask_view
        mask.fill_(ids is None)
        if ids is not None:
            mask[torch.as_tensor(ids, dtype=torch.long, device=mask.device)] = True

        def launch() -> None:
            self.mjw.reset_data(self.model, self.data, reset=self._reset_mask)

        self._run("reset", launch)
        if stage != STAGE_NONE:
            self.forward(stage=stage)

    def forward(self, ids: np.ndarray | None = None, stage: int = STAGE_ACC) -> None:
        """The forward stages up to ``stage`` at the state the env wrote (on every world: the
        others' derived fields are recomputed unchanged)."""
        self._run(f"forward{stage}", lambda: self._stage(stage))

    def step(self, nstep: int = 1, stage: int = STAGE_ACC) -> None:
        """``nstep`` physics steps with the controls the env wrote, then the forward stages up to
        ``stage`` at the new state."""
        def launch() -> None:
            for _ in range(int(nstep)):
                self.mjw.step(self.model, self.data)
            self._stage(stage)

        self._run(f"step{int(nstep)}-{stage}", launch)


class WarpSimulation:
    """Mixin that puts a :class:`~armeta_rl.envs.batched_mujoco.BatchedMujocoEnv` subclass's
    simulations on MuJoCo Warp and its step on the warp device:
    ``class HalfCheetahVelWarpEnv(WarpSimulation, HalfCheetahVelEnv)`` is HalfCheetah-Vel with
    the same model, reward, observation, identifiers and seeding (module docstring).

    Args:
        *args: the task env's positional arguments, passed on.
        warp_device: where the physics runs: ``"cuda"``, ``"cuda:N"`` or ``"cpu"`` (warp's CPU
            backend, for checks).
        nconmax: contacts per world (``None``: MuJoCo Warp's default).
        njmax: constraints per world (``None``: MuJoCo Warp's default).
        graphs: replay the physics as CUDA graphs (``None``: on CUDA; :class:`WarpBatch`).
        **kwargs: the task env's keyword arguments, passed on unchanged (``threads`` is unused
            by MuJoCo Warp, accepted so that a config can swap the env class alone); ``device``
            (the torch device of the outputs) defaults to the warp device's.
    """

    xp = torch

    def __init__(
        self,
        *args: Any,
        warp_device: str = "cuda",
        nconmax: int | None = None,
        njmax: int | None = None,
        graphs: bool | None = None,
        **kwargs: Any,
    ) -> None:
        self._warp = {"device": str(warp_device), "nconmax": nconmax, "njmax": njmax,
                      "graphs": graphs}
        if kwargs.get("device") is None:
            kwargs["device"] = torch_device_of(find_warp_device(str(warp_device)))
        super().__init__(*args, **kwargs)

    def _make_batch(self, threads: int) -> WarpBatch:
        return WarpBatch(self.model, self.n_sims, **self._warp)

    @property
    def sim_device(self) -> torch.device:
        return self.sim.torch_device

    def _new_observation(self) -> torch.Tensor:
        return torch.empty(self.n_sims, self.observation_size(), device=self.sim_device)

    def _as_sim(self, tensor: torch.Tensor) -> torch.Tensor:
        """``tensor`` as the simulation's arrays: float32 on the warp device."""
        return tensor.detach().to(self.sim_device, torch.float32)

    def _as_torch(self, array: torch.Tensor) -> torch.Tensor:
        return array

    def _snapshot(self, array: torch.Tensor) -> torch.Tensor:
        return array.clone()


def warp_env(env: type | str, warp_device: str = "cuda", device_key: str = DEVICE_KEY,
             **kwargs: Any) -> Callable[..., Any]:
    """The Warp env class ``env`` (a :class:`WarpSimulation` subclass, or its import path
    ``"module.Class"``) with ``warp_device`` and ``kwargs`` as a ``make_env`` for the episode
    collectors, once ``warp_device`` is checked: a config naming a device warp lacks fails when
    the collector is built, before any training (the env itself is built at the first
    collection). ``device_key`` is the config key errors name for ``warp_device``.

    ``configs/benchmark/half_cheetah_vel_warp.yaml`` builds its ``make_env`` as
    ``warp_env("armeta_rl.envs.locomotion_warp.HalfCheetahVelWarpEnv", "cuda", **options)``.
    """
    given = env
    if isinstance(env, str):
        module, _, name = env.rpartition(".")
        try:
            env = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError):
            env = None
    if not (isinstance(env, type) and issubclass(env, WarpSimulation)):
        raise ConfigError(device_key.rpartition(".")[0] + ".env", given,
                          "the import path of a MuJoCo Warp env class "
                          "(armeta_rl.envs.locomotion_warp.HalfCheetahVelWarpEnv, ...)")
    find_warp_device(warp_device, device_key)
    return partial(env, warp_device=warp_device, **kwargs)
