"""What the benchmark harness (``benchmarks/timing.py``) measures beside a row's time: the phases
of a meta-iteration charge each second to the innermost phase running, the physics floor of a
rollout replays that rollout's own trajectories, and the products floor finds the matrix-product
kernels a call runs among all the kernels it dispatches."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.envs.locomotion import HalfCheetahVelEnv
from armeta_rl.rl.policy import GaussianMLP
from armeta_rl.tasks import TASK_KEY


def test_each_second_is_charged_to_the_innermost_phase(timing, monkeypatch):
    """On a clock that the calls advance by hand: a row's call of 1 + 3 + 2 units, whose inner
    phase takes the 3 (with a nested phase of 1 inside it), splits into other 3, inner step 2,
    baseline fit 1; outside a row's call an instrumented function runs untimed."""
    now = [0.0]
    monkeypatch.setattr(timing, "CLOCK_SOURCE", [lambda: now[0]])

    def advance(units: float) -> None:
        now[0] += units

    fit = timing.in_phase(lambda: advance(1), "baseline fit")
    inner = timing.in_phase(lambda: (advance(1), fit(), advance(1)), "inner step")
    seconds = dict.fromkeys(timing.PHASES, 0.0)
    row = timing.in_phase(lambda: (advance(1), inner(), advance(2)), "other", seconds)
    row()
    assert {phase: s for phase, s in seconds.items() if s} == {
        "other": 3.0, "inner step": 2.0, "baseline fit": 1.0}
    inner()
    assert sum(seconds.values()) == 6.0 and not timing.CLOCK.open


def test_a_row_beyond_its_extra_rollouts_is_its_overhead_over_the_first(timing):
    """A method that runs the first row's iteration plus two more rollouts is 1.00× beyond its
    extra rollouts however dear they are, one 10 % dearer than that 1.10×; against one rollout,
    an iteration of two rollouts and as much arithmetic again reads 2.00×."""
    maml, rollout = 1500.0, 450.0  # ms per call, MAML's iteration and one rollout
    assert timing.beyond_rollouts_cell(maml + 2 * rollout, maml, 4 * rollout, 2 * rollout) == (
        "1.00×")
    assert timing.beyond_rollouts_cell(1.1 * (maml + 2 * rollout), maml, 4 * rollout,
                                       2 * rollout) == "1.10×"
    assert timing.beyond_rollouts_cell(4 * rollout, rollout, 2 * rollout, rollout) == "2.00×"


def test_the_physics_floor_replays_the_rollout_it_bounds(timing):
    """The replay resets the simulations to the seeded rollout's start and steps them with its
    actions: it ends where the rollout ended, bit for bit (no episode of HalfCheetah ends
    early), and every seeded rollout is the same one."""
    collector = EpisodeCollector(partial(HalfCheetahVelEnv, threads=1), episodes=3, max_steps=8)
    tasks = TensorDict({TASK_KEY: torch.tensor([[0.5], [1.5]])}, [2])
    collect = partial(timing.seeded_rollout, collector, tasks, GaussianMLP(20, 6, (8,)))
    replay = timing.replayed_physics(collector, collect)
    first = collect()
    env = collector.env(2)
    end = env._qpos.copy(), env._qvel.copy()
    assert torch.equal(collect()["observation"], first["observation"])
    replay()
    assert np.array_equal(env._qpos, end[0]) and np.array_equal(env._qvel, end[1])


def test_the_products_floor_finds_the_matrix_products_and_kernels_a_call_runs(timing):
    """Each product kernel with its shapes, its dtypes (the adversary's are float64) and how often
    the calls ran it, and every kernel dispatched, backward passes included; a call without
    products has a floor of 0."""
    a, b, c = torch.randn(64, 64), torch.randn(8, 64, 64), torch.randn(5, 3, dtype=torch.float64)
    products, kernels = timing.recorded_kernels(lambda: (a + a).tanh().sum(), calls=2)
    assert (products, kernels) == ({}, 6) and timing.products_ms(products) == 0.0
    products, kernels = timing.recorded_kernels(lambda: (a @ a, b @ b, c.T @ c), calls=2)
    assert products == {
        ("aten::mm", ((64, 64), (64, 64)), (torch.float32, torch.float32)): 2,
        ("aten::bmm", ((8, 64, 64), (8, 64, 64)), (torch.float32, torch.float32)): 2,
        ("aten::mm", ((3, 5), (5, 3)), (torch.float64, torch.float64)): 2}
    # batched matmul dispatches expand, view, bmm and _unsafe_view; c.T a permute: 9 a call
    assert kernels == 18 and timing.products_ms(products) > 0.0
    w = torch.randn(3, requires_grad=True)
    assert timing.recorded_kernels(lambda: (w * w).sum().backward(), calls=1)[1] > 2
    assert 0.0 < timing.empty_kernel_us(repeats=200) < 1000.0


def test_the_products_table_splits_a_row_into_products_kernels_and_rollouts(timing):
    """``bench_products``'s HalfCheetah-Vel group at its tiny size: MAML-TRPO's products are a
    share of its time between 0 and 100 %, it dispatches kernels, the rest of its time per kernel
    and an empty kernel's cost are times, its eager ceiling is a share; and its cost over the
    rollouts it is made of is computed from the turns' phases, not from the calls that recorded
    the first row's products afterwards (which charged that row's rollouts twice)."""
    body = timing.compare_in_turns("bench_products", ["--tiny", "--no-doc", "--benchmarks",
                                                      "half_cheetah_vel"])
    lines = [line for line in body.splitlines() if line.startswith("| ")]
    columns = [cell.strip() for cell in lines[0].strip("|").split(" | ")]
    rollout, maml = ({column: cell.strip() for column, cell in
                      zip(columns, line.strip("|").split(" | "))} for line in lines[1:])
    share = float(maml["products ms (share)"].split("(")[1].rstrip(" %)"))
    assert 0 < share < 100
    assert int(maml["kernels"].replace(",", "")) > 100
    rest, empty = maml["rest per kernel µs (empty kernel µs)"].rstrip(")").split(" (")
    assert float(rest) > 0 and float(empty) > 0
    assert 0 < float(maml["eager ceiling of the share"].rstrip(" %")) <= 100
    ms = {row["row"]: float(row["median ms"]) for row in (rollout, maml)}
    rolled = {row["row"]: float(row["rollout"].split(" (")[0]) for row in (rollout, maml)}
    expected = ms["maml"] / (ms["one rollout"] + rolled["maml"] - rolled["one rollout"])
    beyond = float(maml["× first row + its extra rollouts"].rstrip("×"))
    assert beyond == pytest.approx(expected, rel=0.02, abs=0.01)  # the cells are rounded


def test_a_compiled_call_gets_its_products_cell_alone(timing):
    """Under the recording dispatch mode a compiled function runs its ops eagerly: it dispatches
    as many kernels as the eager function, not the fused few it runs unrecorded. So a compiled
    row's kernel, rest-per-kernel and ceiling cells would describe the eager path; it gets its
    products' cell alone."""
    a = torch.randn(256, 256)

    def eager() -> torch.Tensor:
        return ((a @ a).tanh() * 2 + 1).sum()

    compiled = torch.compile(eager)
    compiled()
    assert timing.recorded_kernels(compiled, 1)[1] == timing.recorded_kernels(eager, 1)[1] > 3
    products, *rest = timing.floor_cells(compiled, 2, 1.0, compiled=True)
    assert rest == ["–"] * 3 and float(products.split(" (")[0]) > 0 and products.endswith("%)")
