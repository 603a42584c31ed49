"""``armeta-reproduce <experiment> [profile=quick|paper|paper_ray|paper_warp|tiny]
[benchmarks=a,b] [seeds=0,1] [results=DIR] [launcher=local|basic|ray|slurm|none] [jobs=N]
[pack=true [adopt=true]] [hydra.launcher.…=…] [+train.<key>=<value>]``: one artefact of the
paper.

It trains the experiment's runs (one ``armeta-train`` multirun), then its attack runs against the
finished ones (a second), scores them on the adversaries (one ``armeta-eval`` multirun) and
aggregates everything into ``<experiment>.csv``, ``<experiment>.md`` and PNG figures in the
results directory (default ``results/<experiment>``).
Runs that have their ``eval.json`` (evaluations: their report) are skipped, and a run that was
interrupted resumes from its last checkpoint (from the start if it wrote none), so running the
same command again continues a sweep.
``benchmarks=`` and ``seeds=`` restrict the experiment to some of its benchmarks and seeds (the
report keeps the other benchmarks' finished runs), ``launcher=none`` only aggregates, ``hydra.*``
and ``hydra/<group>=`` arguments go to both multiruns (launcher settings) and
``+train.<key>=<value>`` is appended to every training run's overrides.
``pack=true`` packs the reports the plan accepts, with their runs' configs, into
``reports.jsonl.gz`` and ``configs.jsonl.gz``; the report is then rebuilt from those files alone
where the run directories are gone (``launcher=none``), and runs packed there are never run
again. ``adopt=true`` packs reports written before reports recorded their run too, recording it.
A sweep that leaves runs missing exits 1 and names each on stderr with why.
"""

from __future__ import annotations

import copy
import os
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import NoReturn

from omegaconf import OmegaConf

from armeta_rl.config import CONFIG_BYTES
from armeta_rl.errors import ConfigError
from armeta_rl.preemption import listening
from armeta_rl.reproduce import experiment_names, figures, help_text
from armeta_rl.reproduce.aggregate import (
    INITIAL,
    collect,
    display,
    finished_reports,
    lost_checkpoints,
    progress_note,
    train_seconds,
    write_csv,
)
from armeta_rl.reproduce.curves import collect_curves, curves_path, read_curves, write_curves
from armeta_rl.reproduce.launch import (
    LAUNCHERS,
    check_ray_address,
    eval_job,
    launch,
    launcher_overrides,
    ray_address,
    train_job,
)
from armeta_rl.reproduce.packed import (
    CONFIGS_FILE,
    NOTHING_PACKED,
    REPORTS_FILE,
    Packed,
    read_packed,
)
from armeta_rl.reproduce.packed import pack as pack_runs
from armeta_rl.reproduce.plan import (
    EvalJob,
    Plan,
    TrainRun,
    composed,
    finished,
    make_plan,
    packable,
    report_path,
    report_problem,
    run_command,
)
from armeta_rl.reproduce.reports import LAYOUTS, late_trend, learner_label
from armeta_rl.run_files import FileRefused, plain_yaml, read_text
from armeta_rl.trainers.run_dir import (
    check_contents,
    staged_leftovers,
    write_text_atomically,
)

PROG = "armeta-reproduce"
MANIFEST = "reproduce.yaml"
OPTIONS = ("profile", "benchmarks", "seeds", "results", "launcher", "jobs", "pack", "adopt")
MISSING_SHOWN = 20
"""The most missing runs and evaluations a partial sweep names on stderr, each with why."""
DEFAULT_STOP_SIGNALS = ("SIGTERM", "SIGUSR1")
"""The signals (besides SIGINT) on which a sweep stops: its runs in flight finish their
iteration and checkpoint, no further job starts, and the command exits 75 (SIGINT: 130)."""


def _fail(message: str) -> NoReturn:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    sys.exit(2)


