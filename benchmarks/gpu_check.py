"""The GPU check: the CUDA and MuJoCo Warp tests, meta-iterations of the benchmark families on the
CPU and on CUDA, and the MuJoCo Warp envs' throughput, each workload one line under ``gpu_check``
in ``benchmarks/workloads.yaml``; it writes the ``gpu_check`` section of docs/benchmarks.md, the
machine named.

``benchmarks/gpu_check.sh`` runs it on a lent GPU machine: the repository is the working directory
and is not pip-installed (``armeta_rl`` and ``hydra_plugins`` come from the root on
``PYTHONPATH``, in front of e.g. a ``pip install --target`` directory of carried wheels), there
is no network, and torch with CUDA, pytest, tqdm and matplotlib are preinstalled (the preflight
names any module that is missing). Every part (the preflight, each test file, each workload line)
runs in its own process under its own time limit and never stops the others; the test files run
one after the other beside the timings; all of them stay within ``--budget`` seconds (a part that
would start with too little left is skipped and says so). Everything goes under ``--out``:
``gpu_check.log`` (every part's output), ``tests.log``, ``results.jsonl`` (one JSON row per
measurement), ``summary.txt`` (the parts and the targets) and a copy of docs/benchmarks.md.

Without CUDA the CUDA rows say ``skipped: no CUDA`` and the rest runs. ``--dry-run`` runs every
workload in this process at tiny sizes and lists the test files without running them: the check
of the check, seconds on a CPU machine (``tests/test_gpu_check.py``); ``--warp-device cpu`` runs
the MuJoCo Warp lines on warp's CPU device; ``--only BENCHMARK ...`` runs those lines only.
Timing rows report the peak RSS of their process and, on CUDA, the peak of
``torch.cuda.max_memory_allocated``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
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
from collections.abc import Callable
from pathlib import Path

from timing import (
    BENCHMARKS_PAGE,
    REFERENCE_ROWS,
    ROOT,
    as_trained,
    markdown_table,
    peak_rss_mib,
    trainer_for,
    wall_times,
    workloads,
    write_section,
)

BUDGET_S, REPORT_RESERVE_S, MIN_PART_S = 430, 25, 15
COMPILE_OVERRIDES = ["learner.maml.compile=true", "risk.ar.compile=true"]
TINY = {"tasks": 1, "episodes": 1, "steps": 2}
"""The MuJoCo Warp lines' size in a dry run (meta lines run with ``trainer.meta_batch=2``)."""
WARP_PARTS = ("warp-warmup", "warp-steps", "warp-physics", "warp-meta")


# -- the checks: each appends its rows to ``results`` as soon as it has them --------------------

def append_row(results: Path, row: dict) -> None:
    """Append one JSON row at once (a part killed later keeps it) and print it to the log."""
    with results.open("a") as handle:
        handle.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)


def no_cuda(*devices: str) -> str | None:
    """Why ``devices`` cannot run here, or ``None``."""
    import torch

    if any(device.startswith("cuda") for device in devices) and not torch.cuda.is_available():
        return "no CUDA"
    return None


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


def failure(row: dict, error: BaseException) -> dict:
    """``row`` marked failed with the error's last line; the traceback goes to the log."""
    traceback.print_exc()
    return {**row, "status": "error", "error": f"{type(error).__name__}: {error}"[:500]}


def meta(entry: dict, results: Path) -> None:
    """Meta-iterations of one benchmark on each of the entry's devices, one row per device."""
    as_trained()
    for device in entry["devices"]:
        row = {"part": "meta", "device": device,
               **{key: entry[key] for key in ("benchmark", "method", "variant")}}
        if reason := no_cuda(device):
            append_row(results, {**row, "status": "skipped", "reason": reason})
            continue
        try:
            sync, gpu_peak = device_tools(device)
            trainer, _ = trainer_for(f"benchmark={entry['benchmark']}",
                                     f"method={entry['method']}", f"device={device}",
                                     *entry["overrides"])
            start = time.perf_counter()
            wall_times(trainer.train_iteration, 0, warmup=entry["warmup"], sync=sync)
            first = time.perf_counter() - start
            times = wall_times(trainer.train_iteration, entry["iterations"], warmup=0, sync=sync,
                               budget_s=entry["seconds"])
            row.update(status="ok", warmup_s=first, iterations=len(times),
                       median_ms=1000 * statistics.median(times), min_ms=1000 * min(times),
                       peak_gpu_mib=gpu_peak(), peak_rss_mib=peak_rss_mib())
        except Exception as error:  # one failed row must not stop the others
            row = failure(row, error)
        append_row(results, row)


