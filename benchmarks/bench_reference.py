"""Our meta-iterations against the reference implementations, timed in turns in one session.

The references are the authors' AR-MAML code (github.com/lvyiqin/AR-MAML: Sinusoid-U, Pendulum-U and
Acrobot-U with the paper's protocol) and pytorch-maml-rl (github.com/tristandeleu/pytorch-maml-rl:
the point robot, "2DNavigation-v0", exact MAML-TRPO), each cloned by the user to a path given on
the command line. Neither is edited or copied: each runs its own training loop, unchanged, in a
worker process of its own, with these shims applied at import time only:

* the authors' code: ``logger.Logger``, a module its repository does not ship, as an empty class;
  ``Tensor.cuda`` as the identity where CUDA is absent (its data pipeline calls ``.cuda()``
  unconditionally); its files written to a temporary working directory; its evaluations
  (``eval_init``, ``eval_iter`` on 500 tasks, run once, at iteration 0, before anything is timed)
  returning NaN: on the acrobot they fail whenever one of the 500 random episodes terminates
  early (its data collection stacks episodes of unequal length). Its training collection has the
  same defect, so an acrobot run stops if one of its 16 training episodes terminates early; seed 0
  gets through the timed iterations;
* pytorch-maml-rl: ``torch.lstsq`` (its linear baseline's solver, removed from torch since 1.13)
  as ``torch.linalg.lstsq``, the same least-squares solution;
* both: the method that opens each of their meta-iterations (the adversary's forward pass in
  training, ``Distribution_Adversary.forward(..., train=True)``; ``MultiTaskSampler.sample_tasks``)
  wrapped by a :class:`Gate` that records the time and, after a turn's iterations, reports them
  and waits for the next turn.

Both references need the old ``gym`` API and NumPy < 2 (``np.float_``): give them their own
interpreter with ``--reference-python`` (a venv with torch, ``numpy<2``, ``gym==0.17.3``, scipy,
pyyaml, tqdm). Our side runs ``armeta-train``'s trainer on the corresponding ``*_paper`` benchmark
(point robot: ``point_nav``, MAML-TRPO with exact Hessian-vector products, as pytorch-maml-rl);
the workloads are the lines under ``reference`` in ``benchmarks/workloads.yaml``.

The workers warm up (two untimed iterations: the authors' first includes their evaluation), then
take turns (:func:`timing.in_turns`) of ``--turn`` iterations. Each round gives the ratio of the
turn medians, in wall and in CPU time (user and system, of the worker and of its live child
processes: on an overloaded machine two programs' wall times stretch unevenly, their CPU times
much less). One torch thread everywhere; pytorch-maml-rl samples in one worker process beside its
learner, as its README runs it. With ``--compiled`` a third worker takes turns: ours with the
workload's compile switches on. After the rounds our worker's matrix products of one more turn are
replayed alone (:func:`products_ms`): no removal of overhead can take ours below that, so the
reference's median over it is the highest ratio reachable on this machine, stated beside the
measured one.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_reference.py --authors PATH --maml-rl PATH
--reference-python PATH/bin/python [--workloads sinusoid pendulum acrobot point_robot]
[--rounds 5] [--compiled]``; it prints the tables, writes them to its section of
docs/benchmarks.md and the medians to ``timing.REFERENCE_ROWS``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import select
import statistics
import subprocess
import sys
import tempfile
import time
import types
from collections.abc import Callable
from pathlib import Path

import timing

WORKLOADS = timing.workloads("reference")
WARMUP = 2
"""Untimed meta-iterations of every worker before its first turn."""
PRODUCTS = {"aten::mm": 2, "aten::bmm": 2, "aten::addmm": 3, "aten::baddbmm": 3,
            "aten::addmv": 3, "aten::mv": 2, "aten::dot": 2}
"""The matrix-product kernels and their number of tensor arguments."""


# -- workers: one side each, answering the driver with JSON lines on their original stdout ------

def cpu_seconds() -> float:
    """CPU time, user and system, of this process and of its live child processes
    (pytorch-maml-rl samples in one): what the work cost, whatever else shares the machine."""
    total, tick = time.process_time(), os.sysconf("SC_CLK_TCK")
    for task in Path("/proc/self/task").iterdir():
        for pid in (task / "children").read_text().split():
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            except FileNotFoundError:
                continue
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return total


class Gate:
    """Called at the start of every meta-iteration of a side's own loop: records each iteration's
    wall and CPU time and, after the warm-up and after every turn, answers the driver (the turn's
    times) and waits for its next command: ``run N`` or ``profile N`` (where the side can answer
    it); anything else, or the end of stdin, ends the process. The time spent waiting is not
    counted. Whatever the code under test prints
    goes to stderr (the worker's log): file descriptor 1 is kept for the answers."""

    def __init__(self, profile: Callable[[int], dict] | None = None) -> None:
        self.channel = os.fdopen(os.dup(1), "w")
        os.dup2(2, 1)
        sys.stdout = sys.stderr
        self.profile, self.seen, self.wanted = profile, 0, 0
        self.times: list[float] = []
        self.cpu: list[float] = []

    def reply(self, message: dict) -> None:
        self.channel.write(json.dumps(message) + "\n")
        self.channel.flush()

    def __call__(self, *args: object, **kwargs: object) -> None:
        now = (time.perf_counter(), cpu_seconds())
        self.seen += 1
        if self.seen > WARMUP + 1:
            self.times.append(now[0] - self.last[0])
            self.cpu.append(now[1] - self.last[1])
        if self.seen > WARMUP and len(self.times) >= self.wanted:
            self.reply({"times": self.times, "cpu": self.cpu,
                        "peak_rss_mib": timing.peak_rss_mib()})
            self.times, self.cpu = [], []
            command = sys.stdin.readline().split()
            while command[:1] == ["profile"] and self.profile is not None:
                self.reply(self.profile(int(command[1])))
                command = sys.stdin.readline().split()
            if command[:1] != ["run"]:  # the driver is done, or gone
                for child in multiprocessing.active_children():  # pytorch-maml-rl's samplers
                    child.terminate()
                os._exit(0)  # the references' loops have no clean stop
            self.wanted = int(command[1])
        self.last = (time.perf_counter(), cpu_seconds())


def gated(method: Callable, gate: Gate,
          when: Callable[[dict], bool] = lambda kw: True) -> Callable:
    """``method`` passing the gate first on the calls whose keyword arguments satisfy ``when``."""
    def wrapper(*args, **kwargs):
        if when(kwargs):
            gate()
        return method(*args, **kwargs)
    return wrapper


def authors_worker(path: Path, workload: dict) -> None:
    """The authors' ``ar_ml_run`` (AR-MAML, game framework) on ``workload``'s task."""
    import torch

    gate = Gate()
    sys.path.insert(0, str(path))
    sys.modules["logger"] = types.ModuleType("logger")  # missing from their repository
    sys.modules["logger"].Logger = type("Logger", (), {})  # an attribute holder
    if not torch.cuda.is_available():
        torch.Tensor.cuda = lambda self, *args, **kwargs: self
    os.chdir(tempfile.mkdtemp(prefix="ar_maml_"))  # they write logs and models to the cwd
    import ar_maml
    import ar_maml_model
    import arguments

    nan = float("nan")
    ar_maml.eval_init = lambda *args, **kwargs: (nan, nan, [nan] * 3)
    ar_maml.eval_iter = lambda *args, **kwargs: (nan, nan, nan, [nan] * 3)
    adversary = ar_maml_model.Distribution_Adversary  # train=True: a training iteration opens
    adversary.forward = gated(adversary.forward, gate, lambda kw: kw.get("train", False))
    sys.argv = ["main.py", "--ar_maml", "--train", "--run_type", "armaml", "--init_dis",
                "Uniform", "--seed", "0", "--n_iter", str(10**9), *workload["args"]]
    ar_maml.ar_ml_run(arguments.parse_args(), log_interval=10**9, dist_interval=1, rerun=True,
                      game_framework=True)


def maml_rl_worker(path: Path, workload: dict) -> None:
    """pytorch-maml-rl's ``train.main`` on the 2D-navigation config, one sampler worker."""
    import torch

    gate = Gate()
    torch.lstsq = lambda b, a: (torch.linalg.lstsq(a, b).solution, None)  # before its forks
    sys.path.insert(0, str(path))
    os.chdir(path)
    from maml_rl.samplers import MultiTaskSampler

    MultiTaskSampler.sample_tasks = gated(MultiTaskSampler.sample_tasks, gate)
    import train

    train.main(argparse.Namespace(config=workload["config"], output_folder=None, seed=0,
                                  num_workers=1, device="cpu"))


def ours_worker(workload: dict, overrides: list[str]) -> None:
    """Our trainer on ``workload``'s benchmark with its defaults (eager) and ``overrides``."""
    gate = Gate(profile=lambda n: {"products_ms": products_ms(trainer, n)})
    timing.as_trained()
    benchmark, method = workload["ours"]
    trainer, _ = timing.trainer_for(f"benchmark={benchmark}", f"method={method}", *overrides)
    while True:
        gate()
        trainer.train_iteration()


def products_ms(trainer: object, iterations: int) -> float:
    """Milliseconds per meta-iteration that the matrix products of ``iterations`` iterations
    take when replayed alone: every product call is recorded with its operand shapes
    (``torch.profiler``), then each distinct call is timed by itself (:func:`timing.median_s`) on
    fresh contiguous operands of those shapes and counted as often as it was called. A floor for
    the computation on this machine (the same products at the same sizes, nothing between them);
    the profiler's own self times are none: recording inflates them (on the point robot
    fivefold)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as profiler:
        for _ in range(iterations):
            trainer.train_iteration()
    seconds = 0.0
    for event in profiler.key_averages(group_by_input_shape=True):
        if event.key in PRODUCTS:
            operands = [torch.randn(shape) for shape in event.input_shapes[:PRODUCTS[event.key]]]
            product = getattr(torch.ops.aten, event.key.split("::")[1])
            seconds += timing.median_s(lambda p=product, o=operands: p(*o), 20, 3) * event.count
    return 1000 * seconds / iterations


# -- the driver -----------------------------------------------------------------------------------

class Worker:
    """A worker process taking commands on stdin and answering JSON lines on stdout."""

    def __init__(self, python: str, *args: str, log: Path) -> None:
        self.log = log.open("w")
        self.process = subprocess.Popen(
            [python, str(Path(__file__).resolve()), "worker", *args], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self.log, text=True, cwd=timing.ROOT,
            env={**os.environ, "OMP_NUM_THREADS": "1",
                 "PYTHONPATH": os.pathsep.join([str(timing.ROOT), str(Path(__file__).parent)])})

    def ask(self, command: str = "", timeout: float = 900.0) -> dict:
        """Send ``command`` (none: wait for the warm-up's answer) and return the answer."""
        if command:
            self.process.stdin.write(command + "\n")
            self.process.stdin.flush()
        ready, _, _ = select.select([self.process.stdout], [], [], timeout)
        line = self.process.stdout.readline() if ready else ""
        if not line:
            self.process.kill()
            raise RuntimeError(f"worker {self.process.args} stopped or silent for {timeout:.0f} s;"
                               f" see {self.log.name}")
        return json.loads(line)

    def stop(self) -> None:
        """End the worker: its stdin closed (its gate's cue), killed if still there in 30 s."""
        self.process.stdin.close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self.log.close()


def compare(name: str, args: argparse.Namespace, logs: Path) -> dict:
    """Rounds of turns between the reference and ours on workload ``name``: each side's median
    wall and CPU ms of every turn, its last peak RSS, the load of every round."""
    workload, turn = WORKLOADS[name], args.turn or WORKLOADS[name]["turn"]
    path = args.authors if workload["reference"] == "authors" else args.maml_rl
    workers = {"reference": Worker(args.reference_python, workload["reference"], name, str(path),
                                   log=logs / f"{name}_reference.log"),
               "ours": Worker(sys.executable, "ours", name, log=logs / f"{name}_ours.log")}
    if args.compiled and workload["compiled"]:
        workers["compiled"] = Worker(sys.executable, "compiled", name,
                                     log=logs / f"{name}_compiled.log")
    answers: dict[str, list[dict]] = {side: [] for side in workers}

    def one_turn(side: str) -> None:
        answers[side].append(workers[side].ask(f"run {turn}"))
        print(f"{name} {side}: {1000 * statistics.median(answers[side][-1]['times']):.1f} ms",
              flush=True)

    try:
        for worker in workers.values():
            worker.ask(timeout=1800)  # set up and warmed up (compiled)
        _, loads = timing.in_turns({side: lambda side=side: one_turn(side) for side in workers},
                                   calls=1, rounds=args.rounds, warmup=0,
                                   between=lambda: os.getloadavg()[0])
        products = workers["ours"].ask(f"profile {turn}")["products_ms"]
    finally:
        for worker in workers.values():
            worker.stop()
    return {"name": name, "turn": turn, "products_ms": products, "load": loads["reference"],
            **{key: {side: [1000 * statistics.median(a[field]) for a in answers[side]]
                     for side in workers} for key, field in (("wall", "times"), ("cpu", "cpu"))},
            "rss": {side: answers[side][-1]["peak_rss_mib"] for side in workers}}


def table(result: dict) -> str:
    """A workload's summary line and its table of rounds: each side's wall and CPU ms, and the
    reference's over each of ours."""
    wall, cpu, sides = result["wall"], result["cpu"], list(result["wall"])
    ours = sides[1:]
    rows = [(i + 1, *(f"{wall[side][i]:.1f} / {cpu[side][i]:.1f}" for side in sides),
             *(f"{wall['reference'][i] / wall[side][i]:.1f}× / "
               f"{cpu['reference'][i] / cpu[side][i]:.1f}×" for side in ours),
             f"{load:.1f}") for i, load in enumerate(result["load"])]
    workload = WORKLOADS[result["name"]]
    reference = ("authors' AR-MAML" if workload["reference"] == "authors"
                 else "pytorch-maml-rl")
    summary = "; ".join(f"{side} {timing.ratio_cell(wall['reference'], wall[side], 1)} (CPU time "
                        f"{timing.ratio_cell(cpu['reference'], cpu[side], 1)})" for side in ours)
    rss = ", ".join(f"{side} {mib:.0f} MiB" for side, mib in result["rss"].items())
    ceiling = statistics.median(wall["reference"]) / result["products_ms"]
    head = (f"**{result['name']}**: {reference} against `{workload['ours'][0]}` "
            f"`{workload['ours'][1]}`, {result['turn']} iterations a turn; ratio reference ms / "
            f"ours ms, median over the rounds: {summary}; peak RSS: {rss}. Our matrix products "
            f"alone (replayed, `products_ms`) take {result['products_ms']:.1f} ms a "
            f"meta-iteration: no removal of the rest can take ours past **{ceiling:.1f}×** "
            "(median reference ms over that).")
    header = ("round", *(f"{side} ms / CPU ms" for side in sides),
              *(f"reference / {side} (wall / CPU)" for side in ours), "load (1 min)")
    return head + "\n\n" + timing.markdown_table(header, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--authors", type=Path, help="a clone of lvyiqin/AR-MAML")
    parser.add_argument("--maml-rl", type=Path, help="a clone of tristandeleu/pytorch-maml-rl")
    parser.add_argument("--reference-python", default=sys.executable,
                        help="the interpreter of the references (old gym, numpy < 2)")
    parser.add_argument("--workloads", nargs="+", default=list(WORKLOADS), choices=WORKLOADS)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--turn", type=int, help="iterations per turn (default: per workload)")
    parser.add_argument("--compiled", action="store_true",
                        help="also take turns with our compiled form (its compile in the warm-up)")
    if sys.argv[1:2] == ["worker"]:  # (internal) one side: worker SIDE WORKLOAD [PATH]
        side, workload = sys.argv[2], WORKLOADS[sys.argv[3]]
        if side in ("ours", "compiled"):
            ours_worker(workload, workload["compiled"] if side == "compiled" else [])
        else:
            (authors_worker if side == "authors" else maml_rl_worker)(Path(sys.argv[4]), workload)
        return
    args = parser.parse_args()
    for name in args.workloads:
        authors = WORKLOADS[name]["reference"] == "authors"
        path = args.authors if authors else args.maml_rl
        if path is None or not path.is_dir():
            parser.error(f"{name} needs {'--authors' if authors else '--maml-rl'} (a clone of the "
                         f"reference), got {path}")
    if args.rounds < 1:
        parser.error(f"--rounds must be at least 1, got {args.rounds}")
    logs = Path(tempfile.mkdtemp(prefix="bench_reference_"))
    results = [compare(name, args, logs) for name in args.workloads]
    print(f"workers' logs: {logs}")
    body = ("Meta-iterations of the reference implementations and of ours, in turns (module "
            "docstring of `benchmarks/bench_reference.py`), one torch thread each; per round the "
            "median iteration of each side's turn.\n\n"
            + "\n\n".join(table(result) for result in results))
    print(body)
    rows = json.loads(timing.REFERENCE_ROWS.read_text()) if timing.REFERENCE_ROWS.exists() else {}
    rows.update({result["name"]: {
        "date": time.strftime("%Y-%m-%d"), "machine": timing.this_machine(),
        "load": statistics.median(result["load"]), "products_ms": result["products_ms"],
        **{f"{side}_ms": statistics.median(ms) for side, ms in result["wall"].items()}}
        for result in results})
    timing.REFERENCE_ROWS.write_text(json.dumps(rows, indent=1, sort_keys=True) + "\n")
    timing.write_section("bench_reference", "Against the reference implementations "
                         "(bench_reference.py)", body)


if __name__ == "__main__":
    main()
