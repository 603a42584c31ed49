"""The run directory: its layout, its lock, and writing files in it atomically.

A run directory holds ``run.lock`` (while a run holds it), ``config.yaml`` (the resolved
config), ``checkpoints/``, ``logs/``, ``eval.json`` and ``density.png``.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from armeta_rl.errors import ConfigError
from armeta_rl.run_files import FileRefused, read_file
from armeta_rl.trainers.checkpoint import write_file

LOCK_FILE = "run.lock"
CSV_LOG_DIR = "logs"
LOG_BYTES = 2**28
"""The most a CSV log of one scalar is read on resume (256 MiB; a row takes a few dozen
bytes)."""


def check_run_dir(run_dir: Path, key: str) -> None:
    """Refuse, before anything is written, a run directory that is an existing file, a link to
    nothing or a link loop, a path the file system cannot name (a component over 255 bytes, a
    path over 4,096), or that cannot be created or written (a read-only file system or
    directory: tried by creating and removing a hidden file, which also holds for root and for
    special file systems)."""
    try:
        os.stat(run_dir)
    except FileNotFoundError:
        if run_dir.is_symlink():
            raise ConfigError(key, str(run_dir), "is a link to nothing") from None
    except NotADirectoryError:
        pass  # a file where a parent should be: named below
    except OSError as error:
        raise ConfigError(key, _shown(run_dir), f"cannot be used ({error.strerror})") from None
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(key, str(run_dir), "is an existing file, not a directory")
    existing = next(p for p in (run_dir, *run_dir.parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(key, str(run_dir), f"cannot be created: {existing} is a file")
    problem = unwritable(existing)
    if problem is not None:
        raise ConfigError(key, str(run_dir), f"cannot be written in {existing} ({problem})")


def check_contents(run_dir: Path, key: str) -> None:
    """Refuse, before anything in it is read or written, a run directory that holds anything but
    folders and regular files of one link: a symbolic link (which a run would read or write
    through, outside its directory), a hard link (a file shared with another place, which a log
    appended to would change there too) or a special file (a pipe, which a read would wait on
    forever). A run writes none of them; the lock file is checked as it is taken
    (:func:`run_lock`)."""
    pending = [run_dir]
    while pending:
        folder = pending.pop()
        with os.scandir(folder) as entries:
            for entry in entries:
                info = entry.stat(follow_symlinks=False)
                name = Path(entry.path).relative_to(run_dir)
                if stat.S_ISDIR(info.st_mode):
                    pending.append(Path(entry.path))
                elif entry.name == LOCK_FILE and folder == run_dir:
                    continue
                elif stat.S_ISLNK(info.st_mode):
                    raise ConfigError(key, str(run_dir), f"its {name} is a link: a run "
                                      "directory holds no links (remove it)")
                elif not stat.S_ISREG(info.st_mode):
                    raise ConfigError(key, str(run_dir), f"its {name} is not a regular file (a "
                                      "pipe, a device, a socket): remove it")
                elif info.st_nlink != 1:
                    raise ConfigError(key, str(run_dir), f"its {name} has {info.st_nlink} hard "
                                      "links: a run's files have one (copy the run with cp -r, "
                                      "not cp -l)")


def _shown(path: Path, most: int = 120) -> str:
    """``path`` as an error line shows it: its end, where it is over ``most`` characters."""
    text = str(path)
    return text if len(text) <= most else "…" + text[-most:]


def unwritable(directory: Path) -> str | None:
    """Why no file can be created in ``directory`` (``read-only``, ...), or ``None``: a hidden
    file is created there and removed."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".armeta-probe-", dir=directory)
    except OSError as error:
        return "read-only" if error.errno in (errno.EACCES, errno.EPERM, errno.EROFS) else (
            error.strerror or str(error)).lower()
    os.close(fd)
    os.unlink(probe)
    return None


