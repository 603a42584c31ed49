"""A training run end to end: build, (resume,) train, evaluate, write the run directory."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import CSVLogger, Logger, WandbLogger

from armeta_rl.collectors.base import TaskCollector
from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.collectors.regression import NoisySupport
from armeta_rl.compiling import COMPILE_KEYS
from armeta_rl.config import CONFIG_FILE, check_config, load_run_config
from armeta_rl.errors import CollectionFailed, ConfigError, RunDirectoryError, TrainingDiverged
from armeta_rl.tasks import TaskDistribution
from armeta_rl.trainers.checkpoint import RunCheckpoint, newest_intact, write_file
from armeta_rl.trainers.density import DensityFrames
from armeta_rl.trainers.evaluation import evaluate_on, format_table
from armeta_rl.trainers.game import GameTrainer
from armeta_rl.trainers.runs import (
    Players,
    build_players,
    check_run_dir,
    load_players,
    run_lock,
)

EVAL_FILE = "eval.json"
DENSITY_FILE = "density.png"
CSV_LOG_DIR = "logs"


def make_logger(cfg: DictConfig, run_dir: Path) -> Logger | None:
    """CSV (default), wandb (offline unless ``WANDB_MODE=online``) or none."""
    kind = cfg.logger.kind
    if kind == "none":
        return None
    if kind == "csv":
        return CSVLogger(exp_name=CSV_LOG_DIR, log_dir=str(run_dir))
    if kind == "wandb":
        run_id = "armeta-" + hashlib.sha1(str(run_dir.resolve()).encode()).hexdigest()[:12]
        offline = os.environ.get("WANDB_MODE", "offline") != "online"
        logger = WandbLogger(
            exp_name=run_dir.name,
            offline=offline,
            save_dir=str(run_dir),
            id=run_id,
            project=cfg.logger.project,
            log_env_packages=False,
        )
        logger.log_hparams(OmegaConf.to_container(cfg, resolve=True))
        return logger
    raise ConfigError("logger.kind", kind, "allowed: csv, wandb, none")


def evaluate_players(
    cfg: DictConfig, players: Players, adversary: TaskDistribution | None = None
) -> dict[str, Any]:
    """``eval.json``'s content: the leader on p0 and on an adversarial distribution.

    ``adversary`` defaults to the run's own p_φ (AR methods); ERM-style runs have none unless one
    is given (``armeta-eval`` scores any learner on any saved adversary).
    """
    ev = cfg.eval
    noisy = noisy_support_collector(cfg, players)
    adversary = adversary if adversary is not None else players.adversary
    distributions = {"initial": players.initial}
    if adversary is not None:
        distributions["adversarial"] = adversary
    report: dict[str, Any] = {
        "metric": players.leader.metric,
        "benchmark": cfg.benchmark.name,
        "method": cfg.method.name,
    }
    for offset, (name, distribution) in enumerate(distributions.items()):
        report[name] = evaluate_on(
            players.leader,
            distribution,
            players.eval_collector,
            ev.n_tasks,
            list(ev.alphas),
            ev.seed + offset,
        )
        report[name].update(distribution_stats(distribution, players.initial, ev.seed + offset))
    if noisy is not None:
        report["support_noise"] = ev.support_noise
        for offset, (name, distribution) in enumerate(distributions.items()):
            report[f"{name}_noisy"] = evaluate_on(
                players.leader, distribution, noisy, ev.n_tasks, list(ev.alphas), ev.seed + offset
            )
    return report


def noisy_support_collector(cfg: DictConfig, players: Players) -> TaskCollector | None:
    """The evaluation collector with N(0, σ²) noise on the support labels for σ =
    ``eval.support_noise`` (the paper's random perturbation test), or ``None`` when σ = 0.

    RL benchmarks adapt on episodes, which have no support labels, so σ > 0 is refused there;
    :func:`run_training` asks before training, so the error does not wait for the evaluation.
    """
    sigma = cfg.eval.support_noise
    if not sigma > 0:
        return None
    if isinstance(players.eval_collector, EpisodeCollector):
        raise ConfigError(
            "eval.support_noise", sigma,
            f"must be 0 on {cfg.benchmark.name}: its tasks are adapted from episodes, which have "
            "no support labels to perturb",
        )
    return NoisySupport(players.eval_collector, sigma)


def distribution_stats(distribution: TaskDistribution, initial: TaskDistribution, seed: int,
                       samples: int = 4096) -> dict[str, float]:
    """Entropy H[p] and KL(p0 ‖ p) of a task distribution (Monte Carlo with exact log-densities;
    the paper's entropy table reports H of p0 and of the learned p_φ)."""
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        torch.manual_seed(seed)
        entropy = float(distribution.entropy(samples))
        kl = float(distribution.kl_from(initial, samples))
    return {"entropy": entropy, "kl_p0": kl}


def eval_scalars(report: dict[str, Any]) -> dict[str, float]:
    """Dashboard names ``eval/<distribution>/mean``, ``…/sem`` and ``…/cvar_<α>``."""
    scalars = {}
    for name, section in report.items():
        if isinstance(section, dict) and "mean" in section:
            scalars[f"eval/{name}/mean"] = section["mean"]
            if section.get("sem") is not None:
                scalars[f"eval/{name}/sem"] = section["sem"]
            scalars.update({f"eval/{name}/cvar_{a}": v for a, v in section["cvar"].items()})
    return scalars


def run_training(cfg: DictConfig, run_dir: str | Path, progress: bool = True) -> dict | None:
    """Train ``cfg`` in ``run_dir`` (resuming from its checkpoint if ``cfg.resume`` is set),
    holding the run directory's lock throughout.

    Returns the evaluation report, or ``None`` when the run stopped early at ``trainer.stop_at``.

    Raises:
        ConfigError: a bad value, a run directory that cannot be written or that another run
            holds, or (on resume) no intact checkpoint.
        TrainingDiverged: the losses left ``trainer.max_loss``; names the checkpoint kept.
        RunDirectoryError: a checkpoint, log or report could not be written (e.g. a full disk);
            names the checkpoint kept.
    """
    run_dir = Path(run_dir)
    key = "resume" if cfg.resume else "hydra.run.dir"
    check_config(cfg)
    check_run_dir(run_dir, key)
    with run_lock(run_dir, key):
        try:
            return _train_locked(cfg, run_dir, progress)
        except (TrainingDiverged, CollectionFailed, RunDirectoryError, OSError) as error:
            stopped = isinstance(error, (TrainingDiverged, CollectionFailed))
            kind = type(error) if stopped else RunDirectoryError
            if isinstance(error, OSError):  # e.g. a log or eval.json on a full disk
                error = f"cannot write {error.filename or run_dir}: {error.strerror or error}"
            kept = newest_intact(run_dir / "checkpoints")
            raise kind(
                f"{error}; the last good checkpoint {kept.name} is kept: armeta-train "
                f"resume={run_dir} continues from it"
                if kept is not None
                else f"{error}; no checkpoint had been written yet"
            ) from None


def _train_locked(cfg: DictConfig, run_dir: Path, progress: bool) -> dict | None:
    torch.set_num_threads(cfg.threads)
    players = build_players(cfg)
    noisy_support_collector(cfg, players)
    checkpoint = RunCheckpoint(run_dir / "checkpoints", players.leader, players.principle)
    checkpoint.clean_staging()
    staged = [*run_dir.glob(f".{CONFIG_FILE}.*"), *run_dir.glob(f".{EVAL_FILE}.*"),
              *(run_dir / CSV_LOG_DIR).rglob(".*.csv.*")]
    for path in staged:  # what write_text_atomically left when a crash interrupted it
        path.unlink()
    start = 0
    if cfg.resume:
        if checkpoint.checkpoints():
            start = checkpoint.restore("resume")
        drop_csv_rows_after(run_dir, start)
        saved = load_run_config(run_dir, "resume")
        if saved.trainer.iterations != cfg.trainer.iterations:  # resumed to train longer
            saved.trainer.iterations = cfg.trainer.iterations
            write_config(saved, run_dir / CONFIG_FILE)
    else:
        if checkpoint.checkpoints() or (run_dir / CONFIG_FILE).exists():
            raise ConfigError(
                "hydra.run.dir", str(run_dir),
                "already holds a run: continue it with resume=<dir>, or train into a new "
                "directory",
            )
        write_config(cfg, run_dir / CONFIG_FILE)
    logger = make_logger(cfg, run_dir)
    compiled = [key for key in COMPILE_KEYS if OmegaConf.select(cfg, key, default=False)]
    if compiled:
        print(f"{', '.join(compiled)}: the first iterations wait for torch.compile "
              "(about 2 minutes with an empty compile cache)")
    frames = None
    if players.adversary is not None and cfg.trainer.density_every > 0:
        frames = DensityFrames(players.adversary, players.initial, run_dir,
                               cfg.trainer.density_every, logger)
        if start == 0:
            frames.draw(0)  # p_φ = p0
    trainer = GameTrainer(
        players.leader,
        players.principle,
        iterations=cfg.trainer.iterations,
        meta_batch=cfg.trainer.meta_batch,
        log_every=cfg.trainer.log_every,
        checkpoint=checkpoint,
        checkpoint_every=cfg.trainer.checkpoint_every,
        log=None if logger is None else logger.log_metrics,
        progress=progress and cfg.trainer.progress,
        max_loss=cfg.trainer.max_loss,
        after_iteration=frames,
    )
    trainer.iteration = start
    if trainer.run(stop_at=cfg.trainer.stop_at) < cfg.trainer.iterations:
        print(
            f"stopped at iteration {trainer.iteration}; continue with: "
            f"armeta-train resume={run_dir}"
        )
        return None
    report = evaluate_players(cfg, players)
    write_text_atomically(run_dir / EVAL_FILE, json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    if players.adversary is not None:
        _save_density(players, run_dir / DENSITY_FILE, logger)
    if frames is not None:
        frames.finish(trainer.iteration)
    if logger is not None:
        logger.log_metrics(eval_scalars(report), cfg.trainer.iterations)
    return report


def write_config(cfg: DictConfig, path: Path) -> None:
    """Save the resolved ``cfg`` as ``path`` atomically (a crash leaves the old file or none)."""
    write_text_atomically(path, OmegaConf.to_yaml(cfg, resolve=True))


def write_text_atomically(path: Path, text: str) -> None:
    """Write ``text`` to a hidden sibling of ``path``, fsync it and rename it over ``path``."""
    staged = path.with_name(f".{path.name}.{os.getpid()}")
    try:
        write_file(staged, text.encode())
        os.replace(staged, path)
    finally:
        staged.unlink(missing_ok=True)


def drop_csv_rows_after(run_dir: Path, iteration: int) -> None:
    """Delete the CSV log rows of iterations after ``iteration`` (the checkpoint a run resumes
    from): a run that crashed logged past its last checkpoint, and the resumed run logs those
    iterations again, so without this every scalar would hold them twice. A last row without
    its line end (a write the crash cut short) is dropped too.

    Raises:
        ConfigError: a complete row does not start with an iteration number.
    """
    for path in (run_dir / CSV_LOG_DIR / "scalars").rglob("*.csv"):
        rows = path.read_text(errors="replace").splitlines(keepends=True)
        if rows and not rows[-1].endswith("\n"):
            rows[-1] = ""
        kept = [row for row in rows if row and _csv_step(row, path, run_dir) <= iteration]
        if kept != rows:
            write_text_atomically(path, "".join(kept))


def _csv_step(row: str, path: Path, run_dir: Path) -> int:
    try:
        return int(row.split(",", 1)[0])
    except ValueError:
        raise ConfigError(
            "resume", str(run_dir),
            f"its log {path.relative_to(run_dir)} has a row that does not parse "
            f"({row.strip()[:40]!r}): delete that row or file to resume",
        ) from None


def _save_density(players: Players, path: Path, logger: Logger | None) -> None:
    from armeta_rl.plots import plot_density

    plot_density(players.adversary, players.initial, path)
    if isinstance(logger, WandbLogger):
        import wandb

        logger.experiment.log({"adversary/density": wandb.Image(str(path))})


def cross_evaluate(
    learner_dir: str | Path,
    adversary_dir: str | Path | None,
    eval_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Score the learner saved in ``learner_dir`` on p0 and on the adversary saved in
    ``adversary_dir`` (same benchmark); ``eval_overrides`` replace the learner run's ``eval.*``."""
    cfg, players = load_players(learner_dir, "learner")
    adversary = None
    if adversary_dir is not None:
        adv_cfg, adv_players = load_players(adversary_dir, "adversary")
        if adv_players.adversary is None:
            raise ConfigError(
                "adversary",
                str(adversary_dir),
                f"was trained with method {adv_cfg.method.name}, which has no adversary",
            )
        if adv_players.space != players.space:
            raise ConfigError(
                "adversary",
                str(adversary_dir),
                f"its identifier box {adv_players.space} differs from the learner's "
                f"{players.space}",
            )
        adversary = adv_players.adversary
    cfg = OmegaConf.merge(cfg, {"eval": eval_overrides or {}})
    check_config(cfg)
    report = evaluate_players(cfg, players, adversary)
    report["learner"] = str(learner_dir)
    report["adversary"] = None if adversary_dir is None else str(adversary_dir)
    return report
