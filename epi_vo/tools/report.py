"""The replay report: ``DIR/report/{trajectory,timeline,errors,scale}.png`` and ``DIR/report.html``, one
file that embeds the PNGs as data URIs and needs nothing else.

Lengths are labelled in the run's units (``stats.json`` ``units``: metres once a metric scale source was
established, VO units otherwise). ``scale.png`` is drawn only for a run with a metric scale source
(``scale_source`` other than none); errors.png and nees.png (covariance consistency,
:func:`epi_vo.tools.evaluation.replay_nees`, and the twist's) only with ground truth. Static spans (state ``static``)
are shaded like the other states; spans with movers in view (:mod:`epi_vo.tools.report_movers`) are a
magenta band along the bottom of every timeline panel, and both are listed with what moved.

The data come from :mod:`epi_vo.tools.report_data` (what the tests check), the figures from
:mod:`epi_vo.tools.report_plots`; this module writes them and renders the HTML.
"""

from __future__ import annotations

import argparse
import base64
import datetime
import html
import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.config import config_fields, field_doc
from epi_vo.core.errors import EpiVoError, EvaluationError, ReportError
from epi_vo.io.odometry_bag import read_estimate_odometry
from epi_vo.tools.evaluation import NeesResult, replay_nees
from epi_vo.tools.report_data import (
    NO_SIM3,
    REPORT_HTML,
    REPORT_PNG_DIR,
    STATE_COLOURS,
    AlignmentKind,
    GtAlignment,
    Run,
    RunFigures,
    Span,
    error_series,
    fmt_num,
    load_run,
    reason_groups,
    run_figures,
    run_parameters,
    run_scale,
    scale_series,
    spans,
    timeline,
    units_name,
)
from epi_vo.tools.report_movers import (
    MOVER_FRACTION_MIN,
    MoverSpan,
    StaticSpan,
    mover_series,
    mover_spans,
    static_spans,
)
from epi_vo.tools.report_plots import draw_errors, draw_nees, draw_scale, draw_timeline, draw_trajectory
from epi_vo.tools.report_views import run_extrinsic, trajectory_views
from epi_vo.tools.twist_consistency import TwistNees, replay_twist_nees

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

def write_report(directory: str | Path) -> Path:
    """Write ``DIR/report/*.png`` and the self-contained ``DIR/report.html``; return the HTML's path.

    Raises:
        ReportError: the directory cannot be read as a replay output (see :func:`load_run`), or the
            report cannot be written into it.
    """
    run = load_run(directory)
    try:
        return _write_report(run)
    except OSError as exc:  # DIR/report or report.html not writable, a file where a directory goes, disk full
        where = f" ({exc.filename})" if exc.filename else ""
        msg = f"cannot write the report in {run.directory}: {exc.strerror or exc}{where}"
        raise ReportError(msg) from None


