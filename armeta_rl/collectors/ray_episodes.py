"""Episode collection with the tasks split over Ray actors, on one machine or a cluster (issue
"Scale: GPUs and distributed collection", item 2).

:class:`RayEpisodeCollector` is the Ray counterpart of
:class:`~armeta_rl.collectors.parallel_episodes.TaskSplitEpisodeCollector`: ``workers`` Ray actors
each own a slice of ``K / workers`` tasks with their own goal-conditioned env (its own MuJoCo
batch for Ant), and a :class:`RayTaskSplitEnv` of batch size ``[workers, K / workers, episodes]``
steps them all at once, seen through the same TorchRL ``BatchSizeTransform`` that reshapes it to
``[K, episodes]`` (task ``k`` lives in worker ``k // (K / workers)``). The per-task policy (task
``k``'s parameters on row ``k``) runs in the driver, exactly as in the single-process collector;
actors exchange only TensorDicts of actions in and observations, rewards and done flags out.

Why not TorchRL's ``RayCollector`` (``torchrl.collectors.distributed``): it ships a copy of one
policy to every remote collector and returns ``frames_per_batch`` frames, so it has no notion of
task ``k`` acting with its own adapted parameters on rows ``k`` (MAML's inner step makes one policy
per task, differentiable in the driver), and its remote policies draw actions from their own RNGs,
so the data could not equal the single-process collector's for a seed.

Seeding (as TorchRL's ``SerialEnv`` and ``ParallelEnv``): every ``collect`` reseeds the env from
torch's global RNG; worker ``w`` gets the ``w``-th seed of the chain ``s, seed_generator(s), ...``.
So the data are a function of ``torch.manual_seed`` and the worker count, bit-identical to
``TaskSplitEpisodeCollector(..., workers=N, in_process=True)`` (one process), and with one worker
to :class:`~armeta_rl.collectors.episodes.EpisodeCollector`.

Failures never hang a run: every wait on the actors is bounded by ``timeout_s``; an actor that dies
or does not answer in time ends the collection with :class:`~armeta_rl.errors.CollectionFailed`
(the CLI stops the run with one line, keeping its last checkpoint). An address where no Ray cluster
answers within ``connect_timeout_s`` is a :class:`~armeta_rl.errors.ConfigError` (exit code 2).
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Callable, Iterator, Sequence
from functools import partial
from typing import Any

import ray
import torch
from ray.exceptions import GetTimeoutError, RayActorError, RayTaskError
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import BatchSizeTransform

from armeta_rl.collectors.episodes import EpisodeCollector
from armeta_rl.collectors.parallel_episodes import WORKERS_KEY, _reshape
from armeta_rl.devices import CPU
from armeta_rl.errors import CollectionFailed, ConfigError
from armeta_rl.quiet import native_stderr_silenced

KEY = "benchmark.collector"
ADDRESS_KEY = f"{KEY}.address"
GCS_WAIT = "RAY_gcs_server_port_wait_time_s"  # Ray's connection attempts to a cluster's GCS


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _probe(host: str, port: int, timeout_s: float) -> bool:
    """Whether something accepts TCP connections at ``host:port`` within ``timeout_s``."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:
        return False


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of ``"ray://host:port"`` or ``"host:port"``; ``None`` for other forms."""
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def connect_ray(address: str | None, connect_timeout_s: float = 10.0) -> None:
    """Join the Ray cluster at ``address``; a process that has joined one already keeps it.

    ``address``: ``None`` starts a Ray instance of this machine alone inside this process (all
    local cores);
    ``"auto"`` joins the cluster started on this machine with ``ray start --head``;
    ``"host:port"`` joins a cluster by its head's GCS address (``ray start`` prints it; port 6379
    by default) and ``"ray://host:port"`` through the Ray Client server (port 10001 by default).
    Raises :class:`ConfigError` when nothing answers at ``host:port`` within ``connect_timeout_s``
    or Ray cannot join the cluster.
    """
    if ray.is_initialized():
        return
    allowed = (
        "null (a Ray instance in this process), 'auto' (the cluster of this machine), "
        "'host:port' (a head's GCS address) or 'ray://host:port' (Ray Client)"
    )
    if address is not None and not isinstance(address, str):
        raise ConfigError(ADDRESS_KEY, address, allowed)
    if address not in (None, "auto"):
        target = _host_port(address)
        if target is None:
            raise ConfigError(ADDRESS_KEY, address, allowed)
        if not _probe(*target, connect_timeout_s):
            raise ConfigError(ADDRESS_KEY, address,
                              f"no Ray cluster answers there within {connect_timeout_s:g} s "
                              f"({KEY}.connect_timeout_s); allowed: {allowed}")
    if address is None:
        ray.init(address="local", include_dashboard=False, logging_level="ERROR",
                 log_to_driver=False)
        return
    # Something answers, yet it may not be Ray: one connection attempt then (Ray's own retries
    # would take minutes; each attempt takes about 40 s), its core worker's log lines on stderr
    # summed up in the error.
    try:
        with native_stderr_silenced(), _environment(GCS_WAIT, os.environ.get(GCS_WAIT, "1")):
            ray.init(address=address, logging_level="ERROR", log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError) as error:
        raise ConfigError(ADDRESS_KEY, address,
                          f"Ray cannot join it ({_first_line(error)})") from None


@contextlib.contextmanager
def _environment(name: str, value: str) -> Iterator[None]:
    """Environment variable ``name`` set to ``value`` for the block, then restored."""
    before = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            del os.environ[name]
        else:
            os.environ[name] = before


@ray.remote
class EnvWorker:
    """A Ray actor owning one slice of the tasks: its env, built by :meth:`build` in the actor's
    process with one torch thread and the driver's default dtype (the env's outputs are in it)."""

    def __init__(self, dtype: torch.dtype) -> None:
        torch.set_num_threads(1)
        torch.set_default_dtype(dtype)
        self.env: EnvBase | None = None

    def build(self, make_env: Callable[..., EnvBase], batch_size: Sequence[int], max_steps: int,
              seed: int) -> tuple[TensorDictBase, TensorDictBase]:
        """Build ``make_env(batch_size=..., max_steps=..., seed=...)``; its ``output_spec`` and
        ``input_spec``. (A method rather than the constructor, so that an error raised by
        ``make_env``, such as a :class:`ConfigError`, reaches the driver as itself.)"""
        self.env = make_env(batch_size=tuple(batch_size), max_steps=max_steps, seed=seed)
        return self.env.output_spec, self.env.input_spec

    def set_seed(self, seed: int | None) -> int | None:
        """Seed the env; the next seed of TorchRL's chain."""
        return self.env.set_seed(seed)

    def reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``env.reset`` (TorchRL's ``SerialEnv`` resets its sub-envs through it as well)."""
        return self.env.reset(tensordict)

    def step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """``env._step``: the next observation, reward and done flags of an action."""
        return self.env._step(tensordict)


class RayTaskSplitEnv(EnvBase):
    """``workers`` :class:`EnvWorker` actors as one env of batch size
    ``[workers, tasks_per_worker, episodes]``, each actor stepping its own slice; the driver
    waits at most ``timeout_s`` for every answer.

    Args:
        make_env: builds one worker's env as ``make_env(batch_size=(tasks_per_worker, episodes),
            max_steps=max_steps, seed=seed)``; pickled to the actors.
        workers: number of actors.
        batch_size: ``(tasks_per_worker, episodes)`` of one worker.
        max_steps: episode length limit.
        seed: seed the workers' envs are built with (``set_seed`` reseeds them).
        timeout_s: longest wait for the actors (their start included) before
            :class:`CollectionFailed`.
        cpus_per_worker: CPUs Ray reserves for each actor (0: none; the actors then share cores).
    """

    def __init__(self, make_env: Callable[..., EnvBase], workers: int, batch_size: Sequence[int],
                 max_steps: int, seed: int = 0, timeout_s: float = 300.0,
                 cpus_per_worker: float = 1.0) -> None:
        super().__init__(batch_size=torch.Size((workers, *batch_size)))
        self.timeout_s = float(timeout_s)
        actor = EnvWorker.options(num_cpus=cpus_per_worker, scheduling_strategy="SPREAD")
        self.workers = [actor.remote(torch.get_default_dtype()) for _ in range(workers)]
        builds = [worker.build.remote(make_env, tuple(batch_size), max_steps, seed)
                  for worker in self.workers]
        output_spec, input_spec = self._gather(builds, range(workers))[0]
        # the worker's specs gain the leading worker dimension
        self.full_observation_spec = output_spec["full_observation_spec"].expand(
            workers, *output_spec.shape)
        self.full_reward_spec = output_spec["full_reward_spec"].expand(workers, *output_spec.shape)
        self.full_done_spec = output_spec["full_done_spec"].expand(workers, *output_spec.shape)
        self.full_action_spec = input_spec["full_action_spec"].expand(workers, *input_spec.shape)
        self.full_state_spec = input_spec["full_state_spec"].expand(workers, *input_spec.shape)
        self._reset_keys = [*self.full_observation_spec.keys(True, True),
                            *self.full_done_spec.keys(True, True)]
        self._step_keys = [*self._reset_keys, *self.full_reward_spec.keys(True, True)]
        self._input_keys = [*self.full_action_spec.keys(True, True),
                            *self.full_state_spec.keys(True, True)]

    def _gather(self, refs: list[ray.ObjectRef], ranks: Sequence[int]) -> list[Any]:
        """``ray.get`` of the actors' answers within ``timeout_s``; a dead or silent actor is a
        :class:`CollectionFailed`, an exception raised inside one is raised here."""
        try:
            return ray.get(refs, timeout=self.timeout_s)
        except GetTimeoutError:
            done, _ = ray.wait(refs, num_returns=len(refs), timeout=0)
            late = [rank for rank, ref in zip(ranks, refs) if ref not in done]
            raise CollectionFailed(
                f"Ray worker(s) {late} did not answer within {self.timeout_s:g} s "
                f"({KEY}.timeout_s): dead, stuck, or not placeable with the cluster's free "
                f"resources {ray.available_resources()}") from None
        except RayActorError as error:
            raise CollectionFailed(
                f"a Ray worker died during collection ({type(error).__name__}: "
                f"{_first_line(error)})") from None
        except RayTaskError as error:
            if isinstance(error.cause, ConfigError):  # one line for the CLI
                raise error.cause from None
            raise error.as_instanceof_cause() from None

    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """Seed worker ``w`` with the ``w``-th seed of TorchRL's chain from ``seed`` (as
        ``SerialEnv``); the seed after the last one."""
        for rank, worker in enumerate(self.workers):
            seed = self._gather([worker.set_seed.remote(seed)], [rank])[0]
        return seed

    def _set_seed(self, seed: int | None) -> None:
        self.set_seed(seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n = len(self.workers)
        reset = None if tensordict is None else tensordict.get("_reset", None)
        needs = [True] * n if reset is None else reset.reshape(n, -1).any(-1).tolist()
        parts = [None] * n if tensordict is None else tensordict.unbind(0)
        ranks = [w for w in range(n) if needs[w]]
        refs = [self.workers[w].reset.remote(parts[w]) for w in ranks]
        # rows of a worker with nothing to reset are not read (the reset keeps their step data)
        out = self.full_observation_spec.zero().update(self.full_done_spec.zero())
        for w, answer in zip(ranks, self._gather(refs, ranks)):
            out[w] = answer.select(*self._reset_keys)
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        parts = tensordict.select(*self._input_keys, strict=False).unbind(0)
        refs = [worker.step.remote(part) for worker, part in zip(self.workers, parts)]
        answers = self._gather(refs, range(len(self.workers)))
        return torch.stack([answer.select(*self._step_keys) for answer in answers])

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Stop the actors."""
        for worker in self.workers:
            ray.kill(worker)
        self.workers = []
        super().close(raise_if_closed=raise_if_closed)


def make_ray_task_split_env(
    make_env: Callable[..., EnvBase],
    workers: int,
    batch_size: tuple[int, int],
    max_steps: int,
    seed: int = 0,
    timeout_s: float = 300.0,
    cpus_per_worker: float = 1.0,
) -> TransformedEnv:
    """An env of batch size ``batch_size = (K, episodes)`` made of ``workers`` Ray actors, each
    with ``make_env(batch_size=(K // workers, episodes), max_steps=max_steps, seed=seed)``."""
    tasks, episodes = (int(n) for n in batch_size)
    if int(workers) < 1 or tasks % int(workers):
        raise ConfigError(WORKERS_KEY, workers, f"must be >= 1 and divide the task count {tasks}")
    split = RayTaskSplitEnv(make_env, int(workers), (tasks // int(workers), episodes), max_steps,
                            seed=seed, timeout_s=timeout_s, cpus_per_worker=cpus_per_worker)
    reshape = BatchSizeTransform(reshape_fn=partial(_reshape, shape=(tasks, episodes)))
    reshape.enable_inv_on_reset = True  # reset TensorDicts (goals, "_reset") go to the workers
    return TransformedEnv(split, reshape)


class RayEpisodeCollector(EpisodeCollector):
    """:class:`EpisodeCollector` whose ``K`` tasks are split over ``workers`` Ray actors.

    Args:
        make_env: builds one worker's env, called as ``make_env(batch_size=(K // workers,
            episodes), max_steps=max_steps, seed=seed)``; a Hydra ``_partial_: true`` node. It is
            pickled to the actors, so the nodes of a cluster need ``armeta_rl`` importable.
        episodes: episodes per task (the paper: 20).
        max_steps: episode length limit.
        workers: Ray actors; it must divide every task count collected.
        address: the Ray cluster (:func:`connect_ray`): ``None`` (a Ray instance in this
            process), ``"auto"``, ``"host:port"`` or ``"ray://host:port"``.
        seed: seed the workers' envs are built with (every ``collect`` reseeds them from torch's
            global RNG).
        timeout_s: longest wait for the actors' answers (their start included).
        connect_timeout_s: longest wait for the cluster's address to answer.
        cpus_per_worker: CPUs Ray reserves for each actor (0: none, the actors share cores).
        device: where the trajectories are returned (the actors' envs step on the CPU).

    The cluster is joined when the collector is built (a bad address fails before any training);
    actors start at the first ``collect`` of each task count and stay until :meth:`close`. Output
    and seeding as :class:`EpisodeCollector` (see the module docstring).
    """

    def __init__(
        self,
        make_env: Callable[..., EnvBase],
        episodes: int = 20,
        max_steps: int = 100,
        workers: int = 2,
        address: str | None = None,
        seed: int = 0,
        timeout_s: float = 300.0,
        connect_timeout_s: float = 10.0,
        cpus_per_worker: float = 1.0,
        device: torch.device = CPU,
    ) -> None:
        checks = {
            WORKERS_KEY: (workers, int(workers) >= 1, "must be >= 1"),
            f"{KEY}.timeout_s": (timeout_s, float(timeout_s) > 0, "must be > 0"),
            f"{KEY}.connect_timeout_s": (connect_timeout_s, float(connect_timeout_s) > 0,
                                         "must be > 0"),
            f"{KEY}.cpus_per_worker": (cpus_per_worker, float(cpus_per_worker) >= 0,
                                       "must be >= 0"),
        }
        for key, (value, ok, allowed) in checks.items():
            if not ok:
                raise ConfigError(key, value, allowed)
        connect_ray(address, float(connect_timeout_s))
        self.workers = int(workers)
        self.worker_env = make_env
        split = partial(make_ray_task_split_env, make_env, self.workers, seed=seed,
                        timeout_s=float(timeout_s), cpus_per_worker=float(cpus_per_worker))
        super().__init__(split, episodes, max_steps, device)

    def probe_env(self) -> EnvBase:
        """One worker's env of batch size ``[1, 1]``, built here (no actors), to check task boxes
        and read sizes on."""
        return self.worker_env(batch_size=(1, 1), max_steps=1)

    def close(self) -> None:
        """Stop the actors (new ones start at the next ``collect``)."""
        for env in self._envs.values():
            if not env.is_closed:
                env.close()
        self._envs.clear()

