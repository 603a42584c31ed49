"""MuJoCo Warp Ant (AntGoalWarpEnv, AntDirWarpEnv / WarpBatch) against the CPU MuJoCo dynamics,
on warp's CPU device (and on CUDA where there is one). Ant-Dir shares the Ant's model and kernels,
so it is checked here; the other families are in tests/test_warp_families.py.

Tolerance (docs/scale-details.md). Each check starts both engines from the same state and steps
them with the same controls ("teacher forcing": the CPU state is copied into warp before every
step), for 200 physics steps of the gymnasium Ant MJCF with random controls, while the Ant falls,
lands and kicks (0 to 3 contacts). MuJoCo Warp computes in float32, CPU MuJoCo in float64:

* frame-invariant friction (elliptic cone): |Δqpos| <= 1e-5 and |Δqvel| <= 1e-3 on every step,
  contacts included; the torso position and orientation within 1e-5, the observed contact
  forces clip(cfrc_ext, -1, 1) within 1e-2;
* the MJCF as it is (pyramidal cone): away from contacts (none in either engine at the step's
  start or end, nor at the next step's end), 95 % of the steps agree within |Δqpos| <= 1e-6 and
  |Δqvel| <= 1e-5 (the rest touch the floor inside a Runge-Kutta stage); on every step
  |Δqpos| <= 5e-3. With contacts the engines orient the friction pyramid's edges differently
  about the contact normal (each a valid pyramid around the same Coulomb cone: their contact
  frames differ, and with the frame-invariant elliptic cone the engines agree), so their contact
  forces, and the velocities after an impact, differ.

Ant-Dir, env against env, teacher-forced over 20 env steps (100 physics steps, the MJCF as it
is): the reset observations agree within 3e-7; the steps without an impact (most: measured 28 of
40) within 1e-5 in observation and reward; the steps with one differ as above (measured: reward
up to 0.09, from the torso velocity; clipped contact forces up to 1). Every step's reward is the
Ant-Dir reward of warp's own state, within 1e-5.
"""

import os
import subprocess
import sys
from functools import partial
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.envs.ant_goal import AntGoalEnv, load_ant_model
from armeta_rl.envs.locomotion import AntDirEnv
from armeta_rl.errors import ConfigError
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks import TASK_KEY
from conftest import collector_of, compose_train

warp = pytest.importorskip("warp", reason="MuJoCo Warp is not installed (pip install "
                                          "'armeta-rl[gpu]')")
pytest.importorskip("mujoco_warp", reason="MuJoCo Warp is not installed")

from armeta_rl.envs.ant_goal_warp import AntGoalWarpEnv, ant_goal_warp  # noqa: E402
from armeta_rl.envs.locomotion_warp import AntDirWarpEnv  # noqa: E402
from armeta_rl.envs.warp_physics import WarpBatch, find_warp_device  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STEPS, WORLDS = 200, 2
HAS_CUDA = warp.is_cuda_available()
HAS_CPU = "cpu" in [str(device) for device in warp.get_devices()]
DEVICES = [
    pytest.param("cpu", marks=pytest.mark.skipif(
        not HAS_CPU, reason="warp has no CPU device here (its LLVM backend, warp-clang, is "
                            "missing)")),
    pytest.param("cuda", marks=pytest.mark.skipif(
        not HAS_CUDA, reason="no CUDA device: MuJoCo Warp on the GPU is checked where there is "
                             "one")),
]


