"""``epi-vo inspect``: a picture of one frame pair, to see why the pipeline decided what it did.

The pipeline is stateful (the reference keyframe and the map of frame N depend on every frame
before it), so the bag is replayed from the start up to frame N through the same
:class:`~epi_vo.core.pipeline.VoPipeline` as ``epi-vo replay``; only the latest reference keyframe image
is kept in memory.

The picture shows the reference keyframe and frame N side by side, both *undistorted* with their
camera model: the correspondences, F and H all live in undistorted pixels (``uv``), so drawing them on
the undistorted images is exact (the raw image would need the lines bent by the lens distortion).

Residuals are the quantities the pipeline's ORB-SLAM style scoring gates (``geometry.score_*``):

- E chosen: point-to-epipolar-line distance in px, ``l_cur = F x_kf`` in the current image and
  ``l_kf = F^T x_cur`` in the keyframe (H&Z 9.2); the residual is the larger of the two, gated at
  ``score_sigma_px * sqrt(chi2_1dof)``.
- H chosen: transfer error in px, ``H x_kf`` vs ``x_cur`` and ``H^-1 x_cur`` vs ``x_kf`` (the two terms
  of the symmetric transfer error, H&Z 4.2.2); the residual is the larger of the two, gated at
  ``score_sigma_px * sqrt(chi2_2dof)``.

A correspondence passes the scoring when both terms are within the gate, which is the same as the
larger one being within it; every inlier of the chosen model is therefore within the gate (E's
inliers also passed the cheirality check, so an outlier may be within the gate too).
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from epi_vo.core.camera import CameraModel, DistortionModel
from epi_vo.core.config import VoConfig
from epi_vo.core.debug_image import mover_mask
from epi_vo.core.errors import BagError, OutputError
from epi_vo.core.frame import FrameResult, Model
from epi_vo.core.geometry import CHI2_1DOF, CHI2_2DOF, epipolar_distances_sq, homogeneous, transfer_errors_sq
from epi_vo.core.pipeline import downscale
from epi_vo.io import bagio, checks
from epi_vo.io.params import load_config
from epi_vo.runner.frames import FrameHandler
from epi_vo.tools.replay import frame_input

F64 = NDArray[np.float64]
Gray = NDArray[np.uint8]

MAX_LINES = 150  # correspondences drawn across the pair; more make the picture unreadable
MAX_OUTLIER_SHARE = 1 / 3  # of MAX_LINES: outliers are few but the interesting ones, keep them visible
N_EPILINES = 6  # inliers whose epipolar lines (or H transfers) are drawn


@dataclass(frozen=True)
class PairData:
    """Residuals of the chosen model and what to draw, for one frame pair (row order of ``Matches``).

    ``residual_px`` (N,) the chosen model's residual of every correspondence (see module doc), empty
    when no model was chosen; ``gate_px`` its inlier gate; ``inliers`` (N,) the pipeline's inliers;
    ``movers`` (N,) the features that moved on their own, as the debug image draws them
    (:func:`epi_vo.core.debug_image.mover_mask`); ``moving_region`` their box (x0, y0, x1, y1), undistorted px.
    ``line_idx`` rows whose correspondence lines are drawn (at most ``MAX_LINES``); ``epi_idx`` (k,)
    inlier rows shown in detail: ``lines_cur``/``lines_kf`` (k, 3) their epipolar lines
    ``F x_kf`` / ``F^T x_cur`` (E), or ``transfer_cur``/``transfer_kf`` (k, 2) their points mapped by
    ``H`` / ``H^-1`` (H); the other pair is empty. All in undistorted pixels.
    """

    model: Model
    residual_px: F64
    residual_label: str
    gate_px: float
    gate_rule: str
    inliers: NDArray[np.bool_]
    movers: NDArray[np.bool_]
    moving_region: tuple[int, int, int, int] | None
    uv_kf: F64
    uv_cur: F64
    line_idx: NDArray[np.int64]
    epi_idx: NDArray[np.int64]
    lines_cur: F64
    lines_kf: F64
    transfer_cur: F64
    transfer_kf: F64

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def n_movers(self) -> int:
        return int(np.count_nonzero(self.movers))


@dataclass(frozen=True)
class Inspection:
    """One frame of a bag as the pipeline saw it, with its reference keyframe.

    ``keyframe_index`` is the keyframe the frame's correspondences were measured against (the
    reference *while* the frame was processed; None for the very first frame). Images and cameras are
    those the pipeline processed (after ``max_image_width`` downscaling), not undistorted.
    """

    bag: str
    frame_index: int
    frame_count: int
    result: FrameResult
    keyframe_index: int | None
    keyframe_stamp_ns: int | None
    gray_kf: Gray | None
    camera_kf: CameraModel | None
    gray_cur: Gray
    camera: CameraModel
    data: PairData


# -------------------------------------------------------------------------------------------------
# Pure computation


def pair_data(result: FrameResult, sigma_px: float, max_lines: int = MAX_LINES,
              n_epilines: int = N_EPILINES) -> PairData:
    """Residuals of ``result``'s chosen model over all its correspondences, and the drawing selection.

    ``sigma_px`` is the pipeline's ``score_sigma_px`` (the gates are chi-square quantiles in units of
    it). Pure: depends on the frame result only.
    """
    m = result.matches
    n = m.uv_kf.shape[0]
    model = result.model
    residual = np.zeros(0)
    label = "no model"
    gate = math.nan
    rule = ""
    if model is Model.ESSENTIAL and np.any(m.F):
        d_cur_sq, d_kf_sq = epipolar_distances_sq(m.F, m.uv_kf, m.uv_cur)
        residual = np.sqrt(np.maximum(d_cur_sq, d_kf_sq))
        label = "point-to-epipolar-line distance, worse image (px)"
        gate = sigma_px * math.sqrt(CHI2_1DOF)
        rule = f"sigma {sigma_px:g} px x sqrt({CHI2_1DOF}), chi2 1 dof 95 %"
    elif model is Model.HOMOGRAPHY and np.any(m.H):
        e_cur_sq, e_kf_sq = transfer_errors_sq(m.H, m.uv_kf, m.uv_cur)
        residual = np.sqrt(np.maximum(e_cur_sq, e_kf_sq))
        label = "H transfer error, worse direction (px)"
        gate = sigma_px * math.sqrt(CHI2_2DOF)
        rule = f"sigma {sigma_px:g} px x sqrt({CHI2_2DOF}), chi2 2 dof 95 %"
    else:
        model = Model.NONE
    inliers = np.asarray(m.inliers, dtype=bool)
    epi_idx = _spread_inliers(m.uv_cur, inliers, n_epilines) if model is not Model.NONE else np.zeros(0, np.int64)
    z3, z2 = np.zeros((0, 3)), np.zeros((0, 2))
    lines_cur = lines_kf = z3
    transfer_cur = transfer_kf = z2
    if model is Model.ESSENTIAL:
        lines_cur = homogeneous(m.uv_kf[epi_idx]) @ m.F.T  # l_cur = F x_kf
        lines_kf = homogeneous(m.uv_cur[epi_idx]) @ m.F  # l_kf = F^T x_cur
    elif model is Model.HOMOGRAPHY:
        transfer_cur = _apply_h(m.H, m.uv_kf[epi_idx])
        transfer_kf = _apply_h(np.linalg.inv(m.H), m.uv_cur[epi_idx])
    return PairData(model=model, residual_px=residual, residual_label=label, gate_px=gate, gate_rule=rule,
                    inliers=inliers, movers=mover_mask(result), moving_region=result.moving_region,
                    uv_kf=np.asarray(m.uv_kf), uv_cur=np.asarray(m.uv_cur),
                    line_idx=_subsample_lines(inliers, max_lines) if n else np.zeros(0, np.int64),
                    epi_idx=epi_idx, lines_cur=lines_cur, lines_kf=lines_kf, transfer_cur=transfer_cur,
                    transfer_kf=transfer_kf)


def _apply_h(H: F64, uv: F64) -> F64:
    p = homogeneous(uv) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:3]


def _evenly(idx: NDArray[np.int64], k: int) -> NDArray[np.int64]:
    if idx.size <= k:
        return idx
    return idx[np.linspace(0, idx.size - 1, k).round().astype(np.int64)]


def _subsample_lines(inliers: NDArray[np.bool_], max_lines: int) -> NDArray[np.int64]:
    """At most ``max_lines`` rows, evenly spread; outliers keep up to a third of the budget."""
    out_idx, in_idx = np.flatnonzero(~inliers), np.flatnonzero(inliers)
    n_out = min(out_idx.size, max(int(max_lines * MAX_OUTLIER_SHARE), max_lines - in_idx.size))
    keep = np.concatenate([_evenly(out_idx, n_out), _evenly(in_idx, max_lines - n_out)])
    return np.sort(keep)


def _spread_inliers(uv: F64, inliers: NDArray[np.bool_], k: int) -> NDArray[np.int64]:
    """k inlier rows spread over the image (farthest-point sampling from the left-most inlier)."""
    idx = np.flatnonzero(inliers)
    if idx.size <= k:
        return idx
    pts = uv[idx]
    chosen = [int(np.argmin(pts[:, 0]))]
    d = np.sum((pts - pts[chosen[0]]) ** 2, axis=1)
    while len(chosen) < k:
        j = int(np.argmax(d))
        chosen.append(j)
        d = np.minimum(d, np.sum((pts - pts[j]) ** 2, axis=1))
    return idx[np.array(chosen, dtype=np.int64)]


def line_in_box(line: F64, width: int, height: int) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The segment of the line ``a u + b v + c = 0`` inside [0, width-1] x [0, height-1], or None."""
    a, b, c = (float(x) for x in line)
    w, h = width - 1.0, height - 1.0
    pts: list[tuple[float, float]] = []
    if abs(b) > 1e-12:
        pts += [(u, -(a * u + c) / b) for u in (0.0, w)]
    if abs(a) > 1e-12:
        pts += [(-(b * v + c) / a, v) for v in (0.0, h)]
    eps = 1e-6
    inside = [(u, v) for u, v in pts if -eps <= u <= w + eps and -eps <= v <= h + eps]
    if len(inside) < 2:
        return None
    inside.sort()
    return inside[0], inside[-1]


