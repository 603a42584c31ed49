"""What a TorchRL user does with the package's envs: tasks drawn at every reset by a transform in
any collector (multi-process too), their episodes' losses back to the sampler, identifiers
required behind transforms and batched envs, specs that TorchRL's checks accept under the usual
transforms, resets that torchrl 0.15 will still honor, and random actions through TorchRL."""

from __future__ import annotations

import subprocess
import sys
import warnings
from functools import partial
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvCreator,
    ExcludeTransform,
    ParallelEnv,
    RewardScaling,
    RewardSum,
    SerialEnv,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs import PendulumEnv as TorchRLPendulum
from torchrl.envs.utils import check_env_specs

from armeta_rl.adversary import FlowAdversary, TaskSampler
from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.envs import (
    AcrobotEnv,
    AntDirEnv,
    AntGoalEnv,
    HalfCheetahDirEnv,
    HalfCheetahVelEnv,
    PendulumEnv,
    PointNavigationEnv,
)
from armeta_rl.errors import ConfigError, IdentifierError
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks import (
    TASK_KEY,
    BoxUniform,
    TaskSpace,
    TaskTransform,
    finished_episodes,
)

GOALS = TaskSpace(["goal_x", "goal_y"], [-0.5, -0.5], [0.5, 0.5])
MASSES = TaskSpace(["m", "l"], [0.5, 0.5], [1.5, 1.5])


class Numbered:
    """A task source whose k-th draw is the goal (k/1000 − 0.4, 0.1): every task it proposes is
    different and tells when it was drawn."""

    def __init__(self) -> None:
        self.drawn = 0

    def sample(self, n: int) -> TensorDict:
        k = torch.arange(self.drawn, self.drawn + n, dtype=torch.float32)
        self.drawn += n
        goals = torch.stack([k / 1000 - 0.4, torch.full_like(k, 0.1)], -1)
        return TensorDict({TASK_KEY: goals}, [n])


def navigation(source, entries: int = 3, steps: int = 4) -> TransformedEnv:
    return TransformedEnv(PointNavigationEnv(batch_size=(entries,), seed=0),
                          Compose(TaskTransform(source), StepCounter(steps), RewardSum()))


def test_a_collector_runs_one_drawn_task_per_episode_and_reports_each_episode():
    """A plain Collector with no manual reset: every episode runs a task of the source, drawn
    when it started (consecutive episodes of an entry differ), and :func:`finished_episodes`
    gives each finished episode's task and its return, the sum of its rewards."""
    source = Numbered()
    collector = Collector(navigation(source), policy=None, frames_per_batch=30, total_frames=60)
    seen = []
    for batch in collector:
        episodes = finished_episodes(batch)
        seen.append(episodes[TASK_KEY])
        goal = batch[TASK_KEY]
        assert (goal == batch["next", TASK_KEY]).all()  # constant within a step
        ends = batch["next", "done"].squeeze(-1)
        for entry in range(3):
            done_steps = ends[entry].nonzero().squeeze(-1).tolist()
            starts = [0] + [t + 1 for t in done_steps[:-1]]
            for start, end in zip(starts, done_steps):
                if start == 0 and batch["step_count"][entry, 0] != 0:
                    continue  # an episode begun in the previous batch
                assert (goal[entry, start:end + 1] == goal[entry, end]).all()
                reward = batch["next", "reward"][entry, start:end + 1].sum()
                torch.testing.assert_close(batch["next", "episode_reward"][entry, end, 0],
                                           reward)
    collector.shutdown()
    tasks = torch.cat(seen)
    assert len(torch.unique(tasks, dim=0)) == len(tasks)  # one fresh task per episode
    index = ((tasks[:, 0] + 0.4) * 1000).round().long()
    assert int(index.max()) < source.drawn  # every one of them drawn by the source


def test_a_partial_reset_draws_for_its_entries_only():
    env = navigation(Numbered(), entries=4)
    first = env.reset()[TASK_KEY].clone()
    mask = torch.tensor([True, False, True, False])
    reset = env.reset(TensorDict({"_reset": mask[:, None]}, [4]))
    again = env.rand_step(reset)["next", TASK_KEY]  # what the env runs
    assert (again[~mask] == first[~mask]).all() and (again[mask] != first[mask]).any(-1).all()


