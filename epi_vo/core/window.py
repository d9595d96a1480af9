"""The windowed map stage: the last keyframes, the tracks linking them, and their bundle adjustment.

After ``mapping`` made a keyframe, the pipeline hands it to :class:`WindowedMap`. Every ``ba_every_keyframes``
tracking keyframes the last ``ba_window_keyframes`` keyframes are adjusted together (``epi_vo.core.bundle``,
GTSAM): map points observed by at least two of them (tracks that survived across keyframes, linked by the
keyframes' track ids), a Huber loss, the oldest keyframe fixed (gauge) and the scale held by wheel distances
(``wheel_odometry``) or by the distance from the oldest keyframe to the farthest. The metric scale of
``ground_plane`` is the scale stage's: its filter, not the window, owns it (``added``: a keyframe whose step
the scale stage corrected rescales the window's keyframes with it; a floor prior inside the window would
re-decide the scale every few keyframes from too little floor). An adjustment is submitted at a keyframe and
its result collected at the next one, so it can run beside the frame loop in a worker process (``ba_solver:
process``, ``epi_vo.runner.bundle_worker``; ``inline`` solves at the submission): either way it is applied at
the same keyframe, and the poses are the same. With ``ba_wait: false`` (a live node) the frame loop never
waits for the worker: a result not back at the next keyframe is collected at the first keyframe after it is,
and every keyframe added meanwhile moves with it; no new adjustment starts while one is under way. The result
moves the keyframe it adjusted and its map points, and the keyframe made since from that keyframe's old pose
moves with it (``correct``): its pose by the same correction, its adjusted map points, and its covariance with
the window's (``WindowUpdate``) in place of the chain's part. Older window poses are kept for the next
adjustment. The window is dropped whenever the map is (restart, metric scale newly established), since its
poses and points would no longer agree; an adjustment under way then is dropped as it comes back.

GTSAM is imported only when the adjustment is switched on (``ba_window_keyframes > 0``): the rest of
the pipeline runs without it (a ROS install whose gtsam has no Python wrapper), and switching it on
without gtsam is a ConfigError saying what to install.

The window is a frozen value of the tracking state: every change returns the window after it. Where the
adjustment runs is the solver's (``epi_vo.core.workers.WindowSolver``), given at each call.
"""

from __future__ import annotations

import dataclasses
import importlib
import itertools
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from epi_vo.core import covariance as covm
from epi_vo.core.errors import ConfigError
from epi_vo.core.geometry import nearest_rotation
from epi_vo.core.scale import WindowAnchor
from epi_vo.core.transforms import invert_T
from epi_vo.core.workers import WindowSolver

if TYPE_CHECKING:
    from epi_vo.core import bundle

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

MAX_POINTS = 300  # the most-observed tracks are adjusted; the cost grows with the observations


@dataclass(frozen=True)
class Entry:
    """One keyframe of the window; ``key`` names it for as long as it is in the window (and in an
    adjustment under way), whatever its values become."""

    key: int
    T_w_kf: F64
    ids: I64
    xn: F64
    X_kf: F64
    anchor: WindowAnchor | None = None  # what the scale source knows in metres about this keyframe
    cov_w: F64 | None = None  # its pose covariance in w (position first), as the pipeline had it