def undistorted_image(gray: Gray, camera: CameraModel) -> Gray:
    """The image as seen by the ideal pinhole camera with the same K (the ``uv`` pixels of camera.py)."""
    if not camera.is_distorted:
        return gray
    size = (camera.width, camera.height)
    if camera.model is DistortionModel.EQUIDISTANT:
        map1, map2 = cv2.fisheye.initUndistortRectifyMap(camera.K, camera.D, np.eye(3), camera.K, size,
                                                         cv2.CV_32FC1)
    else:
        map1, map2 = cv2.initUndistortRectifyMap(camera.K, camera.D, None, camera.K, size, cv2.CV_32FC1)
    return cv2.remap(gray, map1, map2, cv2.INTER_LINEAR)


# -------------------------------------------------------------------------------------------------
# Bag replay up to one frame


def nearest_frame(stamps_ns: list[int], stamp_s: float) -> int:
    """Index of the stamp nearest to ``stamp_s`` seconds (the first one on a tie)."""
    target = stamp_s * 1e9
    return int(np.argmin([abs(s - target) for s in stamps_ns]))


def inspect_bag(bag_path: str | Path, frame: int | None = None, *, stamp_s: float | None = None,
                cfg: VoConfig | None = None, image_topic: str | None = None,
                camera_info_topic: str | None = None) -> Inspection:
    """Replay the bag from its first image up to ``frame`` (or the frame nearest ``stamp_s``).

    Frames before it that cannot be used are rejected as in ``epi-vo replay`` (the same per-frame rule,
    :class:`epi_vo.runner.frames.FrameHandler`), so the picture shows what the replay did at that frame.

    Raises:
        BagError: frame index out of range, unreadable bag, ambiguous topics, or the frame itself was
            rejected (the message says why: no camera_info, undecodable image, bad calibration, ...).
        ValueError: not exactly one of ``frame`` and ``stamp_s`` given.
    """
    if (frame is None) == (stamp_s is None):
        raise ValueError("give exactly one of frame and stamp_s")
    cfg = cfg or VoConfig()
    handler = FrameHandler(cfg)
    with bagio.open_camera_bag(bag_path, image_topic, camera_info_topic) as bag:
        count = bag.frame_count
        if stamp_s is not None:  # a first pass over the stamps: the pipeline must stop at the chosen frame
            frame = nearest_frame([f.stamp_ns for f in bag.iter_frames()], stamp_s)
        if frame is None or not 0 <= frame < count:
            raise BagError(f"frame {frame} is out of range: bag {bag_path} has {count} frames (0..{count - 1})")
        ref: tuple[int, int, Gray, CameraModel] | None = None  # latest keyframe: index, stamp, image, camera
        for f in bag.iter_frames():
            processed = handler.handle(frame_input(bag, f))
            result, gray, camera = processed.result, processed.gray, processed.camera
            if gray is None or camera is None:  # rejected before the pipeline saw it
                if f.index == frame:
                    raise BagError(f"frame {f.index} (stamp {f.stamp_ns * 1e-9:.6f} s) was rejected: "
                                   f"{processed.problem}")
                continue
            gray_p, camera_p = downscale(gray, camera, cfg.max_image_width)
            if f.index == frame:
                # The reference while this frame was processed: even when this frame becomes a
                # keyframe, its correspondences were measured against the previous one.
                kf_index, kf_stamp, gray_kf, camera_kf = ref if ref is not None else (None, None, None, None)
                return Inspection(str(bag_path), frame, count, result, kf_index, kf_stamp, gray_kf, camera_kf,
                                  gray_p, camera_p, pair_data(result, cfg.score_sigma_px))
            if result.is_keyframe:
                ref = (f.index, f.stamp_ns, gray_p, camera_p)
    raise BagError(f"bag {bag_path} ended before frame {frame} (metadata says {count} frames)")