def claim(results: Path, plan: Plan, extra: tuple[str, ...]) -> dict:
    """The results directory's manifest (a new one for a new directory; nothing is written). A
    path that is a file or cannot be written, a manifest that cannot be read, a directory of
    another experiment (unless the plan shares its runs: ``shares_runs_with``), another profile
    or other ``+train.`` overrides of keys that change a result (one of
    :data:`~armeta_rl.cli.jobs.NO_RESULT_KEYS`, such as how often the runs checkpointed, may be
    left out or differ), or a non-empty directory without a manifest, is refused."""
    from armeta_rl.trainers.run_dir import check_run_dir

    check_run_dir(results, "results")
    path = results / MANIFEST
    if path.exists() or path.is_symlink():
        manifest = read_manifest(results)
        allowed = {plan.experiment, *plan.spec.get("shares_runs_with", [])}
        if manifest["experiment"] not in allowed:
            raise ConfigError("results", str(results),
                              f"holds the runs of experiment {manifest['experiment']}, not "
                              f"{plan.experiment}: choose another results directory")
        if manifest["profile"] != plan.profile or (
                _changing_results(manifest["train"]) != _changing_results(extra)):
            raise ConfigError("results", str(results),
                              f"holds profile {manifest['profile']} with +train overrides "
                              f"{manifest['train']}: choose another results directory")
        return manifest
    if results.is_dir() and any(results.iterdir()):
        raise ConfigError("results", str(results),
                          f"is not empty and has no {MANIFEST}: not an {PROG} results directory")
    return {"experiment": plan.experiment, "profile": plan.profile, "train": list(extra),
            "wall_seconds": {}}


def _changing_results(train: list[str] | tuple[str, ...]) -> list[str]:
    """The ``+train.`` overrides of ``train`` whose keys change a result (not one of
    :data:`~armeta_rl.cli.jobs.NO_RESULT_KEYS`)."""
    from armeta_rl.cli.jobs import NO_RESULT_KEYS

    return [o for o in train if o.split("=", 1)[0].lstrip("+") not in NO_RESULT_KEYS]


def read_manifest(results: Path) -> dict:
    """The results directory's ``reproduce.yaml``; :class:`ConfigError` naming ``results`` when
    it cannot be read or lacks its keys."""
    import yaml

    path = results / MANIFEST
    try:
        text = plain_yaml(read_text(path, CONFIG_BYTES, results), path)
        manifest = OmegaConf.to_container(OmegaConf.create(text))
    except FileRefused as error:
        raise ConfigError("results", str(results), f"its {MANIFEST} {error.reason}: delete "
                          "it to start the directory's manifest again") from None
    except (OSError, yaml.YAMLError, ValueError) as error:
        raise ConfigError("results", str(results), f"its {MANIFEST} cannot be read "
                          f"({' '.join(str(error).split())[:120]}): delete it to start the "
                          "directory's manifest again") from None
    keys = {"experiment": str, "profile": str, "train": list, "wall_seconds": dict}
    if not isinstance(manifest, dict) or any(
            not isinstance(manifest.get(k), kind) for k, kind in keys.items()):
        raise ConfigError("results", str(results),
                          f"its {MANIFEST} is not a manifest (it needs {', '.join(keys)}): "
                          "delete it to start the directory's manifest again")
    return manifest


def save_manifest(results: Path, manifest: dict) -> None:
    """Write ``manifest`` as the results directory's ``reproduce.yaml`` atomically (a kill
    leaves the old file or the new one)."""
    write_text_atomically(results / MANIFEST, OmegaConf.to_yaml(OmegaConf.create(manifest)))


class SweepClock:
    """Time an invocation's sweeps and keep the running total in the results manifest.

    Inside the ``with`` block a thread writes, every ``every`` seconds, ``manifest`` with
    ``wall_seconds[experiment]`` = its value before the block + the time so far. A sweep killed
    mid-batch (a preempted job, a session's end) so keeps its wall time up to the last write,
    where counting only at the end would lose the whole invocation. ``manifest`` itself is not
    changed: :attr:`seconds` is the block's time, for the caller's final manifest.
    """

    def __init__(self, results: Path, manifest: dict, experiment: str,
                 every: float = 60.0) -> None:
        self.results = results
        self.manifest = copy.deepcopy(manifest)
        self.before = self.manifest["wall_seconds"].get(experiment, 0.0)
        self.experiment = experiment
        self.every = every
        self.started = 0.0
        self.ended: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._keep, name="sweep-clock", daemon=True)

    @property
    def seconds(self) -> float:
        """The time inside the block (so far, while it runs)."""
        return (self.ended if self.ended is not None else time.time()) - self.started

    def _keep(self) -> None:
        while not self._stop.wait(self.every):
            self.manifest["wall_seconds"][self.experiment] = self.before + self.seconds
            save_manifest(self.results, self.manifest)

    def __enter__(self) -> SweepClock:
        self.started = time.time()
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.ended = time.time()
        self._stop.set()
        self._thread.join()


