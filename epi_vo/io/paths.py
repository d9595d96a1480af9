"""Paths the tools read and write (no rclpy): what may be opened as an input, which outputs would land on an
input, and a recursive glob that cannot loop.

* **Special files.** Opening a FIFO for reading blocks until a writer comes, a character device may never end,
  a socket cannot be opened at all: :func:`special_file_kind` names such a path so that a caller refuses it
  (one line) before anything opens it (:func:`refuse_special_file`; for a bag, its directory's metadata and
  storage files too, :func:`check_bag_path`). A symlink counts as what it points to.
* **Overlap.** :func:`find_overlap` says whether an output path is, or lies in, an input: the same file (also
  through a symlink or a hard link), or anything inside an input directory (a rosbag2 bag directory is one
  input). Callers check every output against every input before any file is opened for writing.
* **Globs.** :func:`glob_paths` is ``glob.glob(pattern, recursive=True)`` except that ``**`` never descends
  into a directory symlink and never visits a directory twice (bind mounts): a link back to an ancestor
  would otherwise make the walk endless.
"""

from __future__ import annotations

import fnmatch
import glob
import os
import stat
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

from epi_vo.core.errors import BagError

_KINDS = (
    (stat.S_ISFIFO, "FIFO (named pipe)"),
    (stat.S_ISCHR, "character device"),
    (stat.S_ISBLK, "block device"),
    (stat.S_ISSOCK, "socket"),
)