def test_a_task_sampler_learns_from_the_episodes_it_proposed():
    """The documented loop: the collector's episodes go back to TaskSampler.update as
    (tasks, −return); the env then draws from the updated p_φ (the same sampler object)."""
    torch.manual_seed(0)
    sampler = TaskSampler(FlowAdversary(GOALS, BoxUniform(GOALS)), lr=0.05)
    env = navigation(sampler, entries=4, steps=5)
    assert env.transform[0].tasks is sampler
    collector = Collector(env, policy=None, frames_per_batch=40, total_frames=400)
    for batch in collector:
        episodes = finished_episodes(batch)
        sampler.update(episodes, episodes[TASK_KEY][:, 0].double() * 10)  # loss: goal_x
    collector.shutdown()
    assert sampler.sample(2000)[TASK_KEY][:, 0].mean() > 0.1  # p0's mean is 0
    assert env.reset()[TASK_KEY][:, 0].mean() > -0.5


def make_shared_env(sampler: TaskSampler) -> TransformedEnv:
    return navigation(sampler, entries=4, steps=5)


def test_a_multi_process_collector_draws_from_the_current_sampler():
    """MultiSyncCollector with EnvCreator: the workers' copies of the sampler draw from the flow's
    tensors as the main process updates them (shared through TaskTransform's state)."""
    torch.manual_seed(0)
    sampler = TaskSampler(FlowAdversary(GOALS, BoxUniform(GOALS)), lr=0.05)
    collector = MultiSyncCollector([EnvCreator(partial(make_shared_env, sampler))] * 2,
                                   policy=None, frames_per_batch=80, total_frames=240)
    goals = []
    for batch in collector:
        episodes = finished_episodes(batch)
        goals.append(episodes[TASK_KEY][:, 0].mean())
        if len(goals) == 1:  # move p_φ far toward goal_x = 0.5 after the first batch
            for _ in range(150):
                tasks = sampler.sample(64)
                sampler.update(tasks, tasks[TASK_KEY][:, 0].double() * 10)
    collector.shutdown()
    assert sampler.sample(2000)[TASK_KEY][:, 0].mean() > 0.3
    assert abs(goals[0]) < 0.2 and goals[-1] > 0.3


@pytest.mark.parametrize("make", [
    lambda: PointNavigationEnv(batch_size=(2, 3)),
    lambda: PendulumEnv(batch_size=(2, 3)),
    lambda: SerialEnv(2, lambda: PendulumEnv(batch_size=(3,))),
])
def test_specs_hold_with_drawn_tasks_and_with_identifiers_left_out_of_the_data(make):
    base = make()
    space = GOALS if isinstance(base, PointNavigationEnv) else MASSES
    check_env_specs(TransformedEnv(base, TaskTransform(BoxUniform(space))))
    quiet = TransformedEnv(make(), Compose(TaskTransform(BoxUniform(space)),
                                           ExcludeTransform(TASK_KEY)))
    check_env_specs(quiet)
    assert TASK_KEY not in quiet.rollout(3).keys(True)


def test_a_fixed_shift_runs_the_same_tasks_every_episode():
    shift = torch.tensor([0.3, -0.2])
    env = navigation(shift, entries=2, steps=3)
    rollout = env.rollout(9, break_when_any_done=False)
    assert (rollout[TASK_KEY] == shift).all()
    per_entry = torch.tensor([[0.3, -0.2], [-0.1, 0.4]])
    assert (navigation(per_entry, entries=2).reset()[TASK_KEY] == per_entry).all()
    with pytest.raises(ConfigError, match="identifiers \\[d\\] or \\[\\*batch, d\\]"):
        navigation(torch.zeros(3, 2), entries=2).reset()