def check_runs(plan: Plan) -> None:
    """Compose and check the config of every distinct run (seeds aside) before launching, so a
    bad override in an experiment's YAML fails with one line instead of in every job; with
    ``shifts:`` in the YAML, each run's benchmark must have those shifts in its suite."""
    from armeta_rl.cli.compose import checked
    from armeta_rl.factory import build_space
    from armeta_rl.tasks.shifts import suite_shifts

    distinct = {run_command(run): run.target is not None for run in (*plan.runs, *plan.attacks)}
    for command, attack in distinct.items():
        config = checked(composed(command))
        benchmark = config.benchmark
        if plan.spec.get("shifts") is not None and not attack:
            suite_shifts(build_space(benchmark.space), benchmark.shift_suite, benchmark.name,
                         plan.spec["shifts"])
        if attack and config.method.risk != "ar":
            raise ConfigError("attacks", config.method.name,
                              "an attack trains a flow adversary: allowed: the ar_* methods")


def run_times(records: list[dict]) -> str:
    """``; a training run: <benchmark> <minutes>, …`` (the mean wall time of a benchmark's runs,
    :func:`~armeta_rl.reproduce.aggregate.train_seconds`: the pauses of a resumed run left out
    where its log is at hand; measured as they ran: parallel jobs share the cores)."""
    times: dict[str, list[float]] = {}
    for record in records:
        if record["distribution"] == INITIAL and not record["noisy"] and record["train_seconds"]:
            times.setdefault(record["benchmark"], []).append(record["train_seconds"])
    if not times:
        return ""
    return "; a training run: " + ", ".join(
        f"{display(b)} {sum(t) / len(t) / 60:.1f} min" for b, t in times.items())


def machines(records: list[dict], attack_reports: Iterable[dict] = ()) -> str:
    """`` Training machines: <machine> (<n> runs), …, not recorded (<n> runs).`` over the
    finished runs, the learners' (their p0 records) and the attack runs' (their reports)
    (:func:`~armeta_rl.devices.machine_name`: one seed's numbers differ between processors), or
    nothing when no run's report records one."""
    names = [record.get("machine", "not recorded") for record in records
             if record["distribution"] == INITIAL and not record["noisy"]]
    names += [report.get("machine", "not recorded") for report in attack_reports]
    counts = Counter(names)  # in first-seen order
    if set(counts) <= {"not recorded"}:
        return ""
    return " Training machines: " + ", ".join(
        f"{name} ({n} run{'s' if n > 1 else ''})" for name, n in counts.items()) + "."


def write_report(plan: Plan, results: Path, wall_seconds: float,
                 seconds: dict[str, float], packed: Packed = NOTHING_PACKED) -> Path:
    """``<experiment>.csv`` and ``<experiment>.md`` (with its figures) from the finished runs,
    in their directories or ``packed``, with each run's wall time from ``seconds``."""
    records = collect(plan, results, seconds, packed)
    write_csv(records, results / f"{plan.experiment}.csv")
    body = LAYOUTS[plan.spec["layout"]](plan, records, results) if records else "No run finished."
    body += learning_curves_section(plan, results, packed)
    minutes = wall_seconds / 60
    text = (f"# {plan.spec['title']}\n\n{plan.spec.get('description', '').strip()}\n\n"
            f"{progress_note(plan, results, packed)} Wall time of the sweeps so far: "
            f"{minutes:.1f} min"
            f"{run_times(records)}."
            f"{machines(records, finished_reports(plan.attacks, results, packed))}\n"
            f"Cells: mean ± std over seeds unless marked s.e.; every run's numbers are in "
            f"`{plan.experiment}.csv`.\n\n{body}\n")
    path = results / f"{plan.experiment}.md"
    write_text_atomically(path, text)
    return path


