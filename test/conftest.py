"""Shared pytest fixtures of the epi_vo test suite.

Keep each group of fixtures in its own marked section.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

# ============================================================================================
# Synthetic two-view scenes (seeded) -- used by test_geometry.py
# ============================================================================================
#
# Frames and conventions are those of epi_vo.core.geometry: X_cur = R_cur_ref @ X_ref + t_cur_ref, pixels
# of an ideal pinhole camera K (no distortion), the reference camera at the origin looking along +z.

SCENE_K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
SCENE_WIDTH, SCENE_HEIGHT = 640, 480
SCENE_KINDS = ("general", "planar", "rotation")


@dataclass(frozen=True)
class TwoViewScene:
    """N points seen by a reference and a current camera, with the ground truth to compare against.

    ``uv_ref``/``uv_cur`` are the exact (N, 2) projections; ``uv_ref_obs``/``uv_cur_obs`` add Gaussian
    pixel noise and, in the current image, gross outliers at the rows where ``is_outlier`` is set.
    ``plane_n_ref``/``plane_d`` describe the plane ``n . X_ref = d`` of a planar scene (else None);
    ``H_true`` is the exact homography ref -> cur of a planar or a pure-rotation scene (else None).
    """

    kind: str
    K: NDArray[np.float64]
    R_cur_ref: NDArray[np.float64]
    t_cur_ref: NDArray[np.float64]
    X_ref: NDArray[np.float64]
    uv_ref: NDArray[np.float64]
    uv_cur: NDArray[np.float64]
    uv_ref_obs: NDArray[np.float64]
    uv_cur_obs: NDArray[np.float64]
    is_outlier: NDArray[np.bool_]
    plane_n_ref: NDArray[np.float64] | None
    plane_d: float | None
    H_true: NDArray[np.float64] | None

    @property
    def n(self) -> int:
        return int(self.X_ref.shape[0])

    @property
    def X_cur(self) -> NDArray[np.float64]:
        return self.X_ref @ self.R_cur_ref.T + self.t_cur_ref

    def xn(self, uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 2) pixels of this scene's camera -> normalized coordinates."""
        return (uv - self.K[:2, 2]) / np.diag(self.K)[:2]


def _rotation(rvec: tuple[float, float, float]) -> NDArray[np.float64]:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    return np.asarray(R, dtype=np.float64)


def _project(K: NDArray[np.float64], X: NDArray[np.float64]) -> NDArray[np.float64]:
    p = X @ K.T
    return p[:, :2] / p[:, 2:3]


def _in_image(uv: NDArray[np.float64], margin: float) -> NDArray[np.bool_]:
    return ((uv[:, 0] >= margin) & (uv[:, 0] <= SCENE_WIDTH - 1 - margin)
            & (uv[:, 1] >= margin) & (uv[:, 1] <= SCENE_HEIGHT - 1 - margin))


def make_two_view_scene(kind: str = "general", seed: int = 0, n_points: int = 200, noise_px: float = 0.3,
                        outlier_ratio: float = 0.0) -> TwoViewScene:
    """Build a seeded synthetic scene.

    ``general``: points at depth 4-15 m spread over the view, ~3.4 deg rotation and a 0.64 m baseline.
    ``planar``: points on a tilted wall 6 m in front of the reference camera, 0.82 m baseline.
    ``rotation``: points at depth 4-15 m, 4.7 deg rotation about the camera centre (t = 0).
    Outliers replace the current-image observation by a random pixel at least 20 px from the truth.
    """
    if kind not in SCENE_KINDS:
        msg = f"unknown scene kind {kind!r} (choose one of {', '.join(SCENE_KINDS)})"
        raise ValueError(msg)
    rng = np.random.default_rng(seed)
    K = SCENE_K.copy()
    plane_n: NDArray[np.float64] | None = None
    plane_d: float | None = None
    if kind == "general":
        R = _rotation((0.03, -0.05, 0.02))
        t = np.array([0.6, -0.1, 0.2])
    elif kind == "planar":
        R = _rotation((0.02, -0.04, 0.01))
        t = np.array([0.8, 0.1, 0.15])
        plane_n = np.array([0.25, -0.15, 1.0]) / np.linalg.norm([0.25, -0.15, 1.0])
        plane_d = 6.0
    else:
        R = _rotation((0.04, 0.07, -0.03))
        t = np.zeros(3)

    # Oversample in the reference image, keep the points the current camera sees too.
    m = 6 * n_points
    uv0 = np.column_stack([rng.uniform(10.0, SCENE_WIDTH - 11.0, m), rng.uniform(10.0, SCENE_HEIGHT - 11.0, m)])
    rays = np.column_stack([(uv0 - K[:2, 2]) / np.diag(K)[:2], np.ones(m)])
    if plane_n is not None and plane_d is not None:
        depth = plane_d / (rays @ plane_n)
    else:
        depth = rng.uniform(4.0, 15.0, m)
    X_all = rays * depth[:, None]
    X_cur_all = X_all @ R.T + t
    with np.errstate(divide="ignore", invalid="ignore"):
        uv_cur_all = _project(K, X_cur_all)
    visible = (X_cur_all[:, 2] > 0.5) & _in_image(uv_cur_all, 10.0)
    idx = np.flatnonzero(visible)[:n_points]
    if idx.size < n_points:
        msg = f"scene {kind!r} has only {idx.size} points visible in both views"
        raise ValueError(msg)
    X_ref = X_all[idx]
    uv_ref = _project(K, X_ref)
    uv_cur = _project(K, X_ref @ R.T + t)

    uv_ref_obs = uv_ref + rng.normal(0.0, noise_px, uv_ref.shape)
    uv_cur_obs = uv_cur + rng.normal(0.0, noise_px, uv_cur.shape)
    is_outlier = np.zeros(n_points, dtype=bool)
    n_out = round(outlier_ratio * n_points)
    if n_out:
        rows = rng.choice(n_points, n_out, replace=False)
        is_outlier[rows] = True
        for r in rows:
            while True:
                cand = rng.uniform([0.0, 0.0], [SCENE_WIDTH - 1.0, SCENE_HEIGHT - 1.0])
                if np.linalg.norm(cand - uv_cur[r]) >= 20.0:
                    uv_cur_obs[r] = cand
                    break

    H: NDArray[np.float64] | None = None
    if plane_n is not None and plane_d is not None:
        H = K @ (R + np.outer(t, plane_n) / plane_d) @ np.linalg.inv(K)
    elif kind == "rotation":
        H = K @ R @ np.linalg.inv(K)
    arrays = [K, R, t, X_ref, uv_ref, uv_cur, uv_ref_obs, uv_cur_obs, is_outlier]
    arrays += [a for a in (plane_n, H) if a is not None]
    for a in arrays:
        a.setflags(write=False)  # the scenes are shared between tests
    return TwoViewScene(kind, K, R, t, X_ref, uv_ref, uv_cur, uv_ref_obs, uv_cur_obs, is_outlier, plane_n, plane_d,
                        H)


