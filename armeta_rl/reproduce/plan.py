"""An experiment of the paper as data: which ``armeta-train`` runs and ``armeta-eval`` scorings
it needs, read from ``configs/reproduce/<experiment>.yaml`` and the shared profiles in
``configs/reproduce/profiles.yaml``.

An experiment lists *groups* of training runs, each the product benchmarks × methods × variants ×
seeds, and *adversaries*: for every learner run, ``armeta-eval`` scores it on the adversary of
another run of the same benchmark and variant (an AR method at the same seed, or at the next
seed). Its *attacks* add, per run of a target method, an AR run that trains only its adversary
against that run's finished learner (``trainer.frozen_leader``, a second training batch), and
score every learner on that adversary too. A *profile* (``quick``, ``paper``, ``tiny``) sets the
seeds and the overrides per benchmark (iterations, evaluation tasks); the experiment may add its
own per profile.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from armeta_rl.config import CONFIG_BYTES, CONFIG_FILE, value_at
from armeta_rl.config_files import config_files
from armeta_rl.errors import ConfigError
from armeta_rl.reproduce import PROFILES_FILE, experiment_names
from armeta_rl.reproduce.packed import NOTHING_PACKED, Packed
from armeta_rl.run_files import FileRefused, read_text

EVAL_FILE = "eval.json"


@dataclass(frozen=True)
class TrainRun:
    """One ``armeta-train`` run: its directory (relative to the results directory) and overrides
    (benchmark, method, seed and the profile's settings).

    ``benchmark`` is the experiment's row (``sinusoid_normal``: the directory, the report and the
    paper's numbers are keyed by it); ``config`` is the benchmark config that the profile trains
    for that row (``sinusoid_normal_paper`` at the ``paper`` profile). An attack run has a
    ``target``: the run whose finished learner it loads and never trains, training only its
    adversary against it (``trainer.frozen_leader``).
    """

    benchmark: str
    method: str
    variant: str
    seed: int
    overrides: tuple[str, ...]
    config: str
    target: TrainRun | None = None

    @property
    def name(self) -> str:
        """``<method>[-<variant>]``, ``<method>-vs-<target's name>`` for an attack run."""
        if self.target is not None:
            return f"{self.method}-vs-{self.target.name}"
        return self.method if not self.variant else f"{self.method}-{self.variant}"

    @property
    def subdir(self) -> str:
        """``runs/<benchmark>/<name>/seed<seed>``."""
        return f"runs/{self.benchmark}/{self.name}/seed{self.seed}"

    def command(self, results: Path | None = None) -> list[str]:
        """The run's overrides as ``armeta-train`` takes them; an attack run's with ``results``
        also points ``trainer.frozen_leader`` at its target (an absolute path, known at launch)."""
        frozen = ([f"trainer.frozen_leader={results / self.target.subdir}"]
                  if self.target is not None and results is not None else [])
        return [f"benchmark={self.config}", f"method={self.method}", f"seed={self.seed}",
                *self.overrides, *frozen]


SHIFTS_JOB = "shifts"
"""The name of the evaluation job that scores a run on its benchmark's shift suite."""


@dataclass(frozen=True)
class EvalJob:
    """One ``armeta-eval``: ``learner`` scored on the adversary of ``adversary`` (two runs of the
    same benchmark), written to ``<learner>/eval_vs_<name>.json``; or, with ``adversary`` None,
    on ``shifts`` of its benchmark's shift suite (``"all"`` or names), written to
    ``<learner>/eval_shifts.json``. Neither scores p0 again (the run's ``eval.json`` has it)."""

    name: str
    learner: TrainRun
    adversary: TrainRun | None
    shifts: str | tuple[str, ...] | None = None

    @property
    def out(self) -> str:
        """The report's path relative to the results directory."""
        if self.adversary is None:
            return f"{self.learner.subdir}/eval_{SHIFTS_JOB}.json"
        return f"{self.learner.subdir}/eval_vs_{self.name}.json"

    def command(self, results: Path) -> list[str]:
        """The job's overrides as ``armeta-eval`` takes them (absolute paths)."""
        if self.adversary is None:
            chosen = self.shifts if isinstance(self.shifts, str) else f"[{','.join(self.shifts)}]"
            scored = [f"shifts={chosen}"]
        else:
            scored = [f"adversary={results / self.adversary.subdir}"]
        return [f"learner={results / self.learner.subdir}", *scored, "initial=false",
                f"out={results / self.out}"]


@dataclass(frozen=True)
class Plan:
    """An experiment at a profile: its spec (the YAML), training runs, attack runs (trained once
    their targets finished) and evaluation jobs."""

    experiment: str
    profile: str
    spec: dict[str, Any]
    runs: tuple[TrainRun, ...]
    evals: tuple[EvalJob, ...]
    attacks: tuple[TrainRun, ...] = ()


def load_spec(experiment: str) -> dict[str, Any]:
    """The experiment's YAML as a dict; ``ConfigError`` for an unknown name."""
    names = experiment_names()
    if experiment not in names:
        raise ConfigError("experiment", experiment, f"allowed: {', '.join(names)}")
    path = config_files() / "reproduce" / f"{experiment}.yaml"
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True)