# -------------------------------------------------------------------------------------------------
# Text


def _fmt(x: float, spec: str = ".2f", unit: str = "") -> str:
    return f"{x:{spec}}{unit}" if math.isfinite(x) else "n/a"


def summary_line(insp: Inspection) -> str:
    """One line: frame, keyframe, state, model, RH, inliers, parallax, reason."""
    r = insp.result
    kf = f"keyframe {insp.keyframe_index}" if insp.keyframe_index is not None else "no keyframe"
    line = (f"frame {insp.frame_index} (stamp {r.stamp_ns * 1e-9:.6f} s) vs {kf}: {r.state.value}, model "
            f"{r.model.value}, RH {_fmt(r.rh)}, inliers {r.n_inliers}/{r.n_tracked} ({r.inlier_ratio:.0%}), "
            f"parallax {_fmt(r.median_parallax_deg, unit=' deg')}, triangulated {r.n_triangulated}, "
            f"{moving_text(r)}")
    return line + (f"; {r.reason}" if r.reason else "")


def moving_text(r: FrameResult) -> str:
    """'moving 53 (28%) in x 62-245, y 155-451 px, static score 0.72' (or 'moving 0, ...')."""
    where = ""
    if r.moving_region is not None:
        x0, y0, x1, y1 = r.moving_region
        where = f" in x {x0}-{x1}, y {y0}-{y1} px"
    return f"moving {r.n_moving} ({r.moving_fraction:.0%}){where}, static score {_fmt(r.static_score)}"