def learning_curves_section(plan: Plan, results: Path, packed: Packed = NOTHING_PACKED) -> str:
    """Every training run's learning curve into ``<experiment>_curves.csv.gz`` (rows of runs
    whose logs are gone kept from the file as it was) and their figure, drawn from rows at the
    file's precision (so that a checkout without the logs redraws it byte for byte); the report's
    section that shows them with their late trend (:func:`~armeta_rl.reproduce.reports.late_trend`),
    empty when no run has logged one."""
    path = curves_path(results, plan.experiment)
    try:
        kept = read_curves(path)
    except FileRefused as error:
        raise ConfigError("results", str(results), f"its {path.name} {error.reason}: restore "
                          "it from where it was committed, or delete it") from None
    rows = collect_curves(plan, results, kept, packed)
    if not rows:
        return ""
    write_curves(rows, path)
    labels = {run.name: learner_label(plan, (run.method, run.variant)) for run in plan.runs}
    labels |= {run.name: f"{display(run.method)}'s flow against "
               f"{learner_label(plan, (run.target.method, run.target.variant))} (attack)"
               for run in plan.attacks}
    figures.learning_curves(rows, labels, results / f"{plan.experiment}_curves.png")
    trend = late_trend(rows, labels)
    return (f"\n\n## Learning curves\n\n![learning curves]({plan.experiment}_curves.png)\n\n"
            "Mean over seeds (their number in brackets) of 10-iteration means, band ± one "
            "standard deviation over seeds. Every run's value at every logged iteration is in "
            f"`{path.name}`." + (f"\n\n{trend}" if trend else ""))


def reported_plan(results: Path, experiment: str, profile: str, extra: tuple[str, ...],
                  benchmarks: tuple[str, ...] | None, packed: Packed = NOTHING_PACKED) -> Plan:
    """The plan a report covers: every seed of the requested ``benchmarks`` and of each other
    benchmark of the experiment with a finished run in ``results``, so a sweep restricted to some
    benchmarks never drops the rows that the directory already holds for the others."""
    whole = make_plan(experiment, profile, extra)
    if benchmarks is None:
        return whole
    shown = {*benchmarks, *(run.benchmark for run in whole.runs
                            if finished(results, run, packed))}
    return make_plan(experiment, profile, extra, tuple(shown))