def load_profiles() -> dict[str, Any]:
    """``configs/reproduce/profiles.yaml``: seeds and per-benchmark overrides per profile."""
    return OmegaConf.to_container(OmegaConf.load(config_files() / "reproduce" / PROFILES_FILE))


def benchmark_setting(profile: str, benchmark: str, entry: Any) -> tuple[str, list[str]]:
    """A profile's entry for ``benchmark`` as (benchmark config, overrides): a list of overrides
    trains the benchmark's own config; ``{config: name, overrides: [...]}`` trains ``name``."""
    if isinstance(entry, list):
        return benchmark, [str(o) for o in entry]
    if isinstance(entry, dict) and set(entry) <= {"config", "overrides"} and "config" in entry:
        return str(entry["config"]), [str(o) for o in entry.get("overrides", [])]
    raise ConfigError(f"{profile}.benchmarks.{benchmark}", entry,
                      "allowed: a list of overrides, or {config: <benchmark>, overrides: [...]}")


def make_plan(experiment: str, profile: str, extra: tuple[str, ...] = (),
              benchmarks: tuple[str, ...] | None = None,
              seeds: tuple[int, ...] | None = None) -> Plan:
    """The runs and evaluation jobs of ``experiment`` at ``profile``; ``extra`` overrides are
    appended to every training run (last, so they win). ``benchmarks`` and ``seeds`` restrict
    the experiment to some of its benchmarks and seeds: their runs are the same as in the whole
    experiment, and the evaluations kept are those with the learner or the adversary among them
    (an evaluation runs once both exist)."""
    spec = load_spec(experiment)
    profiles = load_profiles()
    if profile not in profiles:
        raise ConfigError("profile", profile, f"allowed: {', '.join(profiles)}")
    declared = list(dict.fromkeys(b for group in spec["groups"] for b in group["benchmarks"]))
    for name in benchmarks or ():
        if name not in declared:
            raise ConfigError("benchmarks", name, f"{experiment} has: {', '.join(declared)}")
    shared = profiles[profile]
    own = spec.get("profiles", {}).get(profile, {})
    all_seeds = [int(s) for s in own.get("seeds", shared["seeds"])]
    for seed in seeds or ():
        if seed not in all_seeds:
            raise ConfigError("seeds", seed, f"{experiment} at profile {profile} has: "
                              f"{', '.join(map(str, all_seeds))}")
    runs: list[TrainRun] = []
    for group in spec["groups"]:
        variants = group.get("variants") or {"": []}
        for benchmark in group["benchmarks"]:
            if benchmarks and benchmark not in benchmarks:
                continue
            if benchmark not in shared["benchmarks"]:
                raise ConfigError(f"{profile}.benchmarks", benchmark,
                                  f"has no settings in {PROFILES_FILE}")
            config, own_settings = benchmark_setting(profile, benchmark,
                                                     shared["benchmarks"][benchmark])
            settings = [*shared.get("overrides", []), *own_settings,
                        *spec.get("overrides", []), *own.get("overrides", []),
                        *own.get("benchmarks", {}).get(benchmark, [])]
            for method in group["methods"]:
                for variant, variant_overrides in variants.items():
                    runs.extend(
                        TrainRun(benchmark, method, variant, seed,
                                 (*settings, *variant_overrides, *extra), config)
                        for seed in all_seeds
                    )
    precision_target(spec)
    attacks = attack_runs(spec, runs)
    jobs = (eval_jobs(spec, runs, all_seeds) + attack_jobs(spec, runs, attacks)
            + shift_jobs(spec, runs))
    if seeds:
        runs = [run for run in runs if run.seed in seeds]
        attacks = [run for run in attacks if run.seed in seeds]
        jobs = [job for job in jobs if job.learner.seed in seeds
                or (job.adversary is not None and job.adversary.seed in seeds)]
    return Plan(experiment, profile, spec, tuple(runs), tuple(jobs), tuple(attacks))


