"""One GPU check, ready to run on a lent GPU machine.

Device-side assumptions (``benchmarks/gpu_check.sh`` sets them up and calls ``run``):

* the repository is the working directory and is NOT pip-installed: ``armeta_rl`` and
  ``hydra_plugins`` are imported from the repository root, which must be on ``PYTHONPATH``
  (``gpu_check.sh`` prepends it, keeping what ``PYTHONPATH`` already holds, e.g. a
  ``pip install --target`` directory with torchrl, tensordict, normflows, hydra-core, omegaconf,
  gymnasium, mujoco, mujoco-warp, warp-lang); there are no console scripts, so every command is
  ``python -m ...`` or ``python -c "from armeta_rl.cli import train; train()"``;
* no network; torch with CUDA preinstalled; pytest, tqdm and matplotlib must be importable too
  (``preflight`` lists whatever is missing in one line, and the parts that need it fail alone);
* everything it writes goes under ``$OUT`` (default ``/tmp/gpu_check``), at most 8 files:
  ``gpu_check.log`` (every part's output, concatenated), ``tests.log`` (the pytest runs),
  ``results.jsonl`` (one JSON object per measured row), ``summary.txt`` and a copy of
  ``docs/benchmarks.md`` after the check wrote its GPU section there.

``run`` runs the two test files (the MuJoCo Warp tests, then ``tests/test_devices.py``) in the
background, one after the other, then times, one part after the other: a meta-iteration of the
benchmark families (``DEFAULT_BENCHMARKS``; ``--benchmarks`` for others) on the CPU (one thread)
and on CUDA, eager (and, with ``--compiled``, compiled where the code offers it:
``learner.maml.compile``, ``risk.ar.compile``), the point robot on CUDA once more with its rollout
launched step by step instead of replayed as a CUDA graph (``--no-graphs``), then the Ant with
MuJoCo Warp in one process that writes each figure as soon as it has it: a tiny env first (it
compiles the warp kernels), the env steps/s of a collection of 40 tasks × 20 episodes × 200 steps
with the policy acting on the env's device, the same env's physics alone (its ceiling), and
MAML-TRPO meta-iterations at that size on CUDA. Every part runs in its own process under its own
time limit, never stops the others, and all of them together stay within ``--budget`` seconds
(default 320): a part that would start with too little time left is skipped and says so. Without
CUDA the CUDA rows and parts are skipped with that reason, and the rest runs.

Each timing row reports the peak RSS of its process (``ru_maxrss``) and, on CUDA, the peak of
``torch.cuda.max_memory_allocated``. ``report`` turns ``results.jsonl`` into the GPU section of
docs/benchmarks.md and a summary against the issue's targets (one H100-class GPU: point robot
>= 20x pytorch-maml-rl's CPU time, Ant >= 100,000 env steps/s, an Ant meta-iteration <= 5 s).

Subcommands (``python benchmarks/gpu_check.py <cmd> --help``): ``run`` (everything), ``preflight``,
``tests``, ``meta``, ``ant``, ``report``. To try every code path on a machine without CUDA:
``python benchmarks/gpu_check.py run --device cpu --warp-device cpu --ant-tasks 2
--ant-episodes 2 --ant-steps 5 --budget 600``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import xml.etree.ElementTree as ElementTree
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS_DIR = ROOT / "benchmarks"
BUDGET_S = 320
REPORT_RESERVE_S = 25
MIN_PART_S = 15

FAMILIES = (  # (benchmark, method): every family's code path once; *_paper: the paper's protocol
    ("point_nav", "maml"),  # first: the point-robot target
    ("sinusoid_uniform", "ar_maml"),
    ("sinusoid_normal_paper", "ar_maml"),
    ("pendulum_uniform_paper", "ar_maml"),
    ("acrobot_uniform_paper", "ar_maml"),
    ("pendulum_uniform", "ar_maml"),
    ("acrobot_uniform", "ar_maml"),
)
DEFAULT_BENCHMARKS = ("point_nav", "pendulum_uniform_paper", "acrobot_uniform_paper",
                      "sinusoid_uniform")
"""The families a default run times (all of them did not fit the last lent machine's budget)."""
COMPILED = ("sinusoid_uniform", "pendulum_uniform_paper")
"""The benchmarks timed compiled as well with ``--compiled``."""
COMPILE_OVERRIDES = ("learner.maml.compile=true", "risk.ar.compile=true")
ANT = {"tasks": 40, "episodes": 20, "steps": 200}
TARGETS = {"ant_steps_per_s": 100_000, "ant_meta_s": 5.0, "point_robot_speedup": 20.0}


# -- measuring ----------------------------------------------------------------------------------

def peak_rss_mib() -> float:
    """This process's peak resident set size in MiB (Linux reports ``ru_maxrss`` in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def append_row(path: Path, row: dict) -> None:
    """Append one JSON row to ``path`` at once, so a part killed later keeps its earlier rows,
    and print it to the part's log."""
    with path.open("a") as handle:
        handle.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)


