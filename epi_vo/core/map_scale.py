"""The map's scale in the pose covariance (numpy only).

A monocular map knows its translation up to one scale. How uncertain that scale is, and how its error
moves the published position, depends on whether a scale source established metres:

* VO units: the map's log-scale is a random walk of ``scale_drift_per_keyframe`` per keyframe. One scale
  error moves every later step alike, so the position error it causes grows coherently along the path:
  the scale variance and its covariance with the position are carried, as an EKF augmented with the scale
  would (``keyframe_cov``). Each keyframe's new points are triangulated with its step's length, so the
  map's next steps are measured in units that carry that length's error: the step's own relative length
  variance (``length_rel_var``) joins the log-scale at the keyframe. A map rebuilt after a loss takes its
  baseline from the last speed, so its scale against the first map's is known only to
  ``NEW_MAP_REL_STD``: its log-scale starts with that variance. The first map's own units are as sure as
  its depths, which a rotation error across the baseline moves alike at low parallax
  (``first_map_rel_var``). Between keyframes the path since the keyframe carries the same scale term the
  next keyframe step will book (``since_keyframe``).
* Metric: the scale filter's relative standard deviation times each keyframe step (along it), and, once, the
  rescaling of what the map accumulated in VO units when metres are established (``metric_covariance``);
  the source's systematic error scales the whole path about the map's origin (``systematic``).

The calibration's error, which also grows coherently along the path, is ``calibration_cov``'s.

The tracking state holds one ``MapScaleCovariance`` (a frozen value, replaced as keyframes come); each
map's start is given by ``with_origin``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from epi_vo.core.scale import NEW_MAP_REL_STD, ScaleSource

F64 = NDArray[np.float64]


def length_rel_var(c: F64, cov: F64) -> float:
    """Relative variance of the length of a step ``c`` (3,) under its pose covariance ``cov`` (its 3x3
    position block in the same frame): ``c^T P c / |c|^4``; 0 for no step."""
    n2 = float(c @ c)
    if not n2 > 0.0:
        return 0.0
    v = float(c @ cov[:3, :3] @ c) / (n2 * n2)
    return v if math.isfinite(v) and v > 0.0 else 0.0


def first_map_rel_var(d: F64, rot_cov: F64, parallax_deg: float) -> float:
    """Relative variance of a first map's units: its points' depths, and so every step measured against
    them, come from the parallax ``alpha`` between the two views, and a rotation error ``delta`` about an
    axis across the baseline ``d`` (odometry frame) shifts every point's parallax alike, so every depth by
    ``delta / alpha``: a coherent error of the map's scale that no number of points averages out (large
    at low parallax). ``rot_cov``: the rotation's covariance (3x3, odometry frame) at the map's first
    pose; across the baseline: the mean of its two axes normal to ``d``. Capped at a rebuilt map's."""
    n = float(np.linalg.norm(d))
    alpha = math.radians(parallax_deg) if math.isfinite(parallax_deg) else 0.0
    if not (n > 0.0 and alpha > 0.0 and np.all(np.isfinite(rot_cov))):
        return 0.0
    u = d / n
    across = 0.5 * (float(np.trace(rot_cov)) - float(u @ rot_cov @ u))
    v = across / (alpha * alpha)
    return min(v, NEW_MAP_REL_STD**2) if math.isfinite(v) and v > 0.0 else 0.0


def _zeros3() -> F64:
    return np.zeros(3)


def _zeros6() -> F64:
    return np.zeros((6, 6))


