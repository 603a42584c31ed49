"""The run directory: its layout, its lock, and writing files in it atomically.

A run directory holds ``run.lock`` (while a run holds it), ``config.yaml`` (the resolved
config), ``checkpoints/``, ``logs/``, ``eval.json`` and ``density.png``.
"""

from __future__ import annotations

import errno
import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from armeta_rl.errors import ConfigError
from armeta_rl.trainers.checkpoint import write_file

LOCK_FILE = "run.lock"
CSV_LOG_DIR = "logs"


def check_run_dir(run_dir: Path, key: str) -> None:
    """Refuse, before anything is written, a run directory that is an existing file, or that
    cannot be created or written (a read-only file system or directory)."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(key, str(run_dir), "is an existing file, not a directory")
    existing = next(p for p in (run_dir, *run_dir.parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(key, str(run_dir), f"cannot be created: {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(key, str(run_dir), f"cannot be written: {existing} is read-only")


@contextmanager
def run_lock(run_dir: Path, key: str) -> Iterator[Path]:
    """Hold an exclusive lock on ``run_dir`` (``fcntl.flock`` on ``run.lock``, which names the
    holder's pid) for the ``with`` block, creating the directory.

    The lock file is removed when the block ends; the kernel releases the lock when its holder
    exits, however it exits, so a lock file left by a dead process is taken over. Taking a lock
    this process already holds is a no-op (the CLI locks the run directory before Hydra writes
    to it, and the run locks it again).

    Raises:
        ConfigError: naming ``key``, if another live process holds the lock.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_FILE
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
            os.close(fd)
            if error.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            if holder == str(os.getpid()):
                yield path
                return
            raise ConfigError(
                key, str(run_dir),
                f"is in use by another run (pid {holder or '?'}): wait for it to end or choose "
                "another directory",
            ) from None
        if _same_file(fd, path):
            break
        os.close(fd)  # locked a file its holder removed on release: lock the one there now
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        path.unlink(missing_ok=True)
        os.close(fd)


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``fd`` is still the file at ``path`` (a lock's holder removes it on release)."""
    try:
        return os.fstat(fd).st_ino == os.stat(path).st_ino
    except FileNotFoundError:
        return False


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
