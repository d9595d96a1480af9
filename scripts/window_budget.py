"""The windowed bundle adjustment against a live node's frame budget, from replays' frames.jsonl.

`epi-vo replay` runs flat out: the next keyframe comes a few milliseconds after the last, and the frame
loop waits there for the adjustment the worker process is still solving (``window_wait``). A live node
gets its frames at the camera's rate, so the worker has the stamp interval between the two keyframes.
For each replay output directory this prints:

* flat out: ms/frame median and p95 as the replay measured them (waits included);
* live: ms/frame median and p95 without the waits (the frame loop's own work), valid where the worker is
  done in time;
* the adjustments: how many, the worker's solve time (median, p95, max; measured while the replay
  competed with it for the two cores, so a live node's are shorter) and how many would be late at the
  bag's camera rate (solve time longer than the stamp interval from the keyframe that submitted it to
  the one that collects it): each late one would make the live frame loop wait with ``ba_wait: true``
  (with ``false`` it does not wait: the result is applied at a later keyframe, and the column counts
  those taken at a keyframe sooner after the previous one than the solve took).

    .venv/bin/epi-vo replay bags/ground_robot/bag --output /tmp/gr --params window.yaml
    .venv/bin/python scripts/window_budget.py /tmp/gr [more replay dirs]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Budget:
    frames: int
    flat_median_ms: float
    flat_p95_ms: float
    live_median_ms: float
    live_p95_ms: float
    adjustments: int
    solve_median_ms: float
    solve_p95_ms: float
    solve_max_ms: float
    late: int


def budget(records: list[dict]) -> Budget:
    """The figures of one replay's frame records (in frame order)."""
    flat, live, solves, late = [], [], [], 0
    last_kf_stamp: float | None = None
    for r in records:
        t = r.get("timings_ms") or {}
        if "total" in t:
            flat.append(t["total"])
            live.append(t["total"] - t.get("window_wait", 0.0))
        if "window_solve" in t:
            solves.append(t["window_solve"])
            # Collected at this keyframe, submitted at the one before.
            if last_kf_stamp is not None and t["window_solve"] > 1e3 * (r["stamp"] - last_kf_stamp):
                late += 1
        if r.get("is_keyframe"):
            last_kf_stamp = r["stamp"]
    flat_a, live_a, solve_a = (np.array(v) if v else np.zeros(1) for v in (flat, live, solves))
    return Budget(len(flat), float(np.median(flat_a)), float(np.percentile(flat_a, 95)), float(np.median(live_a)),
                  float(np.percentile(live_a, 95)), len(solves), float(np.median(solve_a)),
                  float(np.percentile(solve_a, 95)), float(solve_a.max()), late)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="epi-vo replay output directories")
    args = ap.parse_args(argv)
    print(f"{'replay':24s} {'frames':>6s} {'flat med':>8s} {'p95':>6s} {'live med':>8s} {'p95':>6s} "
          f"{'adjust':>6s} {'solve med':>9s} {'p95':>6s} {'max':>6s} {'late':>5s}")
    for d in args.dirs:
        path = d / "frames.jsonl"
        if not path.is_file():
            print(f"{d}: no frames.jsonl (not a replay output directory)", file=sys.stderr)
            return 2
        b = budget([json.loads(line) for line in path.read_text().splitlines() if line.strip()])
        print(f"{d.name:24s} {b.frames:6d} {b.flat_median_ms:8.2f} {b.flat_p95_ms:6.2f} {b.live_median_ms:8.2f} "
              f"{b.live_p95_ms:6.2f} {b.adjustments:6d} {b.solve_median_ms:9.1f} {b.solve_p95_ms:6.1f} "
              f"{b.solve_max_ms:6.1f} {b.late:5d}")
    print("ms/frame: processing per frame (flat out: as replayed, waits for the worker included; live: without "
          "them); solve: the worker's time per adjustment; late: adjustments slower than the stamp interval "
          "between the keyframe that started them and the one that takes their result")
    return 0


if __name__ == "__main__":
    sys.exit(main())