@dataclass(frozen=True)
class WindowUpdate:
    """What an adjustment changes: the newest keyframe's pose and the map points of its rows, and its
    covariance: GTSAM's marginal given the window's fixed oldest keyframe, chained onto that keyframe's
    own covariance (None when no covariance was given for it), widened where the keyframe chain's is
    wider (``covariance.cover``). The marginal knows the window's shared tracks but takes their
    observations as independent, which the tracks' drift from keyframe to keyframe is not, and holds
    the scale by the longest baseline; the chain knows neither the tracks' sharing nor the drift.
    Either alone was too narrow somewhere: with the marginal alone, position NEES 19.8 on ground_robot
    and 107 on KITTI (window 8); with the cover 6.3 and 59 (72 without a window)."""

    T_w_kf: F64
    X_kf: F64  # (N, 3) the newest keyframe's map points in its own frame after the adjustment
    n_points: int
    n_keyframes: int
    ms: float
    T_w_kf_before: F64  # the newest keyframe's pose when the adjustment was submitted
    point_ids: I64  # track ids of the adjusted points ...
    points_w: F64  # ... and where they are in w (NaN: not adjusted)
    cov_w_kf: F64 | None = None
    cov_w_before: F64 | None = None  # the newest keyframe's covariance when submitted

    @property
    def correction(self) -> F64:
        """The rigid transform of w that moved the newest keyframe (``T_w_kf = correction @ before``): the
        poses made from its old pose move by it (``correct``), and so does the twist's reference."""
        return self.T_w_kf @ invert_T(self.T_w_kf_before)


@dataclass(frozen=True)
class Pending:
    """An adjustment under way: the keyframes submitted (oldest first, as they are now: a rescale since moved
    those still in the window), the adjusted tracks, the newest one's pose and covariance when submitted."""

    entries: tuple[Entry, ...]
    point_ids: I64  # track id of each adjusted point
    T_w_kf_before: F64  # the newest one's pose when submitted
    cov_w_before: F64 | None  # and its covariance
    # (r, b): p -> r p + b, the scale stage's corrections since it was submitted (``WindowedMap._rescaled``)
    similarity: tuple[float, F64] = (1.0, np.zeros(3))