@dataclass(frozen=True)
class MapScaleCovariance:
    """The scale part of the pose covariance of the current map (see module doc); frozen: what learns
    returns the value after it."""

    drift_per_keyframe: float
    origin_w: F64 = field(default_factory=_zeros3)  # where the current map was initialised (odometry frame)
    origin_cov: F64 = field(default_factory=_zeros6)  # and the pose covariance it started from
    var: float = 0.0  # VO units: the map's log-scale variance ...
    cov_ps: F64 = field(default_factory=_zeros3)  # ... and its covariance with the position
    mapped: bool = False  # a map was made before the current one (VO units: the current one was rebuilt)

    @property
    def q(self) -> float:
        return self.drift_per_keyframe**2

    def with_origin(self, origin_w: F64, origin_cov: F64) -> MapScaleCovariance:
        """A map starts at ``origin_w`` with the pose covariance ``origin_cov``."""
        return dataclasses.replace(self, origin_w=np.array(origin_w, dtype=np.float64),
                                   origin_cov=np.array(origin_cov, dtype=np.float64))

    def step_rel_std(self, scale: ScaleSource) -> float:
        """Relative standard deviation of one step's length through the map's scale (the twist's): the
        scale source's once metric (its systematic error included), else one keyframe's scale transfer.

        In VO units a step is measured in the current map's units, which differ from the last keyframe's
        by one transfer; the drift accumulated since the first map is the position's (it is in the pose
        covariance, ``keyframe_cov``), not the velocity's: a step's length is as uncertain after a hundred
        keyframes as after one."""
        if scale.established:
            return scale.rel_std
        return math.sqrt(self.q)

    def keyframe_cov(self, scale: ScaleSource, new_map: bool, d: F64, step_rel_var: float = 0.0,
                     first_rel_var: float = 0.0) -> tuple[MapScaleCovariance, F64]:
        """The position covariance a keyframe step ``d`` (odometry frame, map units) adds through the map's
        scale error, and the value after the step. Metric: the scale filter's relative standard deviation
        times the step, along the step (a scale error lengthens a step, it does not turn it). VO units:
        var_p += d d^T var_s + c d^T + d c^T, c += d (var_s + r), var_s += q + r, with ``r``
        (``step_rel_var``) the step's own relative length variance: the new keyframe's points, and so the
        next steps' units, take it on, and the step's position already holds it (hence its covariance with
        the scale). On a new map the first baseline's length (E's covariance along it) is the map's scale
        error itself. A rebuilt map's units are the old ones carried by the last speed
        (``NEW_MAP_REL_STD``): its first baseline and every later step are that uncertain against the
        first map's units, which the judge's one Sim(3) scale measures in."""
        q = self.q
        if scale.established:
            return dataclasses.replace(self, mapped=True), np.outer(d, d) * scale.filter.rel_std ** 2
        if new_map:
            if not self.mapped:
                r = first_rel_var
                return dataclasses.replace(self, var=q + r, cov_ps=d * (q + r), mapped=True), np.outer(d, d) * r
            vs = NEW_MAP_REL_STD**2
            return dataclasses.replace(self, var=vs + q, cov_ps=d * vs), np.outer(d, d) * vs
        vs, c = self.var, self.cov_ps
        # A step known worse than the hand-over's speed carries units no worse than a rebuilt map's: past
        # that, a first-order log-scale says nothing more (and a step of almost no length would claim any).
        r = min(step_rel_var, NEW_MAP_REL_STD**2)
        after = dataclasses.replace(self, cov_ps=c + d * (vs + r), var=vs + q + r)
        return after, np.outer(d, d) * vs + np.outer(c, d) + np.outer(d, c)

    def since_keyframe(self, s: F64) -> F64:
        """The position covariance the map's scale error gives the part ``s`` (odometry frame, map units) of
        the path since the last keyframe: that part is measured in the current map's units as the next
        keyframe step will be (``keyframe_cov`` books it there), so between keyframes it carries the same
        ``s s^T var_s + c s^T + s c^T``, without which the covariance would grow only at keyframes."""
        return np.outer(s, s) * self.var + np.outer(self.cov_ps, s) + np.outer(s, self.cov_ps)

    def metric_covariance(self, scale: ScaleSource, cov_w_c: F64, factor: float, d: F64) -> F64:
        """The pose covariance when the map's VO units become metres: what the map added since its origin
        (not the covariance of the held pose it started from) is rescaled with the positions by ``factor``,
        and the scale source's own uncertainty lies along the displacement ``d`` from the map's origin."""
        base = self.origin_cov
        J = np.diag([factor] * 3 + [1.0] * 3)
        cov = base + J @ (cov_w_c - base) @ J.T
        cov[:3, :3] += np.outer(d, d) * scale.filter.rel_std ** 2
        return 0.5 * (cov + cov.T)

    def systematic(self, scale: ScaleSource, p_w: F64) -> F64:
        """Position covariance of the scale source's systematic error (``ScaleSource.systematic_rel``):
        it scales the whole path of the current map about its origin, so it grows with the distance from
        there, not as a random walk."""
        d = p_w - self.origin_w
        return np.outer(d, d) * scale.systematic_rel**2