@pytest.mark.parametrize("env", [
    lambda: TransformedEnv(PointNavigationEnv(batch_size=(4,)),
                           Compose(TaskTransform(), StepCounter(10))),
    lambda: TransformedEnv(SerialEnv(2, lambda: PointNavigationEnv(batch_size=(2,))),
                           TaskTransform()),
    lambda: SerialEnv(2, lambda: TransformedEnv(PointNavigationEnv(batch_size=(2,)),
                                                Compose(TaskTransform(), StepCounter(5)))),
    lambda: TransformedEnv(HalfCheetahVelEnv(batch_size=(4,)),
                           Compose(TaskTransform(), StepCounter(5))),
])
def test_required_identifiers_refuse_a_misspelled_key_behind_transforms_and_batched_envs(env):
    """Behind a transform TorchRL forwards only state-spec keys, so "goal" never reaches the env:
    with identifiers required, the reset is refused instead of keeping the old goals."""
    env = env()
    with pytest.raises(IdentifierError, match="'params' = missing: task identifiers are required"):
        env.reset(TensorDict({"goal": torch.zeros(*env.batch_size, 2)}, env.batch_size))
    width = env.state_spec[TASK_KEY].shape[-1]
    start = env.reset(TensorDict({TASK_KEY: torch.full((*env.batch_size, width), 0.25)},
                                 env.batch_size))
    assert (start[TASK_KEY] == 0.25).all()
    rollout = env.rollout(12, break_when_any_done=False, auto_reset=False, tensordict=start)
    assert (rollout[TASK_KEY] == 0.25).all()  # automatic partial resets keep each entry's task


def test_an_env_without_identifiers_under_the_key_is_refused():
    """TorchRL's own pendulum keeps a nested TensorDict of constants under "params": not task
    identifiers, so a TaskTransform on it is refused when built."""
    with pytest.raises(ConfigError, match="takes no task identifiers"):
        TransformedEnv(TorchRLPendulum(), TaskTransform(BoxUniform(MASSES)))


def misspelled(env) -> TensorDict:
    """A reset TensorDict carrying pendulum identifiers under "param" instead of "params"."""
    return TensorDict({"param": torch.full((*env.batch_size, 2), 2.0)}, env.batch_size)


@pytest.mark.parametrize("make", [
    lambda: PendulumEnv(batch_size=(4,), seed=0),
    lambda: TransformedEnv(PendulumEnv(batch_size=(4,), seed=0), StepCounter(200)),
    lambda: SerialEnv(2, lambda: PendulumEnv(batch_size=(3,), seed=0)),
    lambda: SerialEnv(2, lambda: TransformedEnv(PendulumEnv(batch_size=(3,), seed=0),
                                                StepCounter(5))),
    lambda: TransformedEnv(HalfCheetahVelEnv(batch_size=(2,), seed=0), StepCounter(5)),
    lambda: TransformedEnv(PointNavigationEnv(batch_size=(2,), seed=0), StepCounter(5)),
], ids=["bare", "step_counter", "serial", "serial_of_transformed", "half_cheetah",
        "point_nav"])
def test_a_misspelled_identifier_key_is_refused_wherever_the_env_sits(make):
    """The issue's reset, `{"param": ...}`: refused with one line naming the key, whether the
    env sees the key (bare, in a SerialEnv) or only the empty TensorDict TransformedEnv leaves
    of it; never run on the default identifiers."""
    env = make()
    with pytest.raises(IdentifierError) as error:
        env.reset(misspelled(env))
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith(("tensordict key 'param' = ", "tensordict key 'params' = missing"))


def test_a_misspelled_key_is_refused_in_a_parallel_env(capfd):
    """A ParallelEnv's worker refuses the reset (TorchRL reports the worker's end, the worker
    the one line)."""
    env = ParallelEnv(2, partial(PendulumEnv, batch_size=(3,), seed=0), mp_start_method="fork")
    with pytest.raises(RuntimeError):
        env.reset(misspelled(env))
        env.close()
    assert "tensordict key 'params' = missing" in capfd.readouterr().err