@dataclass(frozen=True)
class WindowedMap:
    """The last ``size`` keyframes with their track ids (frozen: every change returns the window after it).

    An adjustment is ``submitted`` at a keyframe and its result ``collected`` at the next one (``adjusted``
    does both at once), through a ``WindowSolver`` (``epi_vo.core.workers``: in line; a worker process
    beside the frame loop: ``epi_vo.runner``). Results come back in the order sent; those of adjustments the
    window was cleared since are the solver's in-flight ones beyond the pending one, dropped at the next
    collection."""

    size: int
    every: int
    sigma_px: float
    entries: tuple[Entry, ...] = ()
    since: int = 0  # tracking keyframes added since the last adjustment started
    pending: Pending | None = None  # the adjustment submitted and not yet collected
    next_key: int = 0

    @staticmethod
    def create(size: int, every: int, sigma_px: float) -> WindowedMap:
        """An empty window; with ``size`` > 0 GTSAM must be importable (ConfigError naming it else)."""
        if size > 0:
            try:
                importlib.import_module("epi_vo.core.bundle")
            except ImportError as exc:
                raise ConfigError(f"ba_window_keyframes={size} needs the gtsam Python package "
                                  f"(pip install gtsam==4.3.0): {exc}") from None
        return WindowedMap(size, max(every, 1), sigma_px)

    def __len__(self) -> int:
        return len(self.entries)

    def cleared(self) -> WindowedMap:
        """The keyframes forgotten; an adjustment still under way is dropped when it comes back."""
        return dataclasses.replace(self, entries=(), since=0, pending=None)

    def added(self, T_w_kf: F64, ids: I64 | None, xn: F64, X_kf: F64, anchor: WindowAnchor | None = None,
              cov_w: F64 | None = None, rescale: float = 1.0) -> WindowedMap:
        """A new keyframe; ``anchor`` becomes a scale prior of the adjustments; ``cov_w`` is its pose
        covariance. ``rescale``: the scale stage corrected this keyframe's step and map points by that
        factor (the map's scale was wrong by it), so the window's keyframes are rescaled with it first
        (``_rescaled``)."""
        if self.size <= 0 or ids is None:
            return self
        win = self._rescaled(rescale)
        entry = Entry(win.next_key, T_w_kf.copy(), ids.copy(), xn.copy(), X_kf.copy(), anchor,
                      None if cov_w is None else cov_w.copy())
        return dataclasses.replace(win, entries=(*win.entries, entry)[-max(self.size, 1):], since=win.since + 1,
                                   next_key=win.next_key + 1)

    def _rescaled(self, factor: float) -> WindowedMap:
        """The map's scale changes by ``factor`` from the newest keyframe on: every keyframe of the window
        moves about the newest one's centre by it and its map points scale with it, as does an adjustment
        under way when it comes back (``Pending.similarity``). Without this the window would keep the old
        scale and each adjustment would undo the scale stage's corrections."""
        if factor == 1.0 or not self.entries:
            return self
        c = self.entries[-1].T_w_kf[:3, 3].copy()
        moved = {}
        for e in self.entries:
            T = e.T_w_kf.copy()
            T[:3, 3] = c + factor * (e.T_w_kf[:3, 3] - c)
            moved[e.key] = dataclasses.replace(e, T_w_kf=T, X_kf=e.X_kf * factor)
        pending = self.pending
        if pending is not None:  # p -> c + f (r p + b - c)
            r, b = pending.similarity
            pending = dataclasses.replace(pending, entries=tuple(moved.get(e.key, e) for e in pending.entries),
                                          similarity=(factor * r, factor * b + (1.0 - factor) * c))
        return dataclasses.replace(self, entries=tuple(moved[e.key] for e in self.entries), pending=pending)

    def due(self) -> bool:
        """An adjustment is due: enough keyframes in the window, ``every`` added since the last, and none
        under way (``ba_wait: false`` leaves one pending until its result is back)."""
        return self.size > 0 and len(self.entries) >= 3 and self.since >= self.every and self.pending is None

    def submitted(self, solver: WindowSolver, fx: float, exclude_ids: I64 | None = None) -> tuple[WindowedMap, bool]:
        """Start adjusting the window (False when it cannot be: too few shared tracks). Tracks
        ``exclude_ids`` (judged to move on their own) are left out. Its result is ``collected`` later."""
        assert self.size > 0 and self.pending is None
        win = dataclasses.replace(self, since=0)
        entries = self.entries
        window, point_ids = _build(importlib.import_module("epi_vo.core.bundle"), entries, self.sigma_px, fx,
                                   exclude_ids)
        if window is None:
            return win, False
        newest = entries[-1]
        solver.send(window)
        pending = Pending(entries, point_ids, newest.T_w_kf.copy(),
                          None if newest.cov_w is None else newest.cov_w.copy())
        return dataclasses.replace(win, pending=pending), True

    def collected(self, solver: WindowSolver, wait: bool = True) -> tuple[WindowedMap, WindowUpdate | None]:
        """The submitted adjustment's result, applied to the keyframes it adjusted and moving the ones
        added since (``_carried``); None when none was submitted, the optimiser refused the window, or,
        without ``wait``, the result is not back yet (it stays pending: ask again at the next keyframe)."""
        while solver.in_flight() > (self.pending is not None):  # of adjustments dropped by a clear
            if not (wait or solver.ready()):
                return self, None
            solver.receive()
        pending = self.pending
        if pending is None or not (wait or solver.ready()):
            return self, None
        win = dataclasses.replace(self, pending=None)
        result = solver.receive()
        if result is None:
            return win, None
        r, b = pending.similarity  # the scale stage's corrections since it was submitted
        adjusted = []
        for entry, T in zip(pending.entries, result.T_w_kf, strict=True):
            T = T.copy()
            T[:3, 3] = r * T[:3, 3] + b
            adjusted.append(dataclasses.replace(entry, T_w_kf=T))
        points_w = r * result.points_w + b
        newest = adjusted[-1]
        X_kf = newest.X_kf.copy()
        ok, Xw = _adjusted_rows(pending.point_ids, points_w, newest.ids)
        T_kf_w = invert_T(newest.T_w_kf)
        X_kf[ok] = Xw[ok] @ T_kf_w[:3, :3].T + T_kf_w[:3, 3]
        cov = None
        oldest = adjusted[0]
        if oldest.cov_w is not None and np.all(np.isfinite(result.cov_newest)):
            cov = covm.floored(covm.chain_world(oldest.cov_w, oldest.T_w_kf[:3, 3], newest.T_w_kf[:3, 3],
                                                result.cov_newest))
            if newest.cov_w is not None:  # no narrower than the keyframe chain's (see WindowUpdate)
                cov = covm.cover(covm.floored(newest.cov_w), cov)
        adjusted[-1] = newest = dataclasses.replace(newest, X_kf=X_kf, cov_w=newest.cov_w if cov is None else cov)
        update = WindowUpdate(newest.T_w_kf.copy(), X_kf, int(np.count_nonzero(np.isfinite(result.points_w[:, 0]))),
                              len(adjusted), result.ms, pending.T_w_kf_before, pending.point_ids, points_w,
                              cov, pending.cov_w_before)
        return win._carried(update, {e.key: e for e in adjusted}), update

    def _carried(self, update: WindowUpdate, adjusted: dict[int, Entry]) -> WindowedMap:
        """The window with the adjusted keyframes as adjusted, and those added since the adjustment was
        submitted (a result collected late, ``ba_wait: false``) moved with the adjusted one: they were made
        from its old pose (``correct``), so the next adjustment starts from poses that agree."""
        entries = []
        for entry in self.entries:
            if entry.key in adjusted:
                entries.append(adjusted[entry.key])
                continue
            T, X, cov = correct(update, entry.T_w_kf, entry.ids, entry.X_kf,
                                entry.cov_w if entry.cov_w is not None else np.zeros((6, 6)))
            entries.append(dataclasses.replace(entry, T_w_kf=T, X_kf=X, cov_w=None if entry.cov_w is None else cov))
        return dataclasses.replace(self, entries=tuple(entries))

    def adjusted(self, solver: WindowSolver, fx: float, exclude_ids: I64 | None = None
                 ) -> tuple[WindowedMap, WindowUpdate | None]:
        """Adjust the window now (``submitted`` and ``collected``); None when it cannot be (too few shared
        tracks, the optimiser refused)."""
        win, _ = self.collected(solver)
        win, sent = win.submitted(solver, fx, exclude_ids)
        return win.collected(solver) if sent else (win, None)