def _teacher_forced(cone: int, device: str) -> dict[str, np.ndarray]:
    """Per step and world: max |Δqpos|, max |Δqvel|, max |Δ torso xpos, xmat|, max |Δ clipped
    cfrc_ext| and the contact count after the step (the larger of the two engines'), stepping
    MjData (mj_step, then mj_forward at the new state) and WarpBatch from the same state."""
    model = load_ant_model()
    model.opt.cone = cone
    datas = [mujoco.MjData(model) for _ in range(WORLDS)]
    batch = WarpBatch(model, WORLDS, device)
    rng = np.random.default_rng(0)
    for data in datas:
        data.qpos[:] = model.qpos0 + rng.uniform(-0.1, 0.1, model.nq)
        data.qvel[:] = rng.normal(0.0, 0.1, model.nv)
    torso = model.body("torso").id
    out = {"qpos": [], "qvel": [], "torso": [], "forces": [], "ncon": []}
    def host(name: str) -> np.ndarray:  # the warp field, read on the host in float64
        return batch.bind(name).cpu().numpy().astype(np.float64)

    for _ in range(STEPS):
        ctrl = rng.uniform(-1.0, 1.0, (WORLDS, model.nu))
        for name in ("qpos", "qvel"):
            batch.bind(name).copy_(torch.tensor(np.array([getattr(d, name) for d in datas])))
        batch.bind("ctrl").copy_(torch.tensor(ctrl))
        batch.step(nstep=1)
        for data, row in zip(datas, ctrl):
            data.ctrl[:] = row
            mujoco.mj_step(model, data)
            mujoco.mj_forward(model, data)
        out["qpos"].append(np.abs(host("qpos") - [d.qpos for d in datas]).max(-1))
        out["qvel"].append(np.abs(host("qvel") - [d.qvel for d in datas]).max(-1))
        pose = np.concatenate([host("xpos")[:, torso], host("xmat")[:, torso]], -1)
        reference = [np.concatenate([d.xpos[torso], d.xmat[torso]]) for d in datas]
        out["torso"].append(np.abs(pose - reference).max(-1))
        forces = [np.clip(d.cfrc_ext, -1, 1) for d in datas]
        out["forces"].append(np.abs(np.clip(host("cfrc_ext"), -1, 1) - forces).max((-2, -1)))
        nacon = int(batch.data.nacon.numpy()[0])
        warp_ncon = np.bincount(batch.data.contact.worldid.numpy()[:nacon], minlength=WORLDS)
        out["ncon"].append(np.maximum([d.ncon for d in datas], warp_ncon))
    return {key: np.array(value) for key, value in out.items()}


@pytest.mark.parametrize("device", DEVICES)
def test_warp_equals_cpu_mujoco_with_frame_invariant_friction(device):
    errors = _teacher_forced(mujoco.mjtCone.mjCONE_ELLIPTIC, device)
    assert errors["ncon"].max() >= 2  # the check covers contact dynamics
    assert errors["qpos"].max() <= 1e-5
    assert errors["qvel"].max() <= 1e-3
    assert errors["torso"].max() <= 1e-5
    assert errors["forces"].max() <= 1e-2  # the observation's clip(cfrc_ext, -1, 1)


@pytest.mark.parametrize("device", DEVICES)
def test_warp_equals_cpu_mujoco_on_the_ant_mjcf_away_from_contacts(device):
    errors = _teacher_forced(mujoco.mjtCone.mjCONE_PYRAMIDAL, device)
    air = errors["ncon"] == 0
    # no contact in either engine at the step's start, its end, or the next step's end
    free = air & np.roll(air, 1, axis=0) & np.roll(air, -1, axis=0)
    free[0], free[-1] = air[0] & air[1], False
    assert free.sum() >= 40 and (~free).sum() >= 40  # both regimes are covered
    assert np.quantile(errors["qpos"][free], 0.95) <= 1e-6
    assert np.quantile(errors["qvel"][free], 0.95) <= 1e-5
    assert np.quantile(errors["torso"][free], 0.95) <= 1e-6
    assert np.isfinite(errors["qvel"]).all() and errors["qpos"].max() <= 5e-3