@pytest.mark.parametrize("make", [
    lambda **kw: PendulumEnv(batch_size=(2, 3), seed=0, **kw),
    lambda **kw: TransformedEnv(PendulumEnv(batch_size=(2, 3), seed=0, **kw), StepCounter(4)),
    lambda **kw: TransformedEnv(SerialEnv(2, lambda: PendulumEnv(batch_size=(3,), seed=0, **kw)),
                                StepCounter(4)),
    lambda **kw: TransformedEnv(HalfCheetahVelEnv(batch_size=(2, 3), seed=0, **kw),
                                StepCounter(4)),
    lambda **kw: TransformedEnv(PointNavigationEnv(batch_size=(2, 3), seed=0, **kw),
                                StepCounter(4)),
], ids=["bare", "step_counter", "serial_behind_transform", "half_cheetah", "point_nav"])
def test_identifiers_declared_required_refuse_every_full_reset_without_them(make):
    """require_identifiers=True: a reset without identifiers (none given, or a misspelled key
    that a batched env behind a transform turns into none) is refused; with them every episode,
    after automatic partial resets too, runs them."""
    assert make().reset()[TASK_KEY].shape[-1] > 0  # by default the stored ones are kept
    env = make(require_identifiers=True)
    with pytest.raises(IdentifierError, match="'params' = missing: this env requires"):
        env.reset()
    with pytest.raises(IdentifierError):
        env.reset(TensorDict({"param": torch.ones(*env.batch_size, 2)}, env.batch_size))
    width = env.observation_spec[TASK_KEY].shape[-1]
    start = env.reset(TensorDict({TASK_KEY: torch.full((*env.batch_size, width), 0.25)},
                                 env.batch_size))
    rollout = env.rollout(10, break_when_any_done=False, auto_reset=False, tensordict=start)
    assert (rollout[TASK_KEY] == 0.25).all()
    assert rollout["next", "done"].any() or not isinstance(env, TransformedEnv)


@pytest.mark.parametrize("batched", [SerialEnv, partial(ParallelEnv, mp_start_method="fork")],
                         ids=["serial", "parallel"])
@pytest.mark.parametrize("env_class", [PendulumEnv, AcrobotEnv])
def test_a_batched_reset_carries_the_identifiers_to_every_worker_without_a_warning(env_class,
                                                                                   batched):
    """A plain reset of a batched env, and the automatic partial resets of its rollout behind
    a StepCounter, with every warning an error (TorchRL's FutureWarning about a reset carrying
    state that 0.15 would drop included): each worker runs the identifiers it was given, as a
    single env given them does (the same rewards), so identifiers dropped anywhere fail."""
    names = env_class.param_names
    identifiers = torch.tensor([[0.6, 1.4], [1.3, 0.7]])[:, None].expand(2, 3, len(names))
    env = TransformedEnv(batched(2, partial(env_class, batch_size=(3,), seed=1)), StepCounter(3))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            env.set_seed(0)
            start = env.reset(TensorDict({TASK_KEY: identifiers}, [2, 3]))
            rollout = env.rollout(7, break_when_any_done=False, auto_reset=False,
                                  tensordict=start)
    finally:
        env.close(raise_if_closed=False)
    assert (rollout[TASK_KEY] == identifiers[:, :, None]).all()
    single = env_class(batch_size=(3,), seed=1)
    for ids, worker_run in zip(identifiers, rollout):
        single.reset(TensorDict({TASK_KEY: ids, "state": worker_run["state"][:, 0]}, [3]),
                     from_state=True)
        step = single.step(TensorDict({"action": worker_run["action"][:, 0]}, [3]))
        torch.testing.assert_close(step["next", "reward"], worker_run["next", "reward"][:, 0])


def test_a_float64_env_works_under_double_to_float():
    """The envs draw random actions through TorchRL's rand_action (no override), so a transform
    that changes the action (DoubleToFloat) gets actions of its own spec."""
    env = TransformedEnv(PendulumEnv(batch_size=(2, 3), dtype=torch.float64, seed=0),
                         DoubleToFloat())
    check_env_specs(env)
    step = env.rand_step(env.reset())
    assert step["action"].dtype == torch.float32 and step["next", "observation"].dtype == (
        torch.float32)
    assert env.rollout(5).batch_size == (2, 3, 5)


def test_random_actions_are_torchs_seeded_draws():
    """rand_action draws from torch's global RNG, uniform_ over the torque range (the acrobot:
    randint over its three actions), so seeded system-identification data follow the seed."""
    for env, expected in [
        (PendulumEnv(batch_size=(2, 3)), lambda: torch.empty(2, 3, 1).uniform_(-2.0, 2.0)),
        (AcrobotEnv(batch_size=(2, 3)), lambda: torch.randint(0, 3, (2, 3))),
    ]:
        torch.manual_seed(11)
        action = env.rand_action()["action"]
        torch.manual_seed(11)
        assert torch.equal(action, expected())