def correct(update: WindowUpdate, T_w_kf: F64, ids: I64 | None, X_kf: F64, cov_w: F64,
            factor: float = 1.0) -> tuple[F64, F64, F64]:
    """A keyframe made after the adjusted one (from its pose before the adjustment) moved with it: its
    pose by the adjusted keyframe's correction, its map points that were adjusted put where the
    adjustment has them (times ``factor``, the scale stage's correction of this keyframe, not yet in
    the window: its other points have it), and its covariance with the adjusted keyframe's part
    replaced by the window's. Returns the pose, the map points (its own frame) and the covariance."""
    T = update.correction @ T_w_kf
    T[:3, :3] = nearest_rotation(T[:3, :3])  # the products' rounding would add up keyframe after keyframe
    X = X_kf.copy()
    if ids is not None:
        ok, Xw = _adjusted_rows(update.point_ids, update.points_w, ids)
        T_kf_w = invert_T(T)
        X[ok] = (Xw[ok] @ T_kf_w[:3, :3].T + T_kf_w[:3, 3]) * factor
    cov = cov_w
    if update.cov_w_kf is not None and update.cov_w_before is not None:
        cov = covm.floored(cov_w + update.cov_w_kf - update.cov_w_before)
    return T, X, cov


def _adjusted_rows(point_ids: I64, points_w: F64, ids: I64) -> tuple[NDArray[np.bool_], F64]:
    """For each of ``ids``: whether the adjustment has a (finite) point for it, and that point in w."""
    if not point_ids.size:
        return np.zeros(ids.size, bool), np.full((ids.size, 3), np.nan)
    pos = np.clip(np.searchsorted(point_ids, ids), 0, point_ids.size - 1)
    Xw = points_w[pos]
    return (point_ids[pos] == ids) & np.all(np.isfinite(Xw), axis=1), Xw