def record_lines(insp: Inspection, width: int = 78) -> list[str]:
    """The frame record as aligned 'name  value' lines for the picture, wrapped at ``width`` characters."""
    r, d = insp.result, insp.data
    kf = "none (first frame)" if insp.keyframe_index is None else str(insp.keyframe_index)
    dt = ("" if insp.keyframe_stamp_ns is None
          else f"  (dt {(r.stamp_ns - insp.keyframe_stamp_ns) * 1e-9:.3f} s)")
    gate = f"{d.gate_px:.2f} px" if math.isfinite(d.gate_px) else "n/a"
    within = (f"{int(np.count_nonzero(d.residual_px <= d.gate_px))}/{d.residual_px.size}"
              if d.residual_px.size else "n/a")
    rows = [
        ("frame", f"{insp.frame_index} of {insp.frame_count}   stamp {r.stamp_ns * 1e-9:.6f} s"
                  + ("   [becomes keyframe]" if r.is_keyframe else "")),
        ("reference keyframe", kf + dt),
        ("state", f"{r.state.value}   pose {'yes' if r.has_pose else 'held'}"),
        ("model", f"{r.model.value}   RH {_fmt(r.rh)}"),
        ("features / tracked", f"{r.n_features} / {r.n_tracked}"),
        ("inliers", f"{r.n_inliers}   ratio {r.inlier_ratio:.1%}"),
        ("within gate", f"{within}   gate {gate}"),
        ("median parallax", _fmt(r.median_parallax_deg, ".3f", " deg")),
        ("triangulated", str(r.n_triangulated)),
        ("positive depth", _fmt(100.0 * r.positive_depth_ratio, ".1f", " %")),
        ("median reproj. error", _fmt(r.median_reproj_err_px, ".3f", " px")),
        ("relative scale", _fmt(r.relative_scale, ".4f")),
        ("moving features", moving_text(r)),
        ("keyframes so far", str(r.n_keyframes)),
    ]
    lines = [f"{k:<21}{v}" for k, v in rows]
    lines += textwrap.wrap(r.reason or "-", width=width, initial_indent=f"{'reason':<21}",
                           subsequent_indent=" " * 21)
    return lines