def cuda_state(device: str) -> tuple[bool, str]:
    """Whether ``device`` can run here, and why not."""
    import torch

    if device.startswith("cuda") and not torch.cuda.is_available():
        return False, "CUDA not available (no CUDA device, or a torch built without CUDA)"
    return True, ""


def timed_calls(fn: Callable[[], object], warmup: int, most: int, budget_s: float,
                sync: Callable[[], None]) -> tuple[float, list[float]]:
    """Seconds of ``warmup`` untimed-for-the-median calls (compiles, caches), then the seconds of
    up to ``most`` timed calls, stopping after ``budget_s`` (at least two timed calls)."""
    start = time.perf_counter()
    for _ in range(warmup):
        fn()
    sync()
    first = time.perf_counter() - start
    times: list[float] = []
    begin = time.perf_counter()
    while len(times) < most and (len(times) < 2 or time.perf_counter() - begin < budget_s):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return first, times


def device_tools(device: str) -> tuple[Callable[[], None], Callable[[], float]]:
    """(synchronize, peak GPU MiB since the last call) for ``device``; no-ops on the CPU."""
    import torch

    if not device.startswith("cuda"):
        return (lambda: None), (lambda: float("nan"))
    torch.cuda.reset_peak_memory_stats()

    def peak() -> float:
        value = torch.cuda.max_memory_allocated() / 2**20
        torch.cuda.reset_peak_memory_stats()
        return value

    return torch.cuda.synchronize, peak


def compose(*overrides: str):
    """The ``armeta-train`` config for ``overrides``, composed as the CLI composes it."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from armeta_rl.cli import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        return hydra_compose("train", overrides=list(overrides))


def trainer_for(overrides: Sequence[str]):
    """A seeded trainer of the config ``overrides`` (players built as ``armeta-train`` builds
    them), and its players."""
    from armeta_rl.config import TrainerConfig, validate
    from armeta_rl.trainers.game import GameTrainer
    from armeta_rl.trainers.players import build_players

    cfg = compose(*overrides, "trainer.progress=false", "logger=none")
    players = build_players(validate(cfg))
    trainer = GameTrainer(players.leader, players.principle, TrainerConfig(
        iterations=10**9, meta_batch=cfg.trainer.meta_batch, progress=False))
    return trainer, players


def failure(row: dict, error: BaseException) -> dict:
    """``row`` marked failed with the error's last line; the traceback goes to the log."""
    traceback.print_exc()
    return {**row, "status": "error", "error": f"{type(error).__name__}: {error}"[:500]}


def meta(args: argparse.Namespace) -> None:
    """Time meta-iterations of one benchmark on each device (one row per device)."""
    import torch

    from armeta_rl.allocator import keep_freed_memory

    torch.set_num_threads(1)
    keep_freed_memory()  # as armeta-train does
    out = Path(args.results)
    graphs = ["benchmark.collector.graphs=false"] if args.no_graphs else []
    for device in args.devices:
        variant = ("compiled" if args.compile else "eager") + (
            ", no CUDA graphs" if args.no_graphs else "")
        row = {"part": "meta", "benchmark": args.benchmark, "method": args.method,
               "device": device, "variant": variant}
        ok, reason = cuda_state(device)
        if not ok:
            append_row(out, {**row, "status": "skipped", "reason": reason})
            continue
        try:
            overrides = [f"benchmark={args.benchmark}", f"method={args.method}",
                         f"device={device}", *graphs, *args.overrides]
            if args.compile:
                overrides += COMPILE_OVERRIDES
            sync, gpu_peak = device_tools(device)
            trainer, _ = trainer_for(overrides)
            first, times = timed_calls(trainer.train_iteration, args.warmup, args.iterations,
                                       args.seconds, sync)
            row.update(status="ok", warmup_iterations=args.warmup, warmup_s=first,
                       iterations=len(times), median_ms=1000 * statistics.median(times),
                       min_ms=1000 * min(times), peak_gpu_mib=gpu_peak(),
                       peak_rss_mib=peak_rss_mib())
        except Exception as error:  # one failed row must not stop the others
            row = failure(row, error)
        append_row(out, row)


def ant_overrides(args: argparse.Namespace) -> list[str]:
    """The ant_goal_warp config at the check's sizes, on ``args.device``."""
    return ["benchmark=ant_goal_warp", "method=maml", f"device={args.device}",
            f"benchmark.collector.make_env.warp_device={args.warp_device}",
            f"trainer.meta_batch={args.tasks}", f"benchmark.collector.episodes={args.episodes}",
            f"benchmark.collector.max_steps={args.steps}", *args.overrides]


