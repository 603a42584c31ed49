"""Ant goal-position on MuJoCo Warp: the :class:`~armeta_rl.envs.ant_goal.AntGoalEnv` task (same
MJCF, reward, termination, observation, seeding) with its physics on a warp device, a GPU where
there is one (issue "Scale: GPUs and distributed collection", item 3).

:class:`WarpBatch` stands in for the ``mujoco.batch.Batch`` of the CPU env: the same calls
(``bind``, ``reset``, ``forward``, ``step``) on ``nsim`` worlds of one ``mujoco_warp`` model. The
env's state and outputs live in host arrays as with ``Batch``; a call uploads the state the env
wrote (qpos, qvel, ctrl), runs the warp kernels on every world, and downloads the state and the
fields the env reads (``cfrc_ext``, ``xpos``, ``xmat``). ``step`` runs ``nstep`` ``mjw.step``
then ``mjw.forward`` at the new state, whose sensor stage (the torso accelerometer of
:func:`~armeta_rl.envs.ant_goal.load_ant_model`) computes the contact forces ``cfrc_ext``, as the
CPU batch does with ``stage=mjSTAGE_ACC``.

MuJoCo Warp computes in float32 (the CPU env in float64) and solves contacts with its own
parallel solver, so its trajectories equal the CPU dynamics only up to a tolerance, stated and
checked in ``tests/test_ant_goal_warp.py``. It runs on warp's ``"cpu"`` device too (for checks
without a GPU; far slower than the native CPU batch); ``warp_device="cuda"`` needs a CUDA device
and fails with a :class:`~armeta_rl.errors.ConfigError` where there is none.

``mujoco-warp`` is an optional dependency (``pip install 'armeta-rl[gpu]'``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import mujoco
import numpy as np

from armeta_rl.envs.ant_goal import AntGoalEnv
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
    that :class:`~armeta_rl.envs.ant_goal.AntGoalEnv` makes.

    Args:
        model: the MuJoCo model (copied to the device).
        nsim: number of simulations (warp worlds).
        device: warp device name (:func:`find_warp_device`).
        nconmax, njmax: contacts and constraints allocated per world (``None``: MuJoCo Warp's
            defaults for the model).
    """

    def __init__(self, model: mujoco.MjModel, nsim: int, device: str = "cuda",
                 nconmax: int | None = None, njmax: int | None = None) -> None:
        self.wp, self.mjw = _import_warp()
        self.device = find_warp_device(device)
        with self.wp.ScopedDevice(self.device):
            self.model = self.mjw.put_model(model)
            self.data = self.mjw.make_data(model, nworld=nsim, nconmax=nconmax, njmax=njmax)
        self.nsim = nsim
        self._shapes = {"qpos": (model.nq,), "qvel": (model.nv,), "ctrl": (model.nu,),
                        "cfrc_ext": (model.nbody, 6), "xpos": (model.nbody, 3),
                        "xmat": (model.nbody, 9)}  # as mujoco.batch.Batch binds them
        self._host = {name: self._download(name) for name in (*STATE, *OUTPUTS)}

    def _download(self, name: str) -> np.ndarray:
        values = getattr(self.data, name).numpy()
        return values.reshape(self.nsim, *self._shapes[name]).astype(np.float64)

    def bind(self, name: str) -> np.ndarray:
        """The live host array ``(nsim, ...)`` of field ``name`` (float64): writes to a state
        field are uploaded by the next call, outputs are refreshed by every call."""
        return self._host[name]

    def _sync(self, upload: bool) -> None:
        """Upload the host state (``upload``), or download the state and the outputs."""
        if upload:
            for name in STATE:
                values = self._host[name].astype(np.float32)
                getattr(self.data, name).assign(self.wp.array(values, device=self.device))
            return
        for name in (*STATE, *OUTPUTS):
            self._host[name][...] = self._download(name)

    def _mask(self, ids: np.ndarray | None):
        mask = np.zeros(self.nsim, dtype=bool)
        mask[slice(None) if ids is None else ids] = True
        return self.wp.array(mask, dtype=bool, device=self.device)

    def reset(self, ids: np.ndarray | None = None,
              stage: int = mujoco.mjtStage.mjSTAGE_ACC.value) -> None:
        """Reset simulations ``ids`` (``None``: all) to the model's defaults, then run the forward
        pass unless ``stage`` is ``mjSTAGE_NONE``."""
        self._sync(upload=True)
        with self.wp.ScopedDevice(self.device):
            self.mjw.reset_data(self.model, self.data, reset=self._mask(ids))
            if stage != mujoco.mjtStage.mjSTAGE_NONE.value:
                self.mjw.forward(self.model, self.data)
        self._sync(upload=False)

    def forward(self, ids: np.ndarray | None = None,
                stage: int = mujoco.mjtStage.mjSTAGE_ACC.value) -> None:
        """The forward pass at the state the env wrote (on every world: the others' derived
        fields are recomputed unchanged)."""
        self._sync(upload=True)
        with self.wp.ScopedDevice(self.device):
            self.mjw.forward(self.model, self.data)
        self._sync(upload=False)

    def step(self, nstep: int = 1, stage: int = mujoco.mjtStage.mjSTAGE_ACC.value) -> None:
        """``nstep`` physics steps with the controls the env wrote, then the forward pass at the
        new state (``stage`` ``mjSTAGE_ACC``, the only stage the env asks for)."""
        self._sync(upload=True)
        with self.wp.ScopedDevice(self.device):
            for _ in range(int(nstep)):
                self.mjw.step(self.model, self.data)
            self.mjw.forward(self.model, self.data)
        self._sync(upload=False)


class AntGoalWarpEnv(AntGoalEnv):
    """:class:`~armeta_rl.envs.ant_goal.AntGoalEnv` with its simulations on MuJoCo Warp.

    Args:
        args, kwargs: :class:`~armeta_rl.envs.ant_goal.AntGoalEnv`'s arguments, passed on
            unchanged (``threads`` is unused by MuJoCo Warp, accepted so that a config can swap
            the env class alone).
        warp_device: where the physics runs: ``"cuda"``, ``"cuda:N"`` or ``"cpu"`` (warp's CPU
            backend, for checks).
        nconmax, njmax: contacts and constraints per world (``None``: MuJoCo Warp's defaults).
    """

    def __init__(
        self,
        *args: Any,
        warp_device: str = "cuda",
        nconmax: int | None = None,
        njmax: int | None = None,
        **kwargs: Any,
    ) -> None:
        self._warp = {"device": str(warp_device), "nconmax": nconmax, "njmax": njmax}
        super().__init__(*args, **kwargs)

    def _make_batch(self, threads: int) -> WarpBatch:
        return WarpBatch(self.model, self.n_sims, **self._warp)


def ant_goal_warp(warp_device: str = "cuda", **kwargs) -> Callable[..., AntGoalWarpEnv]:
    """``AntGoalWarpEnv`` with ``kwargs`` as a ``make_env`` for the episode collectors, once
    ``warp_device`` is checked: a config naming a device warp lacks fails when the collector is
    built, before any training (the env itself is built at the first collection)."""
    find_warp_device(warp_device)
    return partial(AntGoalWarpEnv, warp_device=warp_device, **kwargs)
