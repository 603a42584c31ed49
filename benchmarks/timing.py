"""The benchmark harness: ``python -m benchmarks.timing NAME [option ...] [override ...]`` runs
comparison ``NAME`` of ``benchmarks/workloads.yaml`` (the workloads as data; no script of its own)
and writes its table into its section of the docs pages it names.

* workloads: :func:`workloads` reads the file, :func:`trainer_for` builds a run's trainer from
  config overrides as ``armeta-train`` builds it, :func:`timed_call` picks what a row times;
* timing: :func:`wall_times` (calls of one function) and :func:`in_turns` (several functions
  taking turns in one session, so that a shared machine's slow spells fall on all alike: the way
  two forms are compared), with :func:`reference_product_ms`, a yardstick of the machine's speed,
  taken between turns;
* what a row's time is made of: :func:`instrument` splits a meta-iteration into its
  :data:`PHASES` (``phases: true``), :func:`replayed_physics` is a rollout's physics floor (the
  ``physics`` rows), :func:`products_ms` its matrix products' floor and :func:`floor_cells` the
  kernels it dispatches around them (``products: true``);
* tables: :func:`markdown_table` and :func:`write_section`, which replaces a section of a page
  (between ``<!-- name:start -->`` and ``<!-- name:end -->``) with its tables, its command, the
  date and the machine (the studies in ``studies/`` write their pages with it too).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import shlex
import statistics
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from armeta_rl.devices import cpu_model

if TYPE_CHECKING:
    from tensordict import TensorDictBase

    from armeta_rl.collectors.episodes import EpisodeCollector
    from armeta_rl.rl.policy import GaussianMLP
    from armeta_rl.trainers.game import GameTrainer
    from armeta_rl.trainers.players import Players

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
WORKLOADS = Path(__file__).with_name("workloads.yaml")
SIZE_KEYS = ("trainer.meta_batch", "benchmark.collector.episodes", "benchmark.collector.max_steps")
"""What a group's ``size`` (tasks x episodes x steps) sets."""


# -- workloads ----------------------------------------------------------------------------------

def workloads() -> dict:
    """The comparisons of ``benchmarks/workloads.yaml``, by name."""
    import yaml

    return yaml.safe_load(WORKLOADS.read_text())


def trainer_for(*overrides: str) -> tuple[GameTrainer, Players]:
    """A seeded ``GameTrainer`` of the ``armeta-train`` config with ``overrides``, its players
    built as the CLI builds them (no logger, no progress bar), and the players."""
    from hydra import compose, initialize_config_dir

    from armeta_rl.cli.compose import config_dir
    from armeta_rl.config import validate
    from armeta_rl.trainers.game import GameTrainer
    from armeta_rl.trainers.players import build_players

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg = compose("train", overrides=[*overrides, "trainer.progress=false", "logger=none"])
    config = validate(cfg)
    players = build_players(config)
    trainer = GameTrainer(players.leader, players.principle,
                          dataclasses.replace(config.trainer, iterations=10**9))
    return trainer, players


def as_trained() -> None:
    """This process set up as ``armeta-train`` sets up a run (one torch thread here, glibc keeping
    freed memory: ``trainer.keep_freed_memory``), torch's generator seeded with 0."""
    from armeta_rl.allocator import keep_freed_memory

    torch.set_num_threads(1)
    keep_freed_memory()
    torch.manual_seed(0)


ROLLOUT_SEED = 0
"""The seed of torch's generator at every ``rollout`` call (:func:`seeded_rollout`)."""


def timed_call(call: str, trainer: GameTrainer, players: Players) -> Callable[[], object]:
    """What a row times: ``iteration``, a meta-iteration; ``rollout``, one collection of the
    meta-batch's tasks drawn from p0 with the leader's policy (the unit an iteration is made
    of), the same one at every call (:func:`seeded_rollout`); ``physics``, the physics of that
    rollout alone (:func:`replayed_physics`), the floor of ``rollout``'s time."""
    if call == "iteration":
        return trainer.train_iteration
    collector = players.leader.collector
    collect = partial(seeded_rollout, collector, players.initial.sample(trainer.options.meta_batch),
                      players.leader.net)
    return collect if call == "rollout" else replayed_physics(collector, collect)


