"""The GPU check: the CUDA and MuJoCo Warp tests, meta-iterations of the benchmark families on the
CPU and on CUDA, and the MuJoCo Warp envs' throughput (each workload one line under ``gpu_check``
in ``benchmarks/workloads.yaml``); it writes the ``gpu_check`` section of docs/benchmarks.md.

``benchmarks/gpu_check.sh`` runs it on a lent GPU machine and sets its environment: the repository
root and benchmarks/ on ``PYTHONPATH`` (not pip-installed; in front of e.g. a ``pip install
--target`` directory of carried wheels); no network; torch with CUDA, pytest, tqdm and matplotlib
preinstalled (the preflight names any module that is missing). Every part (the preflight, each
test file, each workload line) runs in its own process under ``timeout``, which ends its process
group, and never stops the others; the test files run one after the other beside the timings; all
stay within ``--budget`` seconds (a part with too little left is skipped and says so). Under
``--out``: ``gpu_check.log`` and ``tests.log`` (the parts' output), ``junit/`` (pytest's
reports), ``results.jsonl`` (one JSON row per measurement), ``summary.txt``, a copy of the page.

Without CUDA the CUDA rows say ``skipped: no CUDA``. ``--dry-run`` runs every workload in this
process at tiny sizes and lists the test files without running them (seconds on a CPU machine:
``tests/test_gpu_check.py``); ``--warp-device cpu`` runs the MuJoCo Warp lines on warp's CPU
device; ``--only BENCHMARK ...`` runs those lines only. Timing rows give their process's peak RSS
and, on CUDA, the peak ``torch.cuda.max_memory_allocated`` over its calls.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import shutil
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

import timing

REPORT_RESERVE_S, MIN_PART_S, TESTS_LIMIT_S = 25, 15, 200
TINY = {"tasks": 1, "episodes": 1, "steps": 2}
"""The MuJoCo Warp lines' size in a dry run (meta lines run with ``trainer.meta_batch=2``)."""
WARP_PARTS = ("warp-warmup", "warp-steps", "warp-physics", "warp-meta")
DEVICE_KEY = "benchmark.collector.make_env.warp_device"
"""Where a Warp benchmark's config takes its warp device (a line's ``device_key`` where else: the
MassVel families build the env under their mass transform)."""
MODULES = ("torch", "torchrl", "tensordict", "normflows", "hydra", "omegaconf", "gymnasium",
           "mujoco", "warp", "mujoco_warp", "tqdm", "matplotlib", "pytest", "numpy",
           "armeta_rl.cli", "hydra_plugins.armeta_run_list")


# -- the checks: each appends its rows to ``results`` as soon as it has them --------------------

def append_row(results: Path, row: dict) -> None:
    """Append one JSON row at once (a part killed later keeps it) and print it to the log."""
    with results.open("a") as handle:
        handle.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)


def no_cuda(*devices: str) -> str | None:
    """Why ``devices`` cannot run here, or ``None``."""
    import torch

    cuda = any(device.startswith("cuda") for device in devices)
    return "no CUDA" if cuda and not torch.cuda.is_available() else None


def measured(fn: Callable[[], object], calls: int, warmup: int, device: str,
             budget_s: float = float("inf")) -> dict:
    """``fn``'s timing (:func:`timing.wall_times`, no call started after ``budget_s`` seconds of
    timed calls): the warm-up's seconds, the calls' median and min, the process's peak RSS and,
    on CUDA, the peak GPU memory allocated over the calls (warm-up included)."""
    import torch

    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    times = timing.wall_times(fn, calls, warmup, budget_s=budget_s,
                              sync=torch.cuda.synchronize if cuda else lambda: None)
    return {"first_call_s": time.perf_counter() - start - sum(times), "calls": len(times),
            "median_s": statistics.median(times), "min_s": min(times),
            "peak_gpu_mib": torch.cuda.max_memory_allocated() / 2**20 if cuda else float("nan"),
            "peak_rss_mib": timing.peak_rss_mib()}


def failure(row: dict, error: BaseException) -> dict:
    """``row`` marked failed with the error's last line; the traceback goes to the log."""
    traceback.print_exc()
    return {**row, "status": "error", "error": f"{type(error).__name__}: {error}"[:500]}