DEVICE_KEY = "benchmark.collector.make_env.warp_device"
"""Where a Warp benchmark's config takes its warp device (a line's ``device_key`` where else: the
MassVel families build the env under their mass transform)."""


def warp(entry: dict, results: Path) -> None:
    """A MuJoCo Warp benchmark at the entry's size, each figure written as it is measured: a tiny
    collection first (it compiles the warp kernels), the env steps/s of one collection with the
    leader's policy on the env's device (``warp-steps``), the env's physics alone
    (``warp-physics``: its batch's ``sim.step``, the ceiling of ``warp-steps``), then
    meta-iterations (``warp-meta``)."""
    keys = ("benchmark", "device", "warp_device", "tasks", "episodes", "steps")
    size = {key: entry[key] for key in keys}
    if reason := no_cuda(entry["device"], entry["warp_device"]):
        for part in WARP_PARTS:
            append_row(results, {"part": part, **size, "status": "skipped", "reason": reason})
        return
    as_trained()
    sync, gpu_peak = device_tools(entry["device"])

    def built(tasks: int, episodes: int, steps: int):
        return trainer_for(
            f"benchmark={entry['benchmark']}", f"method={entry['method']}",
            f"device={entry['device']}",
            f"{entry.get('device_key', DEVICE_KEY)}={entry['warp_device']}",
            f"trainer.meta_batch={tasks}", f"benchmark.collector.episodes={episodes}",
            f"benchmark.collector.max_steps={steps}", *entry.get("overrides", []))

    def collect(players, tasks) -> Callable[[], object]:
        return lambda: players.leader.collector.collect(tasks, None, policy=players.leader.net)

    row: dict = {"part": "warp-warmup", **size}
    try:
        start = time.perf_counter()
        _, players = built(1, 1, 2)
        wall_times(collect(players, players.initial.sample(1)), 0, sync=sync)
        append_row(results, {**row, "status": "ok", "seconds": time.perf_counter() - start})
        row = {"part": "warp-steps", **size}
        trainer, players = built(entry["tasks"], entry["episodes"], entry["steps"])
        steps = entry["tasks"] * entry["episodes"] * entry["steps"]
        start = time.perf_counter()
        times = wall_times(collect(players, players.initial.sample(entry["tasks"])),
                           entry["repeats"], sync=sync)
        env = players.leader.collector.env(entry["tasks"])
        median = statistics.median(times)
        row.update(status="ok", env=type(env).__name__, env_device=str(env.device),
                   first_call_s=time.perf_counter() - start - sum(times), calls=len(times),
                   median_s=median, steps_per_s=steps / median, peak_gpu_mib=gpu_peak(),
                   peak_rss_mib=peak_rss_mib())
        append_row(results, row)
        row = {"part": "warp-physics", **size}
        physics = statistics.median(wall_times(lambda: [env.sim.step(env.frame_skip)
                                                        for _ in range(entry["steps"])],
                                               1, sync=sync))
        append_row(results, {**row, "status": "ok", "median_s": physics,
                             "steps_per_s": steps / physics})
        row = {"part": "warp-meta", **size}
        start = time.perf_counter()
        times = wall_times(trainer.train_iteration, entry["repeats"], sync=sync)
        row.update(status="ok", first_call_s=time.perf_counter() - start - sum(times),
                   calls=len(times), median_s=statistics.median(times), peak_gpu_mib=gpu_peak(),
                   peak_rss_mib=peak_rss_mib())
        append_row(results, row)
    except Exception as error:
        append_row(results, failure(row, error))


