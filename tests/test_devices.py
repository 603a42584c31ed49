"""The ``device`` key: bad values get one line and exit code 2 from the CLIs; every player is built
on the configured device; checkpoints load onto the configured device wherever they were saved;
GPU runs (train on CUDA, evaluate on the CPU with the CUDA scores, resume on CUDA) when CUDA
is present."""

import json
import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict
from torchrl.checkpoint import GlobalRNGState

from armeta_rl.cli import evaluate, train
from armeta_rl.config import validate
from armeta_rl.devices import cpu_model, machine_name, resolve_device
from armeta_rl.envs.point_navigation import PAPER_SPARSE_REGIONS, PointNavigationEnv
from armeta_rl.errors import ConfigError
from armeta_rl.job import Job
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks import TASK_KEY
from armeta_rl.trainers.checkpoint import PortableRNGState
from armeta_rl.trainers.players import Players, load_players
from armeta_rl.trainers.training import run_training
from conftest import SMALL_RUN, compose_train, cross_evaluate, refusal, train_config

TRAIN = [sys.executable, "-c", "from armeta_rl.cli import train; train()"]
CUDA = torch.cuda.is_available()
GPUS = torch.cuda.device_count() if CUDA else 0
needs_cuda = pytest.mark.skipif(not CUDA, reason="CUDA not available")


BAD_DEVICES = [("tpu", "allowed: cpu, cuda, cuda:N"), ("cuda:x", "allowed: cpu, cuda, cuda:N"),
               (f"cuda:{GPUS}", "allowed here: cpu")]
if not CUDA:
    BAD_DEVICES.append(("cuda", "CUDA is not available here"))


@pytest.mark.parametrize("device,allowed", BAD_DEVICES)
def test_a_bad_device_is_one_line_and_exit_2_before_anything_is_written(tmp_path, capsys,
                                                                        device, allowed):
    line = refusal(train, [f"device={device}", f"hydra.run.dir={tmp_path / 'run'}"], capsys)
    assert line.startswith(f"armeta-train: error: config key 'device' = '{device}': ")
    assert allowed in line
    assert not (tmp_path / "run").exists()


def test_resolve_device_names_the_key_and_what_this_machine_allows():
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ConfigError) as error:
        resolve_device(f"cuda:{GPUS}", "eval.device")
    assert error.value.key == "eval.device" and "cpu" in error.value.allowed
    with pytest.raises(ConfigError, match="allowed: cpu, cuda, cuda:N"):
        resolve_device("gpu")