def meta(entry: dict, results: Path) -> None:
    """Meta-iterations of one benchmark on each of the entry's devices, one row per device."""
    timing.as_trained()
    for device in entry["devices"]:
        row = {"part": "meta", "device": device,
               **{key: entry[key] for key in ("benchmark", "method", "variant")}}
        if reason := no_cuda(device):
            append_row(results, {**row, "status": "skipped", "reason": reason})
            continue
        try:
            trainer, _ = timing.trainer_for(f"benchmark={entry['benchmark']}",
                                            f"method={entry['method']}", f"device={device}",
                                            *entry["overrides"])
            row.update(status="ok", **measured(trainer.train_iteration, entry["iterations"],
                                               entry["warmup"], device, budget_s=5))
        except Exception as error:  # one failed row must not stop the others
            row = failure(row, error)
        append_row(results, row)


def warp(entry: dict, results: Path) -> None:
    """A MuJoCo Warp benchmark at the entry's size, each figure written as it is measured: a tiny
    collection first (it compiles the warp kernels), the env steps/s of one collection with the
    leader's policy on the env's device (``warp-steps``), the env's physics alone
    (``warp-physics``: its batch's ``sim.step``, the ceiling of ``warp-steps``), then
    meta-iterations (``warp-meta``)."""
    size = {key: entry[key] for key in ("benchmark", "device", "warp_device", *TINY)}
    if reason := no_cuda(entry["device"], entry["warp_device"]):
        for part in WARP_PARTS:
            append_row(results, {"part": part, **size, "status": "skipped", "reason": reason})
        return
    timing.as_trained()

    def built(tasks: int, episodes: int, steps: int):
        return timing.trainer_for(
            f"benchmark={entry['benchmark']}", f"method={entry['method']}",
            f"device={entry['device']}",
            f"{entry.get('device_key', DEVICE_KEY)}={entry['warp_device']}",
            f"trainer.meta_batch={tasks}", f"benchmark.collector.episodes={episodes}",
            f"benchmark.collector.max_steps={steps}", *entry.get("overrides", []))

    def collect(players, tasks: int) -> Callable[[], object]:
        goals = players.initial.sample(tasks)
        return lambda: players.leader.collector.collect(goals, None, policy=players.leader.net)

    part, steps = "warp-warmup", entry["tasks"] * entry["episodes"] * entry["steps"]
    try:
        start = time.perf_counter()
        _, players = built(1, 1, 2)
        measured(collect(players, 1), 1, 0, entry["device"])
        append_row(results, {"part": part, **size, "status": "ok",
                             "seconds": time.perf_counter() - start})
        part = "warp-steps"
        trainer, players = built(entry["tasks"], entry["episodes"], entry["steps"])
        row = measured(collect(players, entry["tasks"]), entry["repeats"], 1, entry["device"])
        env = players.leader.collector.env(entry["tasks"])
        append_row(results, {"part": part, **size, "status": "ok", **row, "env": type(env).__name__,
                             "env_device": str(env.device), "steps_per_s": steps / row["median_s"]})
        part = "warp-physics"
        row = measured(lambda: [env.sim.step(env.frame_skip) for _ in range(entry["steps"])], 1, 1,
                       entry["device"])
        append_row(results, {"part": part, **size, "status": "ok", "median_s": row["median_s"],
                             "steps_per_s": steps / row["median_s"]})
        part = "warp-meta"
        append_row(results, {"part": part, **size, "status": "ok",
                             **measured(trainer.train_iteration, entry["repeats"], 1,
                                        entry["device"])})
    except Exception as error:
        append_row(results, failure({"part": part, **size}, error))


def preflight(entry: dict, results: Path) -> None:
    """Versions, the GPU, and every module the check imports (missing ones in one line)."""
    import importlib

    found, missing = {}, []
    for name in MODULES:
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
    if shutil.which("nvidia-smi"):  # what the driver sees, where torch sees no GPU
        row["nvidia_smi"] = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total",
             "--format=csv,noheader"], capture_output=True, text=True, timeout=30).stdout.strip()
    if "warp" in found:
        try:
            import warp as wp

            wp.config.log_level = wp.LOG_WARNING
            wp.init()
            row["warp_devices"] = [str(d) for d in wp.get_devices()]
        except Exception as error:  # noqa: BLE001
            row["warp_devices"] = f"warp.init failed: {error}"
    append_row(results, row)


CHECKS = {"preflight": preflight, "meta": meta, "warp": warp}


# -- the plan and the run: one part per test file and per workload line -------------------------