def physics_seconds(env, steps: int, sync: Callable[[], None]) -> float:
    """Seconds for ``steps`` env steps of ``env``'s physics alone (its batch's ``step``: the
    ``frame_skip`` MuJoCo Warp steps and the forward pass, a CUDA graph replayed, with the same
    synchronization as in the env's step), without the policy or TorchRL: what no change outside
    the physics can undercut, so ``tasks × episodes × steps`` over it bounds the env steps/s."""
    env.sim.step(env.frame_skip)
    sync()
    start = time.perf_counter()
    for _ in range(steps):
        env.sim.step(env.frame_skip)
    sync()
    return time.perf_counter() - start


def ant(args: argparse.Namespace) -> None:
    """The Ant with MuJoCo Warp, in one process, each figure written as soon as it is measured
    (a part killed at its time limit keeps what it measured): a tiny env first (it compiles the
    warp kernels), then env steps/s of one collection of ``tasks × episodes`` worlds with the
    leader's policy acting on the env's device, as training collects (part ``ant-steps``), the
    same env's physics alone (part ``ant-physics``, :func:`physics_seconds`: the ceiling of
    ``ant-steps``), then MAML-TRPO meta-iterations on ant_goal_warp (part ``ant-meta``)."""
    import torch

    from armeta_rl.allocator import keep_freed_memory

    out = Path(args.results)
    size = {"device": args.device, "warp_device": args.warp_device, "tasks": args.tasks,
            "episodes": args.episodes, "steps": args.steps}
    for device in (args.device, args.warp_device):
        ok, reason = cuda_state(device)
        if not ok:
            for part in ("ant-steps", "ant-physics", "ant-meta"):
                append_row(out, {"part": part, **size, "status": "skipped", "reason": reason})
            return
    torch.set_num_threads(1)
    keep_freed_memory()  # as armeta-train does
    sync, gpu_peak = device_tools(args.device)
    row: dict = {"part": "ant-warmup", **size}
    try:
        from armeta_rl.envs.ant_goal_warp import AntGoalWarpEnv

        start = time.perf_counter()
        AntGoalWarpEnv((1, 1), max_steps=2, seed=0, warp_device=args.warp_device).rollout(2)
        sync()
        append_row(out, {**row, "status": "ok", "seconds": time.perf_counter() - start})
        row = {"part": "ant-steps", **size}
        trainer, players = trainer_for(ant_overrides(args))
        leader, collector = players.leader, players.leader.collector
        tasks = players.initial.sample(args.tasks)
        steps = args.tasks * args.episodes * args.steps
        start = time.perf_counter()
        collector.collect(tasks, None, policy=leader.net)
        sync()
        env = collector.env(args.tasks)
        row.update(env=type(env).__name__, env_device=str(env.device),
                   policy_device=str(next(leader.net.parameters()).device),
                   first_collect_s=time.perf_counter() - start)
        times: list[float] = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            collector.collect(tasks, None, policy=leader.net)
            sync()
            times.append(time.perf_counter() - start)
            median = statistics.median(times)
            row.update(status="ok", collects=len(times), median_s=median,
                       steps_per_s=steps / median, peak_gpu_mib=gpu_peak(),
                       peak_rss_mib=peak_rss_mib())
            append_row(out, row)
        row = {"part": "ant-physics", **size}
        seconds = physics_seconds(env, args.steps, sync)
        row.update(status="ok", seconds=seconds, steps_per_s=steps / seconds)
        append_row(out, row)
        row = {"part": "ant-meta", **size}
        start = time.perf_counter()
        trainer.train_iteration()
        sync()
        row["first_iteration_s"] = time.perf_counter() - start
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            trainer.train_iteration()
            sync()
            times.append(time.perf_counter() - start)
            row.update(status="ok", iterations=len(times), median_s=statistics.median(times),
                       min_s=min(times), peak_gpu_mib=gpu_peak(), peak_rss_mib=peak_rss_mib())
            append_row(out, row)
    except Exception as error:
        row = failure(row, error)
        append_row(out, row)