def _write_report(run: Run) -> Path:
    png_dir = run.directory / REPORT_PNG_DIR
    png_dir.mkdir(exist_ok=True)
    views = trajectory_views(run)
    tl = timeline(run)
    span_list = spans(run)
    err = error_series(run)
    units = units_name(run_scale(run).units)
    mseries = mover_series(run)
    movers = mover_spans(run, mseries)
    pngs = [(draw_trajectory(views, png_dir / "trajectory.png"), f"Trajectory in the {views.frame}: "
             f"{views.top.title} and {views.side.title}, estimate in {units} with its keyframes; ground truth in the "
             "same frame."),
            (draw_timeline(tl, span_list, png_dir / "timeline.png", movers, mseries), "Per-frame timeline. Shaded: "
             "frames not tracking, by state (static: the camera held still while something moved); magenta band "
             "at the bottom of each panel: movers in view (at least "
             f"{MOVER_FRACTION_MIN:.0%} of the tracked features moved on their own); ticks at the top of each "
             "panel: keyframes. Last panel: the features that moved on their own and the static hypothesis' "
             "score.")]
    errors_png = png_dir / "errors.png"
    if err is not None:
        pngs.append((draw_errors(err, span_list, tl.keyframe_index, errors_png, movers),
                     "Errors against ground truth (evo): ATE of the Sim(3)-aligned estimate over time, RPE between "
                     "consecutive frames."))
    else:
        errors_png.unlink(missing_ok=True)  # a stale plot of an earlier report would contradict this one
    scale = scale_series(run)
    scale_png = png_dir / "scale.png"
    if scale is not None:
        pngs.append((draw_scale(scale, span_list, tl.keyframe_index, scale_png, movers),
                     f"Metric scale ({scale.source}): metres per VO unit of the first map, shaded ±1 sigma "
                     "(scale_rel_std), drawn from the frame metric scale was established" +
                     ("; below, the camera's pitch and roll to the floor." if scale.has_floor else ".")))
    else:
        scale_png.unlink(missing_ok=True)
    nees, nees_note, twist = run_nees(run)
    nees_png = png_dir / "nees.png"
    if nees is not None and nees.evaluated:  # no tracking frame (a static or rotating camera): the summary says so
        frame_range = (int(tl.frame_index[0]), int(tl.frame_index[-1]))
        pngs.append((draw_nees(nees, span_list, tl.keyframe_index, nees_png, frame_range, movers, twist),
                     "Covariance consistency: per tracking frame, the normalised estimation error squared of the "
                     "position and of the rotation against the covariance published in /vo/odometry (3 dof, log "
                     "scale), after the one global scale (Sim(3) anchored at the odometry origin; SE(3) with metric "
                     "scale); below, the same for the published twist's linear and angular velocity against the "
                     "ground truth's motion since the previous frame. A consistent covariance gives a mean of 3 "
                     "and 99 % of the frames below the dashed bound."))
    else:
        nees_png.unlink(missing_ok=True)
    page = render_html(run, run_figures(run), span_list, views.alignment, pngs, nees=nees, nees_note=nees_note,
                       twist=twist,
                       movers=movers, statics=static_spans(run, span_list, mseries))
    out = run.directory / REPORT_HTML
    out.write_text(page, encoding="utf-8")
    return out


def run_nees(run: Run) -> tuple[NeesResult | None, str, TwistNees | None]:
    """The run's covariance consistency (pose; and twist, None when it cannot be judged) and, when there
    is none, why (no ground truth, no output.mcap, ...). output.mcap is read once for both."""
    if run.gt is None:
        return None, "no ground truth", None
    if not (run.directory / "output.mcap").is_file():
        return None, "no output.mcap (the published covariance)", None
    try:
        odometry = read_estimate_odometry(run.directory / "output.mcap")
    except EpiVoError as exc:
        return None, f"not computed: cannot read {run.directory / 'output.mcap'}: {exc}", None
    records = list(run.records)
    T_base_cam = run_extrinsic(run)  # the extrinsic the odometry was made with (None: the default)
    try:
        nees = replay_nees(records, odometry, run.gt, T_base_cam=T_base_cam)
    except EvaluationError as exc:
        return None, f"not computed: {exc}", None
    try:
        twist = replay_twist_nees(records, odometry, run.gt, T_base_cam)
    except (EvaluationError, ValueError, np.linalg.LinAlgError):
        twist = None
    return nees, "", twist


