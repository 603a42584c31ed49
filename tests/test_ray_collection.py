"""RayEpisodeCollector on a local Ray instance (this machine alone, 2 CPUs): its data for a seed
equal the single-process collectors' bit for bit; a dead or silent worker ends the collection with
a clear error instead of a hang; an address where no cluster answers is a one-line config
error."""

import os
import socket
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'armeta-rl[ray]')")

from armeta_rl.collectors.episodes import EpisodeCollector, valid_mask  # noqa: E402
from armeta_rl.collectors.parallel_episodes import TaskSplitEpisodeCollector  # noqa: E402
from armeta_rl.collectors.ray_episodes import RayEpisodeCollector, connect_ray  # noqa: E402
from armeta_rl.envs.ant_goal import AntGoalEnv  # noqa: E402
from armeta_rl.errors import CollectionFailed, ConfigError  # noqa: E402
from armeta_rl.rl.policy import GaussianMLP  # noqa: E402
from armeta_rl.tasks import TaskSpace  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TASKS, EPISODES, STEPS = 4, 2, 15
MAKE_ENV = partial(AntGoalEnv, healthy_z_range=(0.3, 0.7))  # early, staggered terminations
PATIENCE_S = 600
"""How long a test waits on workers that are alive: an actor's first build imports torch, TorchRL
and MuJoCo, which took over 120 s on a 2-core machine under load."""


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


NO_ANSWER = "no Ray cluster answers there within 2 s"


@pytest.mark.parametrize("address,reason", [("127.0.0.1:{port}", NO_ANSWER),
                                            ("ray://127.0.0.1:{port}", NO_ANSWER),
                                            ("nowhere", "= 'nowhere': null (a Ray instance")])
def test_an_address_without_a_cluster_is_a_config_error(address, reason):
    """Refused by the port probe (or, unparsable, before it), never by Ray's own connection
    attempts (about 40 s each): the error says which, and Ray was not started."""
    if ray.is_initialized():
        pytest.skip("this process has joined a Ray cluster already")
    address = address.format(port=_free_port())
    with pytest.raises(ConfigError, match="benchmark.collector.address") as refused:
        connect_ray(address, connect_timeout_s=2)
    assert reason in str(refused.value)
    assert not ray.is_initialized()


