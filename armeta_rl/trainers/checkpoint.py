"""Run checkpoints through ``torchrl.checkpoint``: leader, principle, RNG state and iteration.

A checkpoint is a ``torchrl.checkpoint`` directory ``checkpoints/checkpoint-<12-digit step>``
whose ``manifest.json`` also records, under ``metadata.integrity``, the size and SHA-256 of every
payload file and the SHA-256 of the manifest itself. A load verifies them first, so a truncated,
garbled or half-deleted checkpoint is recognised as broken before any payload is read.

A checkpoint is data handed over with its run directory, never code: it is loaded only as this
package writes it (:func:`verify`, :class:`TorchPayload`): ``manifest.json``, and per component
exactly one ``state.pt`` read by ``torch.load(weights_only=True)`` (tensors, numbers, strings,
containers) or one ``value.json``, each a regular file of one link reached through no link
(:func:`armeta_rl.run_files.read_file`). Anything else (TensorDict memory maps, whose non-tensor
fields are pickles, other files, links, a payload holding any other object) is refused, naming
the file, before anything is unpickled.

Checkpoints load across devices: payloads are read onto the device the players were built on
(``map_location``), so a run saved on a GPU resumes or is evaluated on the CPU and back.

Writes are atomic and durable: a checkpoint is written into a hidden staging directory, sealed
(checksums added, every file and directory fsynced) and only then renamed to its final name.
Payloads are written by :func:`write_file` with plain writes (``torch.save`` into memory first):
no file is memory-mapped, so a full disk raises ``OSError(ENOSPC)`` instead of killing the
process with SIGBUS.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import logging
import os
import pickle
import re
import shutil
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import torch
from torchrl.checkpoint import (
    Checkpoint,
    CheckpointError,
    CheckpointRotation,
    GlobalRNGState,
    JSONCheckpointAdapter,
    StateDictCheckpointAdapter,
)

from armeta_rl.config import value_at
from armeta_rl.devices import CPU
from armeta_rl.errors import CheckpointBroken, ConfigError, RunDirectoryError
from armeta_rl.learners.base import Leader
from armeta_rl.risk.base import RiskPrinciple
from armeta_rl.run_files import FileRefused, read_file

log = logging.getLogger(__name__)

PREFIX = "checkpoint"
MANIFEST = "manifest.json"
MANIFEST_BYTES = 2**20
"""The most a checkpoint's manifest (or a ``value.json``) may hold (a few KiB in practice): a
larger file there is refused, not read without end."""
PAYLOAD_BYTES = 2**34
"""The most a ``state.pt`` is read (16 GiB: a leader, its optimizer and the adversary take a few
MiB at the package's sizes); a payload is read only after its size matched its record."""
PAYLOAD_FILES = {"torchrl.state_dict": "state.pt", "torchrl.json": "value.json"}
"""The one file each component's adapter writes, by adapter: all a checkpoint may hold besides
its manifest."""
IDENTITY_KEYS = ("seed", "benchmark.name", "benchmark.space", "benchmark.initial", "method",
                 "learner", "risk", "trainer.meta_batch", "trainer.follower_rollouts",
                 "trainer.follower_at")
"""The config keys whose values make a run's results what they are (:func:`run_identity`);
those a resume may change (iterations, device, logging) are not among them."""
BROKEN_SUFFIX = ".broken"
_NAME = re.compile(rf"{PREFIX}-(\d{{12}})")


def checkpoint_dirs(directory: Path) -> list[Path]:
    """Every checkpoint directory in a run's ``checkpoints`` folder ``directory``, intact or not,
    oldest first; none when the folder is missing."""
    if not directory.is_dir():
        return []
    found = [p for p in directory.iterdir() if _NAME.fullmatch(p.name) and p.is_dir()]
    return sorted(found, key=lambda p: p.name)


def write_file(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` with plain writes and fsync it: the one writer of checkpoint
    payloads and manifests (fault-injection tests replace it to simulate a full disk)."""
    with open(path, "wb") as file:
        file.write(data)
        file.flush()
        os.fsync(file.fileno())


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _manifest_digest(manifest: Mapping[str, Any]) -> str:
    """SHA-256 of the manifest's canonical JSON without its own digest."""
    body = json.loads(json.dumps(manifest))
    body["metadata"]["integrity"].pop("manifest_sha256", None)
    return _sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())


def load_tensors(path: Path, map_location: Any, below: Path) -> Any:
    """The ``state_dict`` in the ``state.pt`` at ``path`` (:func:`read_file` from ``below``),
    unpickled by ``torch.load(weights_only=True)`` alone: tensors, numbers, strings and
    containers of them. Any other object in it is refused, not built.

    Raises:
        FileRefused: ``path`` is not a file this package writes there, or holds another object
            (torch's reason folded into the one line).
    """
    data = read_file(path, PAYLOAD_BYTES, below)
    try:
        return torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        lines = [line for line in str(error).splitlines() if line.strip() and not line.startswith(
            ("Weights only load failed", "Check the documentation"))]
        reason = lines[0].strip() if lines else "an object other than tensors"
        raise FileRefused(path, f"holds what torch.load(weights_only=True) refuses ({reason}): "
                          "a state.pt holds tensors only") from None
    except (RuntimeError, EOFError, ValueError) as error:
        reason = " ".join(str(error).split())[:160]
        raise FileRefused(path, f"is not a torch.save file ({reason})") from None


class TorchPayload(StateDictCheckpointAdapter):
    """``state_dict`` payloads as one ``state.pt`` per component (torchrl's ``"torch"`` payload
    format), serialised in memory and written by :func:`write_file`, read back by
    :func:`load_tensors` only (torchrl's own load would also take a TensorDict payload there,
    whose non-tensor fields it unpickles). TensorDict directory payloads memory-map their files,
    and a write into a memory map on a full disk is a SIGBUS rather than an error."""

    def __init__(self) -> None:
        super().__init__("torch")

    def save(
        self, component: Any, path: Path, *, args: tuple[Any, ...], kwargs: Mapping[str, Any]
    ) -> Any:
        path.mkdir(parents=True, exist_ok=True)
        state = component.state_dict(*args, **kwargs)
        buffer = io.BytesIO()
        torch.save(state, buffer)
        write_file(path / self.state_torch, buffer.getvalue())
        return state

    def load(
        self, component: Any, path: Path, *, map_location: Any,
        tensor_load_kwargs: Mapping[str, Any], args: tuple[Any, ...], kwargs: Mapping[str, Any],
    ) -> None:
        """Load ``path``'s ``state.pt`` (:func:`load_tensors`) into ``component``."""
        state = load_tensors(path / self.state_torch, map_location, path.parents[1])
        component.load_state_dict(state, *args, **kwargs)


class JsonPayload(JSONCheckpointAdapter):
    """torchrl's JSON values (the iteration count), read by :func:`read_file` only."""

    def load(
        self, component: Any, path: Path, *, map_location: Any,
        tensor_load_kwargs: Mapping[str, Any], args: tuple[Any, ...], kwargs: Mapping[str, Any],
    ) -> Any:
        """Update the mapping ``component`` with ``path``'s ``value.json``."""
        file = path / self.state_filename
        data = read_file(file, MANIFEST_BYTES, path.parents[1])
        try:
            value = json.loads(data)
        except ValueError as error:
            raise FileRefused(file, f"is not JSON ({error})") from None
        if not isinstance(value, dict):
            raise FileRefused(file, "is not a JSON object")
        component.clear()
        component.update(value)
        return component


def run_identity(values: Mapping[str, Any]) -> dict[str, Any]:
    """What makes a run this run: its benchmark, method and seed, and the SHA-256 of the values
    of :data:`IDENTITY_KEYS` in its config's resolved ``values`` (:meth:`TrainConfig.values
    <armeta_rl.config.TrainConfig.values>`, or a saved ``config.yaml`` loaded and resolved), a
    key a config lacks counting as ``null``. A checkpoint records it, and a resume or an
    evaluation refuses a checkpoint of another run (:meth:`RunCheckpoint.restore`)."""
    chosen = {key: value_at(values, key) for key in IDENTITY_KEYS}
    text = json.dumps(chosen, sort_keys=True, default=str)
    return {"benchmark": str(values["benchmark"]["name"]), "method": str(values["method"]["name"]),
            "seed": int(values["seed"]), "config_sha256": _sha256(text.encode())}


def identity_as_saved(text: str) -> dict[str, Any] | None:
    """The identity (:func:`run_identity`) of a run whose ``config.yaml`` holds ``text``, from
    its values as written, not merged into this version's schema: what the run's own
    checkpoints and reports recorded, which a key added since (at a default that keeps the
    run's behaviour) leaves unchanged. ``None`` for a text that is not a run's config (one its
    readers refuse). A fresh dict each call, from a digest remembered by text: a report check
    asks for every run's several times, and resolving a config is most of that check's time."""
    identity = _identity_of_text(text)
    return None if identity is None else dict(identity)


@functools.lru_cache(maxsize=4096)
def _identity_of_text(text: str) -> dict[str, Any] | None:
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from armeta_rl.config import CONFIG_FILE
    from armeta_rl.run_files import plain_yaml

    try:
        values = OmegaConf.to_container(OmegaConf.create(plain_yaml(text, CONFIG_FILE)),
                                        resolve=True)
        return run_identity(values)
    except (FileRefused, ValueError, TypeError, AttributeError, OmegaConfBaseException):
        return None


def saved_identity(run_dir: str | Path) -> dict[str, Any] | None:
    """:func:`identity_as_saved` of the ``config.yaml`` in ``run_dir`` (read bounded, through no
    link), or ``None`` where it cannot be read."""
    from armeta_rl.config import CONFIG_BYTES, CONFIG_FILE
    from armeta_rl.run_files import read_text

    path = Path(run_dir) / CONFIG_FILE
    try:
        return identity_as_saved(read_text(path, CONFIG_BYTES, run_dir))
    except (OSError, FileRefused, UnicodeDecodeError):
        return None


def seal(stage: Path, identity: Mapping[str, Any] | None = None) -> None:
    """Add the size and SHA-256 of every file below ``stage`` and the manifest's own SHA-256 to
    its manifest (and the run's ``identity``, :func:`run_identity`), then fsync every file and
    directory there."""
    manifest_path = stage / MANIFEST
    manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    if identity is not None:
        manifest["metadata"]["identity"] = dict(identity)
    files = {}
    for path in sorted(stage.rglob("*")):
        if path.is_file() and path != manifest_path:
            data = path.read_bytes()
            files[path.relative_to(stage).as_posix()] = {"size": len(data), "sha256": _sha256(data)}
            _fsync(path)
    manifest["metadata"]["integrity"] = {"algorithm": "sha256", "files": files}
    manifest["metadata"]["integrity"]["manifest_sha256"] = _manifest_digest(manifest)
    write_file(manifest_path, (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode())
    for directory in sorted({p.parent for p in stage.rglob("*")} | {stage}, reverse=True):
        _fsync(directory)


def verify(path: Path, below: Path | None = None) -> str | None:
    """Why the checkpoint at ``path`` is broken, or ``None`` if it is intact; every file read
    from ``below`` (the run directory; default ``path``'s parent) through no link
    (:func:`~armeta_rl.run_files.read_file`).

    Checks the manifest's own digest, then that every file the manifest records exists with the
    recorded size and SHA-256, and that every component's listed files are among them.
    Checkpoints written before integrity records existed (no ``metadata.integrity``) are only
    checked for their listed files being present.

    Raises:
        FileRefused: the checkpoint holds what this package never writes there (a link, a hard
            link, a special file, a file or folder outside its layout, a component whose payload
            is not its one ``state.pt`` or ``value.json``): not damage, so no older checkpoint
            stands in for it.
    """
    below = path.parent if below is None else below
    try:
        read_file(path / MANIFEST, MANIFEST_BYTES, below)  # what torchrl then reads unbounded
        manifest = Checkpoint.manifest(path)
    except FileNotFoundError:
        return f"missing {MANIFEST}"
    except (CheckpointError, OSError, ValueError) as error:
        if isinstance(error, FileRefused):
            raise
        return f"unreadable manifest: {' '.join(str(error).split())}"
    check_layout(path, manifest["components"])
    components = manifest["components"]
    listed = {
        f"{record['path']}/{name}" for record in components.values() for name in record["files"]
    }
    metadata = manifest.get("metadata")
    integrity = metadata.get("integrity") if isinstance(metadata, dict) else None
    if integrity is None:
        missing = sorted(name for name in listed if not (path / name).is_file())
        return f"missing {missing[0]}" if missing else None
    files = integrity.get("files") if isinstance(integrity, dict) else None
    if not isinstance(files, dict) or not all(
            isinstance(r, dict) and isinstance(r.get("size"), int) for r in files.values()) or (
            integrity.get("manifest_sha256") != _manifest_digest(manifest)):
        return f"{MANIFEST} does not match its checksum"
    unrecorded = sorted(listed.difference(files))
    if unrecorded:
        return f"{unrecorded[0]} has no checksum"
    for name, record in sorted(files.items()):
        try:
            size = os.stat(path / name, follow_symlinks=False).st_size
            if size != record["size"]:
                return f"{name} has {size} bytes, {record['size']} expected"
            data = read_file(path / name, min(size, PAYLOAD_BYTES), below)
        except FileNotFoundError:
            return f"missing {name}"
        except OSError as error:
            return f"{name} cannot be read ({error.strerror or error})"
        if _sha256(data) != record.get("sha256"):
            return f"{name} does not match its SHA-256"
    return None


def check_layout(path: Path, components: Mapping[str, Any]) -> None:
    """Refuse (:class:`~armeta_rl.run_files.FileRefused`) anything in the checkpoint ``path``
    that this package does not write there: its manifest, and per component one folder
    ``components/<NNNN>-<name>`` holding its one payload file (:data:`PAYLOAD_FILES`), each a
    regular file or folder, not a link. Missing files are left to :func:`verify` (damage)."""
    files, folders = {MANIFEST}, {"components"}
    for name, record in components.items():
        payload = PAYLOAD_FILES.get(record["adapter"])
        if payload is None or record["files"] != [payload] or not re.fullmatch(
                r"components/\d{4}-[\w.%-]+", record["path"]):
            raise FileRefused(path / MANIFEST, f"lists component {name!r} as {record['path']}/"
                              f"{record['files']}: a checkpoint of this package holds one "
                              f"{' or '.join(PAYLOAD_FILES.values())} per component")
        files.add(f"{record['path']}/{payload}")
        folders.add(record["path"])
    pending = [(path, "")]
    while pending:
        folder, prefix = pending.pop()
        with os.scandir(folder) as entries:
            for entry in entries:
                name = prefix + entry.name
                if entry.is_symlink():
                    raise FileRefused(path / name, "is a link: a checkpoint holds no links")
                if entry.is_dir(follow_symlinks=False) and name in folders:
                    pending.append((Path(entry.path), name + "/"))
                elif not (entry.is_file(follow_symlinks=False) and name in files):
                    raise FileRefused(path / name, "is not part of a checkpoint this package "
                                      f"writes (allowed: {MANIFEST}, components/*/"
                                      f"{', components/*/'.join(PAYLOAD_FILES.values())})")


class PortableRNGState(GlobalRNGState):
    """TorchRL's process-global RNG state, restorable where the saving machine's accelerator is
    absent: a run saved on CUDA and resumed on the CPU gets its Python, NumPy and CPU streams back;
    its CUDA streams have nowhere to go and are left out."""

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        """Restore the saved streams this process has a device for."""
        if not torch.cuda.is_available():
            state_dict = {k: v for k, v in state_dict.items() if k != "torch_cuda"}
        super().load_state_dict(state_dict)


class RunCheckpoint:
    """Saves and restores everything a run needs to continue bit-for-bit.

    Components: the leader (parameters and optimizer), the risk principle (adversary, its
    optimizer and scheduler, group weights), the process-global RNG states and the number of
    completed iterations; they are loaded onto ``device``. Payloads are ``torch.save`` files
    loaded with ``weights_only=True`` (no arbitrary pickle); the ``keep_last`` newest checkpoints
    are kept. A restore takes only checkpoints that record ``identity`` (the run's,
    :func:`run_identity`) or one of ``accepts`` (the same run's as its config was saved,
    :func:`saved_identity`), or, with ``adopt``, none (checkpoints written before identities
    were recorded).

    Examples:
        >>> import tempfile
        >>> from armeta_rl.collectors import SinusoidCollector
        >>> from armeta_rl.learners import MAMLLeader, make_mlp
        >>> from armeta_rl.risk import ERMPrinciple
        >>> from armeta_rl.tasks import BoxUniform, TaskSpace
        >>> from armeta_rl.trainers import RunCheckpoint
        >>> space = TaskSpace(["amplitude", "phase"], low=[0.1, 0.0], high=[5.0, 3.1416])
        >>> leader = MAMLLeader(make_mlp(1, 1, hidden=[16]), SinusoidCollector())
        >>> run_dir = tempfile.TemporaryDirectory()
        >>> checkpoint = RunCheckpoint(run_dir.name, leader, ERMPrinciple(BoxUniform(space)))
        >>> checkpoint.save(3).name
        'checkpoint-000000000003'
        >>> checkpoint.restore("resume")  # the iteration it continues from
        3
        >>> run_dir.cleanup()
    """

    def __init__(
        self, directory: str | Path, leader: Leader, principle: RiskPrinciple, keep_last: int = 2,
        device: torch.device = CPU, identity: Mapping[str, Any] | None = None,
        adopt: bool = False, accepts: Collection[Mapping[str, Any] | None] = (),
    ) -> None:
        self.directory = Path(directory)
        self.device = device
        self.identity = None if identity is None else dict(identity)
        self.accepts = [dict(other) for other in accepts if other is not None]
        self.adopt = adopt
        self.progress = {"iteration": 0}
        payload = TorchPayload()
        self.checkpoint = Checkpoint()
        self.checkpoint.register("leader", leader, adapter=payload)
        self.checkpoint.register("principle", principle, adapter=payload)
        self.checkpoint.register("rng", PortableRNGState(), adapter=payload)
        self.checkpoint.register("progress", self.progress, adapter=JsonPayload())
        self.rotation = CheckpointRotation(self.directory, keep_last=keep_last, prefix=PREFIX)

    def checkpoints(self) -> list[Path]:
        """Every checkpoint directory on disk, intact or not, oldest first."""
        return checkpoint_dirs(self.directory)

    def clean_staging(self) -> list[Path]:
        """Remove what interrupted writes left behind (hidden staging, backup and deletion
        directories); call only while holding the run's lock. Returns the removed paths."""
        if not self.directory.is_dir():
            return []
        leftovers = [p for p in self.directory.iterdir() if p.name.startswith(".")]
        for path in leftovers:
            remove_tree(path)
        return leftovers

    def path(self, iteration: int) -> Path:
        """The directory of the checkpoint written after ``iteration`` iterations."""
        return self.directory / f"{PREFIX}-{iteration:012d}"

    def save(self, iteration: int) -> Path:
        """Write a checkpoint after ``iteration`` completed iterations, atomically.

        Raises:
            RunDirectoryError: the checkpoint could not be written (a full disk, a read-only
                directory); the checkpoints written before are untouched.
        """
        self.progress["iteration"] = iteration
        final = self.path(iteration)
        stage = self.directory / f".{final.name}.staging-{os.getpid()}"
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            remove_tree(stage)
            self.checkpoint.save(stage)
            seal(stage, self.identity)
            if final.exists():
                replaced = self.directory / f".{final.name}.replaced-{os.getpid()}"
                os.replace(final, replaced)
                os.replace(stage, final)
                remove_tree(replaced)
            else:
                os.replace(stage, final)
            _fsync(self.directory)
            self.rotation.prune()
        except OSError as error:
            remove_tree(stage)
            raise RunDirectoryError(
                f"cannot write the checkpoint {final}: {error.strerror or error}"
            ) from error
        return final

    def restore(
        self, key: str, components: Collection[str] | None = None, fallback: bool = True
    ) -> int:
        """Load the newest intact checkpoint (all components, or ``components``); returns its
        iteration.

        With ``fallback`` a broken checkpoint is renamed ``<name>.broken``, logged as a warning
        naming it and why, and the next older one is tried; without, it is refused. Every
        checkpoint is verified first (:func:`verify`): one that holds what this package never
        writes is refused, whichever it is, and so is anything else in ``checkpoints/``.

        Raises:
            CheckpointBroken: no intact checkpoint (or, without ``fallback``, the newest is
                broken), naming ``key`` (the option that pointed at the run).
            ConfigError: naming ``key`` and the file, for a file no checkpoint of this package
                holds; a checkpoint of another run, or (without ``adopt``) one that records no
                run; or one that does not fit the players built from the run's config, e.g. a
                run saved by a version of armeta_rl whose defaults built other networks.
        """
        run_dir = str(self.directory.parent)
        try:
            self._check_entries()
            checked = [(path, verify(path, self.directory.parent))
                       for path in reversed(self.checkpoints())]
        except FileRefused as error:
            raise ConfigError(key, run_dir, f"its {self._named(error)}") from None
        broken, earlier = [], self.set_aside()
        for path, reason in checked:
            if reason is None:
                self._check_identity(path, key)
                self._load(path, key, components)
                return int(self.progress["iteration"])
            if not fallback:
                raise CheckpointBroken(
                    key, run_dir,
                    f"its newest checkpoint {path.name} is broken ({reason}); "
                    f"armeta-train resume={run_dir} falls back to the newest intact one",
                )
            aside = path.with_name(path.name + BROKEN_SUFFIX)
            os.replace(path, aside)
            log.warning("checkpoint %s is broken (%s): moved to %s", path, reason, aside.name)
            broken.append(f"{path.name} ({reason})")
        broken += [f"{p.name} (set aside by an earlier resume)" for p in earlier]
        found = f"; broken: {', '.join(broken)}" if broken else ""
        raise CheckpointBroken(key, run_dir, f"has no intact checkpoint{found}")

    def set_aside(self) -> list[Path]:
        """The checkpoints a restore found broken and renamed ``<name>.broken``, oldest first: a
        run that has them was trained, so it never starts again from iteration 0 by itself."""
        if not self.directory.is_dir():
            return []
        return sorted(p for p in self.directory.glob(f"{PREFIX}-*{BROKEN_SUFFIX}") if p.is_dir())

    def _named(self, error: FileRefused) -> str:
        """``error``'s file relative to the run directory, and why it is refused."""
        path = Path(error.path)
        shown = path.relative_to(self.directory.parent) if path.is_relative_to(
            self.directory.parent) else path
        return f"{shown} {error.reason}"

    def _check_entries(self) -> None:
        """Refuse anything in ``checkpoints/`` but checkpoints (``checkpoint-<12 digits>``, and
        those set aside as ``.broken``) and hidden leftovers of interrupted writes: torchrl's
        rotation would read, keep or prune any other ``checkpoint-*`` it finds there."""
        if not self.directory.is_dir():
            return
        for path in self.directory.iterdir():
            name = path.name.removesuffix(BROKEN_SUFFIX)
            if not (path.name.startswith(".") or _NAME.fullmatch(name)):
                raise FileRefused(path, "is not a checkpoint this package writes "
                                  f"({PREFIX}-<12 digits>)")

    def _check_identity(self, path: Path, key: str) -> None:
        """Refuse a checkpoint whose recorded identity is another run's (one copied from another
        run's directory), or that records none unless ``adopt`` says it is this run's."""
        metadata = Checkpoint.manifest(path).get("metadata")
        saved = metadata.get("identity") if isinstance(metadata, dict) else None
        if self.identity is None or saved == self.identity or saved in self.accepts:
            return
        run = (f"benchmark {self.identity['benchmark']}, method {self.identity['method']}, "
               f"seed {self.identity['seed']}")
        if saved is None:
            if self.adopt:
                return
            raise ConfigError(key, str(self.directory.parent), (
                f"its checkpoint {path.name} records no run (written before checkpoints "
                f"recorded theirs, or with it removed), so nothing shows it is this run's "
                f"({run}): if it is, add adopt=true"))
        differ = [f"{name} {saved.get(name)!r} (this run: {value!r})"
                  for name, value in self.identity.items()
                  if not isinstance(saved, dict) or saved.get(name) != value]
        raise ConfigError(key, str(self.directory.parent),
                          f"its checkpoint {path.name} is another run's: {'; '.join(differ)}")

    def _load(self, path: Path, key: str, components: Collection[str] | None) -> None:
        try:
            self.checkpoint.load(path, components=components, map_location=self.device)
        except CheckpointError as error:
            cause = error.__cause__
            if isinstance(cause, FileRefused):
                raise ConfigError(key, str(self.directory.parent),
                                  f"its {self._named(cause)}") from None
            if isinstance(cause, OSError):
                raise ConfigError(key, str(self.directory.parent), (
                    f"its checkpoint {path.name} cannot be read ({cause.strerror or cause})"
                )) from None
            reason = " ".join(str(cause or error).split())
            raise ConfigError(
                key, str(self.directory.parent),
                f"its checkpoint {path.name} does not fit the players its config.yaml builds "
                f"({reason})") from None
        named = int(_NAME.fullmatch(path.name).group(1))
        if (components is None or "progress" in components) and (
                self.progress.get("iteration") != named):
            raise ConfigError(key, str(self.directory.parent), (
                f"its checkpoint {path.name} records iteration "
                f"{self.progress.get('iteration')!r}, not the {named} its name says"))


def newest_intact(directory: Path) -> Path | None:
    """The newest checkpoint below ``directory`` that :func:`verify` accepts, if any."""
    for path in sorted(directory.glob(f"{PREFIX}-*"), reverse=True):
        try:
            if _NAME.fullmatch(path.name) and verify(path, directory.parent) is None:
                return path
        except FileRefused:
            continue
    return None


def remove_tree(path: Path) -> None:
    """Delete a file or directory tree if it exists."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()
