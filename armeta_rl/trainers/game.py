"""The one game loop (docs/architecture.md; paper Algorithm 1 and the GDA updates of Eq.
(14)): the leader steps on tasks proposed by the risk principle, then the follower
steps on the same tasks' losses at θ_{t+1}.

One iteration reads ``tasks = principle.propose(K)``, ``data = leader.collect(tasks)``,
``leader.step(data, weights)`` and ``principle.update(tasks, losses)``: every call takes what it
needs and returns what it makes.

The loop knows nothing about regression or RL: the leader owns collection, adaptation and its
update; the principle owns task proposal, task weights and the follower update.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor
from tqdm.auto import tqdm

from armeta_rl.config import TrainerConfig
from armeta_rl.errors import TrainingDiverged
from armeta_rl.learners.base import Leader
from armeta_rl.preemption import StopRequest
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.tasks.protocol import TASK_KEY, per_rollout, repeat_tasks
from armeta_rl.trainers.checkpoint import RunCheckpoint

LogFn = Callable[[dict[str, float], int], None]


ITERATION_TIME = "time/iteration_ms"
"""The scalar under which every iteration logs its wall time in milliseconds."""
BAR_SCALARS = {"train/leader_loss": "leader loss", "adversary/objective": "adversary objective"}
"""The scalars the progress bar shows, by the names it shows them under."""


class GameTrainer:
    """Alternating Stackelberg updates of leader θ and follower φ.

    Args:
        leader: the meta-learner (MAML, CNP, MAML-TRPO).
        principle: where tasks come from and how their losses are weighted (ERM, AR, DR, ...).
        options: the loop's section of the run config (``trainer``,
            :class:`~armeta_rl.config.TrainerConfig`): ``iterations`` in all, ``meta_batch`` tasks
            per iteration K, ``log_every``, ``checkpoint_every``, ``stop_at`` (:meth:`run` stops
            there, checkpointed), ``progress`` (a tqdm bar with the iteration and current losses),
            ``max_loss`` (the divergence guard: a task loss beyond ±``max_loss`` stops the run
            like a non-finite one; ``None``: only non-finite losses stop it), ``frozen_leader``
            (set: the leader is never stepped; θ stays fixed and the follower is trained
            against it on the losses of its proposed tasks at that θ), ``follower_rollouts``
            (for an on-policy leader, the follower's loss of a task is the mean of this many
            independent rollouts at θ_{t+1}, collected in one batch: less noise in the
            follower's signal for that many more rollouts), ``follower_at`` (``"next"``: a
            follower of the game reads its tasks' losses at θ_{t+1}, paper Algorithm 1;
            ``"step"``: the step's own losses at θ_t, which cost nothing more, where θ_{t+1}
            would take a fresh collection in meta-RL).
        log: called with the scalars of an iteration and its number, every ``log_every``.
        checkpoint: where to save every ``checkpoint_every`` iterations (``None``: never).
        after_iteration: called with the iteration number after every iteration (after its
            logging and checkpoint), e.g. to draw the adversary's density.
        label: the progress bar's name (a run's: its directory's, which tells the jobs of a
            ``-m`` sweep apart).

    Examples:
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.config import TrainerConfig
        >>> from armeta_rl.learners import MAMLLeader, make_mlp
        >>> from armeta_rl.risk import TailRiskPrinciple
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> from armeta_rl.trainers import GameTrainer
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> leader = MAMLLeader(make_mlp(1, 1, hidden=[16]), SinusoidCollector())
        >>> logged = []
        >>> options = TrainerConfig(iterations=4, meta_batch=8, log_every=2, progress=False)
        >>> trainer = GameTrainer(leader, TailRiskPrinciple(BoxUniform(space)), options,
        ...                       log=lambda scalars, i: logged.append(i))
        >>> trainer.run()  # the iteration reached
        4
        >>> logged
        [2, 4]
    """

    def __init__(
        self,
        leader: Leader,
        principle: RiskPrinciple,
        options: TrainerConfig,
        *,
        log: LogFn | None = None,
        checkpoint: RunCheckpoint | None = None,
        after_iteration: Callable[[int], None] | None = None,
        label: str = "meta-iterations",
    ) -> None:
        self.leader, self.principle, self.options = leader, principle, options
        self.log, self.checkpoint = log, checkpoint
        self.after_iteration = after_iteration
        self.label = label
        self.train_leader = options.frozen_leader is None
        self.iteration = 0

    def train_iteration(self) -> dict[str, float]:
        """One meta-iteration t → t+1; returns its scalars.

        The data flow in the open: the principle proposes tasks, the leader collects their data
        and steps on them with the principle's weights of these tasks, and every ``update_every``
        iterations the principle updates on the tasks' losses (:meth:`follower_losses`).
        """
        start = time.perf_counter()
        tasks = self.principle.propose(self.options.meta_batch)
        if not torch.isfinite(tasks[TASK_KEY]).all() or torch.isnan(tasks["log_prob"]).any():
            raise TrainingDiverged(
                f"non-finite task identifiers proposed at iteration {self.iteration + 1}"
            )
        weights = partial(self.principle.weights, tasks=tasks)
        if self.train_leader:
            data = self.leader.collect(tasks, create_graph=True)
            out, scalars = self.leader.step(data, weights)
        else:  # θ stays: its losses on the proposed tasks are the follower's at θ_{t+1} = θ_t
            data = None
            out, scalars = {"loss": self.fresh_losses(tasks)}, {}
        losses = out["loss"]
        self.check_losses(losses)
        logs = {
            "train/leader_loss": float((weights(losses) * losses).sum()),
            "train/task_loss_mean": float(losses.mean()),
        }
        logs.update(
            {f"train/{key}": float(value.mean()) for key, value in out.items() if key != "loss"}
        )
        logs.update({f"train/{key}": value for key, value in scalars.items()})
        self.iteration += 1
        every = self.principle.update_every
        if every and self.iteration % every == 0:
            follower = (self.follower_losses(tasks, data, out[self.principle.label])
                        if self.train_leader else losses)
            logs.update(self.principle.update(tasks, follower))
        logs[ITERATION_TIME] = 1000.0 * (time.perf_counter() - start)
        return logs

    def follower_losses(self, tasks: TensorDict, data: Any, step_losses: Tensor) -> Tensor:
        """The per-task losses the principle's update reads.

        A follower of the game (``needs_next_losses``) reads L at θ_{t+1} (paper Algorithms 1
        and 2): on the step's own data, or, for an on-policy leader whose data are θ_t's rollouts,
        on data collected afresh for the same tasks (the mean of ``follower_rollouts`` of them).
        A principle that only reports statistics of the step, or any principle with
        ``follower_at="step"``, reads the step's losses at θ_t, which cost nothing more.
        """
        if not self.principle.needs_next_losses or self.options.follower_at == "step":
            return step_losses
        if not self.leader.on_policy:
            with torch.no_grad():
                return self.leader.evaluate(data)
        return self.fresh_losses(tasks)

    @torch.no_grad()
    def fresh_losses(self, tasks: TensorDict) -> Tensor:
        """The losses ``[K]`` of ``tasks`` at the current θ on data collected afresh: per task,
        the mean of ``follower_rollouts`` independent rollouts, collected in one batch."""
        rollouts = self.options.follower_rollouts
        losses = self.leader.evaluate(self.leader.collect(repeat_tasks(tasks, rollouts)))
        return losses if rollouts == 1 else per_rollout(losses, rollouts).mean(0)

    def check_losses(self, losses: Tensor) -> None:
        """Raise :class:`TrainingDiverged` on a non-finite task loss or one beyond ±``max_loss``."""
        worst = float(losses.detach().abs().max())
        if not math.isfinite(worst):
            raise TrainingDiverged(
                f"the leader loss is not finite at iteration {self.iteration + 1}"
            )
        max_loss = self.options.max_loss
        if max_loss is not None and worst > max_loss:
            raise TrainingDiverged(
                f"a task loss reached {worst:.3g} at iteration {self.iteration + 1}, beyond "
                f"trainer.max_loss = {max_loss:g}"
            )

    def run(self, stop: StopRequest | None = None) -> int:
        """Train until ``iterations`` (or ``stop_at``, checkpointing there), or until ``stop`` is
        requested: then the current iteration is finished and checkpointed; returns the iteration
        reached. A :class:`TrainingDiverged` propagates and leaves the last good checkpoint."""
        options = self.options
        end = options.iterations if options.stop_at is None else min(options.stop_at,
                                                                     options.iterations)
        start, saved = self.iteration, None
        bar = tqdm(
            total=end,
            initial=self.iteration,
            disable=not options.progress,
            desc=self.label,
            dynamic_ncols=True,
        )
        with bar:
            while self.iteration < end and not (stop is not None and stop.requested):
                logs = self.train_iteration()
                bar.update(1)
                if self.iteration % options.log_every == 0 or self.iteration == end:
                    bar.set_postfix({name: f"{logs[key]:.3g}"
                                     for key, name in BAR_SCALARS.items() if key in logs})
                    if self.log is not None:
                        self.log(logs, self.iteration)
                if self.iteration % options.checkpoint_every == 0 or self.iteration == end:
                    saved = self.save(logs)
                if self.after_iteration is not None:
                    self.after_iteration(self.iteration)
            if self.iteration not in (start, saved):  # stopped on request between checkpoints
                self.save(logs)
        return self.iteration

    def save(self, logs: dict[str, float]) -> int:
        """Checkpoint the iteration just trained (its scalars ``logs`` must be finite); returns
        its number."""
        if self.checkpoint is not None:
            if not all(math.isfinite(v) for v in logs.values()):
                raise TrainingDiverged(f"non-finite training scalars at iteration {self.iteration}")
            self.checkpoint.save(self.iteration)
        return self.iteration