def seeded_rollout(collector: EpisodeCollector, tasks: TensorDictBase, net: GaussianMLP
                   ) -> TensorDictBase:
    """``collector``'s collection of ``tasks`` with the policy ``net``, torch's generator seeded
    with :data:`ROLLOUT_SEED` first: the same start states and actions at every call, so that
    every call meets the same contacts (a MuJoCo step's cost depends on the state)."""
    torch.manual_seed(ROLLOUT_SEED)
    return collector.collect(tasks, None, policy=net)


def replayed_physics(collector: EpisodeCollector, collect: Callable[[], TensorDictBase]
                     ) -> Callable[[], None]:
    """The physics of the rollout ``collect`` returns (:func:`seeded_rollout`) alone: the
    collector's env (a batched MuJoCo env, or a MuJoCo Warp env) reset to that rollout's start
    (the collector reseeds its env from torch's generator, then resets it on the tasks:
    ``EpisodeCollector.collect``), then stepped with its actions, ``frame_skip`` bare
    ``mj_step`` calls a step (``sim.step`` with no forward stage after them; on MuJoCo Warp its
    kernels), on the same MjModels, simulations and threads: no policy, no observation, no
    reward, no forward pass for the observation, no TorchRL. The simulations follow the
    rollout's trajectories, so the floor meets the contacts the rollout meets; an episode that
    ends early (a fall) is not reset as the rollout resets it, and goes on from where it ended
    under the actions the rollout gave its restart."""
    from tensordict import TensorDict

    from armeta_rl.envs.batched_mujoco import STAGE_NONE
    from armeta_rl.tasks.protocol import TASK_KEY

    rollout = collect()
    env = collector.env(rollout.batch_size[0])
    shape, base = env.batch_size, getattr(env, "base_env", env)
    torch.manual_seed(ROLLOUT_SEED)
    env.set_seed(int(torch.randint(0, 2**62, ())))
    identifiers = rollout[TASK_KEY][..., 0, :].to(env.device)
    env.reset(TensorDict({TASK_KEY: identifiers}, shape, device=env.device))
    sim = base.sim
    qpos, qvel, ctrl = (sim.bind(name) for name in ("qpos", "qvel", "ctrl"))
    state = base._snapshot(qpos), base._snapshot(qvel)
    actions = [base._as_sim(action.reshape(base.n_sims, -1))
               for action in rollout["action"].unbind(len(shape))]

    def replay() -> None:
        sim.reset(stage=STAGE_NONE)
        qpos[:], qvel[:] = state
        sim.forward(stage=base.stage)
        for action in actions:
            ctrl[:] = action
            sim.step(nstep=base.frame_skip, stage=STAGE_NONE)

    return replay


# -- timing -------------------------------------------------------------------------------------

CLOCK_SOURCE: list[Callable[[], float]] = [time.perf_counter]
"""The clock every timing reads: wall seconds, or this process's CPU seconds
(``time.process_time``, ``--cpu-time``: on a machine shared with other work, the time spent
waiting for a core is left out)."""


def trimmed_above(fn: Callable[[], object], threshold: int) -> Callable[[], None]:
    """``fn`` run with glibc's trim threshold at ``threshold`` bytes, the process's own setting
    (:func:`as_trained`) restored after each call: a row that trims the heap as a process set so
    would, taking turns with rows that keep it (the threshold applies from the next free on)."""
    from armeta_rl.allocator import keep_freed_memory

    def call() -> None:
        keep_freed_memory(trim_threshold=threshold)
        try:
            fn()
        finally:
            keep_freed_memory()

    return call


def wall_times(fn: Callable[[], object], repeats: int, warmup: int = 1) -> list[float]:
    """Seconds taken by each of ``repeats`` calls of ``fn``, after ``warmup`` untimed calls, on
    :data:`CLOCK_SOURCE` (wall seconds unless ``--cpu-time``)."""
    for _ in range(warmup):
        fn()
    times: list[float] = []
    for _ in range(repeats):
        start = CLOCK_SOURCE[0]()
        fn()
        times.append(CLOCK_SOURCE[0]() - start)
    return times


def in_turns(rows: dict[str, Callable[[], object]], calls: int, rounds: int,
             between: Callable[[], float]) -> tuple[dict[str, list[list[float]]],
                                                    dict[str, list[float]]]:
    """Every row's ``rounds`` turns of ``calls`` timed calls, the rows taking turns (the first
    row of a round rotates, so that no row always follows the same one), so that a shared
    machine's slow spells fall on all rows alike. Returns each row's turns (their calls'
    seconds) and each turn's mean of the yardstick ``between`` taken just before and just after
    it."""
    labels = list(rows)
    turns: dict[str, list[list[float]]] = {label: [] for label in labels}
    marks: dict[str, list[float]] = {label: [] for label in labels}
    before = between()
    for index in range(rounds):
        for label in labels[index % len(labels):] + labels[:index % len(labels)]:
            turns[label].append(wall_times(rows[label], calls, warmup=0))
            after = between()
            marks[label].append((before + after) / 2)
            before = after
    return turns, marks


