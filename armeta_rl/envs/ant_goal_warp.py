"""Ant goal-position on MuJoCo Warp: the :class:`~armeta_rl.envs.ant_goal.AntGoalEnv` task (same
MJCF, reward, termination, observation, seeding) with its physics on a warp device, a GPU where
there is one (issue "Scale: GPUs and distributed collection", item 3), and everything else of a
step there too: nothing goes through the host between steps.

:class:`WarpBatch` stands in for the ``mujoco.batch.Batch`` of the CPU env: the same calls
(``bind``, ``reset``, ``forward``, ``step``) on ``nsim`` worlds of one ``mujoco_warp`` model. Its
``bind`` returns torch views of the warp arrays themselves (``warp.to_torch``: same memory, on the
warp device), so the env writes the controls and reads the state, the contact forces and the torso
pose where the physics keeps them, and computes the observation, reward and termination with the
CPU env's own code (written for NumPy arrays and torch tensors alike,
:class:`~armeta_rl.envs.ant_goal.AntTaskEnv`) in torch on that device. The env's torch device is the
warp device's, so the policy of an episode collector acts there and the trajectories stay there
(:class:`~armeta_rl.collectors.episodes.EpisodeCollector`). ``step`` runs ``nstep`` ``mjw.step``
then ``mjw.forward`` at the new state, whose sensor stage (the torso accelerometer of
:func:`~armeta_rl.envs.ant_goal.load_ant_model`) computes the contact forces ``cfrc_ext``, as the
CPU batch does with ``stage=mjSTAGE_ACC``. On CUDA that sequence (hundreds of small kernels) is
captured once into a CUDA graph and replayed at every step, as are resets (``graphs``; the same
kernels on the same arrays, so the same results); torch's and warp's work are ordered by
synchronizing the device between them.

Reset noise and default goals are drawn on the CPU with the env's generator, exactly as the CPU env
draws them, and copied to the device (resets are rare against steps).

MuJoCo Warp computes in float32 (the CPU env in float64) and solves contacts with its own
parallel solver, so its trajectories equal the CPU dynamics only up to a tolerance, stated and
checked in ``tests/test_ant_goal_warp.py``. It runs on warp's ``"cpu"`` device too (for checks
without a GPU; far slower than the native CPU batch); ``warp_device="cuda"`` needs a CUDA device
and fails with a :class:`~armeta_rl.errors.ConfigError` where there is none.

``mujoco-warp`` is an optional dependency (``pip install 'armeta-rl[gpu]'``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from functools import partial
from typing import Any

import mujoco
import numpy as np
import torch

from armeta_rl.envs.ant_goal import AntGoalEnv, observation_size
from armeta_rl.errors import ConfigError
from armeta_rl.quiet import native_stderr_silenced

DEVICE_KEY = "benchmark.collector.make_env.warp_device"
STATE = ("qpos", "qvel", "ctrl")
OUTPUTS = ("cfrc_ext", "xpos", "xmat")


def _import_warp():
    """``(warp, mujoco_warp)``, started quietly, or a :class:`ConfigError` naming the extra that
    provides them."""
    try:
        import warp
    except ImportError:
        raise ConfigError(DEVICE_KEY, None, "MuJoCo Warp is not installed: "
                          "pip install 'armeta-rl[gpu]' (mujoco-warp)") from None
    warp.config.log_level = warp.LOG_WARNING  # no start-up banner, no line per module loaded
    with native_stderr_silenced():  # its CUDA warning: find_warp_device says it in one line
        warp.init()
    import mujoco_warp

    return warp, mujoco_warp


def find_warp_device(name: str):
    """The warp device ``name`` (``"cuda"``, ``"cuda:N"`` or ``"cpu"``); a :class:`ConfigError`
    when warp has no such device (e.g. ``"cuda"`` on a machine without CUDA)."""
    warp, _ = _import_warp()
    names = [str(device) for device in warp.get_devices()]
    wanted = "cuda:0" if name == "cuda" else str(name)
    if wanted not in names:
        raise ConfigError(DEVICE_KEY, name,
                          f"warp has no such device here (it has: {', '.join(names)}); "
                          "'cuda' needs an NVIDIA GPU and driver")
    return warp.get_device(wanted)


class WarpBatch:
    """``nsim`` simulations of ``model`` on a warp device, with the calls of ``mujoco.batch.Batch``
    that :class:`~armeta_rl.envs.ant_goal.AntGoalEnv` makes, its fields as torch views.

    Args:
        model: the MuJoCo model (copied to the device).
        nsim: number of simulations (warp worlds).
        device: warp device name (:func:`find_warp_device`).
        nconmax, njmax: contacts and constraints allocated per world (``None``: MuJoCo Warp's
            defaults for the model).
        graphs: replay ``step``, ``forward`` and ``reset`` as CUDA graphs (``None``: on CUDA; a
            capture that fails falls back to launching the kernels, with a warning).
    """

    def __init__(self, model: mujoco.MjModel, nsim: int, device: str = "cuda",
                 nconmax: int | None = None, njmax: int | None = None,
                 graphs: bool | None = None) -> None:
        self.wp, self.mjw = _import_warp()
        self.device = find_warp_device(device)
        with self.wp.ScopedDevice(self.device):
            self.model = self.mjw.put_model(model)
            self.data = self.mjw.make_data(model, nworld=nsim, nconmax=nconmax, njmax=njmax)
            self._reset_mask = self.wp.zeros(nsim, dtype=bool)
        self.nsim = nsim
        self.torch_device = torch_device_of(self.device)
        self.graphs = self.device.is_cuda and (graphs is None or bool(graphs))
        self._graphs: dict[str, Any] = {}
        views = {name: self.wp.to_torch(getattr(self.data, name))
                 for name in ("qpos", "qvel", "ctrl", "cfrc_ext", "xpos")}
        views["xmat"] = self.wp.to_torch(self.data.xmat).reshape(nsim, model.nbody, 9)
        self._views = views  # the shapes mujoco.batch.Batch binds
        self._mask_view = self.wp.to_torch(self._reset_mask)

    def bind(self, name: str) -> torch.Tensor:
        """The live torch view ``(nsim, ...)`` (float32, on the warp device) of field ``name``:
        writes to ``qpos``, ``qvel``, ``ctrl`` are what the next call simulates; the outputs are
        refreshed by every call."""
        return self._views[name]

    def _run(self, name: str, launch: Callable[[], None]) -> None:
        """Run ``launch`` (warp kernels) after torch's pending work and before torch's next; as a
        CUDA graph captured at its first call when ``graphs``. Resets are replayed too: some of
        the batch's worlds end at nearly every step, and mujoco_warp's ``reset_data`` builds and
        hashes its kernels anew at each call, while the replay reads
        the reset mask as the env last wrote it."""
        if self.device.is_cuda:
            torch.cuda.synchronize(self.torch_device)
        with self.wp.ScopedDevice(self.device):
            if self.graphs and name not in self._graphs:
                self._graphs[name] = self._capture(name, launch)
            graph = self._graphs.get(name)
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

    def reset(self, ids: np.ndarray | None = None,
              stage: int = mujoco.mjtStage.mjSTAGE_ACC.value) -> None:
        """Reset simulations ``ids`` (``None``: all) to the model's defaults, then run the forward
        pass unless ``stage`` is ``mjSTAGE_NONE``."""
        mask = self._mask_view
        mask.fill_(ids is None)
        if ids is not None:
            mask[torch.as_tensor(ids, dtype=torch.long, device=mask.device)] = True

        def launch() -> None:
            self.mjw.reset_data(self.model, self.data, reset=self._reset_mask)

        self._run("reset", launch)
        if stage != mujoco.mjtStage.mjSTAGE_NONE.value:
            self.forward()

    def forward(self, ids: np.ndarray | None = None,
                stage: int = mujoco.mjtStage.mjSTAGE_ACC.value) -> None:
        """The forward pass at the state the env wrote (on every world: the others' derived
        fields are recomputed unchanged)."""
        self._run("forward", lambda: self.mjw.forward(self.model, self.data))

    def step(self, nstep: int = 1, stage: int = mujoco.mjtStage.mjSTAGE_ACC.value) -> None:
        """``nstep`` physics steps with the controls the env wrote, then the forward pass at the
        new state (``stage`` ``mjSTAGE_ACC``, the only stage the env asks for)."""
        def launch() -> None:
            for _ in range(int(nstep)):
                self.mjw.step(self.model, self.data)
            self.mjw.forward(self.model, self.data)

        self._run(f"step{int(nstep)}", launch)


def torch_device_of(warp_device) -> torch.device:
    """The torch device of a warp device (``cuda:N`` or ``cpu``)."""
    if warp_device.is_cuda:
        return torch.device("cuda", warp_device.ordinal)
    return torch.device("cpu")


class AntGoalWarpEnv(AntGoalEnv):
    """:class:`~armeta_rl.envs.ant_goal.AntGoalEnv` with its simulations on MuJoCo Warp and its
    step on the warp device.

    Args:
        args, kwargs: :class:`~armeta_rl.envs.ant_goal.AntGoalEnv`'s arguments, passed on
            unchanged (``threads`` is unused by MuJoCo Warp, accepted so that a config can swap
            the env class alone); ``device`` (the torch device of the outputs) defaults to the
            warp device's.
        warp_device: where the physics runs: ``"cuda"``, ``"cuda:N"`` or ``"cpu"`` (warp's CPU
            backend, for checks).
        nconmax, njmax: contacts and constraints per world (``None``: MuJoCo Warp's defaults).
        graphs: replay the physics as CUDA graphs (``None``: on CUDA; :class:`WarpBatch`).
    """

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
        return torch.empty(self.n_sims, observation_size(self.model), device=self.sim_device)

    def _as_sim(self, tensor: torch.Tensor) -> torch.Tensor:
        """``tensor`` as the simulation's arrays: float32 on the warp device."""
        return tensor.detach().to(self.sim_device, torch.float32)

    def _as_torch(self, array: torch.Tensor) -> torch.Tensor:
        return array

    def _snapshot(self, array: torch.Tensor) -> torch.Tensor:
        return array.clone()


def ant_goal_warp(warp_device: str = "cuda", **kwargs) -> Callable[..., AntGoalWarpEnv]:
    """``AntGoalWarpEnv`` with ``kwargs`` as a ``make_env`` for the episode collectors, once
    ``warp_device`` is checked: a config naming a device warp lacks fails when the collector is
    built, before any training (the env itself is built at the first collection)."""
    find_warp_device(warp_device)
    return partial(AntGoalWarpEnv, warp_device=warp_device, **kwargs)