def attack_runs(spec: dict[str, Any], runs: list[TrainRun]) -> list[TrainRun]:
    """For every attack of ``spec["attacks"]`` (``{name: {method, target}}``) and every run of its
    target method, the run of ``method`` (an AR method) with the target's benchmark, variant, seed
    and overrides, then the attack's own ``overrides`` (its adversary's settings, which the
    target's run need not carry), that trains its adversary against the target's finished
    learner."""
    attacks = spec.get("attacks", {})
    methods = list(dict.fromkeys(run.method for run in runs))
    found = []
    for name, attack in attacks.items():
        if not isinstance(attack, dict) or not (
                {"method", "target"} <= set(attack) <= {"method", "target", "variant",
                                                        "overrides"}):
            raise ConfigError(f"attacks.{name}", attack, "allowed: {method: <AR method>, "
                              "target: <a method of the experiment>[, variant: <its variant>]"
                              "[, overrides: [<key>=<value>, ...]]}")
        if name in spec.get("adversaries", {}):
            raise ConfigError(f"attacks.{name}", attack,
                              "an adversary of the experiment has that name already")
        if attack["target"] not in methods:
            raise ConfigError(f"attacks.{name}.target", attack["target"],
                              f"allowed: {', '.join(methods)}")
        found += [TrainRun(run.benchmark, attack["method"], run.variant, run.seed,
                           (*run.overrides, *attack.get("overrides", [])), run.config,
                           target=run)
                  for run in runs if run.method == attack["target"]
                  and run.variant == attack.get("variant", run.variant)]
    return found


def attack_jobs(spec: dict[str, Any], runs: list[TrainRun],
                attacks: list[TrainRun]) -> list[EvalJob]:
    """Every run scored on the adversary of each attack (named as in ``spec["attacks"]``) at the
    run's benchmark and seed, against the target of the run's variant, or of the attack's
    ``variant`` where it names one (every learner scored on one attack)."""
    by_key = {(a.method, a.target.method, a.benchmark, a.variant, a.seed): a for a in attacks}
    jobs = []
    for name, attack in spec.get("attacks", {}).items():
        for run in runs:
            variant = attack.get("variant", run.variant)
            key = (attack["method"], attack["target"], run.benchmark, variant, run.seed)
            if key in by_key:
                jobs.append(EvalJob(name, run, by_key[key]))
    return jobs


def eval_jobs(spec: dict[str, Any], runs: list[TrainRun], seeds: list[int]) -> list[EvalJob]:
    """For every run and every adversary of ``spec["adversaries"]`` (``{name: {method,
    seed_shift[, variant]}}``), the job scoring the run on that method's run of the same benchmark
    at the seed ``seed_shift`` places further in ``seeds`` (cyclically), of the run's own variant
    or of the adversary's ``variant`` where it names one (every learner scored on one adversary)."""
    by_key = {(r.benchmark, r.method, r.variant, r.seed): r for r in runs}
    jobs = []
    for name, adversary in spec.get("adversaries", {}).items():
        for run in runs:
            shifted = seeds[(seeds.index(run.seed) + adversary.get("seed_shift", 0)) % len(seeds)]
            variant = adversary.get("variant", run.variant)
            key = (run.benchmark, adversary["method"], variant, shifted)
            if key in by_key:
                jobs.append(EvalJob(name, run, by_key[key]))
    return jobs


def shift_jobs(spec: dict[str, Any], runs: list[TrainRun]) -> list[EvalJob]:
    """With ``spec["shifts"]`` (``all`` or a list of names), every run scored on those shifts of
    its benchmark's shift suite (:mod:`armeta_rl.tasks.shifts`)."""
    chosen = spec.get("shifts")
    if chosen is None:
        return []
    if not (chosen == "all" or (isinstance(chosen, list) and chosen
                                and all(isinstance(c, str) for c in chosen))):
        raise ConfigError("shifts", chosen, "allowed: all, or a list of shift names")
    shifts = chosen if isinstance(chosen, str) else tuple(chosen)
    return [EvalJob(SHIFTS_JOB, run, None, shifts) for run in runs]