def preflight(entry: dict, results: Path) -> None:
    """Versions, the GPU, and every module the check imports (missing ones in one line)."""
    import importlib

    wanted = ("torch", "torchrl", "tensordict", "normflows", "hydra", "omegaconf", "gymnasium",
              "mujoco", "warp", "mujoco_warp", "tqdm", "matplotlib", "pytest", "numpy",
              "armeta_rl.cli", "hydra_plugins.armeta_run_list")
    found, missing = {}, []
    for name in wanted:
        try:
            found[name] = getattr(importlib.import_module(name), "__version__", "")
        except Exception as error:  # noqa: BLE001 — any import failure is reported, not raised
            missing.append(f"{name} ({type(error).__name__}: {error})"[:200])
    row = {"part": "preflight", "python": sys.version.split()[0], "modules": found,
           "missing": missing, "cpus": os.cpu_count(), "machine": platform.machine(),
           "status": "ok" if not missing else "missing"}
    if "torch" in found:
        import torch

        row.update(cuda=torch.cuda.is_available(), torch_cuda=torch.version.cuda)
        if row["cuda"]:
            props = torch.cuda.get_device_properties(0)
            row["gpu"] = f"{props.name}, {props.total_memory / 2**30:.0f} GiB"
    if smi := shutil.which("nvidia-smi"):
        query = subprocess.run([smi, "--query-gpu=name,driver_version,memory.total",
                                "--format=csv,noheader"], capture_output=True, text=True,
                               timeout=30)
        row["nvidia_smi"] = query.stdout.strip() or query.stderr.strip()
    if "warp" in found:
        try:
            import warp as wp

            wp.config.log_level = wp.LOG_WARNING
            wp.init()
            row["warp_devices"] = [str(d) for d in wp.get_devices()]
        except Exception as error:  # noqa: BLE001
            row["warp_devices"] = f"warp.init failed: {error}"
    append_row(results, row)


def tests(entry: dict, results: Path) -> None:
    """Run one pytest file (its CUDA tests run where CUDA is) and record its counts and the
    failing tests' ids."""
    junit = Path(tempfile.mkdtemp()) / "junit.xml"
    start = time.perf_counter()
    code = subprocess.call([sys.executable, "-m", "pytest", *entry["files"], "-v", "-rfEs", "-p",
                            "no:cacheprovider", f"--junitxml={junit}"], cwd=ROOT)
    row = {"part": "tests", "name": entry["name"], "returncode": code,
           "wall_s": time.perf_counter() - start, "status": "ok" if code == 0 else "failed"}
    if junit.exists():
        suite = ElementTree.parse(junit).getroot()
        suite = suite if suite.tag == "testsuite" else suite[0]
        row.update({key: int(suite.get(key, 0)) for key in ("tests", "failures", "errors",
                                                             "skipped")})
        row["failed"] = [f"{case.get('classname')}::{case.get('name')}"
                         for case in suite.iter("testcase")
                         if case.find("failure") is not None or case.find("error") is not None]
        row["skip_reasons"] = sorted({(s.get("message") or "")[:120]
                                      for s in suite.iter("skipped")})
    append_row(results, row)


CHECKS = {"preflight": preflight, "tests": tests, "meta": meta, "warp": warp}


# -- the plan: one part per test file and per workload line --------------------------------------