def special_file_kind(path: str | Path) -> str | None:
    """What ``path`` is when it exists and is neither a regular file nor a directory (``"FIFO (named
    pipe)"``, ``"character device"``, ...); None otherwise (also when it does not exist or cannot be
    examined: opening it then fails with its own error). Never opens the path."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    return next((name for test, name in _KINDS if test(mode)), "special file")


def not_a_file_message(path: str | Path, kind: str, what: str) -> str:
    """The one line that refuses a special file named as ``what`` ('bag', 'ground-truth file', ...)."""
    return f"{path} is a {kind}, not a {what}: refused (reading it could block or never end)"


def refuse_special_file(path: str | Path, what: str, error: type[Exception] = BagError) -> None:
    """Raise ``error`` with :func:`not_a_file_message` when ``path`` is a special file (see
    :func:`special_file_kind`); nothing is opened."""
    kind = special_file_kind(path)
    if kind is not None:
        raise error(not_a_file_message(path, kind, what))


BAG_STORAGE_SUFFIXES = (".mcap", ".db3")


def check_bag_path(path: str | Path) -> Path:
    """``path`` when it can be opened as a bag without blocking: it exists and is a regular file or a
    directory, and in a directory metadata.yaml and the storage files are regular files. BagError naming
    the problem otherwise; nothing is opened (a FIFO would block the reader forever, a device never end)."""
    path = Path(path)
    if not path.exists():
        msg = f"bag not found: {path}"
        raise BagError(msg)
    kind = special_file_kind(path)
    if kind is not None:
        raise BagError(not_a_file_message(path, kind, "bag file or bag directory"))
    if path.is_dir():
        try:
            inside = sorted(c for c in path.iterdir()
                            if c.name == "metadata.yaml" or c.suffix in BAG_STORAGE_SUFFIXES)
        except OSError as err:
            msg = f"cannot list bag directory {path}: {err.strerror or err}"
            raise BagError(msg) from err
        for child in inside:
            kind = special_file_kind(child)
            if kind is not None:
                raise BagError(not_a_file_message(child, kind, "file of a bag"))
    return path


class Overlap(NamedTuple):
    """An output that would land on an input: ``output`` is ``input`` or lies inside it."""

    output: Path
    input: Path


def _inode(path: Path) -> tuple[int, int] | None:
    try:
        info = os.stat(path)
    except (OSError, ValueError):
        return None
    return info.st_dev, info.st_ino


def find_overlap(inputs: Iterable[str | Path], outputs: Iterable[str | Path]) -> Overlap | None:
    """The first output that is an input or lies inside an input directory; None when there is none.

    Paths are compared after resolving symlinks (an output symlinked to an input is that input) and, for
    paths that exist, by device and inode (a hard link is the same file). Nothing is opened or created.
    Linear in the number of outputs (a fleet of thousands of bags checks every output of every bag).
    """
    by_real: dict[Path, Path] = {}
    by_inode: dict[tuple[int, int], Path] = {}
    for given in map(Path, inputs):
        by_real.setdefault(Path(os.path.realpath(given)), given)
        inode = _inode(given)
        if inode is not None:
            by_inode.setdefault(inode, given)
    for out in map(Path, outputs):
        real = Path(os.path.realpath(out))
        for candidate in (real, *real.parents):
            if candidate in by_real:
                return Overlap(out, by_real[candidate])
        inode = _inode(out)
        if inode is not None and inode in by_inode:
            return Overlap(out, by_inode[inode])
    return None


# --------------------------------------------------------------------------------------------------
# Globs


def glob_paths(pattern: str) -> list[str]:
    """The paths matching ``pattern`` as ``glob.glob(pattern, recursive=True)`` gives them (sorted), except
    that ``**`` does not descend into directory symlinks (a symlink is still matched by name, and followed
    when named by a component that is not ``**``) and visits each directory once."""
    if not glob.has_magic(pattern):
        return [pattern] if os.path.lexists(pattern) else []
    root = os.sep if pattern.startswith(os.sep) else ""
    parts = [p for p in pattern.split(os.sep) if p]
    found = set(_expand(root, parts))
    if pattern.endswith(os.sep):  # 'logs/*/': directories only, written with their separator
        found = {os.path.join(p, "") for p in found if os.path.isdir(p)}
    return sorted(found)


def _join(base: str, name: str) -> str:
    return os.path.join(base, name) if base else name


def _expand(base: str, parts: Sequence[str]) -> Iterator[str]:
    if not parts:
        yield base
        return
    head, rest = parts[0], parts[1:]
    if head == "**":
        if not rest:  # a trailing '**': the directory and everything below it
            yield from _walk(base, dirs_only=False)
            return
        for directory in _walk(base, dirs_only=True):
            yield from _expand(directory, rest)
    elif glob.has_magic(head):
        for entry in _scandir(base):
            if entry.name.startswith(".") and not head.startswith("."):
                continue  # hidden names only for a pattern that starts with '.', as glob
            if not fnmatch.fnmatchcase(entry.name, head):
                continue
            path = _join(base, entry.name)
            if rest and not os.path.isdir(path):
                continue
            yield from _expand(path, rest)
    else:
        path = _join(base, head)
        if (rest and os.path.isdir(path)) or (not rest and os.path.lexists(path)):
            yield from _expand(path, rest)


def _scandir(base: str) -> list[os.DirEntry[str]]:
    try:
        with os.scandir(base or ".") as it:
            return list(it)
    except OSError:
        return []


def _walk(base: str, *, dirs_only: bool) -> Iterator[str]:
    """``base`` and every directory below it (also the files with ``dirs_only`` False), depth first, hidden
    names skipped; directory symlinks are not entered, and a directory already seen (same device and inode)
    is not entered again."""
    seen: set[tuple[int, int]] = set()
    stack = [base]
    first = True
    while stack:
        directory = stack.pop()
        try:
            info = os.stat(directory or ".")
        except OSError:
            continue
        key = (info.st_dev, info.st_ino)
        if key in seen:
            continue
        seen.add(key)
        if not first:
            yield directory
        elif dirs_only or base:
            yield _join(base, "") if base else base  # 'logs/' as glob gives it: '**' matching no directory
        first = False
        below = []
        for entry in sorted(_scandir(directory), key=lambda e: e.name):
            if entry.name.startswith("."):
                continue
            path = _join(directory, entry.name)
            try:
                is_real_dir = entry.is_dir(follow_symlinks=False)
            except OSError:
                is_real_dir = False
            if is_real_dir:
                below.append(path)
            elif not dirs_only:
                yield path
        stack.extend(reversed(below))