def _build(bundle_module: ModuleType, entries: tuple[Entry, ...], sigma_px: float, fx: float,
           exclude_ids: I64 | None = None) -> tuple[bundle.Window | None, I64]:
    """The bundle window of these keyframes: tracks seen by two or more of them that have a depth
    (except ``exclude_ids``)."""
    all_ids = np.concatenate([e.ids for e in entries])
    uniq, counts = np.unique(all_ids, return_counts=True)
    shared = uniq[counts >= 2]
    if exclude_ids is not None and exclude_ids.size:
        shared = np.setdiff1d(shared, exclude_ids)
    # Initial point of each shared track: from the newest keyframe that has a depth for it.
    points: dict[int, F64] = {}
    for e in reversed(entries):
        rows = np.flatnonzero(np.isin(e.ids, shared) & np.all(np.isfinite(e.X_kf), axis=1))
        Xw = e.X_kf[rows] @ e.T_w_kf[:3, :3].T + e.T_w_kf[:3, 3]
        for i, x in zip(e.ids[rows], Xw, strict=True):
            points.setdefault(int(i), x)
    if len(points) < 10:
        return None, np.zeros(0, np.int64)
    ids = np.array(sorted(points), dtype=np.int64)
    if ids.size > MAX_POINTS:  # keep the tracks seen by most keyframes
        seen = counts[np.searchsorted(uniq, ids)]
        ids = np.sort(ids[np.argsort(-seen, kind="stable")[:MAX_POINTS]])
    pts_w = np.array([points[int(i)] for i in ids])
    obs_kf, obs_pt, obs_xn = [], [], []
    for k, e in enumerate(entries):
        pos = np.clip(np.searchsorted(ids, e.ids), 0, ids.size - 1)
        rows = np.flatnonzero(ids[pos] == e.ids)
        obs_kf.append(np.full(rows.size, k, np.int64))
        obs_pt.append(pos[rows])
        obs_xn.append(e.xn[rows])
    # The oldest keyframe holds the gauge. Wheel distances carry the scale; without them the distance
    # from the oldest keyframe to the farthest (``bundle``: the longest baseline; the scale stage's
    # corrections are already in it, ``_rescale``).
    window = bundle_module.Window(np.stack([e.T_w_kf for e in entries]), pts_w, np.concatenate(obs_kf),
                                  np.concatenate(obs_pt), np.concatenate(obs_xn), sigma_px, fx, n_fixed=1,
                                  distance_priors=_wheel_priors(bundle_module, entries))
    return window, ids


WHEEL_MIN_SIGMA_M = 0.005  # wheel distance noise floor (encoder resolution, stamp jitter)


def _wheel_priors(bundle_module: ModuleType, entries: tuple[Entry, ...]) -> tuple[bundle.DistancePrior, ...]:
    """The wheel distances between consecutive anchored keyframes, as priors (``wheel_odometry``)."""
    distances = []
    wheel = [(k, e.anchor) for k, e in enumerate(entries) if e.anchor is not None and e.anchor.wheel_xyz is not None]
    for (i, a), (j, b) in itertools.pairwise(wheel):
        assert a.wheel_xyz is not None and b.wheel_xyz is not None
        d = float(np.linalg.norm(b.wheel_xyz - a.wheel_xyz))
        if d > WHEEL_MIN_SIGMA_M:
            distances.append(bundle_module.DistancePrior(i, j, d, max(a.wheel_rel_sigma * d, WHEEL_MIN_SIGMA_M)))
    return tuple(distances)
