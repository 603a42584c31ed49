"""The one reader of the files in a run or results directory, which are data handed over by
others: never code, never followed through a link, never read without a bound.

:func:`read_file` is how the package reads every file there (``config.yaml``, checkpoint
manifests and payloads, reports, logs, density frames, a results directory's manifest, packed
and curve files). It accepts a regular file of one link and at most a given size, reached from
the directory the user named without passing through a symbolic link; anything else (a link, a
hard link to a file elsewhere, a pipe, a device, a directory, a larger file) is refused with
:class:`FileRefused`, naming the file and why, before a byte is read. :func:`gunzip` bounds what
a compressed file may expand to and :func:`plain_yaml` refuses YAML whose aliases could expand
without bound. What the bytes are then read as is the caller's: JSON, YAML without aliases, CSV,
PNG, or tensors by ``torch.load(weights_only=True)``; nothing is unpickled.
"""

from __future__ import annotations

import errno
import os
import stat
import zlib
from pathlib import Path

import yaml

_OPEN = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC
_DIRECTORY = os.O_RDONLY | os.O_NOFOLLOW | os.O_DIRECTORY | os.O_CLOEXEC


class FileRefused(ValueError):
    """A file of a run or results directory that is not read: ``path`` and ``reason`` (``is a
    link``, ``is not a regular file (a pipe)``, ``is larger than …``)."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path, self.reason = str(path), reason
        super().__init__(f"{path} {reason}")

    def __reduce__(self) -> tuple[type, tuple[str, str]]:
        return type(self), (self.path, self.reason)


def _kind(mode: int) -> str:
    names = {stat.S_IFIFO: "a pipe", stat.S_IFCHR: "a device", stat.S_IFBLK: "a device",
             stat.S_IFSOCK: "a socket", stat.S_IFDIR: "a directory", stat.S_IFLNK: "a link"}
    return names.get(stat.S_IFMT(mode), "not a file")


def _open_below(path: Path, below: Path | None) -> int:
    """A descriptor of the directory holding ``path``, reached from ``below`` (``path``'s parent
    when ``None``) one component at a time without following a link."""
    base = Path(below) if below is not None else path.parent
    parts = path.relative_to(base).parts if below is not None else ()
    if below is not None and (not parts or ".." in parts):
        raise FileRefused(path, f"is not a file below {base}")
    fd = os.open(base, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        for part in parts[:-1]:
            try:
                inner = os.open(part, _DIRECTORY, dir_fd=fd)
            except OSError as error:
                if error.errno in (errno.ELOOP, errno.ENOTDIR):
                    mode = os.stat(part, dir_fd=fd, follow_symlinks=False).st_mode
                    raise FileRefused(path, f"is not read: its folder {part} is {_kind(mode)}"
                                      ) from None
                raise
            os.close(fd)
            fd = inner
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_file(path: str | Path, most: int, below: str | Path | None = None) -> bytes:
    """The bytes of ``path``, a regular file with one link (``st_nlink == 1``) of at most
    ``most`` bytes, reached from the directory ``below`` (which may itself be a link: the user
    named it) through no link: the file and every folder between are opened without following
    links, and a special file is not even opened.

    Raises:
        FileRefused: ``path`` is not such a file (a link, a hard link, a pipe, a device, a
            directory, a larger file), naming it.
        OSError: it cannot be read (``FileNotFoundError`` where it does not exist, an I/O
            error, a name the file system cannot hold).
    """
    path = Path(path)
    parent = _open_below(path, None if below is None else Path(below))
    try:
        info = os.stat(path.name, dir_fd=parent, follow_symlinks=False)
        if not stat.S_ISREG(info.st_mode):
            raise FileRefused(path, f"is {_kind(info.st_mode)}, not a regular file")
        fd = os.open(path.name, _OPEN, dir_fd=parent)
    finally:
        os.close(parent)
    with os.fdopen(fd, "rb") as file:
        opened = os.fstat(fd)
        if (opened.st_dev, opened.st_ino) != (info.st_dev, info.st_ino) or not (
                stat.S_ISREG(opened.st_mode)):
            raise FileRefused(path, "changed while it was opened")
        if opened.st_nlink != 1:
            raise FileRefused(path, f"has {opened.st_nlink} hard links, not 1: it may be "
                              "another file's (a link out of its directory)")
        if opened.st_size > most:
            raise FileRefused(path, f"has {opened.st_size} bytes, more than the {most} "
                              "such a file may hold")
        data = file.read(most + 1)
    if len(data) > most:
        raise FileRefused(path, f"grew beyond the {most} bytes such a file may hold")
    return data


def read_text(path: str | Path, most: int, below: str | Path | None = None) -> str:
    """:func:`read_file` decoded as UTF-8 (:class:`FileRefused` if it is not)."""
    data = read_file(path, most, below)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise FileRefused(path, f"is not UTF-8 text (byte {error.start})") from None


def gunzip(data: bytes, most: int, path: str | Path) -> bytes:
    """The gzip ``data`` of the file ``path`` decompressed, if it holds one whole member of at
    most ``most`` bytes; :class:`FileRefused` for more, a member cut short, damaged bytes (the
    CRC is checked) or data after it."""
    inflate = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
    try:
        text = inflate.decompress(data, most + 1)
    except zlib.error as error:
        raise FileRefused(path, f"is damaged ({error})") from None
    if len(text) > most:
        raise FileRefused(path, f"decompresses to more than the {most} bytes such a file may "
                          "hold")
    if not inflate.eof:
        raise FileRefused(path, "is cut short (its gzip stream does not end)")
    if inflate.unused_data:
        raise FileRefused(path, "has data after its gzip stream")
    return text


def plain_yaml(text: str, path: str | Path) -> str:
    """``text`` if it is YAML without anchors and aliases (``&a``, ``*a``, which a loader expands
    into copies: a kilobyte of them can stand for more than memory holds); :class:`FileRefused`
    naming ``path`` otherwise. The package writes none; a text that does not parse is left to
    the caller's parser to name."""
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        for event in yaml.parse(text, Loader=loader):
            if isinstance(event, yaml.AliasEvent) or getattr(event, "anchor", None):
                raise FileRefused(path, "uses YAML anchors or aliases (&name, *name), which "
                                  "no file of a run holds")
    except yaml.YAMLError:
        pass
    return text