def _tensors(players: Players) -> list[torch.Tensor]:
    """Every tensor of the leader's and the principle's checkpoint state."""
    state = {"leader": players.leader.state_dict(), "principle": players.principle.state_dict()}
    found = []

    def walk(value: object) -> None:
        if isinstance(value, torch.Tensor):
            found.append(value)
        elif isinstance(value, dict):
            for item in value.values():
                walk(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                walk(item)

    walk(state)
    return found


def _devices(players: Players) -> set[torch.device]:
    distributions = [players.initial]
    if players.adversary is not None:
        distributions.append(players.adversary)
    buffers = [b for d in distributions for b in d.buffers()]
    return {t.device for t in [*_tensors(players), *buffers]}


@pytest.mark.parametrize("benchmark,method", [("sinusoid_uniform", "ar_maml"),
                                              ("point_nav_plain", "maml")])
def test_explicit_cpu_equals_the_default_bit_for_bit(tmp_path, benchmark, method):
    """``device=cpu`` given explicitly trains exactly the run the default trains, with every
    player's state on the CPU."""
    small = (*SMALL_RUN, f"benchmark={benchmark}", f"method={method}", "trainer.iterations=2",
             "trainer.meta_batch=2", "eval.n_tasks=4")
    if benchmark == "point_nav_plain":
        small += ("benchmark.collector.episodes=2", "benchmark.collector.max_steps=5")
    default = run_training(Job(train_config(*small), tmp_path / "default"))
    explicit_cfg = compose_train(*small, "device=cpu")
    explicit = run_training(Job(validate(explicit_cfg), tmp_path / "explicit"))
    assert explicit == default
    _, players = load_players(tmp_path / "explicit", "learner")
    assert _devices(players) == {torch.device("cpu")}


def test_a_checkpoint_loads_onto_the_device_asked_for_and_scores_as_the_run_reported(tmp_path):
    """A saved run loads on the CPU, its checkpoint's tensors there, and scores exactly as the
    run reported at its end."""
    run = tmp_path / "run"
    report = run_training(Job(train_config(*SMALL_RUN, "method=ar_maml"), run))
    config, players = load_players(run, "learner", "cpu")
    assert config.device == "cpu" and players.device == torch.device("cpu")
    assert _devices(players) == {torch.device("cpu")}
    rescored = cross_evaluate(run, run, device="cpu")
    assert rescored["initial"] == report["initial"]
    assert rescored["adversarial"] == report["adversarial"]
    assert report["machine"] == rescored["machine"] == machine_name(torch.device("cpu"))


def test_the_machine_names_the_processor_its_kernels_and_the_versions(tmp_path):
    """What one seed's numbers depend on besides the config: torch's CPU kernel level and the
    torch and MuJoCo versions; the processor from its first block in cpuinfo (or "unknown CPU"
    where there is none to read, as on another OS)."""
    import mujoco

    name = machine_name(torch.device("cpu"))
    assert name.startswith(cpu_model())
    assert f"({torch.backends.cpu.get_cpu_capability()}); torch {torch.__version__}, " in name
    assert name.endswith(f"mujoco {mujoco.__version__}")
    assert cpu_model(tmp_path / "absent") == "unknown CPU"
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: Neoverse\n\nprocessor\t: 1\nmodel\t: 9\n")
    assert cpu_model(info) == "Neoverse"


@pytest.mark.skipif(CUDA, reason="checks what a machine without CUDA does")
def test_cuda_random_state_in_a_checkpoint_does_not_block_a_cpu_resume():
    """A checkpoint written on CUDA carries the CUDA generators' states; without CUDA they are left
    out and the CPU streams are restored (TorchRL's GlobalRNGState refuses the whole state)."""
    state = GlobalRNGState().state_dict()
    expected = torch.rand(3)
    state["torch_cuda"] = [torch.zeros(16, dtype=torch.uint8)]
    with pytest.raises(RuntimeError, match="CUDA is unavailable"):
        GlobalRNGState().load_state_dict(state)
    PortableRNGState().load_state_dict(state)
    assert torch.equal(torch.rand(3), expected)


def test_resume_and_eval_accept_a_device_and_refuse_a_bad_one(tmp_path, capsys):
    run = tmp_path / "run"
    run_training(Job(train_config(*SMALL_RUN, "method=maml", "trainer.stop_at=3"), run))
    assert "config key 'device' = 'tpu'" in refusal(train, [f"resume={run}", "device=tpu"],
                                                    capsys)
    assert "config key 'device' = 'tpu'" in refusal(evaluate, [f"learner={run}", "device=tpu"],
                                                    capsys)
    resumed = subprocess.run([*TRAIN, f"resume={run}", "device=cpu"], capture_output=True,
                             text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    whole = run_training(Job(train_config(*SMALL_RUN, "method=maml"), tmp_path / "whole"))
    assert json.loads((run / "eval.json").read_text()) == whole


def _scores_agree_across_devices(cpu: Players, cuda: Players) -> None:
    """The players loaded on the CPU are the CUDA run's, tensor for tensor, and score as they do
    on the same data: the same tasks' data collected on the CPU, scored (regression: the
    adapted query losses) or adapted (meta-RL: the inner step's θ'_k, from which every return
    of a scoring follows) on each device. A scoring's own draws differ by device (tasks and
    episodes come from the CPU's or the GPU's generator), so the same data are what can agree.
    Tolerance rtol 1e-4: float32 kernels differ across devices in their summation order (cuBLAS
    against the CPU's BLAS, one ulp, 1.2e-7 relative, per reduction), and an inner step and a
    loss chain a few hundred of them; 1e-4 is far under any difference between two learners."""
    for on_cpu, on_cuda in zip(_tensors(cpu), _tensors(cuda), strict=True):
        assert torch.equal(on_cpu, on_cuda.cpu())
    torch.manual_seed(0)
    data = cpu.leader.collect(cpu.initial.sample(4))
    if isinstance(data, TensorDict):
        torch.testing.assert_close(cuda.leader.evaluate(data.to("cuda")).cpu(),
                                   cpu.leader.evaluate(data), rtol=1e-4, atol=0.0)
        return
    adapted = cuda.leader.adapt(cuda.leader.theta(), data.train.to("cuda"),
                                data.train_advantages.to("cuda"), create_graph=False)
    for name, value in data.adapted.items():
        torch.testing.assert_close(adapted[name].cpu(), value.detach(), rtol=1e-4, atol=1e-6)


@needs_cuda
@pytest.mark.parametrize("benchmark,method", [("sinusoid_uniform", "ar_maml"),
                                              ("sinusoid_uniform", "ar_cnp"),
                                              ("pendulum_uniform", "dro_maml"),
                                              ("point_nav_plain", "ar_maml"),
                                              ("ant_goal_smoke", "maml"),
                                              ("ant_goal_warp", "maml")])
def test_train_on_cuda_evaluate_on_cpu_resume_on_cuda(tmp_path, benchmark, method):
    """Two iterations on CUDA put every player there; the run is scored on the CPU from its CUDA
    checkpoint; it resumes on CUDA to the end; a second seeded CUDA run reproduces it. Ant with
    MuJoCo Warp (ant_goal_warp) steps, acts and learns on the GPU end to end."""
    small = (*SMALL_RUN, f"benchmark={benchmark}", f"method={method}", "trainer.meta_batch=2",
             "eval.n_tasks=4", "trainer.iterations=4", "trainer.checkpoint_every=2")
    if benchmark in ("point_nav_plain", "ant_goal_smoke", "ant_goal_warp"):
        small += ("benchmark.collector.episodes=2", "benchmark.collector.max_steps=5")
    run = tmp_path / "run"
    assert run_training(Job(train_config(*small, "device=cuda", "trainer.stop_at=2"), run)) is None
    cfg, players = load_players(run, "learner")
    assert cfg.device == "cuda" and {d.type for d in _devices(players)} == {"cuda"}
    on_cpu = cross_evaluate(run, None, device="cpu")
    assert on_cpu["initial"]["n_tasks"] == 4
    _, cpu_players = load_players(run, "learner", "cpu")
    _scores_agree_across_devices(cpu_players, players)
    resumed = subprocess.run([*TRAIN, f"resume={run}"], capture_output=True, text=True,
                             timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    again = run_training(Job(train_config(*small, "device=cuda"), tmp_path / "again"))
    assert json.loads((run / "eval.json").read_text()) == again


@needs_cuda
@pytest.mark.parametrize("per_task", [False, True])
def test_the_point_robots_cuda_graph_replays_its_eager_rollout_bit_for_bit(per_task):
    """On CUDA the collectors' point-robot rollout is replayed as a CUDA graph: three rollouts in
    a row (new goals and parameters each time, so the graph's inputs change) equal the eager ones
    bit for bit, and leave torch's CUDA RNG where the eager ones leave it."""
    batch = (4, 5)
    runs = []
    for graphs in (False, True):
        torch.manual_seed(0)
        net = GaussianMLP().cuda()
        env = PointNavigationEnv(batch, max_steps=7, seed=4, device="cuda", graphs=graphs,
                                 sparse_regions=PAPER_SPARSE_REGIONS)
        assert env.graphs is graphs
        rollouts = []
        for _ in range(3):
            params = None
            if per_task:
                params = TensorDict.from_module(net).detach().expand(batch[0]).clone()
                params.apply_(lambda p: p + 0.1 * torch.randn_like(p))
            goals = torch.rand(*batch, 2, device="cuda") - 0.5
            env.reset(TensorDict({TASK_KEY: goals}, batch, device="cuda"))
            rollouts.append(env.gaussian_transitions(20, net, params))
            with torch.no_grad():  # as TRPO updates the policy: in place
                for parameter in net.parameters():
                    parameter.add_(0.01)
        runs.append((rollouts, torch.rand(2, device="cuda")))
    (eager, eager_next), (graphed, graphed_next) = runs
    assert eager[0]["next", "truncated"].any()
    for expected, replayed in zip(eager, graphed):
        for key in expected.keys(True, True):
            assert torch.equal(replayed[key], expected[key]), key
    assert torch.equal(graphed_next, eager_next)