def preflight(args: argparse.Namespace) -> None:
    """Versions, the GPU, and every module the check imports (missing ones in one line)."""
    import importlib

    wanted = ("torch", "torchrl", "tensordict", "normflows", "hydra", "omegaconf", "gymnasium",
              "mujoco", "warp", "mujoco_warp", "tqdm", "matplotlib", "pytest", "numpy",
              "armeta_rl.cli", "hydra_plugins.armeta_run_list")
    found, missing = {}, []
    for name in wanted:
        try:
            module = importlib.import_module(name)
            found[name] = getattr(module, "__version__", "")
        except Exception as error:  # noqa: BLE001 — any import failure is reported, not raised
            missing.append(f"{name} ({type(error).__name__}: {error})"[:200])
    row = {"part": "preflight", "python": sys.version.split()[0], "modules": found,
           "missing": missing, "cpus": os.cpu_count(), "machine": platform.machine(),
           "pythonpath": os.environ.get("PYTHONPATH", "")}
    if "torch" in found:
        import torch

        row["cuda"] = torch.cuda.is_available()
        row["torch_cuda"] = torch.version.cuda
        if row["cuda"]:
            props = torch.cuda.get_device_properties(0)
            row["gpu"] = f"{props.name}, {props.total_memory / 2**30:.0f} GiB"
    smi = shutil.which("nvidia-smi")
    if smi:
        query = subprocess.run([smi, "--query-gpu=name,driver_version,memory.total",
                                "--format=csv,noheader"], capture_output=True, text=True,
                               timeout=30)
        row["nvidia_smi"] = query.stdout.strip() or query.stderr.strip()
    if "warp" in found:
        try:
            import warp

            warp.config.log_level = warp.LOG_WARNING
            warp.init()
            row["warp_devices"] = [str(d) for d in warp.get_devices()]
        except Exception as error:  # noqa: BLE001
            row["warp_devices"] = f"warp.init failed: {error}"
    row["status"] = "ok" if not missing else "missing"
    print(json.dumps(row, indent=1), flush=True)
    if missing:
        print("MISSING MODULES: " + "; ".join(missing), flush=True)
    append_row(Path(args.results), row)


def tests(args: argparse.Namespace) -> None:
    """Run one pytest file (all its tests: the CUDA ones run where CUDA is) and write its counts
    and the failing tests' ids into the results."""
    junit = Path(tempfile.mkdtemp()) / "junit.xml"
    command = [sys.executable, "-m", "pytest", *args.files, "-v", "-rfEs", "-p",
               "no:cacheprovider", f"--junitxml={junit}"]
    start = time.perf_counter()
    code = subprocess.call(command, cwd=ROOT)
    row = {"part": "tests", "name": args.name, "returncode": code,
           "wall_s": time.perf_counter() - start}
    if junit.exists():
        suite = ElementTree.parse(junit).getroot()
        suite = suite if suite.tag == "testsuite" else suite[0]
        counts = {key: int(suite.get(key, 0)) for key in ("tests", "failures", "errors",
                                                           "skipped")}
        failed = [f"{case.get('classname')}::{case.get('name')}" for case in suite.iter("testcase")
                  if case.find("failure") is not None or case.find("error") is not None]
        skipped = sorted({(s.get("message") or "")[:120] for s in suite.iter("skipped")})
        row.update(counts, failed=failed, skip_reasons=skipped)
    row["status"] = "ok" if code == 0 else "failed"
    append_row(Path(args.results), row)


# -- the whole check ----------------------------------------------------------------------------

class Clock:
    """The check's deadline: each part gets its own limit, cut to what the budget has left."""

    def __init__(self, budget_s: float) -> None:
        self.start = time.monotonic()
        self.deadline = self.start + budget_s - REPORT_RESERVE_S

    def left(self) -> float:
        return self.deadline - time.monotonic()

    def limit(self, wanted: float) -> float:
        return min(wanted, self.left())


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of every part: the repository root and benchmarks/ on PYTHONPATH in front
    of what is there (the wheels' --target directory), one OpenMP thread, wandb offline."""
    env = dict(os.environ)
    paths = [str(ROOT), str(BENCHMARKS_DIR), *filter(None, env.get("PYTHONPATH", "").split(":"))]
    env.update(PYTHONPATH=":".join(paths), OMP_NUM_THREADS="1", WANDB_MODE="offline",
               WANDB_SILENT="true", HYDRA_FULL_ERROR="1", PYTHONUNBUFFERED="1")
    env.update(extra or {})
    return env


class Part:
    """One command of the check with its own time limit and log."""

    def __init__(self, name: str, command: list[str], limit_s: float,
                 env: dict[str, str] | None = None) -> None:
        self.name, self.command, self.limit_s = name, command, limit_s
        self.env = child_env(env)
        self.log = Path(tempfile.mkdtemp(prefix="gpu_check_")) / f"{name}.log"
        self.process: subprocess.Popen | None = None
        self.started = self.wall = 0.0
        self.outcome = "not started"

    def start(self, clock: Clock) -> bool:
        limit = clock.limit(self.limit_s)
        if limit < MIN_PART_S:
            self.outcome = f"skipped: {clock.left():.0f} s of the budget left"
            return False
        self.limit_s = limit
        self.started = time.monotonic()
        with self.log.open("w") as handle:
            self.process = subprocess.Popen(self.command, cwd=ROOT, env=self.env, stdout=handle,
                                            stderr=subprocess.STDOUT, start_new_session=True)
        return True

    def wait(self) -> None:
        if self.process is None:
            return
        try:
            code = self.process.wait(timeout=max(1.0, self.started + self.limit_s
                                                 - time.monotonic()))
            self.outcome = "ok" if code == 0 else f"failed (exit code {code})"
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)  # the part and the processes it started
            self.process.wait()
            self.outcome = f"timed out after {self.limit_s:.0f} s"
        self.wall = time.monotonic() - self.started

    def run(self, clock: Clock) -> None:
        if self.start(clock):
            self.wait()

    def append_log(self, log: Path) -> None:
        with log.open("a") as handle:
            handle.write(f"\n===== {self.name}: {self.outcome}, {self.wall:.1f} s\n"
                         f"$ {' '.join(self.command)}\n")
            if self.log.exists():
                handle.write(self.log.read_text(errors="replace"))