# -------------------------------------------------------------------------------------------------
# Drawing

_GREEN, _RED, _MAGENTA = "#19c219", "#e8281e", "#e600e6"  # magenta: movers, as in the debug image
_DETAIL_COLORS = ("#00e5ff", "#00a0a0", "#ff9900", "#3355ff", "#ffee00", "#000000", "#8c564b", "#ffffff")


def draw_inspection(insp: Inspection, path: str | Path) -> Path:
    """Write the picture of ``insp`` as a PNG (matplotlib, Agg canvas; no pyplot global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    d = insp.data
    h, w = insp.gray_cur.shape
    cur = undistorted_image(insp.gray_cur, insp.camera)
    if insp.gray_kf is not None and insp.camera_kf is not None and insp.gray_kf.shape == cur.shape:
        kf = undistorted_image(insp.gray_kf, insp.camera_kf)
    else:
        kf = np.full_like(cur, 128)
    pair = np.hstack([kf, cur])

    fig = Figure(figsize=(16, 10.4), dpi=100)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 2, height_ratios=[1.6, 1.0], width_ratios=[1.1, 1.0],
                            left=0.045, right=0.985, top=0.955, bottom=0.06, hspace=0.12, wspace=0.08)
    ax = fig.add_subplot(grid[0, :])
    _draw_pair(ax, pair, insp, w, h)
    _draw_histogram(fig.add_subplot(grid[1, 0]), d)
    ax_text = fig.add_subplot(grid[1, 1])
    ax_text.axis("off")
    ax_text.text(0.0, 1.0, "\n".join(record_lines(insp)), family="monospace", fontsize=9.5, va="top", ha="left",
                 transform=ax_text.transAxes)
    ref = f"keyframe {insp.keyframe_index}" if insp.keyframe_index is not None else "no reference keyframe"
    fig.suptitle(f"{insp.bag}   frame {insp.frame_index}  vs  {ref}", fontsize=13, y=0.992)
    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=100, format="png")  # PNG whatever the name ends in
    except OSError as exc:
        where = f" ({exc.filename})" if exc.filename and str(exc.filename) != str(out) else ""
        raise OutputError(f"cannot write {out}: {exc.strerror or exc}{where}") from None
    return out


def _draw_pair(ax: Any, pair: Gray, insp: Inspection, w: int, h: int) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    d = insp.data
    ax.imshow(pair, cmap="gray", vmin=-60, vmax=255, interpolation="bilinear")  # lightened: lines stand out
    ax.axvline(w - 0.5, color="white", lw=2)
    ax.set_xlim(-0.5, 2 * w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    kf_label = (f"keyframe {insp.keyframe_index}" if insp.keyframe_index is not None
                else "no reference keyframe (first frame)")
    for x, text in ((8, kf_label), (w + 8, f"frame {insp.frame_index}")):
        ax.text(x, 10, text, color="white", fontsize=12, weight="bold", va="top",
                bbox={"facecolor": "black", "alpha": 0.6, "pad": 3, "lw": 0})
    n = d.uv_kf.shape[0]
    if n == 0:
        ax.text(w / 2, h / 2, "no correspondences with a keyframe", color="black", fontsize=14, ha="center",
                bbox={"facecolor": "white", "alpha": 0.8, "lw": 0})
        return
    kind = np.where(d.inliers, 0, np.where(d.movers, 2, 1))  # 0 inlier, 1 outlier, 2 mover
    n_out = int(np.count_nonzero(kind == 1))
    classes = ((0, _GREEN, 0.7, f"inliers ({d.n_inliers})"), (1, _RED, 1.2, f"outliers ({n_out})"),
               (2, _MAGENTA, 1.2, f"movers ({d.n_movers})"))
    handles = []
    for k, color, lw, label in classes:  # outliers and movers on top, thicker: they are few
        sel = d.line_idx[kind[d.line_idx] == k]
        if k < 2 or d.n_movers:  # movers in the legend only when there are some
            handles.append(Line2D([], [], color=color, lw=2, marker="o", ms=4, label=label))
        if sel.size == 0:
            continue
        u0, v0 = d.uv_kf[sel, 0], d.uv_kf[sel, 1]
        u1, v1 = d.uv_cur[sel, 0] + w, d.uv_cur[sel, 1]
        ax.plot(np.vstack([u0, u1]), np.vstack([v0, v1]), color=color, lw=lw, alpha=0.8)
        ax.plot(np.r_[u0, u1], np.r_[v0, v1], "o", color=color, ms=2.5, mew=0)
    if d.moving_region is not None:
        x0, y0, x1, y1 = d.moving_region
        ax.add_patch(Rectangle((x0 + w, y0), x1 - x0, y1 - y0, fill=False, ec=_MAGENTA, lw=2, ls="--"))
        handles.append(Rectangle((0, 0), 1, 1, fill=False, ec=_MAGENTA, lw=2, ls="--", label="movers' region"))
    ax.legend(handles=handles, loc="lower right", fontsize=9, framealpha=0.85)
    for k, i in enumerate(d.epi_idx):
        c = _DETAIL_COLORS[k % len(_DETAIL_COLORS)]
        if d.model is Model.ESSENTIAL:
            for line, off in ((d.lines_kf[k], 0), (d.lines_cur[k], w)):
                seg = line_in_box(line, w, h)
                if seg is not None:
                    (ua, va), (ub, vb) = seg
                    ax.plot([ua + off, ub + off], [va, vb], color=c, lw=1.3)
        else:
            ax.plot(d.transfer_kf[k, 0], d.transfer_kf[k, 1], "x", color=c, ms=11, mew=1.8)
            ax.plot(d.transfer_cur[k, 0] + w, d.transfer_cur[k, 1], "x", color=c, ms=11, mew=1.8)
        ax.plot(d.uv_kf[i, 0], d.uv_kf[i, 1], "o", mfc="none", mec=c, ms=11, mew=1.8)
        ax.plot(d.uv_cur[i, 0] + w, d.uv_cur[i, 1], "o", mfc="none", mec=c, ms=11, mew=1.8)
    detail = ("epipolar lines of circled inliers: F^T x_cur (left), F x_kf (right)" if d.model is Model.ESSENTIAL
              else "x: circled inliers mapped by H^-1 (left) and H (right)" if d.model is Model.HOMOGRAPHY else "")
    ax.set_xlabel(f"undistorted images; {d.line_idx.size} of {n} correspondences drawn "
                  f"(green: {d.n_inliers} inliers, red: {n_out} outliers of {insp.result.model.value}, "
                  f"magenta: {d.n_movers} movers); {detail}",
                  fontsize=10.5)


def _draw_histogram(ax: Any, d: PairData) -> None:
    if d.residual_px.size == 0:
        ax.axis("off")
        ax.text(0.5, 0.5, "no model chosen: no residuals", ha="center", va="center", fontsize=12,
                transform=ax.transAxes)
        return
    res = d.residual_px
    finite = res[np.isfinite(res)]
    hi = max(3.0 * d.gate_px, float(np.percentile(finite, 98)) if finite.size else 0.0)
    hi = min(hi, 12.0 * d.gate_px)
    bins = np.linspace(0.0, hi, 41)
    clipped = np.clip(np.where(np.isfinite(res), res, hi), 0.0, hi)
    out = ~d.inliers & ~d.movers
    data = [clipped[d.inliers], clipped[out]]
    colors = [_GREEN, _RED]
    labels = [f"inliers ({d.n_inliers})", f"outliers ({int(np.count_nonzero(out))})"]
    if d.n_movers:  # movers only when there are some, as in the picture's legend
        data.append(clipped[d.movers])
        colors.append(_MAGENTA)
        labels.append(f"movers ({d.n_movers})")
    ax.hist(data, bins=bins, stacked=True, color=colors, label=labels)
    ax.axvline(d.gate_px, color="black", ls="--", lw=1.5, label=f"inlier gate {d.gate_px:.2f} px = {d.gate_rule}")
    n_over = int(np.count_nonzero(~(res <= hi)))
    if n_over:
        ax.text(0.99, 0.70, f"{n_over} beyond {hi:.1f} px (in last bin)", ha="right", va="top",
                transform=ax.transAxes, fontsize=9)
    ax.set_yscale("symlog", linthresh=10)
    ax.set_xlim(0.0, hi)
    ax.set_xlabel(f"{d.model.value}: {d.residual_label}")
    ax.set_ylabel("correspondences")
    med = float(np.median(finite)) if finite.size else math.nan
    ax.set_title(f"residuals of the chosen model over all {res.size} correspondences (median {med:.3f} px)",
                 fontsize=11)
    ax.legend(loc="upper right", fontsize=9)


# -------------------------------------------------------------------------------------------------
def run(args: Any) -> int:
    """``epi-vo inspect``: args.bag, args.frame or args.stamp, args.output, args.params, topics."""
    if args.stamp is not None:  # NaN would pick frame 0 (every distance to it compares false)
        checks.number(args.stamp, "--stamp", minimum=0)
    cfg = load_config(args.params)
    out_arg = Path(args.output) if args.output else None
    if out_arg is not None and not out_arg.is_dir() and out_arg.parent.exists() and not out_arg.parent.is_dir():
        raise OutputError(f"cannot write {out_arg}: {out_arg.parent} is not a directory")
    insp = inspect_bag(args.bag, args.frame, stamp_s=args.stamp, cfg=cfg, image_topic=args.image_topic,
                       camera_info_topic=args.camera_info_topic)
    default_name = f"frame_{insp.frame_index}.png"
    # --output may name the picture or the directory to put frame_<N>.png in.
    out_path = default_name if out_arg is None else out_arg / default_name if out_arg.is_dir() else out_arg
    out = draw_inspection(insp, out_path)
    print(out)
    print(summary_line(insp))
    return 0