@pytest.mark.parametrize("device", DEVICES)
def test_warp_env_resets_like_the_cpu_env_and_rolls_out(device):
    """Same seed, same reset noise and goals: the first observations agree to float32 precision;
    the env satisfies TorchRL's spec check and terminates like the CPU env's rule says."""
    goals = TensorDict({TASK_KEY: torch.tensor([[[1.0, -2.0]], [[0.5, 3.0]]])}, [2, 1])
    cpu = AntGoalEnv((2, 1), max_steps=5, seed=3)
    env = AntGoalWarpEnv((2, 1), max_steps=5, seed=3, warp_device=device)
    start, reference = env.reset(goals.clone().to(env.device)), cpu.reset(goals.clone())
    torch.testing.assert_close(start["observation"].cpu(), reference["observation"], atol=1e-6,
                               rtol=0)
    assert torch.equal(start[TASK_KEY].cpu(), reference[TASK_KEY])
    check_env_specs(env)
    rollout = env.rollout(5, auto_reset=True)
    height = rollout["next", "observation"][..., 2]
    healthy = (height >= 0.2) & (height <= 1.0)
    assert torch.equal(rollout["next", "terminated"].squeeze(-1), ~healthy)
    assert rollout["next", "truncated"][..., -1, :].all()  # max_steps = 5


@pytest.mark.parametrize("device", DEVICES)
def test_a_collection_stays_on_the_warp_device_with_the_rewards_of_the_task(device):
    """The env's outputs live on the warp device, so the policy acts there and the trajectories
    stay there; every step's reward is the goal-position reward computed by hand from the
    trajectory's observation (torso xy, contact forces) and action; steps are not aliased."""
    torch_device = torch.device("cuda:0" if device == "cuda" else "cpu")
    collector = EpisodeCollector(partial(AntGoalWarpEnv, warp_device=device, seed=0),
                                 episodes=2, max_steps=6, device=torch_device)
    net = GaussianMLP(119, 8).to(torch_device)
    goals = torch.tensor([[1.0, -2.0], [0.5, 3.0]], device=torch_device)
    data = collector.collect(TensorDict({TASK_KEY: goals}, [2]), policy=net)
    assert collector.env(2).device == torch_device
    assert {t.device for t in data.values(True, True)} == {torch_device}
    observation, action = data["observation"][..., 1:, :], data["action"][..., :-1, :]
    forces = observation[..., 29:107]
    xy = observation[..., 116:118]
    by_hand = (-(xy - goals[:, None, None]).abs().sum(-1) - 0.005 * action.square().sum(-1)
               - 0.0005 * forces.square().sum(-1) + 0.05)
    valid = ~data["done"][..., :-1, 0]  # a reset step's observation is the new episode's
    reward = data["reward"][..., :-1, 0]
    torch.testing.assert_close(reward[valid], by_hand[valid], atol=1e-5, rtol=1e-5)
    assert (data["observation"][..., 1:, :] != data["observation"][..., :-1, :]).any(-1).all()


@pytest.mark.parametrize("device", DEVICES)
def test_ant_dir_on_warp_steps_as_the_cpu_env_and_rewards_its_own_state(device):
    cpu = AntDirEnv((2, 1), max_steps=20, seed=3)
    env = AntDirWarpEnv((2, 1), max_steps=20, seed=3, warp_device=device)
    task = TensorDict({TASK_KEY: torch.tensor([[[0.5]], [[-2.0]]])}, [2, 1])
    a, b = cpu.reset(task.clone()), env.reset(task.clone().to(env.device))
    torch.testing.assert_close(b["observation"].cpu(), a["observation"], atol=1e-6, rtol=0)
    generator = torch.Generator().manual_seed(0)
    direction = torch.tensor([[np.cos(0.5), np.sin(0.5)], [np.cos(-2.0), np.sin(-2.0)]])
    observation, reward, by_hand = [], [], []
    for _ in range(20):
        for name in ("qpos", "qvel"):  # teacher forcing: warp steps from the CPU state
            env.sim.bind(name).copy_(torch.from_numpy(cpu.sim.bind(name)))
        xy = torch.from_numpy(cpu.sim.bind("qpos")[:, :2]).float()
        action = torch.rand(2, 1, 8, generator=generator) * 2 - 1
        a = cpu.step(a.set("action", action))["next"]
        b = env.step(b.set("action", action.to(env.device)))["next"].cpu()
        observation.append((a["observation"] - b["observation"]).abs().amax((-2, -1)))
        reward.append((a["reward"] - b["reward"]).abs().reshape(2))
        state = b["observation"][:, 0]
        velocity = (direction * (state[:, :2] - xy)).sum(-1) / 0.05
        by_hand.append(velocity - 0.5 * action[:, 0].square().sum(-1)
                       - 5e-4 * state[:, 29:107].square().sum(-1) + 1.0 - b["reward"].reshape(2))
    observation, reward = torch.stack(observation), torch.stack(reward)
    agree = (observation <= 1e-5) & (reward <= 1e-5)
    assert agree.float().mean() >= 0.5 and (~agree).any()  # both regimes are covered
    assert reward.max() <= 0.1
    assert torch.stack(by_hand).abs().max() <= 1e-5