def run(args: argparse.Namespace) -> int:
    """``epi-vo report DIR``: write the report and print the HTML's path."""
    print(write_report(args.dir))
    return 0


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;background:#f4f5f7;color:#222}
main{max-width:1320px;margin:0 auto;padding:18px 28px 40px;background:#fff}
h1{font-size:1.5em;margin:.3em 0}
h2{font-size:1.15em;margin:1.4em 0 .5em;border-bottom:1px solid #ddd;padding-bottom:3px}
table{border-collapse:collapse;font-size:.9em;margin:.3em 0}
th,td{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f0f2f5;font-weight:600}td.num{text-align:right;font-variant-numeric:tabular-nums}
.kv th{width:16em}.chip{display:inline-block;padding:1px 7px;border-radius:8px;font-size:.9em}
figure{margin:.8em 0}figure img{max-width:100%;border:1px solid #e3e3e3}
figcaption{font-size:.85em;color:#555}.note{color:#8a5a00}.muted{color:#777}
code{background:#f0f2f5;padding:0 3px;border-radius:3px}
"""

# After load, count the images the browser actually decoded (tests read it with --dump-dom).
_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; });
  document.body.setAttribute('data-images', String(imgs.length));
  document.body.setAttribute('data-loaded', String(ok.length));
});
"""


def render_html(run: Run, figs: RunFigures, span_list: Sequence[Span], alignment: GtAlignment | None,
                pngs: Sequence[tuple[Path, str]], *, nees: NeesResult | None = None, nees_note: str = "",
                movers: Sequence[MoverSpan] = (), statics: Sequence[StaticSpan] = (),
                twist: TwistNees | None = None) -> str:
    """The report page: inline CSS, PNGs as base64 data URIs, no external resource."""
    e = html.escape
    stats = run.stats or {}
    parts = [f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>epi_vo report: {e(run.directory.name)}</title><style>{_CSS}</style></head><body><main>",
             f"<h1>epi_vo report: {e(run.directory.name)}</h1>",
             f"<p class=\"muted\">{e(str(run.directory.resolve()))} &middot; generated "
             f"{e(datetime.datetime.now().astimezone().strftime('%Y-%m-%d %H:%M:%S %Z'))}</p>"]

    unknown = "unknown (no stats.json)" if run.stats is None else "unknown"
    gt_source = stats.get("gt_source") or ("groundtruth.tum" if run.gt is not None else "none")
    parts.append("<h2>Input</h2>")
    parts.append(_kv_table([("bag", e(str(stats.get("bag", unknown)))),
                            ("image topic", e(str(stats.get("image_topic", unknown)))),
                            ("camera_info topic", e(str(stats.get("camera_info_topic", unknown)))),
                            ("ground truth", e(str(gt_source)))]))

    parts.append("<h2>Summary</h2>")
    rows = [("frames", f"{figs.frames}"),
            ("with a pose", f"{figs.frames_with_pose} ({figs.tracked_percent:.1f} %)"),
            ("states", ", ".join(f"{_chip(s)} {n} ({100.0 * n / figs.frames:.1f} %)"
                                 for s, n in sorted(figs.states.items()))),
            ("keyframes", f"{figs.keyframes}"),
            ("models", ", ".join(f"{e(m)} {n}" for m, n in sorted(figs.models.items()))),
            ("time per frame (median)", f"{fmt_num(figs.ms_per_frame, '.2f')} ms total; " +
             ", ".join(f"{e(k)} {fmt_num(v, '.2f')}" for k, v in figs.stage_ms.items()) + " ms"),
            ("path length (estimate)", f"{figs.path_length:.3f} {units_name(figs.scale.units)}"),
            ("scale source", e(figs.scale.source)),
            ("units", "m (metric scale)" if figs.scale.units == "m" else "VO units (no metric scale)"),
            ("metric from frame", "-" if figs.scale.metric_from_frame is None else f"{figs.scale.metric_from_frame}")]
    m = figs.metrics
    if m is not None:
        no_sim3 = f"undefined: {NO_SIM3}"
        rows += [("matched poses (GT)", f"{m.matched_poses}"),
                 ("ATE RMSE (Sim(3))", f"{fmt_num(m.ate_rmse)} GT units ({fmt_num(m.ate_percent_of_path)} % of path), "
                                       f"scale estimate&rarr;GT {fmt_num(m.sim3_scale)}"
                  if math.isfinite(m.ate_rmse) else no_sim3),
                 ("RPE rotation RMSE", f"{fmt_num(m.rpe_rot_deg_per_frame)} deg/frame"),
                 ("RPE translation RMSE", f"{fmt_num(m.rpe_trans_rmse)} GT units/frame"
                  if math.isfinite(m.rpe_trans_rmse) else no_sim3),
                 ("translation direction error", f"{fmt_num(m.trans_direction_err_deg)} deg (mean over "
                                                 f"{m.trans_direction_pairs} steps)"
                  if m.trans_direction_pairs else "undefined: no step with a direction in both trajectories")]
        if figs.metrics_note:
            rows.append(("poses evaluated", e(figs.metrics_note)))
    else:
        rows.append(("ATE / RPE", f"<span class=\"muted\">{e(figs.metrics_note)}</span>"))
    rows += _nees_rows(nees, nees_note, twist)
    parts.append(_kv_table(rows))
    notes = [str(n) for n in stats.get("notes", []) or []]
    if alignment is not None and alignment.kind is not AlignmentKind.SIM3:
        notes.append(alignment.note)
    parts.extend(f"<p class=\"note\">note: {e(n)}</p>" for n in notes)

    parts.append(f"<h2 id=\"spans\">Degenerate and lost spans ({len(span_list)})</h2>")
    if span_list:
        head = ("<table class=\"spans\"><tr><th>state</th><th>frames</th><th>count</th><th>stamps [s]</th>"
                "<th>duration [s]</th><th>reasons</th></tr>")
        body = []
        for s in span_list:
            reasons = "<br>".join(e(ex) + (f" <span class=\"muted\">(and {n - 1} more like it)</span>" if n > 1 else "")
                                  for ex, n in reason_groups(s.reasons)) or "<span class=\"muted\">-</span>"
            frames = f"{s.start_index}" if s.end_index == s.start_index else f"{s.start_index}&ndash;{s.end_index}"
            body.append(f"<tr><td>{_chip(s.state)}</td><td class=\"num\">{frames}</td>"
                        f"<td class=\"num\">{s.n_frames}</td><td class=\"num\">{s.start_stamp_s:.3f}&ndash;"
                        f"{s.end_stamp_s:.3f}</td><td class=\"num\">{s.duration_s:.3f}</td><td>{reasons}</td></tr>")
        parts.append(head + "".join(body) + "</table>")
    else:
        parts.append("<p>None: every frame was tracking.</p>")
    parts.append(_mover_section(movers, statics))
    parts.append("<h2>Parameters</h2>")
    params, source = run_parameters(run)
    docs = {f.name: field_doc(f) for f in config_fields()}
    if source == "stats.json":
        parts.append("<p>As used by the replay (from <code>stats.json</code>).</p>")
    else:
        parts.append("<p>Not recorded in <code>stats.json</code>: the built-in defaults are shown "
                     "(<code>epi-vo params</code>); a <code>--params</code> file given to the replay would not "
                     "be reflected here.</p>")
    # Collapsed: the plots, not 40 numbers, are what a reader scrolls to.
    parts.append(f"<details><summary>{len(params)} values</summary><table><tr><th>parameter</th><th>value</th>"
                 "<th>meaning</th></tr>" +
                 "".join(f"<tr><td><code>{e(k)}</code></td><td>{e(json.dumps(v))}</td><td>{e(docs.get(k, ''))}"
                         f"</td></tr>" for k, v in params.items()) + "</table></details>")

    parts.append("<h2>Plots</h2>")
    if figs.scale.source == "none":
        parts.append("<p class=\"muted\" id=\"scale-note\">No scale source (<code>scale_source: none</code>): the "
                     "run is in VO units, no scale plot.</p>")
    for png, caption in pngs:
        data = base64.b64encode(png.read_bytes()).decode("ascii")
        parts.append(f"<figure id=\"{e(png.stem)}\"><img alt=\"{e(png.stem)}\" src=\"data:image/png;base64,{data}\">"
                     f"<figcaption>{e(caption)}</figcaption></figure>")

    parts.append(f"</main><script>{_SCRIPT}</script></body></html>\n")
    return "\n".join(parts)


def _nees_rows(nees: NeesResult | None, note: str, twist: TwistNees | None = None) -> list[tuple[str, str]]:
    """Summary rows of the covariance consistency (already-escaped HTML)."""
    if nees is None:
        why = html.escape(note or "not computed")
        return [("covariance consistency (NEES)", f"<span class=\"muted\">{why}</span>")]
    skipped = ", ".join(f"{html.escape(k)} {n}" for k, n in sorted(nees.skipped.items())) or "none"
    how = ("SE(3), metric scale" if nees.alignment == "se3"
           else f"Sim(3), scale estimate&rarr;GT {fmt_num(nees.scale)}")
    return [("NEES position (3 dof)", f"mean {fmt_num(nees.mean_nees_pos)}, {fmt_num(nees.inside_pos_percent, '.1f')}"
                                      f" % inside the 99 % bound ({nees.bound:g}); consistent: 3 and 99 %"),
            ("NEES rotation (3 dof)", f"mean {fmt_num(nees.mean_nees_rot)}, {fmt_num(nees.inside_rot_percent, '.1f')}"
                                      " % inside the 99 % bound"),
            ("NEES frames", f"{nees.evaluated} tracking frames evaluated ({how}, anchored at the odometry "
                            f"origin); skipped: {skipped}")] + ([] if twist is None or not twist.nees_linear.size else [
        ("NEES twist (3 dof each)",
         f"linear velocity mean {fmt_num(twist.mean_linear)}, {fmt_num(twist.inside_linear_percent, '.1f')} % "
         f"inside; angular velocity mean {fmt_num(twist.mean_angular)}, "
         f"{fmt_num(twist.inside_angular_percent, '.1f')} % inside ({twist.nees_linear.size} pairs of consecutive "
         "tracking frames, against the ground truth's motion between them)")])


def _mover_section(movers: Sequence[MoverSpan], statics: Sequence[StaticSpan]) -> str:
    """The static-camera and mover spans, in frame order, with what moved."""
    e = html.escape
    rows = [(s.span.start_index, "static camera", s.span.start_index, s.span.end_index, s.span.n_frames,
             s.span.start_stamp_s, s.span.end_stamp_s, STATIC_STATE, s.what) for s in statics]
    rows += [(m.start_index, "movers in view", m.start_index, m.end_index, m.n_frames, m.start_stamp_s,
              m.end_stamp_s, ", ".join(m.states), m.what) for m in movers]
    rows.sort(key=lambda r: (r[0], r[1]))
    out = [f"<h2 id=\"movers\">Static camera and moving objects ({len(statics)} static, {len(movers)} mover "
           "spans)</h2>"]
    if not rows:
        out.append("<p>None: the camera never held still for a moving object, and nothing moved on its own.</p>")
        return "\n".join(out)
    body = []
    for _, kind, a, b, n, t0, t1, states, what in rows:
        frames = f"{a}" if a == b else f"{a}&ndash;{b}"
        chips = " ".join(_chip(st) for st in states.split(", "))
        body.append(f"<tr><td>{e(kind)}</td><td class=\"num\">{frames}</td><td class=\"num\">{n}</td>"
                    f"<td class=\"num\">{t0:.3f}&ndash;{t1:.3f}</td><td>{chips}</td><td>{e(what)}</td></tr>")
    out.append("<table class=\"movers\"><tr><th>span</th><th>frames</th><th>count</th><th>stamps [s]</th>"
               "<th>states</th><th>what moved</th></tr>" + "".join(body) + "</table>")
    return "\n".join(out)


STATIC_STATE = "static"


def _kv_table(rows: Sequence[tuple[str, str]]) -> str:
    """Rows of already-escaped HTML."""
    return "<table class=\"kv\">" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"


def _chip(state: str) -> str:
    return (f"<span class=\"chip\" style=\"background:{STATE_COLOURS.get(state, '#dddddd')}\">"
            f"{html.escape(state)}</span>")
