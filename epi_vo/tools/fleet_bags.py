"""Which bags the arguments of ``epi-vo replay`` name, and the output directory each gets.

* **A bag** is a rosbag2 directory (it holds ``metadata.yaml``; its storage files, split or not, are that
  one bag) or a lone ``.mcap`` / ``.db3`` file (also one that is not a regular file: a FIFO named
  ``x.mcap`` gets its row, failed with the reason, and is never opened).
* **Arguments.** A path that exists is taken as given: a bag, or a directory holding bags (those directly
  in it, and the storage files of a sub-directory without ``metadata.yaml``, which a recorder that died
  leaves). A glob (``**`` recurses, :func:`epi_vo.io.paths.glob_paths`: never into a directory symlink)
  gives the bags it matches: a matched storage file inside a bag directory stands for that directory, so
  ``'logs/**/*.mcap'`` finds ``logs/run1/`` (``run1_0.mcap`` + ``metadata.yaml``) once, whatever number of
  split files it has.
* **Outputs are not bags.** A ``.mcap`` written by epi_vo (its MCAP header names the library, see
  :func:`epi_vo.io.outbag.is_output_bag`) is never found by a directory or a glob: a second run whose
  output lies inside the input tree does not take the first run's ``output.mcap`` files for bags.
"""

from __future__ import annotations

import glob
import logging
from collections.abc import Sequence
from pathlib import Path

from epi_vo.core.errors import BagError
from epi_vo.io.outbag import is_output_bag
from epi_vo.io.paths import BAG_STORAGE_SUFFIXES, glob_paths

_log = logging.getLogger(__name__)

BAG_SUFFIXES = BAG_STORAGE_SUFFIXES


def is_bag_dir(path: Path) -> bool:
    """A rosbag2 bag directory: a directory holding metadata.yaml."""
    return path.is_dir() and (path / "metadata.yaml").exists()


def is_bag_file(path: Path) -> bool:
    """A lone storage file: a .mcap / .db3 path that exists and is no directory (a FIFO too: refused with its
    reason when replayed, never opened here)."""
    return path.suffix in BAG_SUFFIXES and path.exists() and not path.is_dir()


def is_bag(path: Path) -> bool:
    """A rosbag2 directory (with metadata.yaml) or a single .mcap / .db3 file."""
    return is_bag_dir(path) or is_bag_file(path)


def _found(path: Path) -> bool:
    """A bag found by a directory or a glob: not a replay's output."""
    if is_output_bag(path):
        _log.info("%s is an epi_vo replay output, not a bag: passed over", path)
        return False
    return True


def _bags_in(directory: Path) -> list[Path]:
    """The bags directly in ``directory`` (sub-directories that are bags, .mcap / .db3 files), and the
    storage files of a sub-directory without metadata.yaml: a recorder that died (power cut, kill -9)
    leaves its bag directory without it, and such a bag must get its row (replayed from the file, or
    failed with its reason), not be passed over. Replay outputs are passed over."""
    try:
        children = sorted(directory.iterdir())
    except OSError:
        return []
    found = []
    for c in children:
        if is_bag(c):
            found += [c] if _found(c) else []
        elif c.is_dir():
            try:
                found += sorted(f for f in c.iterdir() if is_bag_file(f) and _found(f))
            except OSError:
                continue
    return found


def nested_bags(arg: str) -> list[Path]:
    """The bags one level below a directory that holds none itself (``DIR/<name>/<bag>``, as epi_vo's
    bags/ and scripts/robot_drives.py's output are laid out): a directory is a fleet of the bags directly
    in it, so such a one is named by the glob ``'DIR/*'``, and the error for ``DIR`` says so."""
    path = Path(arg)
    if not path.is_dir() or is_bag(path) or _bags_in(path):
        return []
    return [b for c in sorted(path.iterdir()) if c.is_dir() and not is_bag(c) for b in _bags_in(c)]


def is_fleet(args: Sequence[str]) -> bool:
    """Whether the replay arguments ask for a fleet: several of them, a glob, or one directory holding bags
    (one argument that is a bag, or names nothing usable, is the single-bag replay)."""
    if len(args) != 1:
        return True
    path = Path(args[0])
    if not path.exists():
        return glob.has_magic(args[0])
    return path.is_dir() and not is_bag(path) and bool(_bags_in(path))


def _bags_of_match(match: Path) -> list[Path]:
    """The bags one glob match stands for (see module doc)."""
    if is_bag_file(match) and is_bag_dir(match.parent):
        return [match.parent]  # a storage file of a bag directory: the directory is the bag
    if is_bag(match):
        return [match] if _found(match) else []
    if match.is_dir():
        return _bags_in(match)
    return []


def find_bags(args: Sequence[str]) -> list[Path]:
    """The bags the replay arguments name, in order, each once: bags as given, the bags directly in a directory,
    and what a glob matches (see module doc); a path that does not exist is kept (its replay fails with
    "bag not found", the others go on). BagError when a glob matches no bag, or a directory holds none."""
    found: list[Path] = []
    for arg in args:
        literal = Path(arg)
        if literal.exists() or not glob.has_magic(arg):
            if literal.is_dir() and not is_bag(literal):
                inside = _bags_in(literal)
                if not inside:
                    raise BagError(f"{literal} is neither a bag nor a directory holding bags")
                found += inside
            else:
                found.append(literal)
            continue
        bags = [b for m in glob_paths(arg) for b in _bags_of_match(Path(m))]
        if not bags:
            raise BagError(f"no bag matches {arg!r}")
        found += bags
    unique: dict[Path, Path] = {}
    for path in found:
        unique.setdefault(path.resolve() if path.exists() else path.absolute(), path)
    return list(unique.values())


def output_names(bags: Sequence[Path]) -> list[str]:
    """A directory name per bag: its name (a file's without the suffix); where names repeat, as many parent
    directories as make them differ, joined by '-' (``general_motion-bag``, ``planar-bag``)."""
    parts = [list((p.resolve() if p.exists() else p.absolute()).parent.parts[1:]) for p in bags]
    leaves = [p.stem if p.suffix in BAG_SUFFIXES and not p.is_dir() else p.name for p in bags]
    depth = [0] * len(bags)

    def name(i: int) -> str:
        return "-".join([*parts[i][len(parts[i]) - depth[i]:], leaves[i]]) if depth[i] else leaves[i]

    while True:
        names = [name(i) for i in range(len(bags))]
        clashes = [i for i, n in enumerate(names) if names.count(n) > 1 and depth[i] < len(parts[i])]
        if not clashes:
            break
        for i in clashes:
            depth[i] += 1
    seen: dict[str, int] = {}
    for i, n in enumerate(names):  # still equal (a dir and a .mcap of one name in one place): numbered
        seen[n] = seen.get(n, 0) + 1
        if seen[n] > 1:
            names[i] = f"{n}-{seen[n]}"
    return names