def plan(spec: dict, args: argparse.Namespace) -> list[dict]:
    """The parts of the check, in order: each a check's entry with its ``name``, ``kind`` and
    ``limit_s`` (``background``: run beside the others)."""
    tiny, only = args.dry_run, set(args.only or ())
    lines = {kind: [line for line in spec.get(kind, []) if not only or line["benchmark"] in only]
             for kind in ("meta", "warp")}
    timing = {"warmup": 1, "iterations": 1, "seconds": 5} if tiny else {
        "warmup": 2, "iterations": args.iterations, "seconds": 5}

    def meta_part(line: dict, name: str, devices: list[str], variant: str, overrides: list[str],
                  limit_s: float) -> dict:
        return {"kind": "meta", "name": name, "benchmark": line["benchmark"],
                "method": line["method"], "devices": devices, "variant": variant,
                "overrides": overrides + (["trainer.meta_batch=2"] if tiny else []),
                "limit_s": limit_s, **timing}

    parts = [{"kind": "preflight", "name": "preflight", "limit_s": 60}]
    parts += [{"kind": "tests", "name": Path(path).stem, "files": [path], "background": True,
               "limit_s": args.tests_limit} for path in spec.get("tests", [])]
    for line in lines["meta"]:
        name = f"meta-{line['benchmark']}"
        parts.append(meta_part(line, name, ["cpu", args.device], "eager", [], 45))
        if line.get("no_graphs"):  # the CUDA graph's gain
            parts.append(meta_part(line, f"{name}-no-graphs", [args.device],
                                   "eager, no CUDA graphs", ["benchmark.collector.graphs=false"],
                                   45))
    for line in lines["warp"]:
        size = TINY if tiny else {key: line[key] for key in TINY}
        parts.append({"kind": "warp", "name": f"warp-{line['benchmark']}", **line, **size,
                      "device": "cpu" if args.warp_device == "cpu" else args.device,
                      "warp_device": args.warp_device, "repeats": 1 if tiny else 2,
                      "limit_s": 200})
    parts += [meta_part(line, f"compiled-{line['benchmark']}", [args.device], "compiled",
                        COMPILE_OVERRIDES, 120) for line in lines["meta"] if line.get("compiled")]
    return parts


class Part:
    """One part in its own process, under its own time limit (cut to what the budget has left),
    its output appended to ``log``."""

    def __init__(self, entry: dict, results: Path, log: Path) -> None:
        self.entry, self.name, self.log = entry, entry["name"], log
        self.command = [sys.executable, str(Path(__file__).resolve()), "part", "--results",
                        str(results), json.dumps(entry)]
        self.outcome, self.wall = "not started", 0.0

    def run(self, deadline: float) -> None:
        limit = min(self.entry["limit_s"], deadline - time.monotonic())
        if limit < MIN_PART_S:
            self.outcome = f"skipped: {deadline - time.monotonic():.0f} s of the budget left"
            return
        paths = [str(ROOT), str(ROOT / "benchmarks"),
                 *filter(None, os.environ.get("PYTHONPATH", "").split(":"))]
        env = {**os.environ, "PYTHONPATH": ":".join(paths), "OMP_NUM_THREADS": "1",
               "WANDB_MODE": "offline", "WANDB_SILENT": "true", "HYDRA_FULL_ERROR": "1",
               "PYTHONUNBUFFERED": "1", **self.entry.get("env", {})}
        start = time.monotonic()
        with self.log.open("a") as handle:
            handle.write(f"\n===== {self.name}\n$ {' '.join(self.command)}\n")
            handle.flush()
            process = subprocess.Popen(self.command, cwd=ROOT, env=env, stdout=handle,
                                       stderr=subprocess.STDOUT, start_new_session=True)
            try:
                code = process.wait(timeout=limit)
                self.outcome = "ok" if code == 0 else f"failed (exit code {code})"
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)  # the part and the processes it started
                process.wait()
                self.outcome = f"timed out after {limit:.0f} s"
            self.wall = time.monotonic() - start
            handle.write(f"\n===== {self.name}: {self.outcome}, {self.wall:.1f} s\n")


