"""Where a `ground_plane` run's floor heights go wrong: each floor measurement against the ground truth.

    .venv/bin/python scripts/floor_truth.py BAG --params FILE [--output DIR]

Replays BAG (it must carry ground truth) with the parameters of FILE (``scale_source: ground_plane``)
and, for every keyframe whose floor was measured, prints:

* ``true``: metres per map unit of that keyframe step (ground-truth step length / the VO's step length,
  before the scale source's correction);
* ``floor``: what the floor said (``camera_height_m`` / floor height in map units), and ``ratio`` =
  floor / true (1: a right measurement; 1.07: the floor said 7 % too many metres per map unit);
* ``h_vo``: the floor inliers' height in metres (their map-unit height times ``true``);
* ``h_gt``: the same tracks triangulated with the ground-truth relative pose of the keyframe pair,
  height along the fitted floor normal (the VO's triangulation taken out: when ``h_gt`` is as far from
  ``camera_height_m`` as ``h_vo``, the points themselves are not on the floor the camera height is over);
* ``fresh``: the fraction of floor inliers triangulated from this keyframe pair (not carried over);
* ``|x|``: median offset of the floor inliers across the direction of travel (m), ``z`` their median
  distance ahead (m), ``pitch`` the fit's pitch (deg).

The wrapping is a diagnostic's: the pipeline's keyframe map stage and the floor measurement are wrapped
to keep their inputs; the replay is otherwise the same as `epi-vo replay`.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from typing import Any

import numpy as np

from epi_vo.core import geometry as geo
from epi_vo.core import keyframing as kfm
from epi_vo.core import scale as sc
from epi_vo.core.transforms import rotation_from_quat_xyzw
from epi_vo.io import bagio
from epi_vo.io.params import load_config
from epi_vo.tools.replay import run_replay


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("--params", required=True)
    ap.add_argument("--output", default=None)
    args = ap.parse_args(argv)
    cfg = load_config(args.params)
    if cfg.scale_source != "ground_plane":
        print("floor_truth: the parameters must set scale_source: ground_plane", file=sys.stderr)
        return 2
    with bagio.open_camera_bag(args.bag, None, None) as bag:
        gt = bag.read_ground_truth()
    if gt is None:
        print("floor_truth: the bag has no ground truth", file=sys.stderr)
        return 2

    def pose(stamp_ns: int) -> np.ndarray:
        i = int(np.argmin(np.abs(gt.stamps_ns - stamp_ns)))
        T = np.eye(4)
        T[:3, :3] = rotation_from_quat_xyzw(gt.quats_xyzw[i])
        T[:3, 3] = gt.positions[i]
        return T

    pairs: dict[int, dict[str, Any]] = {}
    floors: list[dict[str, Any]] = []
    keyframe_map = kfm.keyframe_map
    measure = sc.GroundPlaneScale.measure

    def kept_keyframe_map(cfg_: Any, motion: Any, kf: Any, rows: Any, xn_cur: Any, stamp_ns: int, *args: Any) -> Any:
        mapped = keyframe_map(cfg_, motion, kf, rows, xn_cur, stamp_ns, *args)
        if mapped.X_cur is not None:
            pairs[stamp_ns] = {"R": motion.R_cur_kf.copy(), "t": motion.t_cur_kf.copy(), "xn_kf": kf.xn[rows].copy(),
                               "xn_cur": xn_cur.copy(), "K": kf.camera.K.copy()}
        return mapped

    def kept_measure(self: sc.GroundPlaneScale, step: sc.KeyframeStep, wheel: Any
                     ) -> tuple[sc.GroundPlaneScale, tuple[float, float] | None]:
        src, out = measure(self, step, wheel)
        if out is not None and src.plane is not None:
            plane = src.plane  # its inliers: within the source's band of the measured floor
            with np.errstate(invalid="ignore"):
                rows = np.abs(step.X_cur @ plane.normal_up + plane.height) < src.inlier_ratio * plane.height
            floors.append({"step": step, "plane": plane, "rows": rows})
        return src, out

    kfm.keyframe_map = kept_keyframe_map  # type: ignore[assignment]
    sc.GroundPlaneScale.measure = kept_measure  # type: ignore[method-assign]
    with tempfile.TemporaryDirectory() as tmp:
        run_replay(args.bag, args.output or tmp, cfg)

    frame_of = {int(s): i for i, s in enumerate(gt.stamps_ns)}
    print(f"{'frame':>5} {'true':>6} {'floor':>6} {'ratio':>6} {'h_vo':>6} {'h_gt':>6} {'fresh':>5} {'|x|':>5} "
          f"{'z':>5} {'pitch':>5} {'n':>3}")
    logs = []
    for f in floors:
        step, plane, rows = f["step"], f["plane"], f["rows"]
        pair = pairs[step.stamp_ns]
        T_cur_kf = np.linalg.inv(pose(step.stamp_ns)) @ pose(step.kf_stamp_ns)
        true = float(np.linalg.norm(T_cur_kf[:3, 3])) / step.step_length
        floor = cfg.camera_height_m / plane.height
        n = plane.normal_up
        X = step.X_cur[rows]
        tri = geo.triangulate(T_cur_kf[:3, :3], T_cur_kf[:3, 3], pair["xn_kf"][rows], pair["xn_cur"][rows],
                              pair["K"], math.inf, 0.0)
        X_gt = tri.X_ref @ T_cur_kf[:3, :3].T + T_cur_kf[:3, 3]
        X_gt = X_gt[np.all(np.isfinite(X_gt), axis=1) & (X_gt[:, 2] > 0)]
        mine = geo.triangulate(pair["R"], pair["t"], pair["xn_kf"][rows], pair["xn_cur"][rows], pair["K"],
                               math.inf, 0.0)
        X_mine = mine.X_ref @ pair["R"].T + pair["t"]
        fresh = float(np.mean(np.linalg.norm(X_mine - X, axis=1) <= 1e-6 * np.linalg.norm(X, axis=1)))
        ratio = floor / true
        logs.append(math.log(ratio))
        print(f"{frame_of.get(step.stamp_ns, -1):5d} {true:6.3f} {floor:6.3f} {ratio:6.3f} {plane.height * true:6.3f} "
              f"{float(np.median(-(X_gt @ n))):6.3f} {fresh:5.2f} {float(np.median(np.abs(X[:, 0]))) * true:5.1f} "
              f"{float(np.median(X[:, 2])) * true:5.1f} {plane.pitch_deg:5.2f} {int(rows.sum()):3d}")
    if logs:
        z = np.array(logs)
        print(f"{z.size} floor measurements: ratio geometric mean {math.exp(z.mean()):.3f}, "
              f"spread {z.std():.3f} (log), range {math.exp(z.min()):.3f}-{math.exp(z.max()):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