def reproduce(experiment: str, profile: str = "quick", results: Path | None = None,
              launcher: str = "local", jobs: int | None = None,
              hydra_args: tuple[str, ...] = (), extra: tuple[str, ...] = (),
              benchmarks: tuple[str, ...] | None = None,
              seeds: tuple[int, ...] | None = None, pack: bool = False,
              adopt: bool = False) -> int:
    """Run what is missing of ``experiment`` at ``profile`` (restricted to ``benchmarks`` and
    ``seeds``) and aggregate over all seeds the benchmarks of :func:`reported_plan`; the exit
    code (0 when every run and evaluation of the restriction finished; 1 otherwise, with each
    missing one and why on stderr). Runs packed in the results directory's compact files
    (:mod:`armeta_rl.reproduce.packed`) count as finished and are aggregated from them; with
    ``pack``, every report the plan accepts, in the run directories or packed, is packed with
    its run's config into those files before aggregating (``adopt``: reports that record no
    identity too, recording it: :func:`~armeta_rl.reproduce.plan.packable`).

    Raises:
        ConfigError: an unknown experiment, profile or launcher, a results directory that is not
            this experiment's or cannot be read, or a run config that does not compose.
    """
    from armeta_rl.cli import evaluate, train
    from armeta_rl.cli.compose import check_hydra

    plan = make_plan(experiment, profile, extra, benchmarks, seeds)
    if adopt and not pack:
        raise ConfigError("adopt", True, "records the identity of reports as it packs them: "
                          "add pack=true")
    results = resolved_results(results or Path("results") / experiment)
    selected = launcher_overrides(launcher, jobs, hydra_args)
    address = ray_address(hydra_args) if launcher == "ray" else None
    if address is not None:
        given = any(arg.startswith("hydra.launcher.ray.init.address=") for arg in hydra_args)
        check_ray_address(address, "hydra.launcher.ray.init.address" if given else "RAY_ADDRESS")
    for config_name in ("train", "eval"):
        check_hydra((*selected, *hydra_args), config_name)
    manifest = claim(results, plan, extra)
    if results.is_dir():
        check_contents(results, "results")
    check_runs(plan)
    results.mkdir(parents=True, exist_ok=True)
    for path in stale_leftovers(results):
        path.unlink(missing_ok=True)
    save_manifest(results, manifest)
    for item in (*plan.runs, *plan.attacks, *plan.evals):
        if isinstance(item, EvalJob) and not finished(results, item.learner):
            continue  # made again once its learner has finished, whatever it holds
        refused = report_problem(results, item)
        if refused is not None and report_path(results, item).exists():
            print(f"{PROG}: {report_path(results, item)} is not a finished report ({refused}): "
                  "made again", file=sys.stderr)
    packed = packed_runs(results)
    runs = [r for r in plan.runs if not finished(results, r, packed)]
    unfinished = {run.subdir for run in runs}  # a time kept for one is an earlier run's
    manifest["train_seconds"] = {subdir: seconds for subdir, seconds in manifest.get(
        "train_seconds", {}).items() if subdir not in unfinished}
    attack_note = (f", {len(plan.attacks)} attack runs" if plan.attacks else "")
    print(f"{PROG}: {experiment} ({profile}) in {results}: {len(plan.runs)} training runs "
          f"({len(runs)} to run){attack_note}, {len(plan.evals)} evaluations; launcher "
          f"{launcher}", flush=True)
    code = 0
    if launcher == "none":
        runs = []
    local = launcher == "local"
    with listening(DEFAULT_STOP_SIGNALS, forward_to_children=local) as stop, SweepClock(
            results, manifest, experiment) as clock:
        if runs:
            code = launch(train, [train_job(results, r) for r in runs], results,
                          f"{experiment} train", len(plan.runs) - len(runs),
                          (*selected, *hydra_args), local)
        attacks = [] if launcher == "none" or stop.requested else [  # targets finished
            a for a in plan.attacks if not finished(results, a, packed)
            and finished(results, a.target)]
        if attacks:
            code = launch(train, [train_job(results, a) for a in attacks],
                          results, f"{experiment} attack",
                          sum(finished(results, a, packed) for a in plan.attacks),
                          (*selected, *hydra_args), local) or code
        evals = [e for e in plan.evals if not finished(results, e, packed)]
        ready = [] if stop.requested or launcher == "none" else [
            e for e in evals if finished(results, e.learner)
            and (e.adversary is None or finished(results, e.adversary))]
        if ready:
            code = launch(evaluate, [eval_job(results, e) for e in ready],
                          results, f"{experiment} eval", len(plan.evals) - len(evals),
                          (*selected, *hydra_args), local) or code
    wall = manifest["wall_seconds"]
    if runs or attacks or ready:  # aggregating adds no sweep time
        wall[experiment] = clock.before + clock.seconds
    if pack:
        packed = pack_runs(results, packable(results, make_plan(experiment, profile, extra),
                                             packed, adopt))
        print(f"{PROG}: packed {len(packed.reports)} reports and {len(packed.configs)} configs "
              f"into {results / REPORTS_FILE} and {results / CONFIGS_FILE}")
    whole = reported_plan(results, experiment, profile, extra, benchmarks, packed)
    seconds = train_seconds(whole, results, dict(manifest.get("train_seconds", {})))
    manifest["train_seconds"] = seconds
    save_manifest(results, manifest)
    report = write_report(whole, results, wall.get(experiment, 0.0), seconds, packed)
    print(f"{PROG}: {progress_note(whole, results, packed)} Report: {report}")
    if stop.requested:
        in_flight = ("the evaluations in flight stopped, keeping nothing" if ready
                     else "the runs in flight wrote checkpoints")
        print(f"{PROG}: stopped by {stop.name}: {in_flight}; the same command continues the "
              "sweep", file=sys.stderr)
        return stop.exit_code
    missing = [(item, missing_why(results, item, packed))
               for item in (*plan.runs, *plan.attacks, *plan.evals)]
    missing = [(item, problem) for item, problem in missing if problem is not None]
    code = code or int(bool(missing))
    if code == 1:  # a partial sweep (a job refused as bad input has said why: exit 2)
        for item, problem in missing[:MISSING_SHOWN]:
            print(f"{PROG}: missing {report_path(results, item).relative_to(results)}: "
                  f"{problem}", file=sys.stderr)
        if len(missing) > MISSING_SHOWN:
            print(f"{PROG}: missing {len(missing) - MISSING_SHOWN} more (the report counts "
                  "every run finished)", file=sys.stderr)
    return code


def missing_why(results: Path, item: TrainRun | EvalJob, packed: Packed) -> str | None:
    """Why ``item`` has not finished (:func:`report_problem`; an evaluation that could not run
    names the run it waits for, or the run whose checkpoints are gone), or ``None``."""
    problem = report_problem(results, item, packed)
    if problem is None or not isinstance(item, EvalJob):
        return problem
    needs = [run for run in (item.learner, item.adversary) if run is not None]
    waits = [run for run in needs if not finished(results, run, packed)]
    if waits:
        return f"it waits for {waits[0].subdir}, not finished"
    lost = lost_checkpoints(results, item, needs)
    return (f"it cannot run: {lost[0].subdir} finished without a checkpoint to load" if lost
            else problem)


