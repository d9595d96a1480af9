"""The plots of a replay report: PNGs drawn with matplotlib's object API.

A bare ``matplotlib.figure.Figure`` renders through Agg; pyplot (hence any display) is never imported.
Inputs are the data of :mod:`epi_vo.tools.report_data`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from numpy.typing import NDArray

from epi_vo.tools.evaluation import NeesResult
from epi_vo.tools.report_data import (
    EST_COLOUR,
    GT_COLOUR,
    MODEL_COLOURS,
    NO_SIM3,
    STATE_COLOURS,
    AlignmentKind,
    ErrorSeries,
    ScaleSeries,
    Span,
    Timeline,
    fmt_num,
)
from epi_vo.tools.report_movers import MoverSeries, MoverSpan
from epi_vo.tools.report_views import TrajectoryViews
from epi_vo.tools.twist_consistency import TwistNees

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

MOVER_COLOUR = "#e600e6"  # magenta, as the debug image and epi-vo inspect draw movers

def draw_trajectory(views: TrajectoryViews, path: Path) -> Path:
    """trajectory.png: top and side views, estimate (keyframes marked) and aligned ground truth."""
    fig = Figure(figsize=(13, 6.5), dpi=100)
    fig.subplots_adjust(left=0.06, right=0.985, top=0.86, bottom=0.14, wspace=0.16)
    axes = fig.subplots(1, 2)
    gt_label = "ground truth"
    if views.alignment is not None:
        gt_label += {AlignmentKind.SIM3: " (Sim(3)-aligned)", AlignmentKind.ORIGIN: " (origin-aligned, own units)",
                     AlignmentKind.NONE: " (not usable)"}[views.alignment.kind]
    for ax, view in zip(axes, (views.top, views.side), strict=True):
        pts = np.vstack([view.est, view.gt]) if view.gt.size else view.est
        extent = float(np.ptp(pts, axis=0).max()) if pts.size else 0.0
        if view.est.size:
            ax.plot(view.est[:, 0], view.est[:, 1], "-", color=EST_COLOUR, lw=2.2, label="estimate")
            # Heading at ~20 poses: the only visible motion under pure rotation.
            step = max(1, math.ceil(view.est.shape[0] / 20))
            h = view.heading[::step]
            norm = np.linalg.norm(h, axis=1, keepdims=True)
            h = np.divide(h, norm, out=np.zeros_like(h), where=norm > 1e-9) * (0.08 * extent if extent > 1e-9 else 0.6)
            ax.quiver(view.est[::step, 0], view.est[::step, 1], h[:, 0], h[:, 1], angles="xy", scale_units="xy",
                      scale=1, color="#555555", width=0.003, alpha=0.7, label=views.heading_label)
            ax.plot(view.keyframes[:, 0], view.keyframes[:, 1], "^", ms=7, mfc=EST_COLOUR, mec="black", mew=0.6,
                    ls="none", label=f"keyframes ({view.keyframes.shape[0]})")
            ax.plot(*view.est[0], "o", ms=9, mfc="#2ca02c", mec="black", label="start")
            ax.plot(*view.est[-1], "s", ms=8, mfc="black", mec="black", label="end")
        else:
            ax.text(0.5, 0.5, "no estimated poses", transform=ax.transAxes, ha="center", va="center")
        if view.gt.size:  # drawn over the estimate (dashed), which it hides where the two agree
            ax.plot(view.gt[:, 0], view.gt[:, 1], "--", color=GT_COLOUR, lw=1.4, label=gt_label, zorder=4)
        if pts.size and extent < 1e-9:  # a single point: give the equal-aspect box a size
            cx, cy = pts[0]
            ax.set_xlim(cx - 1.0, cx + 1.0)
            ax.set_ylim(cy - 1.0, cy + 1.0)
            ax.set_aspect("equal", adjustable="box")
        else:
            ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(view.title)
        ax.set_xlabel(view.xlabel)
        ax.set_ylabel(view.ylabel)
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    if labels:  # nothing drawn (every frame rejected, no ground truth): no legend (ncol must be > 0)
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9, frameon=False)
    title = f"Trajectory ({views.frame})"
    if views.alignment is not None:
        title += f"\n{views.alignment.note}"
    fig.suptitle(title, fontsize=11)
    return _save(fig, path)


def _shade(ax: Any, span_list: Sequence[Span], keyframes: NDArray[np.int64],
           movers: Sequence[MoverSpan] = ()) -> None:
    for s in span_list:
        ax.axvspan(s.start_index - 0.5, s.end_index + 0.5, color=STATE_COLOURS.get(s.state, "#dddddd"), alpha=0.45,
                   lw=0, zorder=0)
    for m in movers:  # a magenta band along the bottom of the panel: movers in view
        ax.axvspan(m.start_index - 0.5, m.end_index + 0.5, ymin=0.0, ymax=0.05, color=MOVER_COLOUR, alpha=0.8,
                   lw=0, zorder=1)
    if keyframes.size:
        ax.plot(keyframes, np.full(keyframes.shape, 1.0), "|", color="black", ms=9, mew=1.2, clip_on=False,
                transform=ax.get_xaxis_transform(), zorder=5)


def _state_legend(fig: Figure, span_list: Sequence[Span], movers: Sequence[MoverSpan] = ()) -> None:
    states = list(dict.fromkeys(s.state for s in span_list))
    handles: list[Any] = [Patch(color=STATE_COLOURS.get(s, "#dddddd"), alpha=0.6, label=s) for s in states]
    if movers:
        handles.append(Patch(color=MOVER_COLOUR, alpha=0.8, label="movers in view (bottom band)"))
    handles.append(Line2D([], [], marker="|", color="black", ls="none", ms=9, mew=1.2, label="keyframe"))
    fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 1.0), ncol=len(handles), fontsize=9,
               frameon=False)


def draw_timeline(tl: Timeline, span_list: Sequence[Span], path: Path, movers: Sequence[MoverSpan] = (),
                  mseries: MoverSeries | None = None) -> Path:
    """timeline.png: stacked per-frame panels sharing the frame axis (a seventh, the features that moved on
    their own and the static hypothesis' score, with ``mseries``)."""
    # Fixed margins: constrained layout would double the drawing time of this figure.
    rows = 6 if mseries is None else 7
    fig = Figure(figsize=(13, 17 + 2.6 * (rows - 6)), dpi=100)
    fig.subplots_adjust(left=0.065, right=0.935, top=0.955, bottom=0.035, hspace=0.3)
    axes = fig.subplots(rows, 1, sharex=True)
    x = tl.frame_index
    kf = tl.keyframe_index

    ax = axes[0]
    ax.plot(x, tl.n_features, "-", color="#444444", lw=1.2, label="features")
    ax.plot(x, tl.n_tracked, "-", color="#1f77b4", lw=1.2, label="tracked")
    ax.plot(x, tl.n_inliers, "-", color="#2ca02c", lw=1.2, label="inliers")
    ax.set_ylabel("count")
    ax.set_ylim(bottom=0)
    axr = ax.twinx()
    axr.plot(x, tl.inlier_ratio, ":", color="#9467bd", lw=1.6, marker=".", ms=3, label="inlier ratio")
    axr.set_ylim(0, 1.05)
    axr.set_ylabel("inlier ratio")
    _legend_pair(ax, axr)
    ax.set_title("features, tracked, inliers")

    ax = axes[1]
    rh_plot = np.where(np.isfinite(tl.rh), tl.rh, 0.0)
    ax.plot(x, tl.rh, "-", color="#999999", lw=0.8)
    models = np.array(tl.model)
    for name, colour in MODEL_COLOURS.items():
        mask = models == name
        if mask.any():
            ax.plot(x[mask], rh_plot[mask], "x" if name == "none" else "o", ls="none", ms=5, color=colour,
                    label=f"model {name} ({int(mask.sum())})")
    if math.isfinite(tl.rh_threshold):
        ax.axhline(tl.rh_threshold, ls="--", color="black", lw=1,
                   label=f"rh_threshold {tl.rh_threshold:g} ({tl.rh_threshold_source})")
    ax.set_ylim(0, 1)
    ax.set_ylabel("RH = S_H/(S_H+S_E)")
    ax.legend(loc="upper right", fontsize=8, ncol=4)
    ax.set_title("model choice (H above the threshold) and RH")

    ax = axes[2]
    ax.plot(x, tl.median_parallax_deg, "-", color="#8c564b", marker=".", ms=4, lw=1.2)
    ax.set_ylabel("deg")
    ax.set_ylim(bottom=0)
    ax.set_title("median parallax (rotation removed)")

    ax = axes[3]
    ax.bar(x, np.nan_to_num(tl.n_triangulated), width=0.8, color="#17becf", label="triangulated points")
    ax.set_ylabel("points")
    ax.set_ylim(bottom=0)
    _say_if_empty(ax, tl.n_triangulated, "no points triangulated in this run")
    axr = ax.twinx()
    axr.plot(x, tl.positive_depth_ratio, "o", color="#d62728", ms=4, label="positive-depth ratio")
    axr.set_ylim(0, 1.1)
    axr.set_ylabel("ratio")
    _legend_pair(ax, axr)
    ax.set_title("triangulation (keyframes) and cheirality")

    ax = axes[4]
    ax.plot(x, tl.median_reproj_err_px, "-", color="#e377c2", marker="o", ms=4, lw=1.2)
    ax.set_ylabel("px")
    ax.set_ylim(bottom=0)
    _say_if_empty(ax, tl.median_reproj_err_px, "no triangulated points, no reprojection error")
    ax.set_title("median reprojection error of triangulated points")

    ax = axes[5]
    if tl.stage_ms:
        ax.stackplot(x, *[np.nan_to_num(v) for v in tl.stage_ms.values()], labels=list(tl.stage_ms), alpha=0.85)
    ax.plot(x, tl.total_ms, "-", color="black", lw=1, label="total")
    ax.set_ylabel("ms")
    ax.set_ylim(bottom=0)
    ax.legend(loc="upper right", fontsize=8, ncol=len(tl.stage_ms) + 1, framealpha=0.9)
    ax.set_title("processing time per stage (stacked)")

    if mseries is not None:
        ax = axes[6]
        ax.plot(mseries.frame_index, mseries.moving_fraction, "-", color=MOVER_COLOUR, marker=".", ms=4, lw=1.2,
                label="moving fraction (of tracked features)")
        ax.plot(mseries.frame_index, mseries.static_score, ":", color="#555555", marker=".", ms=3, lw=1.2,
                label="static score (features that did not move)")
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("fraction")
        axr = ax.twinx()
        axr.plot(mseries.frame_index, mseries.n_moving, "|", color=MOVER_COLOUR, ms=6, label="moving features")
        axr.set_ylim(bottom=0)
        axr.set_ylabel("features")
        _legend_pair(ax, axr)
        ax.set_title("features that moved on their own, and the static-camera hypothesis")
    axes[-1].set_xlabel("frame index")

    for ax in axes:
        _shade(ax, span_list, kf, movers)
        ax.grid(True, alpha=0.3)
    if x.size:
        axes[-1].set_xlim(x[0] - 0.5, x[-1] + 0.5)
    _state_legend(fig, span_list, movers)
    return _save(fig, path)


def _say_if_empty(ax: Any, y: F64, text: str) -> None:
    if not (np.isfinite(y) & (y != 0)).any():
        ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", fontsize=10, color="#555555")


def _legend_pair(ax: Any, axr: Any) -> None:
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = axr.get_legend_handles_labels()
    axr.legend(h1 + h2, l1 + l2, loc="lower right", fontsize=8, ncol=4)


def draw_errors(err: ErrorSeries, span_list: Sequence[Span], keyframes: NDArray[np.int64], path: Path,
                movers: Sequence[MoverSpan] = ()) -> Path:
    """errors.png: ATE over time (Sim(3)-aligned) and RPE rotation / translation per frame."""
    fig = Figure(figsize=(13, 9), dpi=100)
    fig.subplots_adjust(left=0.065, right=0.985, top=0.92, bottom=0.06, hspace=0.32)
    axes = fig.subplots(3, 1, sharex=True)
    panels = (
        (axes[0], err.frame_index, err.ate, "GT units",
         f"ATE over time (Sim(3)-aligned), RMSE {fmt_num(err.ate_rmse)}"),
        (axes[1], err.rpe_frame_index, err.rpe_rot_deg, "deg / frame",
         f"RPE rotation, RMSE {fmt_num(_rmse(err.rpe_rot_deg))} deg/frame"),
        (axes[2], err.rpe_frame_index, err.rpe_trans, "GT units / frame",
         f"RPE translation (Sim(3)-aligned), RMSE {fmt_num(_rmse(err.rpe_trans))}"),
    )
    for ax, x, y, ylabel, title in panels:
        if np.isfinite(y).any():
            ax.plot(*_break_at_gaps(x, y), "-", color="#d62728", marker=".", ms=4, lw=1.2)
            ax.set_ylim(bottom=0)
        else:
            ax.text(0.5, 0.5, f"undefined: {NO_SIM3}",
                    transform=ax.transAxes, ha="center", va="center", fontsize=10, color="#555555")
            ax.set_yticks([])
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        _shade(ax, span_list, keyframes, movers)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("frame index")
    if err.frame_index.size:
        axes[-1].set_xlim(err.frame_index[0] - 0.5, err.frame_index[-1] + 0.5)
    _state_legend(fig, span_list, movers)
    return _save(fig, path)


def draw_nees(nees: NeesResult, span_list: Sequence[Span], keyframes: NDArray[np.int64], path: Path,
              frame_range: tuple[int, int], movers: Sequence[MoverSpan] = (), twist: TwistNees | None = None) -> Path:
    """nees.png: per-frame position and rotation NEES (log y) with the chi-square 3-dof 99 % bound and the
    consistent mean 3; frames not evaluated (not tracking) are gaps. With ``twist`` (its ``frame_index``
    known), two more panels: the linear and angular velocity's NEES against the published twist."""
    panels = [(nees.frame_index, nees.nees_pos, "position", nees.mean_nees_pos, nees.inside_pos_percent,
               "tracking frames"),
              (nees.frame_index, nees.nees_rot, "rotation", nees.mean_nees_rot, nees.inside_rot_percent,
               "tracking frames")]
    if twist is not None and twist.frame_index.size == twist.nees_linear.size > 0:
        panels += [(twist.frame_index, twist.nees_linear, "linear velocity", twist.mean_linear,
                    twist.inside_linear_percent, "twists"),
                   (twist.frame_index, twist.nees_angular, "angular velocity", twist.mean_angular,
                    twist.inside_angular_percent, "twists")]
    fig = Figure(figsize=(13, 3.75 * len(panels)), dpi=100)
    fig.subplots_adjust(left=0.065, right=0.985, top=1.0 - 0.2 / len(panels), bottom=0.16 / len(panels),
                        hspace=0.35)
    axes = fig.subplots(len(panels), 1, sharex=True)
    for ax, (x, y, name, mean, inside, what) in zip(axes, panels, strict=True):
        ok = np.isfinite(y) & (y > 0)
        if ok.any():
            ax.plot(*_break_at_gaps(x[ok], y[ok]), "-", color="#1f77b4", marker=".", ms=4, lw=1.0,
                    label=f"NEES {name}")
            ax.set_yscale("log")
            lo, hi = float(y[ok].min()), float(y[ok].max())
            ax.set_ylim(min(lo, 1.0) / 2.0, max(hi, nees.bound) * 2.0)  # the bound and the mean 3 always in view
            ax.axhline(nees.bound, ls="--", color="#d62728", lw=1.3, label=f"99 % bound, 3 dof ({nees.bound:g})")
            ax.axhline(3.0, ls=":", color="black", lw=1.2, label="consistent mean (3)")
            ax.legend(loc="upper right", fontsize=8, ncol=3, framealpha=0.9)
        else:
            ax.text(0.5, 0.5, "no tracking frame with ground truth" if not x.size else "undefined: no scale alignment",
                    transform=ax.transAxes, ha="center", va="center", fontsize=10, color="#555555")
            ax.set_yticks([])
        ax.set_ylabel("NEES (3 dof)")
        ax.set_title(f"{name} NEES against the published covariance: mean {fmt_num(mean)}, "
                     f"{fmt_num(inside, '.1f')} % inside the 99 % bound ({x.size} {what})")
        _shade(ax, span_list, keyframes, movers)
        ax.grid(True, alpha=0.3, which="both")
    axes[-1].set_xlabel("frame index")
    axes[-1].set_xlim(frame_range[0] - 0.5, frame_range[1] + 0.5)
    _state_legend(fig, span_list, movers)
    return _save(fig, path)


def draw_scale(series: ScaleSeries, span_list: Sequence[Span], keyframes: NDArray[np.int64], path: Path,
               movers: Sequence[MoverSpan] = ()) -> Path:
    """scale.png: metres per VO unit with its 1-sigma band over frames; the floor's pitch and roll below it
    when the source measured them (ground_plane)."""
    rows = 2 if series.has_floor else 1
    height = 1.3 + 3.2 * rows  # inches: fixed margins for the legend on top and the frame axis below
    fig = Figure(figsize=(13, height), dpi=100)
    fig.subplots_adjust(left=0.065, right=0.985, top=1.0 - 0.75 / height, bottom=0.55 / height, hspace=0.32)
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    x = series.frame_index

    ax = axes[0]
    if np.isfinite(series.scale).any():
        band = np.isfinite(series.lower) & np.isfinite(series.upper)
        ax.fill_between(x, series.lower, series.upper, where=band, color=EST_COLOUR, alpha=0.25, lw=0,
                        label="±1 sigma (scale_rel_std)")
        ax.plot(x, series.scale, "-", color=EST_COLOUR, marker=".", ms=3, lw=1.4, label="scale")
        first = int(x[np.argmax(series.metric)])
        ax.axvline(first, ls="--", color="black", lw=1, label=f"metric from frame {first}")
        ax.legend(loc="lower right", fontsize=8, ncol=3, framealpha=0.9)
    else:
        ax.text(0.5, 0.5, "metric scale never established: the run is in VO units", transform=ax.transAxes,
                ha="center", va="center", fontsize=10, color="#555555")
        ax.set_yticks([])
    ax.set_ylabel("m / VO unit")
    ax.set_title(f"scale ({series.source}): metres per VO unit of the first map")

    if series.has_floor:
        ax = axes[1]
        ax.plot(x, series.floor_pitch_deg, "-", color="#8c564b", marker=".", ms=3, lw=1.2, label="pitch")
        ax.plot(x, series.floor_roll_deg, "-", color="#9467bd", marker=".", ms=3, lw=1.2, label="roll")
        ax.set_ylabel("deg")
        ax.legend(loc="lower right", fontsize=8, ncol=2, framealpha=0.9)
        ax.set_title("camera pitch and roll to the floor (ground plane)")

    for ax in axes:
        _shade(ax, span_list, keyframes, movers)
        ax.grid(True, alpha=0.3)
    axes[-1].set_xlabel("frame index")
    if x.size:
        axes[-1].set_xlim(x[0] - 0.5, x[-1] + 0.5)
    _state_legend(fig, span_list, movers)
    return _save(fig, path)


def _break_at_gaps(x: NDArray[np.int64], y: F64) -> tuple[F64, F64]:
    """Insert a NaN where frames are missing (no pose), so that no line is drawn across them."""
    gaps = np.flatnonzero(np.diff(x) > 1) + 1
    return np.insert(x.astype(np.float64), gaps, math.nan), np.insert(y, gaps, math.nan)


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, format="png")
    return path


def _rmse(a: F64) -> float:
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan
