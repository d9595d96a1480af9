"""Keyframe windows for the windowed adjustment's tests (test/core/test_window.py, test/runner/)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from epi_vo.core.transforms import invert_T, make_T
from epi_vo.core.window import WindowedMap
from epi_vo.core.workers import InlineSolver


def rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def scene(n_kf: int = 5, n_pts: int = 120, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(seed)
    poses = [make_T(rot_y(2.0 * k), np.array([0.6 * k, 0.0, 0.2 * k])) for k in range(n_kf)]
    pts = np.column_stack([rng.uniform(-3, 5, n_pts), rng.uniform(-2, 2, n_pts), rng.uniform(3, 8, n_pts)])
    return poses, pts


def entry(T_w_kf: np.ndarray, pts_w: np.ndarray, ids: np.ndarray, rng: np.random.Generator, noise: float
          ) -> tuple[np.ndarray, np.ndarray]:
    T_kf_w = invert_T(T_w_kf)
    X = pts_w[ids] @ T_kf_w[:3, :3].T + T_kf_w[:3, 3]
    xn = X[:, :2] / X[:, 2:3] + rng.normal(0, 1.0 / 500.0, (ids.size, 2))
    return xn, X * (1.0 + rng.normal(0, noise, (ids.size, 1)))


def window_of(solver: str) -> Win:
    """The same five keyframes in a window adjusted ``inline`` or in a worker ``process``."""
    from epi_vo.runner.bundle_worker import ProcessSolver

    poses, pts = scene()
    rng = np.random.default_rng(6)
    win = Win(size=5, every=1, sigma_px=1.0, solver=ProcessSolver() if solver == "process" else None)
    ids_all = np.arange(pts.shape[0])
    for k, T in enumerate(poses):
        ids = ids_all[(ids_all + k) % 5 != 0]
        xn, X = entry(T, pts, ids, rng, noise=0.05)
        win.add(T @ make_T(rot_y(0.3 * k), np.array([0.02 * k, 0.0, 0.0])), ids, xn, X)
    return win


def same_update(a: Any, b: Any) -> None:
    for name in ("T_w_kf", "X_kf", "cov_w_kf", "points_w", "point_ids"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


class Win:
    """A ``WindowedMap`` and its solver driven as the pipeline drives them: each call replaces the frozen
    window by the one it returns (``map``)."""

    def __init__(self, size: int, every: int, sigma_px: float, solver: Any = None) -> None:
        self.map = WindowedMap.create(size, every, sigma_px)
        self.solver = solver if solver is not None else InlineSolver()

    def __len__(self) -> int:
        return len(self.map)

    @property
    def entries(self) -> tuple[Any, ...]:
        return self.map.entries

    @property
    def pending(self) -> bool:
        return self.map.pending is not None

    def add(self, *args: Any, **kwargs: Any) -> None:
        self.map = self.map.added(*args, **kwargs)

    def due(self) -> bool:
        return self.map.due()

    def submit(self, fx: float, exclude_ids: Any = None) -> bool:
        self.map, sent = self.map.submitted(self.solver, fx, exclude_ids)
        return sent

    def collect(self, wait: bool = True) -> Any:
        self.map, update = self.map.collected(self.solver, wait)
        return update

    def adjust(self, fx: float, exclude_ids: Any = None) -> Any:
        self.map, update = self.map.adjusted(self.solver, fx, exclude_ids)
        return update

    def clear(self) -> None:
        self.map = self.map.cleared()

    def take_failure(self) -> str:
        return str(self.solver.take_failure())

    def close(self) -> None:
        self.solver.close()
