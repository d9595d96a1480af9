"""Property-based fuzzing (hypothesis) of fleet replays over generated directory layouts.

The whole-replay fuzzer (test_fuzz_replay.py) varies the messages inside one bag; this one varies where bags
are and where the outputs go. Each example is a directory tree of:

* bags: lone ``.mcap`` files and rosbag2 directories (``name/name.mcap`` + ``metadata.yaml``), named from a
  small pool that includes ``output`` (so that a bag may sit where another bag's outputs would go);
* things named like bags that are none: a FIFO ``x.mcap``, a ``.mcap`` of garbage;
* the outputs of an earlier replay (``output.mcap`` written by epi_vo, ``frames.jsonl``, ``stats.json``);
* symlinks back to an ancestor (loops) and to a bag;

replayed with the README's glob ``'ROOT/**/*.mcap'`` or with every bag named, into an output directory that is
apart from the tree, the tree's root, a directory inside it, a bag directory, or the directory a bag's own
outputs would take; sometimes twice. Each run is a subprocess with a generous bound, so a hang (a FIFO opened,
a loop followed) is a failure, not a stuck suite. Every example must satisfy:

1. the run ends; exit status in {0, 2, 4}; no traceback; exit 2 is one line, and a run into a bag directory
   is exit 2;
2. no input is changed: every file of every bag keeps its bytes, and nothing is written into a bag directory;
3. exit 0 or 4: the summary has one row per bag, each bag once (symlinks to it, its directory and its storage
   file are the same bag), no row for an earlier replay's output; the good bags ``ok``, the FIFO and the
   garbage ``failed`` with a reason (exit 4 exactly when one of them is there);
4. a second run: the same rows, the good bags ``skipped: complete``.

Runtime: 8 derandomized examples by default (about a minute on 2 cores); ``--fuzz-examples N`` runs more.
"""

from __future__ import annotations

import atexit
import csv
import dataclasses
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from functools import cache
from pathlib import Path

import pytest
from bag_copies import BAGS, REPO, copy_frames, storage_file
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

DEFAULT_EXAMPLES = 8
RUN_BOUND_S = 300  # a fleet of a few 4-frame bags takes seconds: only a hang reaches this
NAMES = ("a", "g", "output", "run1")
KINDS = ("bag_file", "bag_dir", "fifo", "garbage", "replay_output", "loop", "bag_link")
OUTPUTS = ("apart", "root", "inside", "bag_dir", "collide")


@cache
def _sources() -> tuple[Path, Path]:
    """A 4-frame bag directory and the output directory of its replay (made once per session)."""
    base = Path(tempfile.mkdtemp(prefix="epi_vo_fuzz_fleet_src_"))
    atexit.register(shutil.rmtree, base, ignore_errors=True)
    bag = copy_frames(BAGS / "planar" / "bag", base / "tiny", 4)
    out = base / "replayed"
    subprocess.run([sys.executable, "-m", "epi_vo.cli", "replay", str(bag), "-o", str(out), "--no-progress"],
                   cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, check=True, capture_output=True,
                   timeout=RUN_BOUND_S)
    return bag, out


@dataclasses.dataclass(frozen=True)
class Layout:
    entries: tuple[tuple[str, tuple[str, ...], str], ...]  # (kind, parent directories, name)
    named: bool  # every bag named on the command line (else the glob)
    output: str
    twice: bool


@st.composite
def layouts(draw: st.DrawFn) -> Layout:
    entry = st.tuples(st.sampled_from(KINDS), st.lists(st.sampled_from(NAMES), max_size=2).map(tuple),
                      st.sampled_from(NAMES))
    entries = draw(st.lists(entry, min_size=1, max_size=6))
    # At least one bag, so that there is something to replay.
    entries.append(("bag_file", (), draw(st.sampled_from(NAMES))))
    return Layout(tuple(entries), draw(st.booleans()), draw(st.sampled_from(OUTPUTS)), draw(st.booleans()))


@dataclasses.dataclass
class Built:
    root: Path
    bags: dict[Path, str]  # resolved path -> "good" / "bad" (a FIFO or garbage named .mcap)
    bag_dirs: list[Path]
    named: list[Path]