def precision_target(spec: dict[str, Any]) -> tuple[float, tuple[str, ...]] | None:
    """The experiment's precision target (``precision: {se_below: s, distributions: [...]}``):
    the paired standard error over seeds its protocol asks to get below ``s`` on those
    distributions (``initial``, an adversary's name, ``shift/<name>``); ``None`` without one."""
    target = spec.get("precision")
    if target is None:
        return None
    bound = target.get("se_below") if isinstance(target, dict) else None
    names = target.get("distributions") if isinstance(target, dict) else None
    if (not isinstance(bound, (int, float)) or isinstance(bound, bool) or not bound > 0
            or not isinstance(names, list) or not names
            or not all(isinstance(n, str) for n in names)):
        raise ConfigError("precision", target, "allowed: {se_below: <a number > 0>, "
                          "distributions: [<initial, an adversary or shift/<name>>, ...]}")
    return float(bound), tuple(names)


def report_sections(file: str) -> tuple[str, ...]:
    """The distributions a report must hold: a run's ``eval.json`` p0's, an adversary's
    report (``eval_vs_<name>.json``) the adversary's, a shift report none by name (its
    ``shift/<name>`` sections are checked as every section is)."""
    if file == EVAL_FILE:
        return ("initial",)
    return () if file == f"eval_{SHIFTS_JOB}.json" else ("adversarial",)


def report_path(results: Path, run: TrainRun | EvalJob) -> Path:
    """The report that marks ``run`` finished: its ``eval.json``; an evaluation job's own."""
    return results / (run.out if isinstance(run, EvalJob) else f"{run.subdir}/{EVAL_FILE}")


def report_problem(results: Path, run: TrainRun | EvalJob,
                   packed: Packed = NOTHING_PACKED) -> str | None:
    """Why the report of ``run`` (its ``eval.json``; an evaluation job's own report) does not
    mark it finished, or ``None`` when it does: the file is missing (from the run's directory
    and from ``packed``), unreadable, fails its schema
    (:func:`~armeta_rl.trainers.evaluation.check_report`; a hand-edited mean or a NaN), or is
    not what the plan gives this run (:func:`identity_problem`)."""
    return _checked_report(results, run, packed)[1]


def finished_report(results: Path, run: TrainRun | EvalJob,
                    packed: Packed = NOTHING_PACKED) -> dict[str, Any] | None:
    """The report of ``run`` where it marks it finished (:func:`report_problem`), else ``None``."""
    return _checked_report(results, run, packed)[0]


def _checked_report(results: Path, run: TrainRun | EvalJob, packed: Packed
                    ) -> tuple[dict[str, Any] | None, str | None]:
    """The report of ``run`` and ``None``, or ``None`` and why it does not mark it finished."""
    from armeta_rl.trainers.evaluation import ReportInvalid

    try:
        report = load_report(results, report_path(results, run), packed)
    except ReportInvalid as error:
        return None, str(error)
    problem = identity_problem(report, run, results, packed)
    return (report, None) if problem is None else (None, problem)


def load_report(results: Path, path: Path, packed: Packed = NOTHING_PACKED) -> dict[str, Any]:
    """The report at ``path`` (in a run directory of ``results``) if it passes its schema: the
    file where it exists (read from ``results`` through no link), else its packed copy in
    ``packed``, else :class:`ReportInvalid` (a run's own files win, so a sweep writing into a
    packed directory reads its new reports)."""
    from armeta_rl.trainers.evaluation import ReportInvalid, check_report, read_report

    place = (str(path.parent.relative_to(results)), path.name)
    if path.exists() or path.is_symlink() or place not in packed.reports:
        return read_report(path, report_sections(path.name), results)
    report = packed.reports[place]
    try:
        check_report(report, report_sections(path.name))
    except ReportInvalid as error:
        raise ReportInvalid(f"its packed copy: {error}") from None
    return report


REPORT_IDENTITY = ("benchmark", "method", "seed", "config_sha256")
"""What a report records of the run that wrote it; a report without any of them is not
finished."""


@functools.lru_cache(maxsize=256)
def composed(command: tuple[str, ...]) -> DictConfig:
    """The ``armeta-train`` config of a run's ``command`` (its overrides but the seed), composed
    as the CLI composes it (:func:`armeta_rl.cli.compose.compose_job`), once per command:
    composing is most of an aggregation's time (the config returned is shared: not to be
    changed).

    Raises:
        Refused: an override that does not compose, as one line.
    """
    from hydra import initialize_config_dir

    from armeta_rl.cli.compose import compose_job, config_dir, job_overrides

    with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
        job_overrides(list(command))
        return compose_job(list(command))