def resolved_results(results: Path) -> Path:
    """The results directory ``results`` as an absolute path without links; a link loop or a
    name the file system cannot hold is refused as one line."""
    try:
        return results.resolve()
    except (OSError, RuntimeError) as error:
        reason = getattr(error, "strerror", None) or " ".join(str(error).split())
        raise ConfigError("results", str(results), f"cannot be used ({reason})") from None


def packed_runs(results: Path) -> Packed:
    """The runs packed in ``results``' compact files (:func:`read_packed`); a compact file that
    cannot be read as one is refused as one line naming it."""
    try:
        return read_packed(results)
    except FileRefused as error:
        raise ConfigError("results", str(results), f"its {Path(error.path).name} "
                          f"{error.reason}: restore it from where it was committed, or delete "
                          "it to make its runs again") from None


def stale_leftovers(results: Path) -> list[Path]:
    """The hidden files that an atomic write into ``results`` itself (a report, a figure, a
    compact file: ``.reports.jsonl.<pid>.gz``) left when its process was killed: those of
    processes no longer running (a live one is still writing its own)."""
    stale = []
    for path in staged_leftovers(results, (".",)):
        pid = next(int(part) for part in path.name.split(".")[2:] if part.isdigit())
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            stale.append(path)
        except PermissionError:
            continue
    return stale


def parse(args: list[str]) -> dict:
    """The command line as :func:`reproduce`'s keyword arguments."""
    if not args or "=" in args[0] or args[0].startswith("-"):
        _fail(f"name an experiment first: {PROG} <experiment> [profile=quick|paper] "
              f"(experiments: {', '.join(experiment_names())})")
    options: dict = {"experiment": args[0], "hydra_args": [], "extra": []}
    for arg in args[1:]:
        key, sep, value = arg.partition("=")
        if not sep:
            _fail(f"cannot read the argument {arg!r}: expected key=value")
        if key.startswith(("hydra.", "hydra/")):
            options["hydra_args"].append(arg)
        elif key.startswith("+train."):
            options["extra"].append(arg[len("+train."):])
        elif key == "jobs":
            if not value.isdigit() or int(value) < 1:
                _fail(f"config key 'jobs' = {value!r}: must be an integer >= 1")
            options["jobs"] = int(value)
        elif key == "benchmarks":
            options["benchmarks"] = tuple(value.split(","))
        elif key == "seeds":
            if not all(part.isdigit() for part in value.split(",")):
                _fail(f"config key 'seeds' = {value!r}: must be comma-separated integers")
            options["seeds"] = tuple(int(part) for part in value.split(","))
        elif key in ("pack", "adopt"):
            if value not in ("true", "false"):
                _fail(f"config key '{key}' = {value!r}: allowed: true, false")
            options[key] = value == "true"
        elif key == "results":
            options["results"] = Path(value)
        elif key in OPTIONS:
            options[key] = value
        else:
            _fail(f"config key '{key}' = {value!r}: no such option; allowed: "
                  f"{', '.join(OPTIONS)}, hydra.<key>, hydra/<group>, +train.<key>")
    if options.get("launcher", "local") not in LAUNCHERS:
        _fail(f"config key 'launcher' = {options['launcher']!r}: allowed: {', '.join(LAUNCHERS)}")
    options["hydra_args"] = tuple(options["hydra_args"])
    options["extra"] = tuple(options["extra"])
    return options


def main() -> None:
    """``armeta-reproduce``: exit code 0 when the experiment is complete, 1 when runs failed or
    are missing or a file could not be written, 2 for bad input (one line)."""
    from armeta_rl.cli.failures import OUT_OF_MEMORY, Refused, out_of_memory

    if any(arg in ("--help", "-h") for arg in sys.argv[1:]):
        print(help_text())
        sys.exit(0)
    options = parse(sys.argv[1:])
    try:
        code = reproduce(**options)
    except (ConfigError, Refused) as error:
        _fail(str(error))
    except (MemoryError, OSError) as error:  # a write the disk refused (EFBIG, ENOSPC, ...)
        if out_of_memory(error):
            _fail(OUT_OF_MEMORY)
        print(f"{PROG}: error: cannot write {error.filename or 'a file'}: "
              f"{error.strerror or error}", file=sys.stderr)
        sys.exit(1)
    sys.exit(code)