def build(layout: Layout, root: Path) -> Built:
    tiny, replayed = _sources()
    root.mkdir(parents=True)
    built = Built(root, {}, [], [])
    for kind, parents, name in layout.entries:
        parent = root.joinpath(*parents)
        target = parent / (f"{name}.mcap" if kind in ("bag_file", "fifo", "garbage", "bag_link") else name)
        ancestors = [a for a in (parent, *parent.parents) if a == root or root in a.parents]
        if any((os.path.lexists(a) and not a.is_dir()) or a in built.bag_dirs for a in ancestors):
            continue  # a file where this entry's directory would go, or inside a bag directory
        parent.mkdir(parents=True, exist_ok=True)
        if os.path.lexists(target):
            continue
        if kind == "bag_file":
            shutil.copy(storage_file(tiny), target)
            built.bags[target.resolve()] = "good"
            built.named.append(target)
        elif kind == "bag_dir":
            copy_frames(BAGS / "planar" / "bag", target, 4)
            built.bags[target.resolve()] = "good"
            built.bag_dirs.append(target)
            built.named.append(target)
        elif kind == "fifo":
            os.mkfifo(target)
            built.bags[target.resolve()] = "bad"
            built.named.append(target)
        elif kind == "garbage":
            target.write_bytes(b"\x89MCAP0\r\n garbage, no bag")
            built.bags[target.resolve()] = "bad"
            built.named.append(target)
        elif kind == "replay_output":
            shutil.copytree(replayed, target)
        elif kind == "loop":
            target.symlink_to(os.path.relpath(root, parent))
        elif kind == "bag_link" and built.named and built.bags.get(built.named[0].resolve()) == "good":
            target.symlink_to(built.named[0].resolve())  # the same bag under another name
    return built


def _output(layout: Layout, built: Built, apart: Path) -> Path:
    if layout.output == "root":
        return built.root
    if layout.output == "inside":
        return built.root / "g" / "out"
    if layout.output == "bag_dir" and built.bag_dirs:
        return built.bag_dirs[0]
    if layout.output == "collide":  # where the outputs of a bag ROOT/g.mcap would go, were it one
        return built.root / "g"
    return apart


def _hashes(built: Built) -> dict[str, str]:
    out = {}
    for bag, kind in built.bags.items():
        if kind != "good":
            continue
        for f in [bag] if bag.is_file() else sorted(bag.iterdir()):
            out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
        if bag.is_dir():
            out[f"{bag} (entries)"] = ",".join(sorted(p.name for p in bag.iterdir()))
    return out


def _run(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "epi_vo.cli", "replay", *args, "--no-progress", "-j", "1"],
                          cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True,
                          timeout=RUN_BOUND_S, check=False)


def _rows(out: Path) -> list[dict[str, str]]:
    with (out / "summary.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def check_layout(layout: Layout, tmp: Path) -> None:
    built = build(layout, tmp / "tree")
    out = _output(layout, built, tmp / "apart")
    args = [str(p) for p in built.named] if layout.named else [str(built.root / "**" / "*.mcap")]
    before = _hashes(built)
    note(f"tree: {sorted(str(p.relative_to(tmp)) for p in (tmp / 'tree').rglob('*'))}; out: {out}")
    rows_first: list[dict[str, str]] | None = None
    for attempt in range(2 if layout.twice else 1):
        done = _run([*args, "-o", str(out)])
        note(f"run {attempt}: exit {done.returncode}\n{done.stdout[-1500:]}\n{done.stderr[-1500:]}")
        text = done.stdout + done.stderr
        assert "Traceback" not in text
        assert done.returncode in (0, 2, 4), done.returncode
        assert _hashes(built) == before, "an input was changed"
        if any(out == d or d in out.parents for d in built.bag_dirs):
            assert done.returncode == 2, "a run into a bag directory was not refused"
        if layout.named and len(built.named) == 1 and "bad" in built.bags.values():
            assert done.returncode == 2, "a FIFO or garbage named as the one bag was not refused"
        if done.returncode == 2:
            lines = done.stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("epi-vo: error: "), done.stderr
            return
        if layout.named and len(built.named) == 1:  # one bag named: the single-bag replay, no summary
            assert done.returncode == 0 and (out / "stats.json").is_file()
            return
        rows = _rows(out)
        keys = [Path(r["bag"]).resolve() for r in rows]
        assert sorted(map(str, keys)) == sorted(map(str, built.bags)), "not each bag once"
        for r, key in zip(rows, keys, strict=True):
            want = "ok" if built.bags[key] == "good" else "failed"
            assert r["status"] == want, r
            assert want == "ok" or r["reason"], r
        assert done.returncode == (4 if "bad" in built.bags.values() else 0)
        if rows_first is None:
            rows_first = rows
        else:
            assert [r["name"] for r in rows] == [r["name"] for r in rows_first]
            assert all(r["run"] == "skipped: complete" for r in rows if r["status"] == "ok")


def test_fleet_layouts_keep_the_invariants(pytestconfig: pytest.Config) -> None:
    requested = pytestconfig.getoption("--fuzz-examples", default=None)
    n = int(requested) if requested else DEFAULT_EXAMPLES

    @settings(max_examples=n, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(layouts())
    def probe(layout: Layout) -> None:
        with tempfile.TemporaryDirectory(prefix="epi_vo_fuzz_fleet_") as tmp:
            check_layout(layout, Path(tmp))

    probe()