def plan(args: argparse.Namespace) -> list[dict]:
    """The parts of the check, in order: each a check's entry with its ``name``, ``kind`` and
    ``limit_s``."""
    spec, tiny = timing.workloads("gpu_check"), args.dry_run
    lines = {kind: [line for line in spec[kind] if not args.only or line["benchmark"] in args.only]
             for kind in ("meta", "warp")}

    def meta_part(line: dict, name: str, devices: list[str], variant: str,
                  overrides: list[str], limit_s: float) -> dict:
        return {"kind": "meta", "name": name, "benchmark": line["benchmark"],
                "method": line["method"], "devices": devices, "variant": variant,
                "overrides": overrides + (["trainer.meta_batch=2"] if tiny else []),
                "limit_s": limit_s, "warmup": 1 if tiny else 2,
                "iterations": 1 if tiny else args.iterations}

    parts = [{"kind": "preflight", "name": "preflight", "limit_s": 60}]
    parts += [{"kind": "tests", "name": Path(path).stem, "path": path, "limit_s": TESTS_LIMIT_S}
              for path in spec["tests"]]
    for line in lines["meta"]:
        name = f"meta-{line['benchmark']}"
        parts.append(meta_part(line, name, ["cpu", "cuda"], "eager", [], 45))
        if line.get("no_graphs"):  # the CUDA graph's gain
            parts.append(meta_part(line, f"{name}-no-graphs", ["cuda"], "eager, no CUDA graphs",
                                   ["benchmark.collector.graphs=false"], 45))
    parts += [{"kind": "warp", "name": f"warp-{line['benchmark']}", **line,
               **(TINY if tiny else {}), "device": "cpu" if args.warp_device == "cpu" else "cuda",
               "warp_device": args.warp_device, "repeats": 1 if tiny else 2, "limit_s": 200}
              for line in lines["warp"]]
    parts += [meta_part(line, f"compiled-{line['benchmark']}", ["cuda"], "compiled",
                        ["learner.maml.compile=true", "risk.ar.compile=true"], 120)
              for line in lines["meta"] if line.get("compiled")]
    return parts


def bounded(command: list[str], name: str, limit_s: float, deadline: float, log: Path,
            env: dict[str, str]) -> tuple[str, float]:
    """Run ``command`` under ``timeout`` (its limit cut to what the budget has left), its output
    appended to ``log``; return its outcome and wall seconds."""
    limit = min(limit_s, deadline - time.monotonic())
    if limit < MIN_PART_S:
        return f"skipped: {max(0, deadline - time.monotonic()):.0f} s of the budget left", 0.0
    start = time.monotonic()
    with log.open("a") as handle:
        handle.write(f"\n===== {name}\n$ {shlex.join(command)}\n")
        handle.flush()
        code = subprocess.run(["timeout", "-k", "5", f"{limit:.0f}", *command], cwd=timing.ROOT,
                              env={**os.environ, **env}, stdout=handle,
                              stderr=subprocess.STDOUT).returncode
        outcome = ("ok" if code == 0 else f"timed out after {limit:.0f} s" if code in (124, 137)
                   else f"failed (exit code {code})")
        handle.write(f"\n===== {name}: {outcome}, {time.monotonic() - start:.1f} s\n")
    return outcome, time.monotonic() - start


def run(args: argparse.Namespace) -> None:
    """The whole check (module docstring); a dry run runs every part in this process."""
    out = Path(args.out)
    shutil.rmtree(out / "junit", ignore_errors=True)
    (out / "junit").mkdir(parents=True)
    results = out / "results.jsonl"
    for path in (results, out / "gpu_check.log", out / "tests.log"):
        path.unlink(missing_ok=True)
    parts = plan(args)
    outcomes: dict[str, tuple[str, float]] = {}
    if args.dry_run:
        for part in parts:
            start = time.monotonic()
            if part["kind"] != "tests":
                CHECKS[part["kind"]](part, results)
            outcomes[part["name"]] = ("skipped: dry run" if part["kind"] == "tests" else "ok",
                                      time.monotonic() - start)
    else:
        deadline = time.monotonic() + args.budget - REPORT_RESERVE_S
        # The test files share one MuJoCo Warp kernel cache (the warp tests compile the kernels,
        # test_devices reuses them); the timed warp parts keep their own (two processes compiling
        # into one cache could race).
        cache = {"WARP_CACHE_PATH": tempfile.mkdtemp(prefix="warp_tests_")}

        def run_all(chosen: list[dict], log: Path, env: dict[str, str]) -> None:
            for part in chosen:
                command = ([sys.executable, "-m", "pytest", part["path"], "-v", "-rfEs", "-p",
                            "no:cacheprovider", f"--junitxml={out}/junit/{part['name']}.xml"]
                           if part["kind"] == "tests" else
                           [sys.executable, str(Path(__file__).resolve()), "part", str(results),
                            json.dumps(part)])
                outcomes[part["name"]] = bounded(command, part["name"], part["limit_s"],
                                                 deadline, log, env)

        tests = [part for part in parts if part["kind"] == "tests"]
        timings = [part for part in parts if part["kind"] != "tests"]
        run_all(timings[:1], out / "gpu_check.log", {})  # the preflight, alone
        beside = threading.Thread(target=run_all, args=(tests, out / "tests.log", cache))
        beside.start()
        run_all(timings[1:], out / "gpu_check.log", {})
        beside.join()
    for part in parts:
        outcome, wall = outcomes[part["name"]]
        append_row(results, {"part": "outcome", "name": part["name"], "outcome": outcome,
                             "wall_s": wall})
    append_row(results, {"part": "command", "command": args.command_line})
    report(results, out, Path(args.page))