def ratio_cell(numerators: Sequence[float], denominators: Sequence[float]) -> str:
    """The median of the per-round ratios and their range, as a table cell: ``**1.23×**
    (1.10–1.40)``."""
    ratios = [a / b for a, b in zip(numerators, denominators, strict=True)]
    return f"**{statistics.median(ratios):.2f}×** ({min(ratios):.2f}–{max(ratios):.2f})"


def resident_mib() -> float:
    """This process's resident set now, in MiB."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def reference_product_ms(repeats: int = 5) -> float:
    """Median ms of one ``[16, 190, 128] × [16, 128, 128]`` float32 ``bmm``, the largest product of
    the system-identification MAML step: a yardstick of how fast the machine runs at the moment
    (a shared machine has fast and slow spells)."""
    activations, weights = torch.randn(16, 190, 128), torch.randn(16, 128, 128)
    return 1000 * statistics.median(wall_times(lambda: torch.bmm(activations, weights), repeats))


PRODUCTS = {"aten::mm": 2, "aten::bmm": 2, "aten::addmm": 3, "aten::baddbmm": 3,
            "aten::addmv": 3, "aten::mv": 2, "aten::dot": 2}
"""The matrix-product kernels and their number of tensor arguments."""


Product = tuple[str, tuple[tuple[int, ...], ...], tuple[torch.dtype, ...]]
"""A product kernel's name, its operands' shapes and their dtypes."""


class KernelCounter(TorchDispatchMode):
    """Counts the kernels the ops run under it dispatch, and the matrix-product ones
    (:data:`PRODUCTS`) with their operands' shapes and dtypes, backward passes included (the
    autograd engine dispatches them too). It keeps counters, not a record per op as
    ``torch.profiler`` does (whose record of five exact-curvature point-robot iterations outgrew
    24 GB)."""

    def __init__(self) -> None:
        super().__init__()
        self.products: Counter[Product] = Counter()
        self.kernels = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        name = f"aten::{func._overloadpacket.__name__}"
        self.kernels += 1
        if name in PRODUCTS:
            operands = args[:PRODUCTS[name]]
            self.products[name, tuple(tuple(t.shape) for t in operands),
                          tuple(t.dtype for t in operands)] += 1
        return func(*args, **(kwargs or {}))


def recorded_kernels(fn: Callable[[], object], calls: int) -> tuple[Counter[Product], int]:
    """How often ``calls`` calls of ``fn`` run each matrix-product kernel (:data:`PRODUCTS`) at
    each operand shape and dtype, and how many kernels they dispatch in all
    (:class:`KernelCounter`)."""
    with KernelCounter() as counter:
        for _ in range(calls):
            fn()
    return counter.products, counter.kernels


def products_ms(products: Counter[Product]) -> float:
    """Milliseconds the matrix products ``products`` (:func:`recorded_kernels`) take when
    replayed alone: each distinct kernel timed by itself (the median of 20, after 3) on fresh
    contiguous operands of its shapes and dtypes and counted as often as it ran. A floor for the
    computation on this machine (the same products at the same sizes and precisions, nothing
    between them); the recorded calls' own times are not used: recording slows them."""
    seconds = 0.0
    for (name, shapes, dtypes), count in products.items():
        operands = [torch.randn(shape, dtype=dtype) for shape, dtype in zip(shapes, dtypes)]
        product = getattr(torch.ops.aten, name.split("::")[1])
        seconds += statistics.median(wall_times(lambda p=product, o=operands: p(*o), 20, 3)
                                     ) * count
    return 1000 * seconds