@contextmanager
def run_lock(run_dir: Path, key: str) -> Iterator[Path]:
    """Hold an exclusive lock on ``run_dir`` (``fcntl.flock`` on ``run.lock``, which names the
    holder's pid) for the ``with`` block, creating the directory.

    The lock file is removed when the block ends; the kernel releases the lock when its holder
    exits, however it exits, so a lock file left by a dead process is taken over. A lock is
    taken once per run: a second ``run_lock`` on a directory this process holds is refused like
    another run's (:func:`hold_run_dir` hands the held directory on instead).

    Raises:
        ConfigError: naming ``key``, if another run (in any process) holds the lock.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK_FILE
    while True:
        try:  # never through a link: the lock file is the run's own
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK
                         | os.O_NOCTTY, 0o644)
        except OSError as error:
            if error.errno != errno.ELOOP:
                raise
            raise ConfigError(key, str(run_dir), f"its {LOCK_FILE} is a link, not a lock file "
                              "a run made: remove it") from None
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
            os.close(fd)
            what = ("is not a regular file" if not stat.S_ISREG(info.st_mode) else
                    f"has {info.st_nlink} hard links (a run's lock has one; a run would write "
                    "its pid into the file it shares)")
            raise ConfigError(key, str(run_dir), f"its {LOCK_FILE} {what}: remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
            os.close(fd)
            if error.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            raise ConfigError(
                key, str(run_dir),
                f"is in use by another run (pid {holder or '?'}): wait for it to end or "
                "choose another directory",
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


@dataclass(frozen=True)
class HeldRunDir:
    """A run directory this process has checked and locked (:func:`hold_run_dir`), for as long as
    that block runs: what a caller that took it hands on, so that nothing checks or locks it
    again. ``key``: the config key its errors name (``hydra.run.dir`` or ``resume``).
    ``created``: the outermost of ``path`` and its parents that taking it created (``None``: the
    directory existed), so that a run refused before it wrote anything can remove every
    directory its command made."""

    path: Path
    key: str
    created: Path | None


@contextmanager
def hold_run_dir(run_dir: Path, key: str, resume: bool) -> Iterator[HeldRunDir]:
    """Check ``run_dir`` (:func:`check_run_dir`), lock it (:func:`run_lock`) and, for a resumed
    run, check what it holds under the lock (:func:`check_contents`), once per run: the CLI does
    it before Hydra writes its job log there and hands the result to
    :func:`~armeta_rl.trainers.training.run_training`, which otherwise does it itself."""
    check_run_dir(run_dir, key)
    created = next((p for p in (*reversed(run_dir.parents), run_dir) if not p.exists()), None)
    with run_lock(run_dir, key):
        if resume:
            check_contents(run_dir, key)
        yield HeldRunDir(run_dir, key, created)


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``fd`` is still the file at ``path`` (a lock's holder removes it on release)."""
    try:
        return os.fstat(fd).st_ino == os.stat(path).st_ino
    except FileNotFoundError:
        return False


def write_config(values: dict[str, Any], path: Path) -> None:
    """Save a config's ``values`` (:meth:`armeta_rl.config.TrainConfig.values`) as YAML at
    ``path`` atomically (a crash leaves the old file or none)."""
    write_text_atomically(path, OmegaConf.to_yaml(values))


def write_text_atomically(path: Path, text: str) -> None:
    """Write ``text`` to a hidden sibling of ``path``, fsync it and rename it over ``path``."""
    write_atomically(path, lambda staged: write_file(staged, text.encode()))


def write_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """Have ``write`` write the file ``path`` into a hidden sibling ``.<stem>.<pid><suffix>``
    (the suffix kept: matplotlib and Pillow choose the format by it), fsync it and rename it over
    ``path``: a crash or a full disk leaves the old file or none, never a partial one (the
    sibling is removed, or by the next run, :func:`staged_leftovers`). An ``OSError`` of the
    write names ``path``."""
    staged = path.with_name(f".{path.stem}.{os.getpid()}{path.suffix}")
    try:
        write(staged)
        fd = os.open(staged, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(staged, path)
    except OSError as error:  # named as the file it was writing (EFBIG, ENOSPC, ...)
        if error.filename in (None, str(staged)):
            raise OSError(error.errno, error.strerror or str(error), str(path)) from error
        raise
    finally:
        staged.unlink(missing_ok=True)


def staged_leftovers(run_dir: Path, folders: Iterable[str]) -> list[Path]:
    """The hidden siblings that :func:`write_atomically` left in ``folders`` of ``run_dir``
    (``"."``: the run directory itself; CSV logs: every folder below) when a crash interrupted
    it: hidden files with a pid among their dotted parts (``.eval.4242.json``, and
    ``.eval.json.4242``); remove them only while holding the run's lock."""
    found = []
    for folder in folders:
        where = run_dir / folder
        paths = where.rglob(".*.*") if folder == CSV_LOG_DIR else where.glob(".*.*")
        found += [p for p in paths
                  if p.is_file() and any(part.isdigit() for part in p.name.split(".")[2:])]
    return found


def drop_csv_rows_after(run_dir: Path, iteration: int, evaluated: bool = False) -> None:
    """Delete the CSV log rows of iterations after ``iteration`` (the checkpoint a run resumes
    from): a run that crashed logged past its last checkpoint, and the resumed run logs those
    iterations again, so without this every scalar would hold them twice. The evaluation's rows
    (``eval/``) at ``iteration`` go too, unless ``evaluated`` (the run finished there and is
    resumed to train longer): they were logged by an evaluation that a crash cut short. A last
    row without its line end (a write the crash cut short) is dropped too.

    Raises:
        ConfigError: a complete row does not start with an iteration number.
    """
    scalars = run_dir / CSV_LOG_DIR / "scalars"
    for path in scalars.rglob("*.csv"):
        last = iteration - (not evaluated and path.relative_to(scalars).parts[0] == "eval")
        try:
            text = read_file(path, LOG_BYTES, run_dir).decode(errors="replace")
        except FileRefused as error:
            raise ConfigError("resume", str(run_dir), f"its log {path.relative_to(run_dir)} "
                              f"{error.reason}") from None
        except OSError as error:
            raise ConfigError("resume", str(run_dir), f"its log {path.relative_to(run_dir)} "
                              f"cannot be read ({error.strerror or error})") from None
        rows = text.splitlines(keepends=True)
        if rows and not rows[-1].endswith("\n"):
            rows[-1] = ""
        kept = [row for row in rows if row and _csv_step(row, path, run_dir) <= last]
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
