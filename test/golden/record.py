"""Record the golden outputs of every bundled bag: ``python test/golden/record.py``.

For each bag in ``bags/`` it replays with the default parameters and keeps, per frame, what the
behaviour-preservation test (``test/tools/test_golden.py``) compares: state, model, keyframe flag,
has_pose, skipped, and the pose (trajectory.tum: position and quaternion). Re-record only when a change
of behaviour is intended, and say so in the commit.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent
BAGS = ("general_motion", "planar", "pure_rotation")


def replay_digest(bag: Path, out: Path) -> list[dict[str, Any]]:
    """Per-frame digest of a default-parameter replay of ``bag`` written to ``out``."""
    from epi_vo.tools.replay import run_replay

    run_replay(bag, out)
    poses = {}
    for line in (out / "trajectory.tum").read_text().splitlines():
        vals = line.split()
        poses[vals[0]] = [float(v) for v in vals[1:]]
    digest = []
    for line in (out / "frames.jsonl").read_text().splitlines():
        rec = json.loads(line)
        key = f"{rec['stamp_ns'] * 1e-9:.9f}"
        digest.append({k: rec[k] for k in ("index", "stamp_ns", "state", "model", "is_keyframe", "has_pose",
                                           "skipped")} | {"tum": poses.get(key) if rec["has_pose"] else None})
    return digest


def main() -> int:
    for name in BAGS:
        with tempfile.TemporaryDirectory() as tmp:
            digest = replay_digest(REPO / "bags" / name / "bag", Path(tmp))
        (GOLDEN / f"{name}.json").write_text(json.dumps(digest, indent=0) + "\n")
        print(f"{name}: {len(digest)} frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