def empty_kernel_us(repeats: int = 2000) -> float:
    """Median µs of one call of a kernel with next to nothing to compute, a one-element float32
    ``add`` called from Python: what dispatching a kernel costs on this machine, whatever it
    computes (timed over ``repeats`` calls in blocks of 100)."""
    a, b = torch.ones(1), torch.ones(1)

    def block() -> None:
        for _ in range(100):
            torch.add(a, b)

    return 1e4 * statistics.median(wall_times(block, repeats // 100, 3))


FLOOR_COLUMNS = ("products ms (share)", "kernels", "rest per kernel µs (empty kernel µs)",
                 "eager ceiling of the share")
"""The columns of :func:`floor_cells`."""


def floor_cells(fn: Callable[[], object], calls: int, median_ms: float,
                compiled: bool = False) -> list[str]:
    """The cells of what a call of ``fn`` (``median_ms`` a call) is made of, from ``calls`` calls
    recorded: its matrix products replayed alone (:func:`products_ms`) and their share of the
    call; the kernels it dispatches; the µs per kernel the rest of the call spends (the call less
    its products, over its other kernels) beside what an empty kernel costs
    (:func:`empty_kernel_us`); and the largest share its products could have while it dispatches
    these kernels one by one (:func:`eager_ceiling`): the share left if every other kernel
    computed nothing and nothing ran between kernels. Only fewer kernels (fused by compiling, or
    fewer operations) lift that ceiling. A ``compiled`` call gets its products' cell alone: under
    the recording dispatch mode its compiled code runs eagerly, so the kernels recorded would be
    the eager path's, not the fused ones it runs."""
    products, kernels = recorded_kernels(fn, calls)
    floor = products_ms(products) / calls
    if compiled:
        return [f"{floor:.1f} ({100 * floor / median_ms:.0f} %)", "–", "–", "–"]
    others = (kernels - sum(products.values())) / calls
    empty = empty_kernel_us()
    rest = 1000 * (median_ms - floor) / others if others else float("nan")
    return [f"{floor:.1f} ({100 * floor / median_ms:.0f} %)", f"{kernels / calls:,.0f}",
            f"{rest:.1f} ({empty:.1f})", f"{eager_ceiling(floor, others, empty):.0f} %"]


def eager_ceiling(products_ms: float, other_kernels: float, empty_us: float) -> float:
    """The largest share in % that ``products_ms`` of matrix products can have in a call that
    also dispatches ``other_kernels`` kernels one by one, each costing at least ``empty_us``.

    Examples:
        >>> from benchmarks.timing import eager_ceiling
        >>> eager_ceiling(1.0, 1000, 1.0)  # 1 ms of products beside 1 ms of dispatch
        50.0
        >>> eager_ceiling(0.0, 10, 1.0)  # no products
        0.0
    """
    return 100 * products_ms / (products_ms + other_kernels * empty_us / 1000) if products_ms \
        else 0.0


# -- phases: where a meta-iteration's time goes ------------------------------------------------

PHASES = ("rollout", "GAE", "baseline fit", "inner step", "surrogate gradient", "TRPO HVP",
          "line search", "leader step", "adversary", "other")
"""The phases of an iteration a row's time is split into (:func:`instrument`)."""


class PhaseClock:
    """Exclusive wall time of nested phases: entering a phase pauses the phase it runs inside,
    so that each second is charged to the innermost phase open."""

    def __init__(self) -> None:
        self.open: list[list] = []  # [seconds by phase, phase, since]

    def enter(self, seconds: dict[str, float], phase: str) -> None:
        now = CLOCK_SOURCE[0]()
        if self.open:
            outer = self.open[-1]
            outer[0][outer[1]] += now - outer[2]
        self.open.append([seconds, phase, now])

    def leave(self) -> None:
        now = CLOCK_SOURCE[0]()
        seconds, phase, since = self.open.pop()
        seconds[phase] += now - since
        if self.open:
            self.open[-1][2] = now


CLOCK = PhaseClock()


def in_phase(fn: Callable, phase: str, seconds: dict[str, float] | None = None) -> Callable:
    """``fn`` charging its exclusive wall time to ``phase`` of ``seconds`` (by default: of the
    row whose call is open; outside any row's call ``fn`` runs untimed)."""
    def call(*args: object, **kwargs: object) -> object:
        target = seconds if seconds is not None else CLOCK.open[-1][0] if CLOCK.open else None
        if target is None:
            return fn(*args, **kwargs)
        CLOCK.enter(target, phase)
        try:
            return fn(*args, **kwargs)
        finally:
            CLOCK.leave()

    call.phase = phase
    return call


def instrument(trainer: GameTrainer, players: Players) -> None:
    """Split a row's time into :data:`PHASES`: the collector's ``collect`` (rollout: a meta-RL
    rollout, a regression benchmark's data), the leader's ``advantages`` (GAE, the linear
    baseline's fit apart), ``inner_step``, ``surrogate_gradient``, ``kl_hessian_product`` with
    the conjugate gradient's products (TRPO HVP) and the line search, the rest of the leader's
    ``step`` (leader step: a regression leader's whole meta-update, forward, backward and Adam;
    MAML-TRPO's scoring) and the risk principle's ``propose``, ``weights`` and ``update``
    (adversary: the flow, the predictive model); the rest of the iteration is ``other``. A
    method a leader lacks is left out (its time counts where it runs)."""
    from armeta_rl.learners import maml_trpo
    from armeta_rl.rl import baseline

    leader = players.leader
    methods = [(leader.collector, "collect", "rollout"), (leader, "advantages", "GAE"),
               (leader, "inner_step", "inner step"),
               (leader, "surrogate_gradient", "surrogate gradient"),
               (leader, "kl_hessian_product", "TRPO HVP"), (leader, "step", "leader step"),
               *((trainer.principle, name, "adversary") for name in ("propose", "weights",
                                                                      "update"))]
    functions = [(baseline, "baseline_values", "baseline fit"),
                 (maml_trpo, "trust_region_step", "TRPO HVP"),
                 (maml_trpo, "backtracking_line_search", "line search")]
    for owner, name, phase in [*methods, *functions]:
        fn = getattr(owner, name, None)
        if fn is not None and getattr(fn, "phase", None) is None:
            setattr(owner, name, in_phase(fn, phase))


def beyond_rollouts_cell(row_ms: float, first_ms: float, row_rollout_ms: float,
                         first_rollout_ms: float) -> str:
    """A row's cost against the first row's plus the rollouts the row runs beyond it:
    row / (first + row's rollout − first's rollout). Against MAML this is a method's overhead
    beside the rollouts its follower needs; against one rollout, an iteration's cost over the
    rollouts it is made of (each ms per call; the rollouts from the row's phases).

    Examples:
        >>> from benchmarks.timing import beyond_rollouts_cell
        >>> beyond_rollouts_cell(2500.0, 1500.0, 1900.0, 950.0)  # 950 ms of extra rollouts
        '1.02×'
    """
    return f"{row_ms / (first_ms + row_rollout_ms - first_rollout_ms):.2f}×"


def phase_cells(seconds: dict[str, float], calls: int) -> list[str]:
    """A row's ms per call in each of :data:`PHASES` and its share of the row's time."""
    total = sum(seconds.values()) or 1.0
    return [f"{1000 * seconds[phase] / calls:.0f} ({100 * seconds[phase] / total:.0f} %)"
            for phase in PHASES]


# -- tables and sections ------------------------------------------------------------------------

def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A Markdown table with ``header`` and one line per row (cells as ``str`` gives them)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def markers(name: str) -> tuple[str, str]:
    """The HTML comments that open and close section ``name`` of a page."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def replace_section(page: str, name: str, section: str) -> str:
    """``page`` with the text between ``name``'s markers replaced by ``section`` (the markers
    appended at the end if the page has none yet); everything outside them is kept as it is."""
    start, end = markers(name)
    block = f"{start}\n{section.strip()}\n{end}"
    if start not in page:
        return page.rstrip("\n") + "\n\n" + block + "\n"
    head, rest = page.split(start, 1)
    if end not in rest:
        raise ValueError(f"{name}: '{start}' without '{end}'")
    return head + block + rest.split(end, 1)[1]


def this_machine() -> str:
    """This machine as the benchmark pages name it: processor, CPUs, GPU, torch, its CPU
    kernels and threads."""
    gpu = f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ""
    return (f"{cpu_model()}, {os.cpu_count()} logical CPUs{gpu}, torch "
            f"{torch.__version__} ({torch.backends.cpu.get_cpu_capability()} kernels), "
            f"{torch.get_num_threads()} thread")


def write_section(name: str, title: str, body: str, page: Path, command: str | None = None,
                  ) -> None:
    """Write section ``name`` of ``page``, leaving the other sections untouched: its title, the
    command (by default this process's command line), the date, this machine and its load (other
    processes slow a shared machine down), and ``body``."""
    if command is None:
        script = Path(sys.argv[0]).resolve()
        shown = ("-m benchmarks.timing" if script == Path(__file__).resolve()
                 else script.relative_to(ROOT) if script.is_relative_to(ROOT) else script.name)
        command = "OMP_NUM_THREADS=1 python " + " ".join([str(shown),
                                                           *map(shlex.quote, sys.argv[1:])])
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    text = (f"## {title}\n\n`{command}`, run on {datetime.date.today().isoformat()} "
            f"({this_machine()}; load average at the end {load}).\n\n{body.strip()}\n")
    page.write_text(replace_section(page.read_text() if page.exists() else "", name, text))
    print(f"wrote the {name} section of {page}")


# -- a comparison: groups of rows in turns ------------------------------------------------------

def group_rows(group: dict, base: Sequence[str], last: Sequence[str], cuda_as: str | None,
               compiling: bool, warmup: int, phases: dict[str, dict[str, float]] | None = None,
               ) -> tuple[dict[str, Callable[[], object]], dict[str, tuple[float, str] | str],
                          set[str]]:
    """A group's rows built and warmed up (``warmup`` calls); each row's warm-up seconds and
    notes (its peak GPU memory on CUDA), or why it did not run (``skipped: no CUDA`` for a row on
    CUDA without one, the error's line for a row that failed to build or warm up: the others
    still run); and the labels of the rows that compile. A row is a list of config overrides
    (a meta-iteration), or ``{call: ..., overrides: [...]}`` (:func:`timed_call`), with
    ``trim_threshold: BYTES`` where its calls trim glibc's heap (:func:`trimmed_above`); its config
    is the comparison's ``base``, the group's size and base, the row's overrides and ``last``,
    with ``cuda`` read as ``cuda_as`` where given; rows that compile are left out unless
    ``compiling``. With ``phases``, each row's calls after the warm-up are split into
    :data:`PHASES` there (:func:`instrument`)."""
    sized = [f"{key}={n}" for key, n in zip(SIZE_KEYS, group["size"].split("x"), strict=True)
             ] if "size" in group else []
    rows, warm, compiled = {}, {}, set()
    for label, row in group["rows"].items():
        row = {"overrides": row} if isinstance(row, list) else row
        every = [f"benchmark={group['benchmark']}", *base, *sized, *group.get("base", []),
                 *row["overrides"], *last]
        if cuda_as:
            every = [o.removesuffix("=cuda") + f"={cuda_as}" if o.endswith("=cuda") else o
                     for o in every]
        if any(o.endswith("compile=true") for o in every):
            if not compiling:
                continue
            compiled.add(label)
        if any(o.partition("=")[2].startswith("cuda") for o in every) \
                and not torch.cuda.is_available():
            warm[label] = "skipped: no CUDA"
            continue
        try:
            trainer, players = trainer_for(*every)
            fn = timed_call(row.get("call", "iteration"), trainer, players)
            if "trim_threshold" in row:
                fn = trimmed_above(fn, int(row["trim_threshold"]))
            cuda = torch.cuda.is_initialized()
            rows[label] = (lambda fn=fn: (fn(), torch.cuda.synchronize())) if cuda else fn
            if phases is not None:
                instrument(trainer, players)
                phases[label] = dict.fromkeys(PHASES, 0.0)
                rows[label] = in_phase(rows[label], "other", phases[label])
            if cuda:
                torch.cuda.reset_peak_memory_stats()
            seconds = sum(wall_times(rows[label], warmup, warmup=0))
            if phases is not None:  # the warm-up's calls do not count
                phases[label].update(dict.fromkeys(PHASES, 0.0))
            warm[label] = (seconds, f"peak GPU {torch.cuda.max_memory_allocated() / 2**20:,.0f} "
                           "MiB in the warm-up " if cuda else "")
        except Exception as error:  # noqa: BLE001 — one failed row must not stop the others
            traceback.print_exc()
            rows.pop(label, None)
            warm[label] = " ".join(f"error: {type(error).__name__}: {error}".split())[:300]
    return rows, warm, compiled


def group_label(group: dict, tiny: bool) -> str:
    """A group's name in its table: its benchmark, its size, and whether it ran tiny."""
    size = group.get("size", "").replace("x", " × ")
    return f"{group['benchmark']} {size}".strip() + (" (tiny)" if tiny else "")


def growth_tracked(rows: dict[str, Callable[[], object]]) -> tuple[dict, dict[str, float]]:
    """``rows`` each adding its calls' change of the resident set to its entry of the returned
    dict: for a row alone in its group, its resident set at the end minus at the start of its
    turns. A run that keeps references to old iterations' tensors (a leak) grows with their
    count; one that does not stays within allocator noise."""
    grown = dict.fromkeys(rows, 0.0)

    def tracked(label: str, fn: Callable[[], object]) -> Callable[[], None]:
        def call() -> None:
            before = resident_mib()
            fn()
            grown[label] += resident_mib() - before
        return call

    return {label: tracked(label, fn) for label, fn in rows.items()}, grown


def compare_in_turns(name: str, argv: Sequence[str] | None = None) -> str:
    """Run comparison ``name`` of ``workloads.yaml`` (options: ``--help``; other arguments are
    config overrides of every row), write its table into its section of each of its pages after
    every group (a run stopped later keeps the groups it finished; not with ``--no-doc``), and
    return the section's body.

    Every row runs its warm-up calls (timed together: compiles, actors' starts and env builds
    fall there), then the rows of a group take turns (:func:`in_turns`). A row's ms are the
    median of its turn medians; its fast-spell median is the median of its turns whose yardstick
    is at most the lower quartile of the group's (the code's cost in the run's fastest spells);
    its ratio is its turn over the group's first row's turn of the same round."""
    spec = workloads()[name]
    parser = argparse.ArgumentParser(prog=f"python -m benchmarks.timing {name}",
                                     description=spec["about"])
    parser.add_argument("--rounds", "--turns", type=int, default=spec["rounds"])
    parser.add_argument("--calls", type=int, default=spec["calls"], help="calls per turn")
    parser.add_argument("--warmup", type=int, default=spec["warmup"], help="calls before turns")
    parser.add_argument("--benchmarks", nargs="+", help="the groups run (default: all)")
    parser.add_argument("--compile", action="store_true", help="run the rows that compile")
    parser.add_argument("--no-compile", action="store_true", help="skip the rows that compile")
    parser.add_argument("--tiny", action="store_true",
                        help="a dry run: one call of each row, with the comparison's tiny "
                        "overrides; writes no section")
    parser.add_argument("--cuda-as", help="run the rows written for CUDA on this device instead")
    parser.add_argument("--no-doc", action="store_true", help="print the table only")
    parser.add_argument("--label", help="write the table as a section of its own, NAME@LABEL, "
                        "titled with LABEL (e.g. the code revision measured: a run of older "
                        "code beside the current one)")
    parser.add_argument("--cpu-time", action="store_true",
                        help="time this process's CPU seconds instead of wall seconds")
    parser.add_argument("--docs", type=Path, default=DOCS,
                        help="the folder of the pages written (default: this checkout's docs/)")
    args, overrides = parser.parse_known_args(argv)
    if min(args.rounds, args.calls) < 1:
        parser.error(f"--rounds and --calls must be at least 1, got {args.rounds}, {args.calls}")
    if args.tiny:
        args.rounds = args.calls = args.warmup = 1
        args.no_doc = True
    compiling = args.compile or (spec.get("compile") != "opt-in" and not args.no_compile)
    CLOCK_SOURCE[0] = time.process_time if args.cpu_time else time.perf_counter
    last = [*overrides, *(spec.get("tiny", []) if args.tiny else [])]
    as_trained()
    table, marks_seen, body = [], [], ""
    for group in spec["groups"]:
        if args.benchmarks and group["benchmark"] not in args.benchmarks:
            continue
        phases: dict[str, dict[str, float]] | None = {} if spec.get("phases") else None
        built, warm, compiled = group_rows(group, spec.get("base", []), last, args.cuda_as,
                                           compiling, args.warmup, phases)
        if len(warm) < (1 if spec.get("products") else min(2, len(group["rows"]))):
            continue  # a group left without a row to compare (or, timing products, to time)
        rows, grown = growth_tracked(built) if spec.get("memory") else (built, {})
        turns, marks = in_turns(rows, args.calls, args.rounds, reference_product_ms
                                ) if rows else ({}, {})
        every = [mark for label in rows for mark in marks[label]]
        fast = statistics.quantiles(every, n=4)[0] if len(every) > 1 else max(every, default=0)
        marks_seen += every
        medians = {label: [statistics.median(turn) for turn in turns[label]] for label in rows}
        first = next(iter(medians.values()), [])
        shown = group_label(group, args.tiny)
        timed = args.rounds * args.calls
        turned = {label: dict(phases[label]) for label in rows} if phases is not None else {}
        for label, note in warm.items():  # recording a row's products calls it again: use turned
            split = [] if phases is None else ["–"] * (len(PHASES) + 1) if label not in rows \
                else [*phase_cells(turned[label], timed), beyond_rollouts_cell(
                    statistics.median(medians[label]), statistics.median(first),
                    turned[label]["rollout"] / timed, turned[next(iter(rows))]["rollout"] / timed)]
            if spec.get("products"):
                split[:0] = ["–"] * len(FLOOR_COLUMNS) if label not in rows else floor_cells(
                    built[label], args.calls, 1000 * statistics.median(medians[label]),
                    label in compiled)
            if label not in rows:
                table.append((shown, label, *["–"] * 5, note, *split))
                continue
            quick = [t for mark, turn in zip(marks[label], turns[label]) if mark <= fast
                     for t in turn]
            table.append((shown, label, f"{1000 * statistics.median(medians[label]):.1f}",
                          f"{1000 * min(min(turn) for turn in turns[label]):.1f}",
                          f"{1000 * statistics.median(quick):.1f}" if quick else "–",
                          ratio_cell(medians[label], first), f"{note[0]:.1f}", (note[1] + (
                              f"resident set {grown[label]:+,.0f} MiB over the turns"
                              if label in grown else "")).strip() or "–", *split))
            print(" | ".join(table[-1]), flush=True)
        body = turns_body(spec, args, marks_seen, table)
        for page in [] if args.no_doc else spec["pages"]:
            write_section(f"{name}@{args.label}" if args.label else name,
                          f"{spec['title']}, {args.label}" if args.label else spec["title"],
                          body, args.docs / page)
    print(body)
    return body


def turns_body(spec: dict, args: argparse.Namespace, marks: list[float], table: list) -> str:
    """A comparison's section body: what it times and how, and its table."""
    yardstick = (f", median {statistics.median(marks):.2f} ms, range {min(marks):.2f}–"
                 f"{max(marks):.2f} ms" if marks else "")
    clock = "this process's CPU time (`--cpu-time`)" if args.cpu_time else "wall time"
    return (f"{spec['about']} Times are {clock}. Per row: {args.warmup} warm-up calls (their "
            "seconds in the "
            f"last-but-one column, compiles included), then {args.rounds} rounds of {args.calls} "
            "calls, the rows of a benchmark taking turns (`timing.compare_in_turns`); ms: median "
            "of the turn medians; fast-spell: the turns whose machine yardstick "
            f"(`timing.reference_product_ms`{yardstick}) was at most the benchmark's lower "
            "quartile; ratio: the row's turn over the first row's turn of the same round."
            + (" Phases (`timing.instrument`): a row's ms per call in each phase of its timed "
               "calls (each second charged to the innermost phase running) and its share of "
               "the row's time; beyond rollouts: the row's median over the first row's plus "
               "the rollout time the row spends beyond the first row's "
               "(`timing.beyond_rollouts_cell`)." if spec.get("phases") else "")
            + (" Products: the ms a call's matrix products take replayed alone "
               "(`timing.products_ms`, one turn's calls recorded after the turns), and their "
               "share of the row's median; kernels: the kernels a call dispatches, backward "
               "passes included (`timing.recorded_kernels`); rest per kernel: the row's median "
               "less its products, over its other kernels, beside one empty kernel's cost "
               "(`timing.empty_kernel_us`, a one-element add); eager ceiling: the products' "
               "share if every other kernel cost only that and nothing ran between kernels "
               "(`timing.eager_ceiling`); a compiled row has its products' cell alone (the "
               "recording runs its compiled code eagerly)." if spec.get("products") else "")
            + "\n\n"
            + markdown_table(("benchmark", "row", "median ms", "min ms", "fast-spell median ms",
                              "× first row (median, range)", f"first {args.warmup} calls s",
                              "notes", *(FLOOR_COLUMNS if spec.get("products") else ()),
                              *((*PHASES, "× first row + its extra rollouts")
                                if spec.get("phases") else ())), table))


def main(argv: Sequence[str]) -> None:
    """``python -m benchmarks.timing NAME [option ...] [override ...]``: comparison ``NAME`` of
    ``workloads.yaml`` (:func:`compare_in_turns`); an unknown name gets one line naming the
    known ones (exit code 2)."""
    names = list(workloads())
    if argv and argv[0] in ("-h", "--help"):
        print("usage: python -m benchmarks.timing NAME [--help] [option ...] [override ...]\n"
              f"NAME: {', '.join(names)} (the comparisons of benchmarks/workloads.yaml; NAME "
              "--help lists the options)")
        return
    if not argv or argv[0] not in names:
        got = repr(argv[0]) if argv else "nothing"
        print(f"benchmarks.timing: NAME = {got}: allowed: {', '.join(names)} (the comparisons "
              "of benchmarks/workloads.yaml)", file=sys.stderr)
        sys.exit(2)
    compare_in_turns(argv[0], argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