def test_the_ant_dir_warp_benchmark_collects_on_warp():
    """``ant_dir_warp`` is ``ant_dir`` (same box, reward weights) with the env on MuJoCo Warp."""
    cfg = compose_train("benchmark=ant_dir_warp", "benchmark.collector.make_env.warp_device=cpu",
                        "benchmark.collector.episodes=1", "benchmark.collector.max_steps=2")
    plain = compose_train("benchmark=ant_dir")
    assert cfg.benchmark.space == plain.benchmark.space
    env = collector_of(cfg).env(2)
    assert isinstance(env, AntDirWarpEnv) and env.ctrl_cost_weight == 0.5
    rollout = env.rollout(2, tensordict=env.reset(TensorDict(
        {TASK_KEY: torch.tensor([[[0.5]], [[-2.0]]])}, [2, 1])), auto_reset=False)
    assert rollout["next", "reward"].shape == (2, 1, 2, 1)


@pytest.mark.skipif(not HAS_CUDA, reason="no CUDA device: CUDA graphs are checked where they run")
def test_the_cuda_graph_replays_the_same_physics_as_the_kernels_launched_one_by_one():
    goals = TensorDict({TASK_KEY: torch.tensor([[[1.0, -2.0]] * 3, [[0.5, 3.0]] * 3])}, [2, 3])
    actions = torch.rand(10, 2, 3, 8, generator=torch.Generator().manual_seed(0)) * 2 - 1
    observations = {}
    for graphs in (True, False):
        env = AntGoalWarpEnv((2, 3), max_steps=10, seed=3, warp_device="cuda", graphs=graphs)
        assert env.sim.graphs is graphs
        td = env.reset(goals.clone().to(env.device))
        steps = []
        for action in actions:
            td = env.step(td.set("action", action.to(env.device)))["next"]
            steps.append(td["observation"])
        observations[graphs] = torch.stack(steps)
    assert observations[True].device.type == "cuda"
    torch.testing.assert_close(observations[True], observations[False], atol=1e-4, rtol=0)


@pytest.mark.skipif(HAS_CUDA, reason="this machine has CUDA")
def test_warp_on_cuda_without_cuda_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="benchmark.collector.make_env.warp_device"):
        find_warp_device("cuda")
    with pytest.raises(ConfigError, match="benchmark.collector.make_env.warp_device"):
        ant_goal_warp(warp_device="cuda")
    result = subprocess.run(
        [sys.executable, "-c", "from armeta_rl.cli import train; train()",
         "benchmark=ant_goal_warp", "logger=none", "trainer.iterations=1",
         "trainer.meta_batch=2", "benchmark.collector.episodes=1",
         "benchmark.collector.max_steps=2", f"hydra.run.dir={tmp_path}"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "warp_device" in lines[0] and "cuda" in lines[0]