def test_cli_unreachable_ray_address_is_one_line_and_exit_2(tmp_path):
    address = f"127.0.0.1:{_free_port()}"
    result = subprocess.run(
        [sys.executable, "-c", "from armeta_rl.cli import train; train()",
         "benchmark=ant_goal_ray", f"benchmark.collector.address={address}",
         "benchmark.collector.connect_timeout_s=2", "logger=none", f"hydra.run.dir={tmp_path}"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "benchmark.collector.address" in lines[0] and address in lines[0]
    assert NO_ANSWER in lines[0]  # the probe's refusal, not Ray's own attempts


@pytest.fixture(scope="module")
def local_cluster() -> str:
    """A Ray instance of this machine alone, with 2 CPUs, and its GCS address (where other
    processes join it); its workers import armeta_rl from this checkout."""
    if ray.is_initialized():
        ray.shutdown()
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="ERROR",
             log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": "1"}})
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


def _policy_and_tasks() -> tuple[GaussianMLP, TensorDict, TensorDict]:
    torch.manual_seed(3)
    net = GaussianMLP(119, 8)
    params = TensorDict(dict(net.named_parameters()), []).expand(TASKS).clone()
    params["log_std"] = torch.linspace(-1.0, 0.5, TASKS)[:, None].expand(TASKS, 8).clone()
    goals = TensorDict({"params": torch.tensor([[2.0, 1.0], [-1.0, 0.5], [0.0, -3.0], [3.0, 3.0]])},
                       [TASKS])
    return net, params, goals


def _collect(collector, seed: int) -> TensorDict:
    net, params, goals = _policy_and_tasks()
    torch.manual_seed(seed)
    return collector.collect(goals, params, policy=net)


def test_ray_workers_equal_the_single_process_collectors(local_cluster):
    """2 Ray actors give the data of the same split stepped in this process (TorchRL SerialEnv)
    bit for bit, through terminations and automatic resets; 1 actor gives the data of the plain
    single-process EpisodeCollector; the seed matters."""
    ray2 = RayEpisodeCollector(MAKE_ENV, EPISODES, STEPS, workers=2, timeout_s=PATIENCE_S)
    ray1 = RayEpisodeCollector(MAKE_ENV, EPISODES, STEPS, workers=1, timeout_s=PATIENCE_S)
    serial = TaskSplitEpisodeCollector(MAKE_ENV, EPISODES, STEPS, workers=2, in_process=True)
    single = EpisodeCollector(partial(MAKE_ENV, seed=0), EPISODES, STEPS)
    data = _collect(ray2, 0)
    assert data.batch_size == torch.Size([TASKS, EPISODES, STEPS])
    assert not data["mask"].all() and data["terminated"].any()  # resets inside the rollout
    assert torch.equal(data["mask"], valid_mask(data["done"].squeeze(-1)))
    assert (data == _collect(serial, 0)).all()
    assert (data == _collect(ray2, 0)).all()  # the actors' envs are reseeded at every collect
    assert not torch.equal(data["observation"], _collect(ray2, 1)["observation"])
    ray2.close()  # hands its 2 CPUs back to the cluster
    assert (_collect(ray1, 0) == _collect(single, 0)).all()
    ray1.close()


def test_a_worker_killed_mid_collection_stops_it_with_a_clear_error(local_cluster):
    """The worker is killed as the policy acts for the third step of a 100 000-step collection:
    the collection ends with CollectionFailed within a few steps of the kill, not at the end of
    the horizon, and says the worker died, not that it was waited on until the timeout."""
    collector = RayEpisodeCollector(partial(AntGoalEnv, healthy_z_range=(-1.0, 10.0)), EPISODES,
                                    100_000, workers=1, timeout_s=PATIENCE_S)
    worker = collector.env(TASKS).base_env.workers[0]  # starts the actor
    net, params, goals = _policy_and_tasks()
    steps = []

    def kill_at_the_third_step(*_) -> None:  # the policy's activation runs once a step
        steps.append(len(steps))
        if len(steps) == 3:
            ray.kill(worker)

    activation = next(layer for layer in net.mean if not isinstance(layer, torch.nn.Linear))
    activation.register_forward_hook(kill_at_the_third_step)
    torch.manual_seed(0)
    with pytest.raises(CollectionFailed, match="Ray worker died during collection"):
        collector.collect(goals, params, policy=net)
    assert 3 <= len(steps) < 3 + 100  # the kill lands while a step or two are in flight
    collector.close()


def test_a_silent_worker_times_out_instead_of_hanging(local_cluster):
    collector = RayEpisodeCollector(MAKE_ENV, EPISODES, STEPS, workers=1, timeout_s=0.001)
    with pytest.raises(CollectionFailed, match=r"did not answer within 0.001 s"):
        _collect(collector, 0)
    collector.close()


def test_bad_values_are_config_errors_also_from_inside_the_actors(local_cluster):
    with pytest.raises(ConfigError, match="benchmark.collector.workers"):
        _collect(RayEpisodeCollector(MAKE_ENV, EPISODES, STEPS, workers=3), 0)
    with pytest.raises(ConfigError, match="benchmark.collector.timeout_s"):
        RayEpisodeCollector(MAKE_ENV, timeout_s=0)
    bad_env = partial(AntGoalEnv, goal_range=-1.0)
    collector = RayEpisodeCollector(bad_env, EPISODES, STEPS, workers=1, cpus_per_worker=0)
    with pytest.raises(ConfigError, match="benchmark.collector.goal_range"):
        _collect(collector, 0)
    collector.close()


def _wait_until_all_cpus_are_free(timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while ray.available_resources().get("CPU") != ray.cluster_resources()["CPU"]:
        assert time.monotonic() < deadline, "the Ray instance never reported all its CPUs free"
        time.sleep(0.1)


def test_the_box_and_sizes_are_read_on_one_workers_env_without_actors(local_cluster):
    """``check_space`` and the sizes probe one worker's env in this process: with 2 workers a
    1-task probe cannot be split over actors, and no actor starts before the first collection."""
    collector = RayEpisodeCollector(MAKE_ENV, EPISODES, STEPS, workers=2, timeout_s=PATIENCE_S)
    _wait_until_all_cpus_are_free()  # a fresh instance may report its CPUs late
    collector.check_space(TaskSpace(["goal_x", "goal_y"], [-3.0, -3.0], [3.0, 3.0]))
    assert (collector.in_features, collector.out_features) == (119, 8)
    assert ray.available_resources().get("CPU") == ray.cluster_resources()["CPU"]  # no actor
    with pytest.raises(ConfigError, match="benchmark.space"):
        collector.check_space(TaskSpace(["x", "y", "z"], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]))
    collector.close()


def test_a_run_whose_workers_stop_answering_stops_with_one_line_keeping_its_checkpoint(
        tmp_path, local_cluster):
    """End to end through the CLI, joining a running cluster by its GCS address: a run that wrote
    its first checkpoint resumes against actors that cannot answer in time (``timeout_s`` set to
    1 ms in its config.yaml); it stops soon with exit code 1 and one line naming the late worker
    and the checkpoint kept."""
    run = tmp_path / "run"
    train = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
    small = ["benchmark=ant_goal_ray", "method=maml", "trainer.iterations=3", "trainer.stop_at=1",
             "trainer.checkpoint_every=1", "trainer.meta_batch=2", "eval.n_tasks=2",
             "benchmark.collector.workers=1", "benchmark.collector.cpus_per_worker=0",
             "benchmark.collector.episodes=2", "benchmark.collector.max_steps=5",
             "benchmark.collector.make_env.threads=1", "logger=none", "trainer.progress=false",
             "trainer.density_every=0", f"benchmark.collector.address={local_cluster}"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    first = subprocess.run([*train, *small, f"hydra.run.dir={run}"], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    config = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(config.replace("timeout_s: 300", "timeout_s: 0.001"))
    stopped = subprocess.run([*train, f"resume={run}"], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=600)
    assert stopped.returncode == 1, stopped.stderr
    lines = stopped.stderr.strip().splitlines()
    assert len(lines) == 1, stopped.stderr
    assert "did not answer within 0.001 s" in lines[0]
    assert "checkpoint-000000000001 is kept" in lines[0]
    assert (run / "checkpoints" / "checkpoint-000000000001").is_dir()