# -- the report ---------------------------------------------------------------------------------

def fmt(value: float | None, digits: int = 1) -> str:
    return "–" if value is None or value != value else f"{value:,.{digits}f}"


def why(row: dict) -> str:
    return f"{row.get('status')}: {row.get('reason') or row.get('error', '')}"


def test_row(name: str, outcome: str, junit: Path) -> tuple:
    """A test file's line: its outcome, and its counts, failing tests and skip reasons from
    pytest's JUnit report."""
    if not junit.exists():
        return name, outcome, 0, 0, 0, "–", "–"
    suite = next(ElementTree.parse(junit).getroot().iter("testsuite"))
    count = {key: int(suite.get(key, 0)) for key in ("tests", "failures", "errors", "skipped")}
    failed = [f"{case.get('classname')}::{case.get('name')}" for case in suite.iter("testcase")
              if case.find("failure") is not None or case.find("error") is not None]
    reasons = sorted({(skip.get("message") or "")[:120] for skip in suite.iter("skipped")})
    return (name, outcome, count["tests"] - count["failures"] - count["errors"] - count["skipped"],
            count["failures"] + count["errors"], count["skipped"], ", ".join(failed) or "–",
            "; ".join(reasons) or "–")


def meta_table(rows: list[dict]) -> str:
    """One line per benchmark × device × form, with its ratio to the benchmark's CPU row."""
    by_key = {(r["benchmark"], r["device"], r["variant"]): r for r in rows if r["part"] == "meta"}
    table = []
    for (benchmark, device, variant), row in by_key.items():
        cells = ["–"] * 6 + [why(row)]
        if row["status"] == "ok":
            cpu = by_key.get((benchmark, "cpu", "eager"), {})
            ratio = (cpu["median_s"] / row["median_s"]
                     if cpu.get("status") == "ok" and device != "cpu" else None)
            cells = [fmt(1000 * row["median_s"]), fmt(1000 * row["min_s"]), fmt(ratio, 2),
                     fmt(row["first_call_s"]), fmt(row["peak_rss_mib"], 0),
                     fmt(row["peak_gpu_mib"], 0), "–"]
        table.append((benchmark, row["method"], device, variant, *cells))
    return timing.markdown_table(("benchmark", "method", "device", "form", "median ms", "min ms",
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
            steps = part == "warp-steps"
            cells = (size, f"{r['steps_per_s']:,.0f} env steps/s" if steps
                     else f"{r['median_s']:.2f} s / iteration", f"{r['first_call_s']:.1f}",
                     fmt(r["peak_rss_mib"], 0), fmt(r["peak_gpu_mib"], 0),
                     (f"{r['env']} on {r['env_device']}, " if steps else "")
                     + f"median of {r['calls']} ({r['median_s']:.2f} s)")
        table.append((benchmark, part, *cells))
    return timing.markdown_table(("MuJoCo Warp", "part", "tasks × episodes × steps", "measured",
                                  "first call s", "peak RSS MiB", "peak GPU MiB", "notes"), table)


def targets(spec: dict, rows: list[dict]) -> list[str]:
    """One line per target of ``spec``'s lines: the figure measured against it, or why there is
    none; a figure measured at another size than the line's is given without a verdict."""
    def found(part: str, benchmark: str, **match: object) -> tuple[list[dict], str]:
        """The ok rows of ``part`` on ``benchmark`` matching ``match``, and why there is none."""
        mine = [r for r in rows if r["part"] == part and r.get("benchmark") == benchmark
                and all(r.get(key) == value for key, value in match.items())]
        return ([r for r in mine if r["status"] == "ok"],
                f"not measured ({why(mine[-1])})" if mine else "not measured")

    lines = []
    for line in spec["warp"]:
        for key, part, field, unit, better in (
                ("target_steps_per_s", "warp-steps", "steps_per_s", "env steps/s", 1),
                ("target_meta_s", "warp-meta", "median_s", "s / iteration", -1)):
            if key not in line:
                continue
            ok, text = found(part, line["benchmark"])
            if ok:
                size = (ok[-1]["tasks"], ok[-1]["episodes"], ok[-1]["steps"])
                verdict = (("met" if better * (ok[-1][field] - line[key]) >= 0 else "NOT met")
                           if size == (line["tasks"], line["episodes"], line["steps"]) else
                           f"at {' × '.join(map(str, size))}, not the target's size")
                text = f"{ok[-1][field]:,.2f} ({verdict})"
            lines.append(f"{line['benchmark']} {'>=' if better > 0 else '<='} {line[key]:,} "
                         f"{unit}: {text}")
    rows_json = timing.REFERENCE_ROWS
    reference = json.loads(rows_json.read_text()) if rows_json.exists() else {}
    for line in (line for line in spec["meta"] if "target_speedup" in line):
        name, ours = line["benchmark"], reference.get(line["reference"])
        cuda = [r["median_s"] for r in rows if r["part"] == "meta" and r["status"] == "ok"
                and r["benchmark"] == name and r["device"].startswith("cuda")]
        text = f"{name} >= {line['target_speedup']}x the reference's CPU time"
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


def report(results: Path, out: Path, page: Path = timing.BENCHMARKS_PAGE) -> str:
    """Write the GPU section of ``page`` (copied to ``out``) and the summary; return the
    section's body."""
    rows = [json.loads(line) for line in results.read_text().splitlines() if line.strip()]
    pre = next((r for r in rows if r["part"] == "preflight"), {})
    torch_version = pre.get("modules", {}).get("torch", "?")
    machine = (f"{pre.get('gpu', 'no GPU')}, {pre.get('cpus', '?')} CPUs, Python "
               f"{pre.get('python', '?')}, torch {torch_version} (CUDA {pre.get('torch_cuda')}), "
               f"warp devices {pre.get('warp_devices', '–')}")
    missing = f" Missing modules: {'; '.join(pre['missing'])}." if pre.get("missing") else ""
    spec = timing.workloads("gpu_check")
    goals = targets(spec, rows)
    parts = [(r["name"], r["outcome"], f"{r['wall_s']:.0f}") for r in rows
             if r["part"] == "outcome"]
    tested = {Path(path).stem for path in spec["tests"]}
    body = "\n\n".join([
        f"Machine: {machine}.{missing}",
        "Targets:\n\n" + "\n".join(f"- {goal}" for goal in goals),
        timing.markdown_table(("tests", "result", "passed", "failed", "skipped", "failing tests",
                               "skip reasons"),
                              [test_row(name, outcome, out / "junit" / f"{name}.xml")
                               for name, outcome, _ in parts if name in tested]),
        warp_table(rows),
        "Meta-iterations, one torch thread, the CPU and CUDA rows of a benchmark in one process "
        "(its peak RSS covers both; peak GPU memory is `torch.cuda.max_memory_allocated`):\n\n"
        + meta_table(rows),
        "Parts (each in its own process under its own time limit; the test files ran beside the "
        "timings; a dry run runs them all in one):\n\n"
        + timing.markdown_table(("part", "outcome", "wall s"), parts)])
    command = next(r["command"] for r in rows if r["part"] == "command")
    where = (f"{pre.get('machine', '?')}, {pre.get('cpus', '?')} logical CPUs, torch "
             f"{torch_version}, 1 thread")
    timing.write_section("gpu_check", "GPU check (gpu_check.sh)", body, page, command, where)
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
    """``run [option ...]``: the whole check (what gpu_check.sh runs); ``part RESULTS ENTRY``
    (internal): one part of the plan, its rows appended to ``RESULTS``."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["part"]:
        entry = json.loads(argv[2])
        CHECKS[entry["kind"]](entry, Path(argv[1]))
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("command", choices=["run"])
    parser.add_argument("--out", default=os.environ.get("OUT") or "/tmp/gpu_check")
    parser.add_argument("--page", default=str(timing.BENCHMARKS_PAGE),
                        help="the page whose gpu_check section is written")
    parser.add_argument("--budget", type=float, default=430, help="seconds for the whole check")
    parser.add_argument("--warp-device", default="cuda")
    parser.add_argument("--iterations", type=int, default=3,
                        help="timed meta-iterations per row (at most)")
    parser.add_argument("--only", nargs="*", help="the benchmarks whose lines run")
    parser.add_argument("--dry-run", action="store_true",
                        help="every part in this process, at tiny sizes, tests not run")
    parser.add_argument("--command-line", default="benchmarks/gpu_check.sh")
    run(parser.parse_args(argv))


if __name__ == "__main__":
    main()
