"""Our meta-iterations against the reference implementations, timed in turns in one session.

The references are the authors' AR-MAML code (github.com/lvyiqin/AR-MAML: Sinusoid-U, Pendulum-U and
Acrobot-U with the paper's protocol) and pytorch-maml-rl (github.com/tristandeleu/pytorch-maml-rl:
the point robot, "2DNavigation-v0", exact MAML-TRPO), each cloned by the user to a path given on
the command line. Neither is edited or copied: each runs its own training loop, unchanged, in a
worker process of its own, with these shims applied at import time only:

* the authors' code: ``logger.Logger``, a module its repository does not ship, as an empty class;
  ``Tensor.cuda`` as the identity where CUDA is absent (its data pipeline calls ``.cuda()``
  unconditionally); its files written to a temporary working directory; its evaluations
  (``eval_init``, ``eval_iter`` on 500 tasks, which its loop runs once, at iteration 0, before
  anything is timed) returning NaN: on the acrobot they fail whenever one of the 500 random
  episodes terminates early (its data collection stacks episodes of unequal length). Its
  training collection has the same defect, so an acrobot run stops if one of its 16 training
  episodes terminates early; seed 0 gets through the timed iterations;
* pytorch-maml-rl: ``torch.lstsq`` (its linear baseline's solver, removed from torch since 1.13)
  as ``torch.linalg.lstsq``, the same least-squares solution;
* both: the method that opens each of their meta-iterations (the adversary's forward pass in
  training, ``Distribution_Adversary.forward(..., train=True)``; ``MultiTaskSampler.sample_tasks``)
  wrapped by a gate that records the time and, after a turn's iterations, reports them and waits
  for the next turn.

Both references need the old ``gym`` API and NumPy < 2 (``np.float_``); give them their own
interpreter with ``--reference-python`` (a venv with torch, ``numpy<2``, ``gym==0.17.3``, scipy,
pyyaml, tqdm). Our side runs ``armeta-train``'s trainer on the corresponding ``*_paper`` benchmark
(point robot: ``point_nav``, MAML-TRPO with exact Hessian-vector products, as pytorch-maml-rl);
the workloads are the lines under ``reference`` in ``benchmarks/workloads.yaml``.

Turn-taking: the workers are started and warmed up (the authors' first iteration includes their
evaluation on 500 tasks, so it is not timed), then each round runs one turn of ``--turn``
iterations in each, the first side rotating from round to round, so that a shared machine's slow
spells fall on all. Each round gives the ratio of the turn medians, in wall time and in CPU time
(user and system, of the worker and of its live child processes: on an overloaded machine the
wall times of two programs stretch unevenly, the CPU time each spends on its own work much
less). One torch thread everywhere; pytorch-maml-rl samples in one worker process
(``--num-workers 1``) beside its learner, as its README runs it. With ``--compiled`` a third
worker takes turns: ours with the workload's compile switches on, its compile in its warm-up.

After the rounds our worker records the matrix products of one more turn and times them replayed
alone (:func:`products_ms`): the part of our meta-iteration that no removal of overhead can take
away, so the reference's median over it is the highest ratio our computation can reach on this
machine; the table states it next to the measured ratio.

Run: ``OMP_NUM_THREADS=1 python benchmarks/bench_reference.py --authors PATH --maml-rl PATH
--reference-python PATH/bin/python [--workloads sinusoid pendulum acrobot point_robot]
[--rounds 5] [--compiled]``; it prints the tables and writes them to its section of
docs/benchmarks.md.
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

from timing import (
    REFERENCE_ROWS,
    as_trained,
    markdown_table,
    peak_rss_mib,
    ratio_cell,
    this_machine,
    trainer_for,
    workloads,
    write_section,
)

HERE = Path(__file__).resolve().parent

WORKLOADS = workloads("reference")
"""Each workload: our (benchmark, method), the reference with its arguments or config, the
iterations of a turn, and the overrides of our compiled form (``--compiled``)."""


# -- workers ------------------------------------------------------------------------------------

CHANNEL: list = []
"""The worker's answers go to its original stdout; whatever the code under test prints goes to
stderr (the worker's log), see :func:`own_stdout`."""


def own_stdout() -> None:
    """Keep file descriptor 1 for the answers and send every print (Python's or a library's) to
    the log instead."""
    CHANNEL.append(os.fdopen(os.dup(1), "w"))
    os.dup2(2, 1)
    sys.stdout = sys.stderr


def reply(message: dict) -> None:
    """One JSON line to the driver."""
    CHANNEL[0].write(json.dumps(message) + "\n")
    CHANNEL[0].flush()


def cpu_seconds() -> float:
    """CPU time of this process and of its live child processes (pytorch-maml-rl samples in
    one), user and system: what the work cost, whatever else shares the machine."""
    total = time.process_time()
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path("/proc/self/task").iterdir():
        children = (task / "children").read_text().split()
        for pid in children:
            try:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            except FileNotFoundError:
                continue
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return total


class Gate:
    """Called at the start of every meta-iteration of a reference's own loop: records the wall
    and CPU time (:func:`cpu_seconds`), and after a turn's iterations reports them to the driver
    and waits for the next command (``run N``, ``profile N`` where the side can answer it, or
    ``quit``). The time spent waiting is not counted."""

    def __init__(self, warmup: int, profile: Callable[[int], dict] | None = None) -> None:
        self.warmup, self.seen, self.profile = warmup, 0, profile
        self.last = (0.0, 0.0)
        self.times: list[float] = []
        self.cpu: list[float] = []
        self.wanted = 0

    def __call__(self) -> None:
        now = (time.perf_counter(), cpu_seconds())
        self.seen += 1
        timing = self.seen > self.warmup + 1
        if timing:
            self.times.append(now[0] - self.last[0])
            self.cpu.append(now[1] - self.last[1])
        if self.seen == self.warmup + 1:
            reply({"ready": True})
            self.wait()
        elif timing and len(self.times) >= self.wanted:
            reply({"times": self.times, "cpu": self.cpu, "peak_rss_mib": peak_rss_mib()})
            self.times, self.cpu = [], []
            self.wait()
        self.last = (time.perf_counter(), cpu_seconds())

    def wait(self) -> None:
        command = sys.stdin.readline().split()
        while command and command[0] == "profile" and self.profile is not None:
            reply(self.profile(int(command[1])))
            command = sys.stdin.readline().split()
        if not command or command[0] == "quit":
            for child in multiprocessing.active_children():  # pytorch-maml-rl's samplers
                child.terminate()
            os._exit(0)  # the references' loops have no clean stop
        self.wanted = int(command[1])


def gated(method: Callable, gate: Gate,
          when: Callable[[dict], bool] = lambda kwargs: True) -> Callable:
    """``method`` passing the gate first on the calls whose keyword arguments satisfy ``when``."""
    def wrapper(*args, **kwargs):
        if when(kwargs):
            gate()
        return method(*args, **kwargs)
    return wrapper


def authors_worker(path: Path, workload: dict) -> None:
    """The authors' ``ar_ml_run`` (AR-MAML, game framework) on ``workload``'s task."""
    import torch

    sys.path.insert(0, str(path))
    logger = types.ModuleType("logger")
    logger.Logger = type("Logger", (), {})  # missing from their repository; an attribute holder
    sys.modules["logger"] = logger
    if not torch.cuda.is_available():
        torch.Tensor.cuda = lambda self, *args, **kwargs: self
    os.chdir(tempfile.mkdtemp(prefix="ar_maml_"))  # they write logs and models to the cwd
    import ar_maml
    import ar_maml_model
    import arguments

    nan = float("nan")
    ar_maml.eval_init = lambda *args, **kwargs: (nan, nan, [nan] * 3)
    ar_maml.eval_iter = lambda *args, **kwargs: (nan, nan, nan, [nan] * 3)

    # The adversary's forward pass with train=True opens each training iteration (its
    # evaluations call it with train=False).
    adversary = ar_maml_model.Distribution_Adversary
    adversary.forward = gated(adversary.forward, Gate(warmup=2),
                              lambda kwargs: kwargs.get("train", False))

    sys.argv = ["main.py", "--ar_maml", "--train", "--run_type", "armaml", "--init_dis",
                "Uniform", "--seed", "0", "--n_iter", str(10**9), *workload["args"]]
    args = arguments.parse_args()
    ar_maml.ar_ml_run(args, log_interval=10**9, dist_interval=1, rerun=True,
                      game_framework=True)


def maml_rl_worker(path: Path, workload: dict) -> None:
    """pytorch-maml-rl's ``train.main`` on the 2D-navigation config, one sampler worker."""
    import torch

    def lstsq(b: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, None]:
        return torch.linalg.lstsq(a, b).solution, None

    torch.lstsq = lstsq  # its sampler processes are forked after this
    sys.path.insert(0, str(path))
    os.chdir(path)
    from maml_rl.samplers import MultiTaskSampler

    gate = Gate(warmup=2)
    MultiTaskSampler.sample_tasks = gated(MultiTaskSampler.sample_tasks, gate)
    import train

    args = argparse.Namespace(config=workload["config"], output_folder=None, seed=0,
                              num_workers=1, device="cpu")
    train.main(args)


def ours_worker(workload: dict, overrides: list[str]) -> None:
    """Our trainer on ``workload``'s benchmark with its defaults (eager) and ``overrides``."""

    as_trained()
    benchmark, method = workload["ours"]
    trainer, _ = trainer_for(f"benchmark={benchmark}", f"method={method}", *overrides)
    gate = Gate(warmup=2, profile=lambda n: {"products_ms": products_ms(trainer, n)})
    while True:
        gate()
        trainer.train_iteration()


PRODUCTS = {"aten::mm": 2, "aten::bmm": 2, "aten::addmm": 3, "aten::baddbmm": 3,
            "aten::addmv": 3, "aten::mv": 2, "aten::dot": 2}
"""The matrix-product kernels and their number of tensor arguments."""


def products_ms(trainer: object, iterations: int) -> float:
    """Milliseconds per meta-iteration that the matrix products of ``iterations`` iterations
    take when replayed alone: every product call is recorded with its operand shapes
    (``torch.profiler``), then each distinct call is timed by itself on fresh contiguous operands
    of those shapes and counted as often as it was called. This is a floor for the computation on
    this machine (the same products at the same sizes, without anything between them), so the
    reference's time over it bounds the ratio any removal of overhead could reach. The profiler's
    own self times are no such floor: recording inflates them (on the point robot fivefold)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as profiler:
        for _ in range(iterations):
            trainer.train_iteration()
    seconds = 0.0
    for event in profiler.key_averages(group_by_input_shape=True):
        if event.key not in PRODUCTS:
            continue
        operands = [torch.randn(shape) for shape in event.input_shapes[:PRODUCTS[event.key]]]
        product = getattr(torch.ops.aten, event.key.split("::")[1])
        for _ in range(3):
            product(*operands)
        repeats = 20
        start = time.perf_counter()
        for _ in range(repeats):
            product(*operands)
        seconds += (time.perf_counter() - start) / repeats * event.count
    return 1000 * seconds / iterations


# -- driver -------------------------------------------------------------------------------------

class Worker:
    """A worker process taking commands on stdin and answering JSON lines on stdout."""

    def __init__(self, command: list[str], log: Path) -> None:
        self.log = log.open("w")
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=self.log, text=True, cwd=HERE.parent,
                                        env={**os.environ, "OMP_NUM_THREADS": "1",
                                             "PYTHONPATH": os.pathsep.join(
                                                 [str(HERE.parent), str(HERE)])})

    def answer(self, timeout: float = 900.0) -> dict:
        ready, _, _ = select.select([self.process.stdout], [], [], timeout)
        if not ready:
            self.process.kill()
            raise RuntimeError(f"worker {self.process.args} silent for {timeout:.0f} s; see "
                               f"{self.log.name}")
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {self.process.args} stopped; see {self.log.name}")
        return json.loads(line)

    def turn(self, iterations: int) -> dict:
        self.process.stdin.write(f"run {iterations}\n")
        self.process.stdin.flush()
        return self.answer()

    def profile(self, iterations: int) -> dict:
        self.process.stdin.write(f"profile {iterations}\n")
        self.process.stdin.flush()
        return self.answer()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.stdin.write("quit\n")
            self.process.stdin.flush()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
        self.log.close()


def compare(name: str, args: argparse.Namespace, logs: Path) -> dict:
    """Rounds of turns between the reference and ours on workload ``name``."""
    workload = WORKLOADS[name]
    me = str(Path(__file__).resolve())
    path = args.authors if workload["reference"] == "authors" else args.maml_rl
    spec = json.dumps(workload)
    workers = {"reference": Worker([args.reference_python, me, "worker", workload["reference"],
                                    spec, "--path", str(path)], logs / f"{name}_reference.log"),
               "ours": Worker([sys.executable, me, "worker", "ours", spec],
                              logs / f"{name}_ours.log")}
    if args.compiled and workload["compiled"]:
        workers["compiled"] = Worker([sys.executable, me, "worker", "ours", spec, "--overrides",
                                      *workload["compiled"]], logs / f"{name}_compiled.log")
    try:
        for worker in workers.values():
            worker.answer(timeout=1800)  # ready: set up and warmed up (compiled)
        turn = args.turn or workload["turn"]
        rounds = []
        for index in range(args.rounds):
            # each side goes first in turn, so that no side always follows the same one
            names = list(workers)
            order = names[index % len(names):] + names[:index % len(names)]
            answers = {side: workers[side].turn(turn) for side in order}
            rounds.append({**{f"{side}_ms": 1000 * statistics.median(answer["times"])
                              for side, answer in answers.items()},
                           **{f"{side}_cpu_ms": 1000 * statistics.median(answer["cpu"])
                              for side, answer in answers.items()},
                           **{f"{side}_rss": answer["peak_rss_mib"]
                              for side, answer in answers.items()},
                           "load": os.getloadavg()[0]})
            print(f"{name} round {index + 1}: " + ", ".join(
                f"{side} {rounds[-1][f'{side}_ms']:.1f} ms" for side in workers), flush=True)
        products = workers["ours"].profile(turn)["products_ms"]
    finally:
        for worker in workers.values():
            worker.stop()
    return {"name": name, "turn": turn, "rounds": rounds, "sides": list(workers),
            "products_ms": products}


def table(result: dict) -> str:
    """A workload's summary line and its table of rounds: each side's wall and CPU ms, and the
    reference's over each of ours."""
    workload, rounds, sides = WORKLOADS[result["name"]], result["rounds"], result["sides"]
    wall = {side: [r[f"{side}_ms"] for r in rounds] for side in sides}
    cpu = {side: [r[f"{side}_cpu_ms"] for r in rounds] for side in sides}
    ours = sides[1:]
    rows = [(i + 1, *(f"{wall[side][i]:.1f} / {cpu[side][i]:.1f}" for side in sides),
             *(f"{wall['reference'][i] / wall[side][i]:.1f}× / "
               f"{cpu['reference'][i] / cpu[side][i]:.1f}×" for side in ours),
             f"{r['load']:.1f}") for i, r in enumerate(rounds)]
    benchmark, method = workload["ours"]
    reference = ("authors' AR-MAML" if workload["reference"] == "authors"
                 else "pytorch-maml-rl")
    summary = "; ".join(f"{side} {ratio_cell(wall['reference'], wall[side], 1)} (CPU time "
                        f"{ratio_cell(cpu['reference'], cpu[side], 1)})" for side in ours)
    rss = ", ".join(f"{side} {rounds[-1][f'{side}_rss']:.0f} MiB" for side in sides)
    ceiling = statistics.median(wall["reference"]) / result["products_ms"]
    head = (f"**{result['name']}**: {reference} against `{benchmark}` `{method}`, "
            f"{result['turn']} iterations a turn; ratio reference ms / ours ms, median over the "
            f"rounds: {summary}; peak RSS: {rss}. Our matrix products alone (replayed, "
            f"`products_ms`) take {result['products_ms']:.1f} ms a meta-iteration: no removal of "
            f"the rest can take ours past **{ceiling:.1f}×** (median reference ms over that).")
    header = ("round", *(f"{side} ms / CPU ms" for side in sides),
              *(f"reference / {side} (wall / CPU)" for side in ours), "load (1 min)")
    return head + "\n\n" + markdown_table(header, rows)


def write_rows(results: list[dict]) -> None:
    """Merge each workload's medians into ``timing.REFERENCE_ROWS``, keeping the other
    workloads' rows."""
    rows = json.loads(REFERENCE_ROWS.read_text()) if REFERENCE_ROWS.exists() else {}
    for result in results:
        rounds = result["rounds"]
        rows[result["name"]] = {
            "date": time.strftime("%Y-%m-%d"), "machine": this_machine(),
            "load": statistics.median(r["load"] for r in rounds),
            **{f"{side}_ms": statistics.median(r[f"{side}_ms"] for r in rounds)
               for side in result["sides"]},
            "products_ms": result["products_ms"]}
    REFERENCE_ROWS.parent.mkdir(parents=True, exist_ok=True)
    REFERENCE_ROWS.write_text(json.dumps(rows, indent=1, sort_keys=True) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command")
    worker = sub.add_parser("worker", help="(internal) one side of a comparison")
    worker.add_argument("side", choices=["ours", "authors", "pytorch-maml-rl"])
    worker.add_argument("workload", type=json.loads, help="its workload, as JSON")
    worker.add_argument("--path", type=Path)
    worker.add_argument("--overrides", nargs="*", default=[])
    parser.add_argument("--authors", type=Path, help="a clone of lvyiqin/AR-MAML")
    parser.add_argument("--maml-rl", type=Path, help="a clone of tristandeleu/pytorch-maml-rl")
    parser.add_argument("--reference-python", default=sys.executable,
                        help="the interpreter of the references (old gym, numpy < 2)")
    parser.add_argument("--workloads", nargs="+", default=list(WORKLOADS), choices=WORKLOADS)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--turn", type=int, default=None,
                        help="iterations per turn (default: per workload)")
    parser.add_argument("--compiled", action="store_true",
                        help="also take turns with our compiled form (regression and system "
                             "identification; its compile is part of the warm-up)")
    args = parser.parse_args()
    if args.command == "worker":
        own_stdout()
        workload = args.workload
        if args.side == "ours":
            ours_worker(workload, args.overrides)
        elif args.side == "authors":
            authors_worker(args.path, workload)
        else:
            maml_rl_worker(args.path, workload)
        return
    needed = {"authors": ("--authors", args.authors),
              "pytorch-maml-rl": ("--maml-rl", args.maml_rl)}
    for name in args.workloads:
        option, path = needed[WORKLOADS[name]["reference"]]
        if path is None or not path.is_dir():
            parser.error(f"{name} needs {option} (a clone of the reference), got {path}")
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
    write_rows(results)
    write_section("bench_reference", "Against the reference implementations "
                  "(bench_reference.py)", body)


if __name__ == "__main__":
    main()