def run(args: argparse.Namespace) -> None:
    """The whole check (module docstring); a dry run runs every part in this process."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results, log, tests_log = out / "results.jsonl", out / "gpu_check.log", out / "tests.log"
    for path in (results, log, tests_log):
        path.unlink(missing_ok=True)
    parts = plan(workloads("gpu_check"), args)
    outcomes = []
    if args.dry_run:
        for entry in parts:
            start = time.monotonic()
            if entry["kind"] == "tests":
                append_row(results, {"part": "tests", "name": entry["name"],
                                     "status": "skipped", "reason": "dry run"})
                outcome = "skipped: dry run"
            else:
                CHECKS[entry["kind"]](entry, results)
                outcome = "ok"
            outcomes.append((entry["name"], outcome, time.monotonic() - start))
    else:
        deadline = time.monotonic() + args.budget - REPORT_RESERVE_S
        # The test files share one MuJoCo Warp kernel cache (the warp tests compile the kernels,
        # test_devices reuses them); the timed warp parts keep their own (two processes compiling
        # into one cache could race).
        cache = {"WARP_CACHE_PATH": tempfile.mkdtemp(prefix="warp_tests_")}
        background = [Part({**entry, "env": cache}, results, tests_log) for entry in parts
                      if entry.get("background")]
        foreground = [Part(entry, results, log) for entry in parts if not entry.get("background")]
        waiter = threading.Thread(target=lambda: [part.run(deadline) for part in background])
        foreground[0].run(deadline)  # the preflight, alone
        waiter.start()
        for part in foreground[1:]:
            part.run(deadline)
        waiter.join()
        outcomes = [(part.name, part.outcome, part.wall) for part in foreground + background]
    with results.open("a") as handle:
        for name, outcome, wall in outcomes:
            handle.write(json.dumps({"part": "outcome", "name": name, "outcome": outcome,
                                     "wall_s": wall}) + "\n")
        handle.write(json.dumps({"part": "command", "command": args.command_line}) + "\n")
    report(results, out, Path(args.page))


# -- the report ---------------------------------------------------------------------------------

def fmt(value: float | None, digits: int = 1) -> str:
    return "–" if value is None or value != value else f"{value:,.{digits}f}"


def why(row: dict) -> str:
    return f"{row.get('status')}: {row.get('reason') or row.get('error', '')}"


def meta_table(rows: list[dict]) -> str:
    """One line per benchmark × device × form, with its ratio to the benchmark's CPU row."""
    by_key = {(r["benchmark"], r["device"], r["variant"]): r for r in rows if r["part"] == "meta"}
    table = []
    for (benchmark, device, variant), row in by_key.items():
        if row["status"] != "ok":
            table.append((benchmark, row["method"], device, variant, *["–"] * 6, why(row)))
            continue
        cpu = by_key.get((benchmark, "cpu", "eager"), {})
        ratio = (cpu["median_ms"] / row["median_ms"]
                 if cpu.get("status") == "ok" and device != "cpu" else None)
        table.append((benchmark, row["method"], device, variant, fmt(row["median_ms"]),
                      fmt(row["min_ms"]), fmt(ratio, 2), fmt(row["warmup_s"]),
                      fmt(row["peak_rss_mib"], 0), fmt(row["peak_gpu_mib"], 0), "–"))
    return markdown_table(("benchmark", "method", "device", "form", "median ms", "min ms",
                           "× CPU", "first iterations s", "peak RSS MiB", "peak GPU MiB",
                           "notes"), table)


