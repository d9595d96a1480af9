"""Every window the windowed bundle adjustment is given during a replay, pickled, to study it offline.

    .venv/bin/python scripts/dump_windows.py BAG OUT --params window.yaml

Replays BAG with the parameter file (which switches the window on, ``ba_window_keyframes``) into
``OUT/replay/`` and writes each window handed to ``core.bundle.adjust`` as ``OUT/window_NNN.pkl`` (a
``core.bundle.Window``, in the order of the replay). The adjustment runs in line (``ba_solver: inline``,
whatever the file says): the poses are the same as with the worker process, and the windows come in
order. ``bundle.adjust(window)`` on one of them gives what the replay got, so an adjustment can be
re-solved, timed or changed without replaying (how the floor's native factors were checked against
the factors they replaced, 2026-11-27: README, "The floor in native factors").
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys
from pathlib import Path
from typing import Any

from epi_vo.core import bundle
from epi_vo.core.errors import EpiVoError
from epi_vo.io.params import load_config
from epi_vo.tools.replay import run_replay


def dump(bag: str | Path, out: str | Path, params: str | Path | None) -> int:
    """Replay ``bag`` with ``params`` into ``out/replay`` and pickle every window; returns how many."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = load_config(params)
    if cfg.ba_window_keyframes <= 0:
        msg = "the parameters do not switch the windowed adjustment on (ba_window_keyframes: 0)"
        raise EpiVoError(msg)
    cfg = dataclasses.replace(cfg, ba_solver="inline")
    count = 0
    adjust = bundle.adjust

    def dumping(window: bundle.Window, **kw: Any) -> bundle.Adjusted | None:
        nonlocal count
        with (out / f"window_{count:03d}.pkl").open("wb") as f:
            pickle.dump(window, f)
        count += 1
        return adjust(window, **kw)

    bundle.adjust = dumping  # type: ignore[assignment]
    try:
        run_replay(bag, out / "replay", cfg)
    finally:
        bundle.adjust = adjust  # type: ignore[assignment]
    return count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bag")
    parser.add_argument("out")
    parser.add_argument("--params", required=True, help="ROS 2 parameter file that sets ba_window_keyframes > 0")
    args = parser.parse_args(argv)
    try:
        n = dump(args.bag, args.out, args.params)
    except EpiVoError as exc:
        print(f"dump_windows: {exc}", file=sys.stderr)
        return 2
    print(f"{n} windows in {args.out} (replay outputs in {Path(args.out) / 'replay'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
