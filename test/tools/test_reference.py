"""Tests of epi_vo.tools.reference on images ray-cast from a seeded, textured three-plane scene."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from epi_vo.core.errors import CameraModelError, ImageConversionError
from epi_vo.tools.reference import ReferencePipeline

WIDTH, HEIGHT = 640, 480
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
NO_DIST = np.zeros(5)
# Strong barrel distortion: ignoring it bends the epipolar geometry by many degrees.
BARREL = np.array([-0.25, 0.08, 0.001, -0.001, 0.0])

# Fronto-parallel planes z_w = z at three depths (x_min, x_max, y_min, y_max in metres): one plane
# would be degenerate for E (a homography explains it), three at different depths are not.
PLANES = (
    (10.0, -30.0, 30.0, -30.0, 30.0),  # background, fills the view
    (6.0, -4.0, -0.5, -3.0, 3.0),
    (3.5, 0.3, 2.5, -1.5, 1.0),
)
TEXELS_PER_M = 80.0


def make_texture(seed: int, size: int = 768) -> NDArray[np.float32]:
    """Blob-like random texture (coarse plus fine cubic-upsampled noise) that ORB finds corners in."""
    rng = np.random.default_rng(seed)
    coarse = cv2.resize(
        rng.random((96, 96)), (size, size), interpolation=cv2.INTER_CUBIC
    )
    fine = cv2.resize(
        rng.random((256, 256)), (size, size), interpolation=cv2.INTER_CUBIC
    )
    tex = coarse + 0.5 * fine
    return ((tex - tex.min()) / (tex.max() - tex.min()) * 255.0).astype(np.float32)


TEXTURES = tuple(make_texture(seed) for seed in range(len(PLANES)))


def render(
    T_w_c: NDArray[np.float64], D: NDArray[np.float64] = NO_DIST
) -> NDArray[np.uint8]:
    """Ray-cast the planes from camera pose T_w_c (camera points into world) with intrinsics K, D.

    Each pixel's ray comes from undistortPoints (distorted pixel -> ideal normalized coordinates), so
    the image is what a camera with distortion D would see.
    """
    u, v = np.meshgrid(
        np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64)
    )
    pix = np.column_stack([u.ravel(), v.ravel()])
    xn = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    rays_w = np.column_stack([xn, np.ones(len(xn))]) @ T_w_c[:3, :3].T
    origin_w = T_w_c[:3, 3]
    nearest = np.full(len(rays_w), np.inf)
    img = np.zeros(len(rays_w), dtype=np.float32)
    for (z, x_min, x_max, y_min, y_max), tex in zip(PLANES, TEXTURES, strict=True):
        lam = (z - origin_w[2]) / rays_w[:, 2]
        X_w = origin_w + lam[:, None] * rays_w
        visible = (
            (lam > 0.0)
            & (lam < nearest)
            & (X_w[:, 0] >= x_min)
            & (X_w[:, 0] <= x_max)
            & (X_w[:, 1] >= y_min)
            & (X_w[:, 1] <= y_max)
        )
        map_x = (
            ((X_w[:, 0] - x_min) * TEXELS_PER_M)
            .astype(np.float32)
            .reshape(HEIGHT, WIDTH)
        )
        map_y = (
            ((X_w[:, 1] - y_min) * TEXELS_PER_M)
            .astype(np.float32)
            .reshape(HEIGHT, WIDTH)
        )
        sampled = cv2.remap(
            tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        ).ravel()
        img[visible] = sampled[visible]
        nearest[visible] = lam[visible]
    return np.clip(img, 0.0, 255.0).astype(np.uint8).reshape(HEIGHT, WIDTH)


def pose(rotvec: list[float], p: list[float]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, dtype=np.float64))[0]
    T[:3, 3] = p
    return T


def angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


def rotation_error_deg(
    R_est: NDArray[np.float64], R_true: NDArray[np.float64]
) -> float:
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(R_est.T @ R_true)[0])))


# Camera 0 defines the world. Camera 1: sideways + forward with a small yaw and roll. Camera 2: a
# further step expressed in camera 1's frame, so the chain T_w_c2 = T_w_c1 @ T_c1_c2 is exercised.
T_W_C0 = np.eye(4)
T_W_C1 = pose([0.0, np.radians(3.0), np.radians(1.0)], [0.25, 0.05, 0.2])
T_W_C2 = T_W_C1 @ pose([np.radians(1.0), np.radians(-2.0), 0.0], [0.3, -0.05, 0.15])


Frames = tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]


@pytest.fixture(scope="module")
def frames() -> Frames:
    return render(T_W_C0), render(T_W_C1), render(T_W_C2)


def test_first_frame_is_identity(frames: Frames) -> None:
    result = ReferencePipeline(K, NO_DIST).process(frames[0], 12.5)
    assert result.ok
    assert result.stamp_s == 12.5
    np.testing.assert_array_equal(result.T_w_c, np.eye(4))
    assert result.n_matches == 0
    assert result.ms > 0.0


def test_two_view_motion_known_answer(frames: Frames) -> None:
    pipeline = ReferencePipeline(K, NO_DIST)
    pipeline.process(frames[0], 0.0)
    result = pipeline.process(frames[1], 0.1)

    assert result.ok
    assert result.n_matches >= result.n_inliers > 100
    # Camera 0 is the world, so T_w_c1 holds R_w_c1 and the unit direction of camera 1's centre.
    assert rotation_error_deg(result.T_w_c[:3, :3], T_W_C1[:3, :3]) < 1.0
    assert angle_deg(result.T_w_c[:3, 3], T_W_C1[:3, 3]) < 5.0
    assert np.linalg.norm(result.T_w_c[:3, 3]) == pytest.approx(
        1.0
    )  # unit step: no scale


def test_pose_chain_over_three_frames(frames: Frames) -> None:
    pipeline = ReferencePipeline(K, NO_DIST)
    results = [pipeline.process(img, 0.1 * i) for i, img in enumerate(frames)]

    assert all(r.ok for r in results)
    T_w_c1, T_w_c2 = results[1].T_w_c, results[2].T_w_c
    assert rotation_error_deg(T_w_c2[:3, :3], T_W_C2[:3, :3]) < 1.5
    # Each step has unit length; its direction in world must match the true step's.
    step_w = T_w_c2[:3, 3] - T_w_c1[:3, 3]
    assert np.linalg.norm(step_w) == pytest.approx(1.0)
    assert angle_deg(step_w, T_W_C2[:3, 3] - T_W_C1[:3, 3]) < 5.0


def test_distorted_camera_is_undistorted() -> None:
    img0, img1 = render(T_W_C0, BARREL), render(T_W_C1, BARREL)

    pipeline = ReferencePipeline(K, BARREL)
    pipeline.process(img0, 0.0)
    result = pipeline.process(img1, 0.1)
    assert result.ok
    assert rotation_error_deg(result.T_w_c[:3, :3], T_W_C1[:3, :3]) < 1.0
    assert angle_deg(result.T_w_c[:3, 3], T_W_C1[:3, 3]) < 5.0

    # The scene does exercise the distortion: raw pixels with K alone are far off.
    raw = ReferencePipeline(K, NO_DIST)
    raw.process(img0, 0.0)
    raw_result = raw.process(img1, 0.1)
    assert not raw_result.ok or angle_deg(raw_result.T_w_c[:3, 3], T_W_C1[:3, 3]) > 5.0


def test_black_frame_fails_and_pose_holds(frames: Frames) -> None:
    black = np.zeros((HEIGHT, WIDTH), dtype=np.uint8)
    pipeline = ReferencePipeline(K, NO_DIST)
    pipeline.process(frames[0], 0.0)
    tracked = pipeline.process(frames[1], 0.1)

    lost = pipeline.process(black, 0.2)
    assert not lost.ok
    assert lost.n_matches == 0
    np.testing.assert_array_equal(lost.T_w_c, tracked.T_w_c)

    # Frame to frame: the next frame is paired with the black one and fails too, pose still held.
    after = pipeline.process(frames[1], 0.3)
    assert not after.ok
    np.testing.assert_array_equal(after.T_w_c, tracked.T_w_c)

    # Then tracking resumes, chained on the held pose.
    resumed = pipeline.process(frames[2], 0.4)
    assert resumed.ok
    assert (
        angle_deg(
            resumed.T_w_c[:3, 3] - tracked.T_w_c[:3, 3], T_W_C2[:3, 3] - T_W_C1[:3, 3]
        )
        < 5.0
    )


def test_black_first_frame_is_identity() -> None:
    black = np.zeros((HEIGHT, WIDTH), dtype=np.uint8)
    pipeline = ReferencePipeline(K, NO_DIST)
    assert pipeline.process(black, 0.0).ok
    second = pipeline.process(black, 0.1)
    assert not second.ok
    np.testing.assert_array_equal(second.T_w_c, np.eye(4))


def test_no_essential_matrix_fails(
    frames: Frames, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(
        cv2, "findEssentialMat", lambda *args, **kwargs: (None, None)
    )  # no E found
    pipeline = ReferencePipeline(K, NO_DIST)
    pipeline.process(frames[0], 0.0)
    result = pipeline.process(frames[1], 0.1)
    assert not result.ok
    assert result.n_matches >= 8
    np.testing.assert_array_equal(result.T_w_c, np.eye(4))


def test_stacked_essential_matrices_use_the_first(
    frames: Frames, monkeypatch: pytest.MonkeyPatch
) -> None:
    find_essential = cv2.findEssentialMat

    def stacked(
        *args: object, **kwargs: object
    ) -> tuple[NDArray[np.float64], NDArray[np.uint8]]:
        E, mask = find_essential(*args, **kwargs)
        return np.vstack(
            [E, np.eye(3)]
        ), mask  # (6, 3): two solutions, the true one first

    monkeypatch.setattr(cv2, "findEssentialMat", stacked)
    pipeline = ReferencePipeline(K, NO_DIST)
    pipeline.process(frames[0], 0.0)
    result = pipeline.process(frames[1], 0.1)
    assert result.ok
    assert angle_deg(result.T_w_c[:3, 3], T_W_C1[:3, 3]) < 5.0


def test_result_is_immutable(frames: Frames) -> None:
    result = ReferencePipeline(K, NO_DIST).process(frames[0], 0.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.ok = False  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        result.T_w_c[0, 3] = 1.0


@pytest.mark.parametrize(
    ("K_bad", "D_bad", "match"),
    [
        (np.eye(2), NO_DIST, r"finite \(3, 3\)"),
        (np.full((3, 3), np.nan), NO_DIST, "non-finite"),
        (np.diag([0.0, 500.0, 1.0]), NO_DIST, "fx, fy > 0"),
        (K, np.zeros(3), "D must hold"),
        (K, np.array([np.nan, 0.0, 0.0, 0.0]), "D must hold"),
    ],
)
def test_bad_calibration(
    K_bad: NDArray[np.float64], D_bad: NDArray[np.float64], match: str
) -> None:
    with pytest.raises(CameraModelError, match=match):
        ReferencePipeline(K_bad, D_bad)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((48, 64, 3), dtype=np.uint8),
        np.zeros((48, 64), dtype=np.float32),
        [[0, 1], [2, 3]],
    ],
)
def test_bad_image(image: object) -> None:
    with pytest.raises(ImageConversionError, match="2-D uint8 grayscale"):
        ReferencePipeline(K, NO_DIST).process(image, 0.0)  # type: ignore[arg-type]


def test_empty_distortion_is_accepted(frames: Frames) -> None:
    assert ReferencePipeline(K, np.zeros(0)).process(frames[0], 0.0).ok
