"""The report's static-camera and moving-object data: pure functions of a run's frame records.

- :func:`mover_series` gives, per frame, the tracked features that moved on their own (``n_moving``,
  ``moving_fraction``), the region they moved in and the static hypothesis' score;
- :func:`mover_spans` finds the runs of consecutive frames with movers in view (at least
  ``MOVER_FRACTION_MIN`` of the tracked features, and at least one feature), whatever the state;
- :func:`static_spans` the runs of frames in state ``static`` (the camera held still while something
  moved), each with what moved during it (:func:`what_moved`).

Records of a replay older than the mover check have no ``n_moving``: no movers, never an error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from epi_vo.tools.report_data import Run, Span, spans

F64 = NDArray[np.float64]

# A frame counts as "movers in view" from this share of its tracked features on: one stray feature that
# the pipeline called moving is no moving object worth a span.
MOVER_FRACTION_MIN = 0.02
STATIC = "static"


def _num(value: Any) -> float:
    return math.nan if value is None else float(value)


@dataclass(frozen=True)
class MoverSeries:
    """Per-frame mover figures, one entry per record."""

    frame_index: NDArray[np.int64]
    n_moving: NDArray[np.int64]
    moving_fraction: F64  # of the tracked features
    static_score: F64  # fraction of tracked features the "no camera motion" hypothesis explains; NaN: not scored
    region: tuple[tuple[int, int, int, int] | None, ...]  # x0, y0, x1, y1 (px) of the movers

    @property
    def has_movers(self) -> NDArray[np.bool_]:
        return (self.n_moving > 0) & (np.nan_to_num(self.moving_fraction) >= MOVER_FRACTION_MIN)


def mover_series(run: Run) -> MoverSeries:
    recs = run.records

    def region(r: dict[str, Any]) -> tuple[int, int, int, int] | None:
        box = r.get("moving_region")
        return None if not box else (int(box[0]), int(box[1]), int(box[2]), int(box[3]))

    return MoverSeries(
        frame_index=np.array([int(r["index"]) for r in recs], dtype=np.int64),
        n_moving=np.array([int(r.get("n_moving") or 0) for r in recs], dtype=np.int64),
        moving_fraction=np.array([_num(r.get("moving_fraction", 0.0)) for r in recs]),
        static_score=np.array([_num(r.get("static_score")) for r in recs]),
        region=tuple(region(r) for r in recs))


@dataclass(frozen=True)
class MoverSpan:
    """A maximal run of consecutive frames with movers in view (see ``MoverSeries.has_movers``)."""

    start_index: int
    end_index: int  # inclusive
    start_stamp_s: float
    end_stamp_s: float
    n_frames: int
    states: tuple[str, ...]  # the frames' states, in order of first appearance
    what: str  # what moved (``what_moved``)


def what_moved(series: MoverSeries, start_index: int, end_index: int) -> str:
    """'up to 60 features (36 %) moved on their own, in x 13-638, y 88-403 px' over frames start..end
    (the region is the union of the frames' regions); 'nothing moved' when no frame had movers."""
    sel = (series.frame_index >= start_index) & (series.frame_index <= end_index) & (series.n_moving > 0)
    if not sel.any():
        return "nothing moved"
    n = int(series.n_moving[sel].max())
    frac = float(np.nanmax(series.moving_fraction[sel])) if np.isfinite(series.moving_fraction[sel]).any() else 0.0
    boxes = [b for b, s in zip(series.region, sel, strict=True) if s and b is not None]
    where = ""
    if boxes:
        a = np.array(boxes)
        where = f", in x {a[:, 0].min()}-{a[:, 2].max()}, y {a[:, 1].min()}-{a[:, 3].max()} px"
    return f"up to {n} features ({100.0 * frac:.0f} %) moved on their own{where}"


def mover_spans(run: Run, series: MoverSeries | None = None) -> list[MoverSpan]:
    """Contiguous runs of frames with movers in view (a frame without them ends a span)."""
    s = mover_series(run) if series is None else series
    flag = s.has_movers
    stamps = [float(r["stamp"]) for r in run.records]
    states = [str(r["state"]) for r in run.records]
    out: list[MoverSpan] = []
    i = 0
    while i < flag.size:
        if not flag[i]:
            i += 1
            continue
        j = i
        while j + 1 < flag.size and flag[j + 1]:
            j += 1
        a, b = int(s.frame_index[i]), int(s.frame_index[j])
        out.append(MoverSpan(a, b, stamps[i], stamps[j], j - i + 1, tuple(dict.fromkeys(states[i:j + 1])),
                             what_moved(s, a, b)))
        i = j + 1
    return out


@dataclass(frozen=True)
class StaticSpan:
    """A run of frames in state ``static`` and what moved in front of the still camera."""

    span: Span
    what: str


def static_spans(run: Run, span_list: Sequence[Span] | None = None,
                 series: MoverSeries | None = None) -> list[StaticSpan]:
    s = mover_series(run) if series is None else series
    return [StaticSpan(sp, what_moved(s, sp.start_index, sp.end_index))
            for sp in (spans(run) if span_list is None else span_list) if sp.state == STATIC]
