"""Console entry points ``armeta-train`` and ``armeta-eval`` (Hydra).

Bad input ends with one line naming the config key, the value and what is allowed (and the
likely key, for a misspelt one), and exit code 2. Every run enters through one door,
:func:`~armeta_rl.cli.jobs.make_job`, which turns a command line, a ``-m`` sweep job's composed
config or a resume directory into a :class:`~armeta_rl.job.Job`: its config composed (Hydra
checks the types and refuses unknown keys, :mod:`armeta_rl.cli.compose`) and validated once
(:func:`armeta_rl.config.validate`: the ranges, the rules between keys, the device resolved), or
a resumed run's saved config read once and merged with the command line's changes. The config of
every job on the command line is checked before Hydra starts, and a single run's directory is
checked and locked then too, so a refused command writes nothing. What runs below the CLI takes
the job, never a composed config. A run stopped by a diverged loss or a failed write ends with
one line and exit code 1 (:func:`~armeta_rl.cli.failures.failure`: the one table of exit codes).
See docs/configuration.md.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf

from armeta_rl.cli.compose import (
    GROUPS,
    check_hydra,
    check_jobs,
    compose_job,
    compose_run,
    config_dir,
    hydra_words,
    job_overrides,
)
from armeta_rl.cli.failures import (
    OUT_OF_MEMORY,
    Refused,
    address_space_refusal,
    failure,
    report_errors,
)
from armeta_rl.cli.help import print_help
from armeta_rl.cli.jobs import make_job, sweep_task, train_task
from armeta_rl.errors import ConfigError

if TYPE_CHECKING:
    from armeta_rl.job import Job


_NO_RUN_FLAGS = ("--cfg", "-c", "--help", "-h", "--hydra-help", "--info", "-i",
                 "--shell-completion", "-sc", "--resolve")
_UNCHECKED_FLAGS = ("--help", "-h", "--hydra-help", "--shell-completion", "-sc")
"""Flags whose command composes nothing to check (its words are not overrides)."""


def _run_hydra(argv: list[str], config_name: str, task: Callable[[DictConfig], None]) -> None:
    """Hydra's command line (``hydra.main``) on ``argv``: Hydra's entry point reads its words
    from ``sys.argv``, which holds them while it runs."""
    import hydra

    main = hydra.main(config_path=str(config_dir()), config_name=config_name,
                      version_base=None)(task)
    program = sys.argv[:1] or ["armeta"]
    saved, sys.argv = sys.argv, [*program, *argv]
    try:
        main()
    finally:
        sys.argv = saved


def _exit_code(main: Callable[[list[str]], None], prog: str, argv: list[str] | None) -> int:
    """``main``'s exit code on ``argv`` (``None``: ``sys.argv[1:]``): 0, the code of its
    ``SystemExit``, or the code of the error it raised, said in one line
    (:func:`~armeta_rl.cli.failures.failure`). Under an address-space limit too small to load
    torch it says so and runs nothing."""
    refusal = address_space_refusal()
    if refusal is not None:
        sys.stderr.write(f"{prog}: error: {refusal}\n")
        return 2
    try:
        main(sys.argv[1:] if argv is None else list(argv))
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except MemoryError:  # e.g. an import that exhausted the heap: said with what is left
        sys.stderr.write(f"{prog}: error: {OUT_OF_MEMORY}\n")
        return 2
    except (Exception, KeyboardInterrupt) as error:
        status = failure(error)
        if status is None:
            raise
        code, line = status
        print(f"{prog}: {line}", file=sys.stderr)
        return code
    return 0


def _program(code: int, argv: list[str] | None) -> int:
    """``code`` returned to a caller that gave ``argv``; the process's exit code when it gave
    none (the console script)."""
    if argv is None:
        sys.exit(code)
    return code


def _without_checks(args: list[str], prog: str, config_name: str,
                    task: Callable[[DictConfig], None], groups: tuple[str, ...], usage: str
                    ) -> bool:
    """Answer ``--help`` (:func:`~armeta_rl.cli.help.print_help`; its other words without ``=``
    name the sections whose keys to list, ``--help trainer learner.maml``) or hand Hydra a flag
    whose words are no overrides (``-sc install=bash``, ``--hydra-help``); whether it did."""
    if any(a in ("--help", "-h") for a in args):
        sections = [a for a in args if not a.startswith("-") and "=" not in a]
        print_help(prog, config_name, groups, usage, sections)
        return True
    if any(a in _UNCHECKED_FLAGS for a in args):
        _run_hydra(args, config_name, task)
        return True
    return False


def train(argv: list[str] | None = None) -> int:
    """``armeta-train``: train a method on a benchmark (see ``configs/train.yaml``); returns the
    exit code of the command line ``argv``. Without ``argv`` it is the program: it runs
    ``sys.argv[1:]`` and exits with that code.

    Every job's config is composed and validated before Hydra starts. A single run's directory
    is checked and locked then too (Hydra writes ``.hydra/`` and its log there); a run refused
    before it wrote a checkpoint removes the directory it created. ``-m`` jobs lock their own
    directories.
    """
    return _program(_exit_code(_train, "armeta-train", argv), argv)


def _train(args: list[str]) -> None:
    prog = "armeta-train"
    if _without_checks(args, prog, "train", report_errors(prog, sweep_task({})), GROUPS,
                       "train a method on a benchmark (armeta-train [group=option ...] "
                       "[key=value ...] [-m])"):
        return
    for arg in args:
        name, _, value = arg.partition("=")
        if name in ("hydra.run.dir", "hydra.sweep.dir") and not value.strip():
            raise Refused(f"config key '{name}' = '': must name a directory")
    resume = next((a.split("=", 1)[1] for a in args if a.startswith("resume=")), None)
    multirun = any(a in ("-m", "--multirun") for a in args)
    no_run = multirun or any(a.split("=")[0] in _NO_RUN_FLAGS for a in args)
    checked_here = {}  # a sweep's configs checked before Hydra starts, by the job's overrides
    if resume:
        if multirun:
            raise Refused(f"config key 'resume' = {resume}: resumes one run, not a -m sweep")
        job = make_job([a for a in args if not a.startswith("-")])
        # the run's job log stays in its own directory, whatever hydra.run.dir says
        args = [a for a in args if not a.startswith(("hydra.run.dir=", "hydra.output_subdir="))]
        check_hydra(args, "train")
        args += [f"hydra.run.dir={resume}", "hydra.output_subdir=null"]
    elif no_run:
        # a run_list sweep's jobs are in its jobs file, checked by armeta-reproduce
        if not ("hydra/sweeper=run_list" in args and job_overrides(args) == [[]]):
            checked_here = check_jobs(args)
        check_hydra(args, "train")
    else:
        job = _new_job(args)
    if no_run:
        _run_hydra(args, "train", report_errors(prog, sweep_task(checked_here)))
        return
    from armeta_rl.trainers.run_dir import hold_run_dir  # torch: after the checks

    run_dir = job.run_dir
    given = [a for a in args if a.startswith("hydra.run.dir=")]
    if not given or "${" in given[-1]:  # pin what Hydra would resolve again (its ${now:...})
        args = [a for a in args if a not in given] + [f"hydra.run.dir={run_dir}"]
    # held before Hydra writes there (a resume's contents checked before it appends to its log)
    with hold_run_dir(run_dir, "resume" if resume else "hydra.run.dir", bool(resume)) as held:
        # Hydra composes the config again for its job; the run takes the one checked here
        task = report_errors(prog, lambda _composed: train_task(job, held))
        try:
            _run_hydra(args, "train", task)
        except SystemExit as exit_:
            if exit_.code == 2 and held.created and not (run_dir / "checkpoints").exists():
                _remove_run_dir(held.created)
            raise


def _new_job(args: list[str]) -> Job:
    """The job of a new single run's command line ``args``: its config composed once with its
    Hydra config (:func:`~armeta_rl.cli.compose.compose_run`) and validated
    (:func:`~armeta_rl.cli.jobs.make_job`), in the directory Hydra will run it in. A command line
    of several jobs (a value with commas) is refused, after each job's config is checked."""
    from hydra import initialize_config_dir

    jobs = job_overrides(args)
    if len(jobs) > 1:
        check_jobs(args)
        check_hydra(args, "train")
        raise Refused(f"a command line of {len(jobs)} jobs (a value with commas): add -m "
                      "to run them all; a list value is written key=[a,b]")
    (job,) = jobs
    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        cfg, run_dir = compose_run(job, hydra_words(args))
        return make_job(job, cfg, run_dir)