def warp_table(rows: list[dict]) -> str:
    """One line per MuJoCo Warp benchmark and part (the last row of each)."""
    last = {(r["benchmark"], r["part"]): r for r in rows if r["part"] in WARP_PARTS}
    table = []
    for (benchmark, part), r in last.items():
        size = f"{r['tasks']} × {r['episodes']} × {r['steps']}"
        if r["status"] != "ok":
            cells = (size, "–", "–", "–", "–", why(r))
        elif part == "warp-warmup":
            cells = ("1 × 1 × 2", f"{r['seconds']:.1f} s", "–", "–", "–",
                     "compiles the warp kernels")
        elif part == "warp-physics":
            cells = (size, f"{r['steps_per_s']:,.0f} env steps/s", "–", "–", "–",
                     f"the physics alone ({r['median_s']:.2f} s): no policy, no TorchRL; the "
                     "ceiling of warp-steps")
        else:
            measured = (f"{r['steps_per_s']:,.0f} env steps/s" if part == "warp-steps"
                        else f"{r['median_s']:.2f} s / iteration")
            notes = (f"{r['env']} on {r['env_device']}, " if part == "warp-steps" else "")
            cells = (size, measured, f"{r['first_call_s']:.1f}", fmt(r["peak_rss_mib"], 0),
                     fmt(r["peak_gpu_mib"], 0),
                     f"{notes}median of {r['calls']} ({r['median_s']:.2f} s)")
        table.append((benchmark, part, *cells))
    return markdown_table(("MuJoCo Warp", "part", "tasks × episodes × steps", "measured",
                           "first call s", "peak RSS MiB", "peak GPU MiB", "notes"), table)


def targets(spec: dict, rows: list[dict]) -> list[str]:
    """One line per target of ``spec``'s lines: the figure measured against it, or why there is
    none; a figure measured at another size than the line's is given without a verdict."""
    def found(part: str, benchmark: str, **match: object) -> tuple[dict | None, str]:
        mine = [r for r in rows if r["part"] == part and r.get("benchmark") == benchmark
                and all(r.get(key) == value for key, value in match.items())]
        ok = [r for r in mine if r["status"] == "ok"]
        if ok:
            return ok[-1], ""
        return None, f"not measured ({why(mine[-1])})" if mine else "not measured"

    lines = []
    for line in spec.get("warp", []):
        name, sized = line["benchmark"], (line["tasks"], line["episodes"], line["steps"])
        for key, part, unit, better in (("target_steps_per_s", "warp-steps", "env steps/s", 1),
                                        ("target_meta_s", "warp-meta", "s / iteration", -1)):
            if key not in line:
                continue
            row, missing = found(part, name)
            if row is not None:
                figure = row["steps_per_s"] if better > 0 else row["median_s"]
                if (row["tasks"], row["episodes"], row["steps"]) != sized:
                    verdict = (f"at {row['tasks']} × {row['episodes']} × {row['steps']}, not "
                               "the target's size")
                else:
                    verdict = "met" if better * (figure - line[key]) >= 0 else "NOT met"
                missing = f"{figure:,.2f} ({verdict})"
            lines.append(f"{name} {'>=' if better > 0 else '<='} {line[key]:,} {unit}: {missing}")
    reference = json.loads(REFERENCE_ROWS.read_text()) if REFERENCE_ROWS.exists() else {}
    for line in spec.get("meta", []):
        if "target_speedup" not in line:
            continue
        name, ours = line["benchmark"], reference.get(line["reference"])
        text = f"{name} >= {line['target_speedup']}x the reference's CPU time"
        cuda = [r["median_ms"] / 1000 for r in rows if r["part"] == "meta" and r["status"] == "ok"
                and r["benchmark"] == name and r["device"].startswith("cuda")]
        if ours is None:
            text += ": no reference time (run benchmarks/bench_reference.py)"
        elif cuda:
            speedup = ours["reference_ms"] / 1000 / min(cuda)
            met = "met" if speedup >= line["target_speedup"] else "NOT met"
            text += (f" ({ours['reference_ms'] / 1000:.2f} s, bench_reference.py on "
                     f"{ours['date']}, {ours['machine']}): {min(cuda):.3f} s on CUDA, "
                     f"{speedup:.1f}x ({met})")
        else:
            text += ": " + found("meta", name, variant="eager", device="cuda")[1]
        lines.append(text)
    return lines


