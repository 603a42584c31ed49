"""The planar locomotion families on MuJoCo Warp (armeta_rl.envs.locomotion_warp: HalfCheetah-Vel,
HalfCheetah-Dir, Walker2d-Vel, and HalfCheetah-MassVel, Walker2d-MassVel with per-world masses)
against their CPU envs, on warp's CPU device (and on CUDA where there is one); Ant-Dir is checked
with the Ant in tests/test_ant_goal_warp.py, whose kernels it shares.

Tolerance (docs/scale-details.md). Each check builds the CPU env and the Warp env with the same
seed and identifiers and steps them with the same actions, copying the CPU state into warp before
every env step ("teacher forcing"), for 12 env steps (60 physics steps of HalfCheetah, 48 of
Walker2d) while the robots touch the floor (contacts in most steps). Measured: the reset
observations are equal, the step observations (which hold the velocities) within 2.1e-4, the
rewards within 6e-6; checked: the observations within 1e-3, the rewards within 1e-4.
"""

from functools import partial

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from armeta_rl.envs.locomotion import HalfCheetahDirEnv, HalfCheetahVelEnv, Walker2dVelEnv
from armeta_rl.envs.mujoco_tasks import physics_task_env
from armeta_rl.errors import ConfigError
from armeta_rl.tasks import TASK_KEY
from conftest import collector_of, compose_train

warp = pytest.importorskip("warp", reason="MuJoCo Warp is not installed (pip install "
                                          "'armeta-rl[gpu]')")
pytest.importorskip("mujoco_warp", reason="MuJoCo Warp is not installed")

from armeta_rl.envs.locomotion_warp import (  # noqa: E402
    HalfCheetahDirWarpEnv,
    HalfCheetahVelWarpEnv,
    Walker2dVelWarpEnv,
)

STEPS = 12
OBS_TOL, REWARD_TOL = 1e-3, 1e-4
HAS_CUDA = warp.is_cuda_available()
DEVICES = [
    pytest.param("cpu", marks=pytest.mark.skipif(
        "cpu" not in [str(d) for d in warp.get_devices()],
        reason="warp has no CPU device here (its LLVM backend, warp-clang, is missing)")),
    pytest.param("cuda", marks=pytest.mark.skipif(
        not HAS_CUDA, reason="no CUDA device: MuJoCo Warp on the GPU is checked where there is "
                             "one")),
]
MASS = [{"name": "mass_scale", "kind": "body_mass_only_scale", "target": "all", "low": 0.75,
         "high": 1.25}]


def _teacher_forced(cpu, env, params: torch.Tensor, same_actions: bool = False) -> dict:
    """Per step: max |Δ observation|, |Δ reward| (and |Δ reward_forward| where the env reports
    it) between the CPU env ``cpu`` and the Warp env ``env`` (either under a transform), and
    whether warp had contacts; also the observations of both, ``[steps, sims, size]``. The CPU
    state is copied into warp before each step; ``same_actions`` gives every simulation the same
    action."""
    shape = cpu.batch_size
    base_cpu = getattr(cpu, "base_env", cpu)
    base_warp = getattr(env, "base_env", env)
    start = TensorDict({TASK_KEY: params}, shape)
    a, b = cpu.reset(start.clone()), env.reset(start.clone().to(env.device))
    assert torch.equal(a["observation"], b["observation"].cpu())
    assert torch.equal(a[TASK_KEY], b[TASK_KEY].cpu())
    generator = torch.Generator().manual_seed(0)
    nu = base_cpu.model.nu
    out = {"obs": [], "reward": [], "forward": [], "contacts": [], "cpu": [], "warp": []}
    for _ in range(STEPS):
        for name in ("qpos", "qvel"):
            base_warp.sim.bind(name).copy_(torch.from_numpy(base_cpu.sim.bind(name)))
        action = torch.rand(*([1] * len(shape) if same_actions else shape), nu,
                            generator=generator) * 2 - 1
        action = action.expand(*shape, nu)
        a = cpu.step(a.set("action", action))["next"]
        b = env.step(b.set("action", action.to(env.device)))["next"].cpu()
        out["obs"].append((a["observation"] - b["observation"]).abs().max().item())
        out["reward"].append((a["reward"] - b["reward"]).abs().max().item())
        if a.get("reward_forward", None) is not None:
            out["forward"].append((a["reward_forward"] - b["reward_forward"]).abs().max().item())
        out["contacts"].append(int(base_warp.sim.data.nacon.numpy()[0]))
        out["cpu"].append(a["observation"].reshape(-1, a["observation"].shape[-1]))
        out["warp"].append(b["observation"].reshape(-1, b["observation"].shape[-1]))
    out["cpu"], out["warp"] = torch.stack(out["cpu"]), torch.stack(out["warp"])
    return {key: np.asarray(value) if key not in ("cpu", "warp") else value
            for key, value in out.items()}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cpu_env,warp_env,task", [
    (HalfCheetahVelEnv, HalfCheetahVelWarpEnv, [1.5, 0.5]),
    (HalfCheetahDirEnv, HalfCheetahDirWarpEnv, [1.0, -1.0]),
    (Walker2dVelEnv, Walker2dVelWarpEnv, [1.5, 0.5]),
], ids=["half_cheetah_vel", "half_cheetah_dir", "walker2d_vel"])
def test_a_warp_family_steps_as_its_cpu_env(cpu_env, warp_env, task, device):
    cpu = cpu_env((2, 1), max_steps=STEPS, seed=3)
    env = warp_env((2, 1), max_steps=STEPS, seed=3, warp_device=device)
    assert env.device.type == ("cuda" if device == "cuda" else "cpu")
    errors = _teacher_forced(cpu, env, torch.tensor(task).reshape(2, 1, 1))
    assert (errors["contacts"] > 0).sum() >= STEPS // 2  # the check covers contact dynamics
    assert errors["obs"].max() <= OBS_TOL
    assert errors["reward"].max() <= REWARD_TOL and errors["forward"].max() <= REWARD_TOL


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cpu_env,warp_env", [
    (HalfCheetahVelEnv, HalfCheetahVelWarpEnv),
    (Walker2dVelEnv, Walker2dVelWarpEnv),
], ids=["half_cheetah_mass_vel", "walker2d_mass_vel"])
def test_each_warp_world_has_the_dynamics_of_its_own_mass(cpu_env, warp_env, device):
    """Two worlds with the same state and actions but masses scaled by 0.75 and 1.25: each Warp
    world steps as the CPU simulation of its mass, and the two worlds' trajectories differ far
    beyond that tolerance (a Warp batch stepping one mass for both would fail)."""
    kwargs = {"batch_size": (2, 1), "max_steps": STEPS, "seed": 3, "reset_noise_scale": 0.0}
    cpu = physics_task_env(cpu_env, MASS, **kwargs)
    env = physics_task_env(partial(warp_env, warp_device=device), MASS, **kwargs)
    check_env_specs(env)
    params = torch.tensor([[[1.0, 0.75]], [[1.0, 1.25]]])
    errors = _teacher_forced(cpu, env, params, same_actions=True)
    assert errors["obs"].max() <= OBS_TOL and errors["reward"].max() <= REWARD_TOL
    between = (errors["cpu"][:, 0] - errors["cpu"][:, 1]).abs().amax(-1)
    assert between.max() > 100 * OBS_TOL
    masses = env.base_env.sim.expand("body_mass").cpu()
    nominal = torch.as_tensor(env.base_env.model.body_mass, dtype=masses.dtype)
    torch.testing.assert_close(masses, nominal * torch.tensor([[0.75], [1.25]]))