def _remove_run_dir(run_dir: Path) -> None:
    """Delete a run directory (with the parents) this command created for a run it then refused."""
    import shutil

    shutil.rmtree(run_dir, ignore_errors=True)


def _eval_task(cfg: DictConfig) -> None:
    """Score the runs ``cfg`` names: each run's saved config, with the command line's ``device``
    and ``eval.*``, validated once (:func:`armeta_rl.trainers.players.saved_run`), the run
    directories first, each named as itself, then the report's path derived from them. A stop
    signal abandons the scoring at once (:func:`~armeta_rl.preemption.abandoning`): it keeps
    nothing until its report is written."""
    from armeta_rl.preemption import abandoning
    from armeta_rl.trainers.evaluation import format_table
    from armeta_rl.trainers.players import saved_run
    from armeta_rl.trainers.report import evaluate_runs
    from armeta_rl.trainers.run_dir import write_text_atomically

    if not isinstance(cfg.initial, bool):
        raise ConfigError("initial", cfg.initial, "must be true or false")
    if not isinstance(cfg.adopt, bool):
        raise ConfigError("adopt", cfg.adopt, "must be true or false")
    overrides = {k: v for k, v in OmegaConf.to_container(cfg.eval).items() if v is not None}
    learner = saved_run(cfg.learner, "learner", cfg.device,
                        {"eval": overrides, "adopt": cfg.adopt})
    adversary = (None if cfg.adversary is None
                 else saved_run(cfg.adversary, "adversary", cfg.device, {"adopt": cfg.adopt}))
    shifts = OmegaConf.to_container(cfg.shifts) if OmegaConf.is_list(cfg.shifts) else cfg.shifts
    suffix = ("" if cfg.adversary is None else f"_vs_{Path(cfg.adversary).name}") or (
        "" if shifts is None else "_shifts")
    out = Path(cfg.out) if cfg.out else Path(cfg.learner) / f"eval{suffix}.json"
    check_writable(out, "out")
    with abandoning(f"scoring {cfg.learner}", "the same command scores it"):
        report = evaluate_runs(cfg.learner, learner, cfg.adversary, adversary, shifts,
                               cfg.initial)
    write_text_atomically(out, json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    print(f"written: {out}")


def check_writable(path: Path, key: str) -> None:
    """Refuse an output file that cannot be written, before the work that fills it: its folder
    is tried by creating and removing a hidden file there (the report is written atomically,
    through such a sibling)."""
    from armeta_rl.trainers.run_dir import unwritable

    if path.is_dir():
        raise ConfigError(key, str(path), "is a directory, not a file")
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise ConfigError(key, str(path), "is not a regular file (a link, a device, a pipe): "
                          "allowed: a new name or a regular file, which the report replaces")
    parent = path.parent
    if not parent.is_dir():
        raise ConfigError(key, str(path), f"cannot be written: {parent} is not a directory")
    problem = unwritable(parent)
    if problem is not None:
        raise ConfigError(key, str(path), f"cannot be written in {parent} ({problem})")


def evaluate(argv: list[str] | None = None) -> int:
    """``armeta-eval``: score a saved learner on p0, on a saved adversary and on its benchmark's
    shift suite; returns the exit code of the command line ``argv``. Without ``argv`` it is the
    program: it runs ``sys.argv[1:]`` and exits with that code."""
    return _program(_exit_code(_evaluate, "armeta-eval", argv), argv)


def _evaluate(args: list[str]) -> None:
    prog = "armeta-eval"
    task = report_errors(prog, _eval_task)
    if _without_checks(args, prog, "eval", task, (), "score a saved learner on p0, on a "
                       "saved adversary and on its benchmark's shift suite (armeta-eval "
                       "learner=<run dir> [adversary=<run dir>] [shifts=all|[name,...]] "
                       "[eval.rollouts=R] [eval.n_tasks=...] [out=<file>])"):
        return
    multirun = "-m" in args or "--multirun" in args  # a sweep's jobs carry their own learner=
    if not multirun and not any(a.startswith("learner=") for a in args):
        raise Refused("config key 'learner' is missing: give the run directory to score, "
                       "e.g. armeta-eval learner=runs/... adversary=runs/...")
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        for job in job_overrides(args, groups=()):
            compose_job(job, "eval")
    check_hydra(args, "eval")
    _run_hydra(args, "eval", task)