def report(results: Path, out: Path, page: Path = BENCHMARKS_PAGE) -> str:
    """Write the GPU section of ``page`` (copied to ``out``) and the summary; return the
    section's body."""
    rows = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    pre = next((r for r in rows if r["part"] == "preflight"), {})
    torch_version = pre.get("modules", {}).get("torch", "?")
    machine = (f"{pre.get('gpu', 'no GPU')}, {pre.get('cpus', '?')} CPUs, Python "
               f"{pre.get('python', '?')}, torch {torch_version} (CUDA {pre.get('torch_cuda')}), "
               f"warp devices {pre.get('warp_devices', '–')}")
    missing = f" Missing modules: {'; '.join(pre['missing'])}." if pre.get("missing") else ""
    goals = targets(workloads("gpu_check"), rows)
    test_table = markdown_table(
        ("tests", "result", "passed", "failed", "skipped", "failing tests", "skip reasons"),
        [(r["name"], why(r) if r["status"] == "skipped" else r["status"],
          r.get("tests", 0) - r.get("failures", 0) - r.get("errors", 0) - r.get("skipped", 0),
          r.get("failures", 0) + r.get("errors", 0), r.get("skipped", 0),
          ", ".join(r.get("failed", [])) or "–", "; ".join(r.get("skip_reasons", [])) or "–")
         for r in rows if r["part"] == "tests"])
    parts = [(r["name"], r["outcome"], f"{r['wall_s']:.0f}") for r in rows
             if r["part"] == "outcome"]
    body = "\n\n".join([
        f"Machine: {machine}.{missing}",
        "Targets:\n\n" + "\n".join(f"- {goal}" for goal in goals),
        test_table, warp_table(rows),
        "Meta-iterations, one torch thread, the CPU and CUDA rows of a benchmark in one process "
        "(its peak RSS covers both; peak GPU memory is `torch.cuda.max_memory_allocated`):\n\n"
        + meta_table(rows),
        "Parts (each in its own process under its own time limit; the test files ran beside the "
        "timings; a dry run runs them all in one):\n\n"
        + markdown_table(("part", "outcome", "wall s"), parts)])
    command = next(r["command"] for r in rows if r["part"] == "command")
    where = (f"{pre.get('machine', '?')}, {pre.get('cpus', '?')} logical CPUs, torch "
             f"{torch_version}, 1 thread")
    write_section("gpu_check", "GPU check (gpu_check.sh)", body, page, command, where)
    shutil.copy(page, out / "benchmarks.md")
    summary = [f"gpu_check {datetime.datetime.now().isoformat(timespec='seconds')}: {machine}"]
    summary += [f"  part {name}: {outcome} ({wall} s)" for name, outcome, wall in parts]
    summary += [f"  target: {goal}" for goal in goals]
    summary += [f"  ERROR {r['part']} {r.get('benchmark', '')}: {r['error']}" for r in rows
                if r.get("status") == "error"]
    print("\n".join(summary))
    (out / "summary.txt").write_text("\n".join(summary) + "\n")
    return body


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    everything = commands.add_parser("run", help="the whole check (what gpu_check.sh runs)")
    everything.add_argument("--out", default=os.environ.get("OUT") or "/tmp/gpu_check")
    everything.add_argument("--page", default=str(BENCHMARKS_PAGE),
                            help="the page whose gpu_check section is written")
    everything.add_argument("--budget", type=float, default=BUDGET_S,
                            help="seconds for the whole check")
    everything.add_argument("--device", default="cuda")
    everything.add_argument("--warp-device", default="cuda")
    everything.add_argument("--iterations", type=int, default=3,
                            help="timed meta-iterations per row (at most)")
    everything.add_argument("--tests-limit", type=float, default=200)
    everything.add_argument("--only", nargs="*", help="the benchmarks whose lines run")
    everything.add_argument("--dry-run", action="store_true",
                            help="every part in this process, at tiny sizes, tests not run")
    everything.add_argument("--command-line", default="benchmarks/gpu_check.sh")
    part = commands.add_parser("part", help="(internal) one part of the plan")
    part.add_argument("--results", type=Path, required=True)
    part.add_argument("entry", type=json.loads)
    args = parser.parse_args(argv)
    if args.command == "run":
        run(args)
    else:
        CHECKS[args.entry["kind"]](args.entry, args.results)


if __name__ == "__main__":
    main()