@pytest.mark.parametrize("device", DEVICES)
def test_every_kind_of_physics_parameter_follows_its_own_warp_world(device):
    """Friction, gravity, mass and inertia, damping and gear, each different in the two worlds:
    each Warp world steps as the CPU simulation of its own physics."""
    parameters = [
        {"name": "friction", "kind": "geom_friction_scale", "target": "all", "low": 0.3,
         "high": 1.5},
        {"name": "gravity", "kind": "gravity_z", "low": -12.0, "high": -8.0},
        {"name": "torso", "kind": "body_mass_scale", "target": "torso", "low": 0.5, "high": 2.0},
        {"name": "damping", "kind": "joint_damping_scale", "target": "all", "low": 0.5,
         "high": 2.0},
        {"name": "gear", "kind": "actuator_gear_scale", "target": "all", "low": 0.5, "high": 2.0},
    ]
    kwargs = {"batch_size": (2, 1), "max_steps": STEPS, "seed": 1, "reset_noise_scale": 0.0}
    cpu = physics_task_env(HalfCheetahVelEnv, parameters, **kwargs)
    env = physics_task_env(partial(HalfCheetahVelWarpEnv, warp_device=device), parameters,
                           **kwargs)
    params = torch.tensor([[[1.0, 0.3, -12.0, 0.5, 0.5, 0.5]], [[1.0, 1.5, -8.0, 2.0, 2.0, 2.0]]])
    errors = _teacher_forced(cpu, env, params, same_actions=True)
    assert errors["obs"].max() <= OBS_TOL and errors["reward"].max() <= REWARD_TOL
    assert (errors["cpu"][:, 0] - errors["cpu"][:, 1]).abs().max() > 100 * OBS_TOL


@pytest.mark.parametrize("benchmark,env_class", [
    ("half_cheetah_vel_warp", HalfCheetahVelWarpEnv),
    ("half_cheetah_dir_warp", HalfCheetahDirWarpEnv),
    ("half_cheetah_mass_vel_warp", HalfCheetahVelWarpEnv),
    ("walker2d_mass_vel_warp", Walker2dVelWarpEnv),
])
def test_a_warp_benchmark_config_collects_on_its_warp_env(benchmark, env_class):
    """Each ``*_warp`` benchmark is its CPU benchmark with the env on MuJoCo Warp (warp's CPU
    device here): same box, and its collector's env is the family's Warp env (under the
    mass-scale transform for MassVel)."""
    key = "benchmark.collector.make_env" + (".make_env" if "mass" in benchmark else "")
    cfg = compose_train(f"benchmark={benchmark}", f"{key}.warp_device=cpu",
                        "benchmark.collector.episodes=1", "benchmark.collector.max_steps=2")
    plain = compose_train("benchmark=" + benchmark.removesuffix("_warp"))
    assert cfg.benchmark.space == plain.benchmark.space
    env = collector_of(cfg).env(2)
    assert isinstance(getattr(env, "base_env", env), env_class)
    low = torch.tensor(list(cfg.benchmark.space.low))
    rollout = env.rollout(2, tensordict=env.reset(TensorDict(
        {TASK_KEY: low.expand(2, 1, -1).clone()}, [2, 1])), auto_reset=False)
    assert rollout["next", "reward"].shape == (2, 1, 2, 1)
    assert (rollout[TASK_KEY] == low).all()


@pytest.mark.skipif(HAS_CUDA, reason="this machine has CUDA")
def test_a_mass_vel_warp_config_names_its_own_device_key_without_cuda():
    cfg = compose_train("benchmark=walker2d_mass_vel_warp")
    with pytest.raises(ConfigError, match=r"benchmark\.collector\.make_env\.make_env\."
                                          r"warp_device' = 'cuda'"):
        collector_of(cfg)