@pytest.fixture(scope="session")
def two_view_scene() -> Callable[..., TwoViewScene]:
    """The scene builder, for tests that need their own seed, size, noise or outlier ratio."""
    return make_two_view_scene


@pytest.fixture(scope="session")
def general_scene() -> TwoViewScene:
    """200 points at 4-15 m, general motion, 0.3 px noise, no outliers."""
    return make_two_view_scene("general", seed=1)


@pytest.fixture(scope="session")
def general_scene_outliers() -> TwoViewScene:
    """As ``general_scene`` with 20 % gross outliers in the current image."""
    return make_two_view_scene("general", seed=2, outlier_ratio=0.2)


@pytest.fixture(scope="session")
def planar_scene() -> TwoViewScene:
    """200 points on a tilted wall 6 m away, general motion, 0.3 px noise."""
    return make_two_view_scene("planar", seed=3)


@pytest.fixture(scope="session")
def rotation_scene() -> TwoViewScene:
    """200 points at 4-15 m, pure rotation about the camera centre, 0.3 px noise."""
    return make_two_view_scene("rotation", seed=4)


# ============================================================================================
# End of the synthetic two-view scenes section.
# ============================================================================================


# ============================================================================================
# Whole-replay fuzzing (hypothesis) -- used by test_fuzz_replay.py
# ============================================================================================
def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--fuzz-examples", type=int, default=None, metavar="N",
                     help="test_fuzz_replay.py: run N generated bags (default 40) and shrink failures to a "
                          "minimal example")


# ============================================================================================
# End of the whole-replay fuzzing section.
# ============================================================================================


# ============================================================================================
# The bag renderer (bags/make_bags.py) for its tests
# ============================================================================================
@pytest.fixture(scope="session")
def make_bags() -> object:
    """``bags/make_bags.py`` (the bag renderer) as a module; skipped without scikit-image."""
    import sys
    from pathlib import Path

    pytest.importorskip("skimage", reason="bags/make_bags.py needs scikit-image (bags/requirements.txt)")
    bags = str(Path(__file__).resolve().parents[1] / "bags")
    sys.path.insert(0, bags)
    try:
        import make_bags
    finally:
        sys.path.remove(bags)
    return make_bags


# ============================================================================================
# The scenario distribution's subset (bags/scenarios.py) -- used by test_scenarios.py and
# test_distribution.py
# ============================================================================================
@pytest.fixture(scope="session")
def scenario_generator() -> object:
    """``bags/scenarios.py`` (the scenario generator) as a module; skipped without scikit-image."""
    pytest.importorskip("skimage", reason="bags/scenarios.py needs scikit-image (bags/requirements.txt)")
    from epi_vo.tools.distribution import load_generator

    return load_generator()


@pytest.fixture(scope="session")
def scenario_subset(scenario_generator: object, tmp_path_factory: pytest.TempPathFactory) -> list:
    """The subset (one short seed per family) in the scenario cache, rendered when missing (a fresh machine
    renders it: about a minute and a half of CPU). The cache is ``$EPI_VO_SCENARIO_CACHE`` or
    ``~/.cache/epi_vo/scenarios``; a temporary one when that cannot be written."""
    from pathlib import Path

    gen = scenario_generator
    root = gen.default_cache_root()
    try:
        root.mkdir(parents=True, exist_ok=True)
        probe = root / f".write-probe-{id(root)}"
        probe.write_text("")
        probe.unlink()
    except OSError:
        root = Path(tmp_path_factory.mktemp("scenario_cache"))
    return gen.ensure(gen.PROFILES["subset"], root=root, jobs=2).sequences


# ============================================================================================
# End of the scenario distribution section.
# ============================================================================================