def test_mujoco_compiler_warnings_are_python_warnings_shown_once():
    """gymnasium's HalfCheetah model uses the compiler's deprecated settotalmass, which MuJoCo
    prints to stdout at every compilation (one line per env): it arrives as a MujocoWarning,
    shown once per process: once for two families of three envs and a single env."""
    code = (
        "from armeta_rl.envs.mujoco_tasks import load_task_family, make_gym_task_env\n"
        "family = load_task_family('configs/task_family/half_cheetah.yaml')\n"
        "for tasks in (3, 3, None):\n"
        "    make_gym_task_env(family, num_tasks=tasks).close()\n"
    )
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            cwd=root, timeout=600)
    assert result.returncode == 0, result.stderr
    assert "settotalmass" not in result.stdout
    shown = [line for line in result.stderr.splitlines() if "MujocoWarning" in line]
    assert len(shown) == 1 and "settotalmass" in shown[0]


def plain_navigation(batch_size, max_steps) -> PointNavigationEnv:
    return PointNavigationEnv(batch_size=batch_size, max_steps=max_steps, seed=0)


def doubled_navigation(batch_size, max_steps) -> TransformedEnv:
    return TransformedEnv(plain_navigation(batch_size, max_steps), RewardScaling(0.0, 2.0))


def test_an_episode_collector_steps_a_transformed_env_through_its_transforms():
    """The point robot's fast transitions serve the bare env only: behind a transform (doubling
    the rewards) the collector steps env.rollout, so the rewards are exactly twice the bare env's
    (TransformedEnv forwards ``gaussian_transitions`` to the env inside, which skipped the
    transform)."""
    tasks = TensorDict({TASK_KEY: torch.tensor([[0.3, -0.2], [-0.4, 0.1]])}, [2])
    rewards = []
    for make_env in (plain_navigation, doubled_navigation):
        torch.manual_seed(0)
        policy = GaussianMLP(2, 2, (8, 8))
        rewards.append(EpisodeCollector(make_env, episodes=3, max_steps=8)
                       .collect(tasks, policy=policy)["reward"])
    assert torch.equal(rewards[1], 2 * rewards[0])


TASK_ENVS = {
    "pendulum_uniform": PendulumEnv,
    "pendulum_gravity": partial(PendulumEnv, identifiers=("m", "l", "g")),
    "acrobot_uniform": AcrobotEnv,
    "half_cheetah_vel": HalfCheetahVelEnv,
    "half_cheetah_dir": HalfCheetahDirEnv,
    "ant_dir": AntDirEnv,
    "ant_goal": AntGoalEnv,
    "point_nav": PointNavigationEnv,
}


@pytest.mark.parametrize("benchmark", sorted(TASK_ENVS))
def test_every_task_env_states_its_task_space_and_a_sampler_is_built_from_the_env_alone(
        benchmark):
    """env.task_space is the box of the benchmark config that trains on the env, and a
    TaskSampler over it (p_φ on env.p0) draws the tasks of a TaskTransform on the same env,
    whose specs hold with the identifiers left out of the data."""
    from omegaconf import OmegaConf

    config = OmegaConf.load(Path(__file__).parents[1] / "configs" / "benchmark"
                            / f"{benchmark}.yaml")
    space = OmegaConf.select(config, "space") or OmegaConf.select(config, "benchmark.space")
    env = TASK_ENVS[benchmark](batch_size=(2, 2), seed=0)
    assert env.task_space == TaskSpace(space.names, space.low, space.high)
    sampler = TaskSampler(FlowAdversary(env.task_space, env.p0))
    drawn = TransformedEnv(TASK_ENVS[benchmark](batch_size=(2, 2), seed=0),
                           Compose(TaskTransform(sampler), ExcludeTransform(TASK_KEY)))
    check_env_specs(drawn)
    tasks = TransformedEnv(TASK_ENVS[benchmark](batch_size=(2, 2), seed=0),
                           TaskTransform(env.p0)).reset()[TASK_KEY]
    assert env.task_space.contains(tasks.reshape(-1, env.task_space.dim)).all()