def run_command(run: TrainRun) -> tuple[str, ...]:
    """``run``'s overrides but its seed: runs that differ only in their seed share one
    :func:`composed` config."""
    return tuple(arg for arg in run.command() if not arg.startswith("seed="))


@functools.lru_cache(maxsize=4096)
def planned_values(run: TrainRun) -> dict[str, Any]:
    """What the plan gives ``run``, by dotted key: the value of every key its command line sets
    (its benchmark's and method's names for their groups, its seed, each override), and under
    ``eval`` its whole ``eval`` section (how its reports are scored), from its :func:`composed`
    config. Keys the command leaves to their defaults are not among them: a run saved by an
    earlier version, whose defaults differed, is still the run its plan names (the values
    returned are shared: not to be changed)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from armeta_rl.cli.compose import GROUPS

    command = run_command(run)
    values = OmegaConf.to_container(composed(command), resolve=True)
    values["seed"] = run.seed
    keys = ["seed", "eval"]
    for override in OverridesParser.create().parse_overrides(list(command)):
        if not override.is_delete():
            name = override.key_or_group
            keys.append(f"{name}.name" if name in GROUPS and name != "logger" else name)
    return {key: value_at(values, key) for key in dict.fromkeys(keys)}


@functools.lru_cache(maxsize=4096)
def saved_config(text: str) -> tuple[str, dict[str, Any]]:
    """The ``config_sha256`` (:func:`~armeta_rl.trainers.checkpoint.run_identity`) and the
    resolved values of a run's ``config.yaml`` text as the run sees it, read as a resume reads
    it (:func:`~armeta_rl.config.read_run_config`: merged into this version's schema), so a run
    saved before a key was added (with its default) and evaluated after keeps its identity;
    ``ConfigError`` for a damaged text (its run's own refusal). Remembered by text, as a report
    asks for every run's several times and composing a config is most of an aggregation's time
    (the values returned are shared: not to be changed)."""
    from armeta_rl.config import read_run_config
    from armeta_rl.trainers.checkpoint import run_identity

    values = OmegaConf.to_container(read_run_config(text, "config", CONFIG_FILE), resolve=True)
    return run_identity(values)["config_sha256"], values


def _config_text(results: Path, run: TrainRun, packed: Packed) -> str:
    """The run's ``config.yaml`` (read from ``results`` through no link), else its packed copy;
    :class:`~armeta_rl.trainers.evaluation.ReportInvalid` when it has neither or it cannot be
    read."""
    from armeta_rl.trainers.evaluation import ReportInvalid

    path = results / run.subdir / CONFIG_FILE
    try:
        return read_text(path, CONFIG_BYTES, results)
    except FileNotFoundError:
        if run.subdir in packed.configs:
            return packed.configs[run.subdir]
        raise ReportInvalid(f"its run has no {CONFIG_FILE} to check it against") from None
    except FileRefused as error:
        raise ReportInvalid(f"its run's {CONFIG_FILE} {error.reason}") from None
    except OSError as error:
        raise ReportInvalid(f"its run's {CONFIG_FILE} cannot be read "
                            f"({error.strerror or error})") from None


def identity_problem(report: dict[str, Any], run: TrainRun | EvalJob,
                     results: Path, packed: Packed = NOTHING_PACKED) -> str | None:
    """Why ``report``, found where ``run`` keeps its report, is not this run's result in this
    experiment, or ``None``: it records no identity (:data:`REPORT_IDENTITY`); its benchmark,
    method or seed differ from the run's (an evaluation job's learner's); the digest of the
    result-changing keys it records is neither that of the run's ``config.yaml`` (its packed
    config where its directory has none) as this version reads it nor as it was saved
    (:func:`~armeta_rl.trainers.checkpoint.identity_as_saved`), as a variant's is; that config
    does not hold what the plan gives the run (:func:`planned_values`, but the keys that change
    no result, :data:`~armeta_rl.cli.jobs.NO_RESULT_KEYS`: another experiment's or profile's run
    copied in); or the report was scored with other evaluation settings than the plan's
    (another experiment's report, :func:`scored_problem`)."""
    from armeta_rl.trainers.checkpoint import identity_as_saved
    from armeta_rl.trainers.evaluation import ReportInvalid

    learner = run.learner if isinstance(run, EvalJob) else run
    missing = [key for key in REPORT_IDENTITY if key not in report]
    if missing:
        return (f"it records no {' or '.join(missing)}: a report that does not say which run "
                "wrote it is not finished")
    expected = {"benchmark": learner.config, "method": learner.method, "seed": learner.seed}
    for key, value in expected.items():
        if report[key] != value:
            return f"it is the report of {key} {report[key]!r}, not this run's {value!r}"
    try:
        text = _config_text(results, learner, packed)
        digest, saved = saved_config(text)
    except ReportInvalid as error:
        return str(error)
    except (ValueError, AttributeError, yaml.YAMLError, OmegaConfBaseException) as error:
        return f"its run's {CONFIG_FILE} cannot be read ({' '.join(str(error).split())})"
    as_saved = identity_as_saved(text)
    if report["config_sha256"] not in (digest, as_saved and as_saved["config_sha256"]):
        return (f"it is the report of another config (config_sha256 "
                f"{str(report['config_sha256'])[:12]}…, not this run's {digest[:12]}…)")
    from armeta_rl.cli.jobs import NO_RESULT_KEYS

    planned = planned_values(learner)
    differ = next((key for key, value in planned.items()
                   if key != "eval" and key not in NO_RESULT_KEYS
                   and value_at(saved, key) != value), None)
    if differ is not None:
        return (f"its run's config has {differ} = {_short(value_at(saved, differ))}, not the "
                f"{_short(planned[differ])} this experiment's plan gives it")
    return scored_problem(report, planned["eval"])


def scored_problem(report: dict[str, Any], scoring: dict[str, Any]) -> str | None:
    """Why ``report`` was not scored with the ``eval`` settings ``scoring`` (its support-label
    noise, every section's number of tasks and CVaR levels), or ``None``."""
    noise = report.get("support_noise", 0.0)
    if noise != scoring["support_noise"]:
        return (f"it was scored with support_noise {noise}, not the "
                f"{scoring['support_noise']} the plan gives")
    alphas = sorted(float(a) for a in scoring["alphas"])
    for name, section in report.items():
        if not isinstance(section, dict):
            continue
        if section.get("n_tasks") != scoring["n_tasks"]:
            return (f"its {name} was scored on {section.get('n_tasks')} tasks, not the "
                    f"{scoring['n_tasks']} the plan gives")
        if sorted(float(a) for a in section.get("cvar", {})) != alphas:
            return (f"its {name} holds CVaR at {sorted(section.get('cvar', {}))}, not at the "
                    f"plan's {alphas}")
    return None


def _short(value: Any, most: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= most else text[: most - 1] + "…"


def packable(results: Path, plan: Plan, packed: Packed = NOTHING_PACKED,
             adopt: bool = False) -> Packed:
    """What ``armeta-reproduce … pack=true`` packs: every report of ``plan`` (in its run's
    directory, else in ``packed``) that marks its run or job finished
    (:func:`report_problem`), with the configs of their runs; a report refused is not packed.
    With ``adopt``, a report that records no identity (written before reports recorded one) is
    taken as its run's own: its identity is recorded from its run and its run's config, which
    must still be what the plan gives."""
    from armeta_rl.trainers.evaluation import ReportInvalid

    reports, configs = {}, {}
    for item in (*plan.runs, *plan.attacks, *plan.evals):
        learner = item.learner if isinstance(item, EvalJob) else item
        path = report_path(results, item)
        try:
            report = load_report(results, path, packed)
            text = _config_text(results, learner, packed)
            if adopt and any(key not in report for key in REPORT_IDENTITY):
                identity = {"benchmark": learner.config, "method": learner.method,
                            "seed": learner.seed, "config_sha256": saved_config(text)[0]}
                report = {**report, **{k: v for k, v in identity.items() if k not in report}}
        except (ReportInvalid, ValueError):
            continue
        if identity_problem(report, item, results, packed) is None:
            reports[(str(path.parent.relative_to(results)), path.name)] = report
            configs[learner.subdir] = text
    return Packed(reports, configs)


def finished(results: Path, run: TrainRun | EvalJob, packed: Packed = NOTHING_PACKED) -> bool:
    """Whether a run has its ``eval.json`` (an evaluation job: its report), in its directory or
    in ``packed``, passing the schema of a report and being this run's
    (:func:`identity_problem`); a damaged, hand-edited or copied one counts as unfinished, so it
    is made again."""
    return report_problem(results, run, packed) is None


def interrupted(results: Path, run: TrainRun) -> bool:
    """Whether an unfinished run was started: its directory holds the config that ``armeta-train
    resume=`` continues under (from its last checkpoint, or from the start if it wrote none)."""
    return not finished(results, run) and (results / run.subdir / CONFIG_FILE).is_file()