def run(args: argparse.Namespace) -> None:
    """The whole check; see the module docstring."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results, log, tests_log = out / "results.jsonl", out / "gpu_check.log", out / "tests.log"
    for path in (results, log, tests_log):
        path.unlink(missing_ok=True)
    clock = Clock(args.budget)
    me = [sys.executable, str(Path(__file__).resolve())]
    res = ["--results", str(results)]
    parts: list[Part] = []

    def part(name: str, command: list[str], limit_s: float, **env: str) -> Part:
        parts.append(Part(name, command, limit_s, env))
        return parts[-1]

    part("preflight", [*me, "preflight", *res], 60).run(clock)
    # The tests run beside the timings, one file after the other, sharing one MuJoCo Warp kernel
    # cache (the warp tests compile the kernels, test_devices' ant_goal_warp run reuses them); the
    # Ant part keeps its own (two processes compiling into one cache could race).
    cache = tempfile.mkdtemp(prefix="warp_tests_")
    background = [
        part("tests-warp", [*me, "tests", "--name", "test_ant_goal_warp", *res,
                            "tests/test_ant_goal_warp.py"], args.tests_limit,
             WARP_CACHE_PATH=cache),
        part("tests-devices", [*me, "tests", "--name", "test_devices", *res,
                               "tests/test_devices.py"], args.tests_limit,
             WARP_CACHE_PATH=cache),
    ]

    def in_order() -> None:
        for test_part in background:
            test_part.run(clock)

    waiters = [threading.Thread(target=in_order)]
    for waiter in waiters:
        waiter.start()
    families = [f for f in FAMILIES if f[0] in (args.benchmarks or DEFAULT_BENCHMARKS)]
    for benchmark, method in families:
        iterations = ["--iterations", str(args.iterations), "--seconds", "5"]
        part(f"meta-{benchmark}", [*me, "meta", *res, "--benchmark", benchmark, "--method",
                                   method, "--devices", "cpu", args.device, *iterations],
             45).run(clock)
    if any(benchmark == "point_nav" for benchmark, _ in families):  # the CUDA graph's gain
        part("meta-point_nav-no-graphs", [*me, "meta", *res, "--benchmark", "point_nav",
                                          "--method", "maml", "--devices", args.device,
                                          "--no-graphs", "--iterations", str(args.iterations),
                                          "--seconds", "5"], 45).run(clock)
    # The Ant last, with whatever the budget has left: it writes each figure as it measures it.
    size = ["--tasks", str(args.ant_tasks), "--episodes", str(args.ant_episodes),
            "--steps", str(args.ant_steps), "--device", args.device,
            "--warp-device", args.warp_device]
    part("ant", [*me, "ant", *res, *size, "--repeats", "2"], 200).run(clock)
    for benchmark, method in families if args.compiled else ():
        if benchmark in COMPILED:
            part(f"compiled-{benchmark}", [*me, "meta", *res, "--benchmark", benchmark,
                                           "--method", method, "--devices", args.device,
                                           "--compile", "--iterations", str(args.iterations),
                                           "--seconds", "5"], 120).run(clock)
    for waiter in waiters:
        waiter.join()
    for item in parts:
        item.append_log(tests_log if item in background else log)
    with results.open("a") as handle:
        for item in parts:
            handle.write(json.dumps({"part": "outcome", "name": item.name,
                                     "outcome": item.outcome, "wall_s": item.wall}) + "\n")
        handle.write(json.dumps({"part": "command", "command": args.command_line}) + "\n")
    report(argparse.Namespace(results=str(results), out=str(out)))


# -- the report ---------------------------------------------------------------------------------

def read_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def fmt(value: float | None, digits: int = 1) -> str:
    if value is None or value != value:  # None or NaN
        return "–"
    return f"{value:,.{digits}f}"


def meta_table(rows: list[dict]) -> str:
    from timing import markdown_table

    table, by_key = [], {}
    for row in rows:
        if row.get("part") == "meta":
            by_key[(row["benchmark"], row["device"], row["variant"])] = row
    for benchmark, method in FAMILIES:
        cpu = by_key.get((benchmark, "cpu", "eager"), {})
        for key, row in by_key.items():
            if key[0] != benchmark:
                continue
            device, variant = key[1], key[2]
            if row.get("status") != "ok":
                why = row.get("reason") or row.get("error", "")
                table.append((benchmark, method, device, variant, "–", "–", "–", "–", "–",
                              f"{row.get('status')}: {why}"))
                continue
            ratio = (cpu["median_ms"] / row["median_ms"]
                     if cpu.get("status") == "ok" and device != "cpu" else None)
            table.append((benchmark, method, device, variant, fmt(row["median_ms"]),
                          fmt(row["min_ms"]), fmt(ratio, 2), fmt(row["warmup_s"]),
                          fmt(row["peak_rss_mib"], 0), fmt(row["peak_gpu_mib"], 0)))
    return markdown_table(("benchmark", "method", "device", "form", "median ms", "min ms",
                           "× CPU", "first iterations s", "peak RSS MiB", "peak GPU MiB"),
                          table)


def report(args: argparse.Namespace) -> None:
    """Write the GPU section of docs/benchmarks.md (and copy the page to the out dir), and print
    and save the summary."""
    from timing import BENCHMARKS_PAGE, markdown_table, write_section

    out, rows = Path(args.out), read_rows(Path(args.results))
    lines = []
    pre = next((r for r in rows if r.get("part") == "preflight"), {})
    machine = (f"{pre.get('gpu', 'no GPU')}, {pre.get('cpus', '?')} CPUs, Python "
               f"{pre.get('python', '?')}, torch {pre.get('modules', {}).get('torch', '?')} "
               f"(CUDA {pre.get('torch_cuda')}), warp devices {pre.get('warp_devices', '–')}")
    lines.append(f"Machine: {machine}.")
    if pre.get("missing"):
        lines.append(f"Missing modules: {'; '.join(pre['missing'])}.")
    test_rows = [r for r in rows if r.get("part") == "tests"]
    test_table = markdown_table(
        ("tests", "result", "passed", "failed", "skipped", "failing tests", "skip reasons"),
        [(r["name"], r["status"],
          r.get("tests", 0) - r.get("failures", 0) - r.get("errors", 0) - r.get("skipped", 0),
          r.get("failures", 0) + r.get("errors", 0), r.get("skipped", 0),
          ", ".join(r.get("failed", [])) or "–", "; ".join(r.get("skip_reasons", [])) or "–")
         for r in test_rows])
    ant_rows = []
    last = {r["part"]: r for r in rows if r.get("part", "").startswith("ant")}
    for part in ("ant-warmup", "ant-steps", "ant-physics", "ant-meta"):
        r = last.get(part)
        if r is None:
            continue
        size = f"{r['tasks']} × {r['episodes']} × {r['steps']}"
        if r.get("status") != "ok":
            ant_rows.append((part, size, "–", "–", "–", "–",
                             f"{r.get('status')}: {r.get('reason') or r.get('error', '')}"))
        elif part == "ant-warmup":
            ant_rows.append((part, "1 × 1 × 2", f"{r['seconds']:.1f} s", "–", "–", "–",
                             "compiles the warp kernels"))
        elif part == "ant-steps":
            ant_rows.append((part, size, f"{r['steps_per_s']:,.0f} env steps/s",
                             f"{r['first_collect_s']:.1f}", fmt(r["peak_rss_mib"], 0),
                             fmt(r["peak_gpu_mib"], 0),
                             f"{r['env']} on {r['env_device']}, policy on {r['policy_device']}, "
                             f"median of {r['collects']} collections ({r['median_s']:.2f} s)"))
        elif part == "ant-physics":
            ant_rows.append((part, size, f"{r['steps_per_s']:,.0f} env steps/s", "–", "–", "–",
                             f"the physics alone ({r['seconds']:.2f} s): the env's step graph "
                             "replayed, no policy, no TorchRL; the ceiling of ant-steps"))
        else:
            ant_rows.append((part, size, f"{r['median_s']:.2f} s / iteration",
                             f"{r['first_iteration_s']:.1f}", fmt(r["peak_rss_mib"], 0),
                             fmt(r["peak_gpu_mib"], 0), f"{r['iterations']} timed"))
    ant_table = markdown_table(("Ant (ant_goal_warp)", "tasks × episodes × steps", "measured",
                                "first call s", "peak RSS MiB", "peak GPU MiB", "notes"),
                               ant_rows)
    from bench_reference import ROWS  # the reference harness's medians

    reference = json.loads(ROWS.read_text()) if ROWS.exists() else {}
    targets = summarize_targets(rows, reference.get("point_robot"))
    parts = [(r["name"], r["outcome"], r["wall_s"]) for r in rows if r.get("part") == "outcome"]
    part_table = markdown_table(("part", "outcome", "wall s"),
                                [(name, outcome, f"{wall:.0f}") for name, outcome, wall in parts])
    body = "\n\n".join([
        " ".join(lines),
        "Targets (one H100-class GPU):\n\n" + "\n".join(f"- {t}" for t in targets),
        test_table, ant_table,
        "Meta-iterations, one torch thread, the CPU and CUDA rows of a benchmark in one process "
        "(its peak RSS covers both; peak GPU memory is `torch.cuda.max_memory_allocated`):\n\n"
        + meta_table(rows),
        "Parts (each in its own process under its own time limit; the test files ran beside the "
        "timings):\n\n" + part_table,
    ])
    command = next((r["command"] for r in reversed(rows) if r.get("part") == "command"),
                   "benchmarks/gpu_check.sh")
    where = (f"{pre.get('machine', '?')}, {pre.get('cpus', '?')} logical CPUs, torch "
             f"{pre.get('modules', {}).get('torch', '?')}, 1 thread") if pre else None
    write_section("gpu_check", "GPU check (gpu_check.sh)", body, command=command, machine=where)
    if out.exists():
        shutil.copy(BENCHMARKS_PAGE, out / "benchmarks.md")
    summary = [f"gpu_check {datetime.datetime.now().isoformat(timespec='seconds')}: {machine}"]
    summary += [f"  part {name}: {outcome} ({wall:.0f} s)" for name, outcome, wall in parts]
    for r in test_rows:
        summary.append(f"  tests {r['name']}: {r['status']}, {r.get('tests', '?')} tests, "
                       f"{r.get('failures', 0) + r.get('errors', 0)} failed, "
                       f"{r.get('skipped', 0)} skipped; failing: {r.get('failed') or '-'}")
    summary += [f"  target: {t}" for t in targets]
    for r in rows:
        if r.get("status") in ("error",):
            summary.append(f"  ERROR {r['part']} {r.get('benchmark', '')} {r.get('device', '')}"
                           f": {r['error']}")
    text = "\n".join(summary)
    print(text)
    if out.exists():
        (out / "summary.txt").write_text(text + "\n")


def summarize_targets(rows: list[dict], point_reference: dict | None) -> list[str]:
    """One line per target of the issue: the figure measured against it, or why there is none.
    A figure measured at other sizes than the target's is given without a verdict.
    ``point_reference`` is the reference harness's point-robot row (``reference_ms``: the median
    pytorch-maml-rl meta-iteration on one CPU core, with its ``date`` and ``machine``)."""
    def ok_row(part: str) -> dict | None:
        found = [r for r in rows if r.get("part") == part and r.get("status") == "ok"]
        return found[-1] if found else None

    def missing(part: str) -> str:
        row = next((r for r in reversed(rows) if r.get("part") == part), None)
        if row is None:
            return "not measured (the part did not finish: see the parts table)"
        return f"not measured ({row['status']}: {row.get('reason') or row.get('error', '')})"

    def verdict(met: bool, row: dict) -> str:
        if any(row.get(key) != value for key, value in ANT.items()):
            return f"at {row['tasks']} × {row['episodes']} × {row['steps']}, not the target's size"
        return "met" if met else "NOT met"

    lines = []
    steps = ok_row("ant-steps")
    target = TARGETS["ant_steps_per_s"]
    physics = ok_row("ant-physics")
    lines.append(f"Ant env steps/s >= {target:,}: " + (
        f"{steps['steps_per_s']:,.0f} ({verdict(steps['steps_per_s'] >= target, steps)})"
        if steps else missing("ant-steps")) + (
        f"; the physics alone: {physics['steps_per_s']:,.0f}" if physics else ""))
    meta_ant = ok_row("ant-meta")
    target = TARGETS["ant_meta_s"]
    lines.append(f"Ant meta-iteration <= {target} s: " + (
        f"{meta_ant['median_s']:.2f} s ({verdict(meta_ant['median_s'] <= target, meta_ant)})"
        if meta_ant else missing("ant-meta")))
    point = {r["device"]: r for r in rows if r.get("part") == "meta"
             and r.get("benchmark") == "point_nav" and r.get("status") == "ok"}
    cuda = [r["median_ms"] / 1000 for device, r in point.items() if device.startswith("cuda")]
    line = f"point robot >= {TARGETS['point_robot_speedup']:.0f}x pytorch-maml-rl's CPU time"
    if point_reference is None:
        line += ": no reference time (run benchmarks/bench_reference.py)"
    elif cuda:
        reference_s, best = point_reference["reference_ms"] / 1000, min(cuda)
        met = reference_s / best >= TARGETS["point_robot_speedup"]
        line += (f" ({reference_s:.2f} s per meta-iteration, bench_reference.py on "
                 f"{point_reference['date']}, {point_reference['machine']}): {best:.3f} s on CUDA, "
                 f"{reference_s / best:.1f}x ({'met' if met else 'NOT met'})")
    else:
        line += ": not measured on CUDA"
    if "cpu" in point:
        line += f"; our CPU row here {point['cpu']['median_ms'] / 1000:.2f} s"
    lines.append(line)
    return lines


# -- command line -------------------------------------------------------------------------------

def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)

    def sub(name: str, fn: Callable[[argparse.Namespace], None], help_: str):
        command = commands.add_parser(name, help=help_)
        command.set_defaults(fn=fn)
        if name not in ("run", "report"):
            command.add_argument("--results", required=True, help="JSON-lines file to append to")
        return command

    everything = sub("run", run, "the whole check (what gpu_check.sh runs)")
    everything.add_argument("--out", default=os.environ.get("OUT") or "/tmp/gpu_check")
    everything.add_argument("--budget", type=float, default=BUDGET_S,
                            help="seconds for the whole check")
    everything.add_argument("--device", default="cuda")
    everything.add_argument("--warp-device", default="cuda")
    everything.add_argument("--iterations", type=int, default=3,
                            help="timed meta-iterations per row (at most)")
    everything.add_argument("--tests-limit", type=float, default=200)
    everything.add_argument("--ant-tasks", type=int, default=ANT["tasks"])
    everything.add_argument("--ant-episodes", type=int, default=ANT["episodes"])
    everything.add_argument("--ant-steps", type=int, default=ANT["steps"])
    everything.add_argument("--benchmarks", nargs="*", default=None,
                            help="the benchmark families timed (default: "
                                 + ", ".join(DEFAULT_BENCHMARKS) + "; all: "
                                 + ", ".join(f for f, _ in FAMILIES) + ")")
    everything.add_argument("--compiled", action="store_true",
                            help="also time " + ", ".join(COMPILED) + " compiled on CUDA (the "
                                 "compile alone took more than 40 s there)")
    everything.add_argument("--command-line", default="benchmarks/gpu_check.sh")

    sub("preflight", preflight, "versions, GPU, importable modules")
    test = sub("tests", tests, "one pytest run")
    test.add_argument("--name", required=True)
    test.add_argument("files", nargs="+")

    timing = sub("meta", meta, "meta-iterations of one benchmark on each device")
    timing.add_argument("--benchmark", required=True)
    timing.add_argument("--method", default="ar_maml")
    timing.add_argument("--devices", nargs="+", default=["cpu", "cuda"])
    timing.add_argument("--compile", action="store_true")
    timing.add_argument("--no-graphs", action="store_true",
                        help="point_nav only: its rollout launched step by step, not replayed "
                             "as a CUDA graph (benchmark.collector.graphs=false)")
    timing.add_argument("--warmup", type=int, default=2)
    timing.add_argument("--iterations", type=int, default=5)
    timing.add_argument("--seconds", type=float, default=8.0,
                        help="stop timing a row after this long (at least 2 iterations)")
    timing.add_argument("--overrides", nargs="*", default=[])

    ant_part = sub("ant", ant, "the Ant on MuJoCo Warp: env steps/s, then meta-iterations")
    ant_part.add_argument("--device", default="cuda")
    ant_part.add_argument("--warp-device", default="cuda")
    ant_part.add_argument("--tasks", type=int, default=ANT["tasks"])
    ant_part.add_argument("--episodes", type=int, default=ANT["episodes"])
    ant_part.add_argument("--steps", type=int, default=ANT["steps"])
    ant_part.add_argument("--repeats", type=int, default=2)
    ant_part.add_argument("--overrides", nargs="*", default=[])

    summary = commands.add_parser("report", help="GPU section and summary from results.jsonl")
    summary.set_defaults(fn=report)
    summary.add_argument("--results", required=True)
    summary.add_argument("--out", default=os.environ.get("OUT") or "/tmp/gpu_check")
    args = parser.parse_args(argv)
    args.fn(args)


if __name__ == "__main__":
    main()
