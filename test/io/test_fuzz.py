"""Property-based fuzzing (hypothesis) of message conversion, two-view geometry and the camera model.

The rule checked everywhere: bad input raises one of the project's own errors (``EpiVoError``
subclasses) or is a documented returned value (``None`` model, empty mask); nothing else escapes, and
outputs documented as finite (scores, masks, returned E / H / R / t, normalized coordinates) contain no
NaN. Every ``@given`` is bounded (``max_examples``) and derandomized so the file runs in seconds and
the same way every time.
"""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from epi_vo.core import geometry as geo
from epi_vo.core.camera import CameraModel
from epi_vo.core.errors import EpiVoError, ImageConversionError
from epi_vo.io.msgconv import (
    SUPPORTED_IMAGE_ENCODINGS,
    compressed_to_gray,
    image_to_gray,
    point_cloud2_fields,
    read_points_xyz,
)

FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
FUZZ_SLOW = settings(max_examples=60, deadline=None, derandomize=True,
                     suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

F64 = NDArray[np.float64]

# --------------------------------------------------------------------------------------------------
# Message conversion
# --------------------------------------------------------------------------------------------------

_BYTES_PER_PIXEL = {"mono8": 1, "8UC1": 1, "mono16": 2, "16UC1": 2, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}
_UNSUPPORTED = ["32FC1", "yuv422", "bayer_rggb8", "mono32", "", "MONO8", "rgb16", "nv21", "8UC3", "jpeg"]


@st.composite
def image_messages(draw: st.DrawFn) -> SimpleNamespace:
    """An Image-like object: any encoding, size, step (padded, exact or too short), byte order and
    payload length (exact, longer, shorter, empty), with a payload of random bytes in several containers."""
    encoding = draw(st.sampled_from([*SUPPORTED_IMAGE_ENCODINGS, *_UNSUPPORTED]) | st.text(max_size=8))
    height = draw(st.integers(0, 24) | st.sampled_from([1, 2**20, 2**31 - 1]))
    width = draw(st.integers(0, 24) | st.sampled_from([1, 2**20]))
    bpp = _BYTES_PER_PIXEL.get(encoding, draw(st.integers(1, 4)))
    row = width * bpp
    step = draw(st.sampled_from([row, row + 1, row + 3, row + 64, max(row - 1, 0), 0]) | st.integers(0, 200))
    need = min(step * height, 1 << 14)  # never allocate huge payloads: a huge claimed size must be rejected
    length = draw(st.sampled_from([need, need + 7, max(need - 1, 0), 0]) | st.integers(0, 2048))
    seed = draw(st.integers(0, 2**32 - 1))
    payload = np.random.default_rng(seed).integers(0, 256, length, dtype=np.uint8)
    container = draw(st.sampled_from(["bytes", "ndarray", "bytearray", "list"]))
    data: Any = {"bytes": payload.tobytes(), "ndarray": payload, "bytearray": bytearray(payload.tobytes()),
                 "list": payload.tolist()}[container]
    return SimpleNamespace(height=height, width=width, encoding=encoding, step=step,
                           is_bigendian=draw(st.booleans()), data=data)


def _valid_image(msg: SimpleNamespace) -> bool:
    bpp = _BYTES_PER_PIXEL.get(msg.encoding)
    return (bpp is not None and msg.height > 0 and msg.width > 0 and msg.step >= msg.width * bpp
            and len(msg.data) >= msg.step * msg.height)


@FUZZ
@given(image_messages())
def test_image_to_gray_raises_only_conversion_errors(msg: SimpleNamespace) -> None:
    try:
        gray = image_to_gray(msg)
    except ImageConversionError as exc:
        assert not _valid_image(msg), f"valid image rejected: {exc}"
        assert str(exc)
        return
    assert _valid_image(msg)
    assert gray.shape == (msg.height, msg.width) and gray.dtype == np.uint8
    # Known answer from the bytes: rows `step` apart, padding never read.
    raw = np.frombuffer(bytes(bytearray(msg.data)), np.uint8)
    bpp = _BYTES_PER_PIXEL[msg.encoding]
    rows = np.stack([raw[r * msg.step: r * msg.step + msg.width * bpp] for r in range(msg.height)])
    if msg.encoding in ("mono8", "8UC1"):
        np.testing.assert_array_equal(gray, rows)
    elif msg.encoding in ("mono16", "16UC1"):
        high = rows[:, 0::2] if msg.is_bigendian else rows[:, 1::2]  # the most significant byte of each sample
        np.testing.assert_array_equal(gray, high)


@FUZZ
@given(st.binary(max_size=600), st.sampled_from(["jpeg", "png", "", "rgb8; jpeg compressed bgr8"]))
def test_compressed_to_gray_random_bytes(payload: bytes, fmt: str) -> None:
    try:
        gray = compressed_to_gray(SimpleNamespace(format=fmt, data=payload))
    except ImageConversionError as exc:
        assert "could not decode CompressedImage" in str(exc)
        return
    assert gray.ndim == 2 and gray.dtype == np.uint8 and gray.size > 0


def _encoded(ext: str) -> bytes:
    img = (np.arange(32 * 24, dtype=np.uint32).reshape(24, 32) * 7 % 251).astype(np.uint8)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


_JPEG, _PNG = _encoded(".jpg"), _encoded(".png")


@FUZZ
@given(st.sampled_from([_JPEG, _PNG]), st.integers(0, 10_000), st.integers(0, 2**32 - 1),
       st.integers(0, 40))
def test_compressed_to_gray_corrupted_or_truncated(valid: bytes, cut: int, seed: int, n_flips: int) -> None:
    """A real JPEG / PNG truncated and with random bytes flipped: an image or an ImageConversionError."""
    data = bytearray(valid[: max(cut, 1)] if cut < len(valid) else valid)
    rng = np.random.default_rng(seed)
    for i in rng.integers(0, len(data), n_flips):
        data[i] = int(rng.integers(0, 256))
    try:
        gray = compressed_to_gray(SimpleNamespace(format="jpeg", data=np.frombuffer(bytes(data), np.uint8)))
    except ImageConversionError:
        return
    assert gray.ndim == 2 and gray.dtype == np.uint8


_COORD = st.floats(allow_nan=True, allow_infinity=True, width=64) | st.floats(-1e6, 1e6) | st.sampled_from(
    [0.0, -0.0, 1e-45, 3.4e38, 3.5e38, -1e39, 1e300, math.nan, math.inf, -math.inf])


@FUZZ
@given(st.lists(st.tuples(_COORD, _COORD, _COORD), max_size=40))
def test_point_cloud2_round_trip(points: list[tuple[float, float, float]]) -> None:
    """Finite rows survive the round trip (as float32); the cloud is dense as it declares: no NaN / inf."""
    pts = np.array(points, dtype=np.float64).reshape(-1, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow in the float32 cast must not happen silently either
        fields = point_cloud2_fields(pts)
    cloud = SimpleNamespace(**fields)
    out = read_points_xyz(cloud)
    assert out.dtype == np.float32 and out.shape == (fields["width"], 3)
    assert fields["is_dense"] and np.all(np.isfinite(out)), "a dense cloud holds a non-finite point"
    with np.errstate(over="ignore"):
        representable = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(pts.astype(np.float32)), axis=1)
    np.testing.assert_array_equal(out, pts[representable].astype(np.float32))
    assert fields["row_step"] == 12 * fields["width"] and len(fields["data"]) == fields["row_step"]


@FUZZ
@given(st.integers(0, 5), st.integers(0, 5), st.integers(0, 40), st.integers(0, 200), st.binary(max_size=300),
       st.booleans(), st.lists(st.tuples(st.sampled_from("xyzw"), st.integers(-4, 40), st.integers(0, 9)),
                               max_size=5))
def test_read_points_xyz_random_layouts(height: int, width: int, point_step: int, row_step: int, data: bytes,
                                        big: bool, fields: list[tuple[str, int, int]]) -> None:
    msg = SimpleNamespace(height=height, width=width, point_step=point_step, row_step=row_step, is_bigendian=big,
                          data=data, fields=[SimpleNamespace(name=n, offset=o, datatype=d, count=1)
                                             for n, o, d in fields])
    try:
        out = read_points_xyz(msg)
    except EpiVoError as exc:
        assert str(exc)
        return
    assert out.shape == (height * width, 3) and out.dtype == np.float32


# --------------------------------------------------------------------------------------------------
# Two-view geometry on random correspondences
# --------------------------------------------------------------------------------------------------

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
_KINDS = ("random", "scene", "duplicated", "collinear", "identical", "huge", "tiny", "zero", "shifted")


def _rot(rvec: F64) -> F64:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return np.asarray(R, dtype=np.float64)


@st.composite
def correspondences(draw: st.DrawFn) -> tuple[str, F64, F64]:
    """(kind, uv_ref, uv_cur), both (N, 2) with N in 0..50; degenerate kinds included."""
    kind = draw(st.sampled_from(_KINDS))
    n = draw(st.integers(0, 50))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "scene":  # a real two-view scene with noise and some outliers: models are found
        X = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(4, 15, n)])
        R = _rot(rng.normal(0, 0.05, 3))
        t = rng.normal(0, 0.5, 3)
        uv_ref = (X @ K.T)[:, :2] / X[:, 2:3]
        Xc = X @ R.T + t
        with np.errstate(divide="ignore", invalid="ignore"):
            uv_cur = (Xc @ K.T)[:, :2] / Xc[:, 2:3]
        uv_cur = np.nan_to_num(uv_cur, nan=0.0, posinf=1e6, neginf=-1e6) + rng.normal(0, 0.5, (n, 2))
        out = rng.random(n) < 0.2
        uv_cur[out] = rng.uniform(0, 640, (int(out.sum()), 2))
        return kind, uv_ref, uv_cur
    uv_ref = rng.uniform([0, 0], [640, 480], (n, 2))
    uv_cur = uv_ref + rng.normal(0, 5, (n, 2))
    if kind == "duplicated":
        k = max(1, n // 5)
        idx = rng.integers(0, k, n)
        uv_ref, uv_cur = uv_ref[idx], uv_cur[idx]
    elif kind == "collinear":
        s = rng.uniform(0, 1, n)[:, None]
        a, b = rng.uniform(0, 640, 2), rng.uniform(0, 640, 2)
        uv_ref = a + s * (b - a)
        uv_cur = uv_ref + rng.normal(0, 2, 2) * (1 + s)
    elif kind == "identical":
        uv_ref = np.tile(rng.uniform(0, 640, 2), (n, 1))
        uv_cur = np.tile(rng.uniform(0, 640, 2), (n, 1))
    elif kind == "huge":
        uv_ref, uv_cur = uv_ref * 1e6, uv_cur * 1e6 - 3e7
    elif kind == "tiny":
        c = rng.uniform(0, 640, 2)
        uv_ref, uv_cur = c + (uv_ref - 320) * 1e-9, c + (uv_cur - 320) * 1e-9
    elif kind == "zero":
        uv_ref, uv_cur = np.zeros((n, 2)), np.zeros((n, 2))
    elif kind == "shifted":  # the same points, one constant shift: no parallax, an exact homography
        uv_cur = uv_ref + rng.uniform(-20, 20, 2)
    return kind, np.ascontiguousarray(uv_ref), np.ascontiguousarray(uv_cur)


def _xn(uv: F64) -> F64:
    return (uv - K[:2, 2]) / np.diag(K)[:2]


def _is_mask(m: Any, n: int) -> bool:
    return isinstance(m, np.ndarray) and m.dtype == np.bool_ and m.shape == (n,)


def _is_rotation(R: F64) -> bool:
    return R.shape == (3, 3) and bool(np.all(np.isfinite(R))) and np.allclose(R @ R.T, np.eye(3), atol=1e-6) \
        and abs(np.linalg.det(R) - 1.0) < 1e-6


@FUZZ
@given(correspondences(), st.sampled_from(sorted(geo.ROBUST_METHOD_FLAGS)))
def test_estimate_models_score_and_select(c: tuple[str, F64, F64], method: str) -> None:
    _, uv_ref, uv_cur = c
    n = uv_ref.shape[0]
    E, in_e = geo.estimate_essential(uv_ref, uv_cur, K, method, 1.0, 0.999, 200)
    H, in_h = geo.estimate_homography(uv_ref, uv_cur, method, 1.0, 0.999, 200)
    assert _is_mask(in_e, n) and _is_mask(in_h, n)
    s_e = s_h = 0.0
    if E is not None:
        assert E.shape == (3, 3) and np.all(np.isfinite(E))
        F = geo.fundamental_from_essential(E, K)
        assert np.all(np.isfinite(F))
        s_e, m = geo.score_fundamental(F, uv_ref, uv_cur, 1.0)
        assert math.isfinite(s_e) and s_e >= 0.0 and _is_mask(m, n)
        d_cur, d_ref = geo.epipolar_distances_sq(F, uv_ref, uv_cur)
        assert not np.any(np.isnan(d_cur)) and not np.any(np.isnan(d_ref))
    else:
        assert not in_e.any()
    if H is not None:
        assert H.shape == (3, 3) and np.all(np.isfinite(H))
        s_h, m = geo.score_homography(H, uv_ref, uv_cur, 1.0)
        assert math.isfinite(s_h) and s_h >= 0.0 and _is_mask(m, n)
        assert _is_rotation(geo.rotation_from_homography(H, K))
    else:
        assert not in_h.any()
    rh = geo.rh_ratio(s_h, s_e)
    assert math.isfinite(rh) and 0.0 <= rh <= 1.0


@FUZZ
@given(correspondences(), st.integers(0, 2**32 - 1))
def test_scores_of_arbitrary_models(c: tuple[str, F64, F64], seed: int) -> None:
    """Scores and masks of any finite F / H (singular ones included) are finite / boolean."""
    _, uv_ref, uv_cur = c
    n = uv_ref.shape[0]
    rng = np.random.default_rng(seed)
    Fs = [geo.fundamental_from_essential(geo.essential_from_pose(_rot(rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3)),
                                         K), np.zeros((3, 3)), rng.normal(0, 1, (3, 3))]
    Hs = [np.eye(3), np.zeros((3, 3)), rng.normal(0, 1, (3, 3)), np.diag([1.0, 1.0, 0.0])]
    for F in Fs:
        s, m = geo.score_fundamental(F, uv_ref, uv_cur, 1.0)
        assert math.isfinite(s) and _is_mask(m, n)
        assert not np.any(np.isnan(geo.sampson_distance_sq(F, uv_ref, uv_cur)))
    for H in Hs:
        s, m = geo.score_homography(H, uv_ref, uv_cur, 1.0)
        assert math.isfinite(s) and _is_mask(m, n)


@FUZZ
@given(correspondences(), st.integers(0, 2**32 - 1))
def test_recover_pose_and_cheirality(c: tuple[str, F64, F64], seed: int) -> None:
    _, uv_ref, uv_cur = c
    n = uv_ref.shape[0]
    rng = np.random.default_rng(seed)
    E, in_e = geo.estimate_essential(uv_ref, uv_cur, K, "magsac", 1.0, 0.999, 200)
    candidates = [(E, in_e)] if E is not None else []
    # Also any valid essential matrix with an arbitrary mask (the pipeline only passes E's own inliers,
    # but recover_pose must not depend on that).
    candidates.append((geo.essential_from_pose(_rot(rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3)),
                       rng.random(n) < 0.7))
    for E_, mask in candidates:
        R, t, inl = geo.recover_pose(E_, uv_ref, uv_cur, K, mask)
        assert _is_rotation(R)
        assert t.shape == (3,) and np.all(np.isfinite(t))
        assert _is_mask(inl, n) and not np.any(inl & ~mask)
        d_ref, d_cur = geo.ray_depths(R, t, _xn(uv_ref), _xn(uv_cur))
        assert d_ref.shape == (n,) and not np.any(np.isnan(d_ref)) and not np.any(np.isnan(d_cur))


@FUZZ
@given(correspondences(), st.integers(0, 2**32 - 1), st.sampled_from(["unit", "zero", "tiny", "huge"]))
def test_triangulate_parallax_ray_depths(c: tuple[str, F64, F64], seed: int, t_kind: str) -> None:
    _, uv_ref, uv_cur = c
    n = uv_ref.shape[0]
    rng = np.random.default_rng(seed)
    R = _rot(rng.normal(0, 0.2, 3))
    t = {"unit": rng.normal(0, 1, 3), "zero": np.zeros(3), "tiny": rng.normal(0, 1e-12, 3),
         "huge": rng.normal(0, 1e8, 3)}[t_kind]
    xn_ref, xn_cur = _xn(uv_ref), _xn(uv_cur)
    tri = geo.triangulate(R, t, xn_ref, xn_cur, K, 2.0, 1.0)
    assert tri.X_ref.shape == (n, 3)
    for m in (tri.good, tri.positive_depth):
        assert _is_mask(m, n)
    assert not np.any(tri.good & ~tri.positive_depth)
    assert np.all(np.isfinite(tri.X_ref[tri.good]))  # NaN is allowed only where the solve failed
    assert not np.any(np.isnan(tri.reproj_err_px)) and not np.any(np.isnan(tri.angle_deg))
    assert 0.0 <= tri.positive_depth_ratio <= 1.0
    assert n == 0 or math.isnan(tri.median_reproj_err_px) or tri.median_reproj_err_px >= 0.0
    par = geo.parallax_deg(R, xn_ref, xn_cur)
    assert par.shape == (n,) and np.all(np.isfinite(par)) and np.all((par >= 0) & (par <= 180))
    d_ref, d_cur = geo.ray_depths(R, t, xn_ref, xn_cur)
    assert not np.any(np.isnan(d_ref)) and not np.any(np.isnan(d_cur))


@FUZZ
@given(correspondences(), st.integers(0, 2**32 - 1), st.integers(1, 12),
       st.sampled_from(["points", "duplicated", "identical", "far", "behind", "on_camera"]))
def test_scale_from_points(c: tuple[str, F64, F64], seed: int, min_points: int, x_kind: str) -> None:
    _, _, uv_cur = c
    n = uv_cur.shape[0]
    rng = np.random.default_rng(seed)
    X = _points(rng, n, x_kind)
    t_dir = rng.normal(0, 1, 3)
    t_dir = t_dir / max(np.linalg.norm(t_dir), 1e-300)
    est = geo.scale_from_points(X, _rot(rng.normal(0, 0.1, 3)), t_dir, _xn(uv_cur), min_points)
    if est is not None:
        assert math.isfinite(est.scale) and est.scale > 0.0
        assert math.isfinite(est.rel_spread) and est.rel_spread >= 0.0
        assert est.n_used >= 1


def _points(rng: np.random.Generator, n: int, kind: str) -> F64:
    X = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(4, 15, n)])
    if kind == "duplicated" and n:
        X = X[rng.integers(0, max(1, n // 5), n)]
    elif kind == "identical":
        X = np.tile(X[:1] if n else np.ones((1, 3)), (n, 1))
    elif kind == "far":
        X = X * 1e9
    elif kind == "behind":
        X[:, 2] *= -1.0
    elif kind == "on_camera":
        X = np.zeros((n, 3))
    return X


@FUZZ_SLOW
@given(correspondences(), st.integers(0, 2**32 - 1),
       st.sampled_from(["points", "duplicated", "identical", "far", "behind", "on_camera", "consistent"]))
def test_refine_pose_pnp(c: tuple[str, F64, F64], seed: int, x_kind: str) -> None:
    _, _, uv_cur = c
    n = uv_cur.shape[0]
    rng = np.random.default_rng(seed)
    R0, t0 = _rot(rng.normal(0, 0.05, 3)), rng.normal(0, 0.3, 3)
    if x_kind == "consistent":  # points that project onto uv_cur under (R0, t0), the pose LM should keep
        X = _points(rng, n, "points")
        Xc = X @ R0.T + t0
        uv_cur = (Xc @ K.T)[:, :2] / Xc[:, 2:3] + rng.normal(0, 0.3, (n, 2))
    else:
        X = _points(rng, n, x_kind)
    res = geo.refine_pose_pnp(X, uv_cur, K, R0, t0, 2.0)
    if res is None:
        return
    R, t, keep, cov = res
    assert _is_rotation(R)
    assert t.shape == (3,) and np.all(np.isfinite(t))
    assert _is_mask(keep, n) and np.count_nonzero(keep) >= 6
    assert cov.shape == (6, 6) and np.all(np.isfinite(cov)), "covariance of a returned pose must be finite"


@FUZZ
@given(correspondences(), st.integers(0, 2**32 - 1))
def test_pose_from_homography(c: tuple[str, F64, F64], seed: int) -> None:
    _, uv_ref, uv_cur = c
    n = uv_ref.shape[0]
    H, in_h = geo.estimate_homography(uv_ref, uv_cur, "usac_fast", 1.0, 0.999, 200)
    if H is None:
        H, in_h = np.eye(3) + np.random.default_rng(seed).normal(0, 0.01, (3, 3)), np.ones(n, bool)
    res = geo.pose_from_homography(H, K, _xn(uv_ref), _xn(uv_cur), in_h, 2.0, 1.0)
    if res is not None:
        R, t, tri = res
        assert _is_rotation(R) and np.all(np.isfinite(t))
        assert _is_mask(tri.good, n)


# --------------------------------------------------------------------------------------------------
# Camera model
# --------------------------------------------------------------------------------------------------

_CAMERAS = {
    "plumb_bob": CameraModel.create(640, 480, K, [-0.08, 0.02, 0.0005, -0.0005, 0.0], "plumb_bob"),
    "plumb_bob_strong": CameraModel.create(640, 480, K, [-0.28, 0.07, 1e-4, -2e-4, 0.0], "plumb_bob"),
    "plumb_bob_none": CameraModel.create(640, 480, K, [], "plumb_bob"),
    "rational_polynomial": CameraModel.create(640, 480, K, [0.1, -0.02, 1e-4, -2e-4, 0.001, 0.4, 0.01, 0.0],
                                              "rational_polynomial"),
    "equidistant": CameraModel.create(800, 800, [300.0, 0, 399.5, 0, 300.0, 399.5, 0, 0, 1],
                                      [-0.01, 0.02, -0.005, 0.001], "equidistant"),
    "equidistant_none": CameraModel.create(640, 480, K, [0, 0, 0, 0], "equidistant"),
}


@FUZZ
@given(st.sampled_from(sorted(_CAMERAS)), st.integers(0, 60), st.integers(0, 2**32 - 1),
       st.sampled_from(["inside", "margin", "corners", "identical"]))
def test_camera_normalize_is_finite(name: str, n: int, seed: int, where: str) -> None:
    """Pixels in the image, or up to 10 % outside it (KLT tracks leave the image), normalize to finite
    coordinates for every distortion model."""
    cam = _CAMERAS[name]
    rng = np.random.default_rng(seed)
    w, h = cam.width - 1.0, cam.height - 1.0
    if where == "inside":
        pts = rng.uniform([0, 0], [w, h], (n, 2))
    elif where == "margin":
        pts = rng.uniform([-0.1 * w, -0.1 * h], [1.1 * w, 1.1 * h], (n, 2))
    elif where == "corners":
        pts = np.array([[0, 0], [w, 0], [0, h], [w, h], [w / 2, h / 2]] * (n // 5 + 1), dtype=np.float64)[:n]
    else:
        pts = np.tile(rng.uniform([0, 0], [w, h]), (n, 1))
    for dtype in (np.float64, np.float32):
        xn = cam.normalize(pts.astype(dtype))
        assert xn.shape == (n, 2) and xn.dtype == np.float64
        assert np.all(np.isfinite(xn)), pts[~np.all(np.isfinite(xn), axis=1)]
    if n:  # and they are the rays of those pixels: projecting back lands on them
        X = np.column_stack([xn, np.ones(n)])
        inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w) & (pts[:, 1] >= 0) & (pts[:, 1] <= h)
        if cam.model.value == "equidistant":
            # Documented limitation (CameraModel.normalize): cv2.fisheye is exact below ~86 deg off axis.
            inside &= np.linalg.norm((pts - cam.K[:2, 2]) / cam.fx, axis=1) < math.radians(80.0)
        np.testing.assert_allclose(cam.project(X)[inside], pts[inside], atol=1e-3)


@FUZZ
@given(st.sampled_from(sorted(_CAMERAS)),
       st.lists(st.tuples(st.floats(-1e7, 1e7), st.floats(-1e7, 1e7)), max_size=20))
def test_camera_normalize_far_pixels_do_not_raise(name: str, pts: list[tuple[float, float]]) -> None:
    """Far outside the image the distortion model means nothing, but normalize must not raise."""
    xn = _CAMERAS[name].normalize(np.array(pts, dtype=np.float64).reshape(-1, 2))
    assert xn.shape == (len(pts), 2)


# --------------------------------------------------------------------------------------------------
# Compressed images: the declared size decides before any decoding
# --------------------------------------------------------------------------------------------------


def _sof_jpeg(width: int, height: int, tail: bytes) -> bytes:
    """SOI, a baseline frame header (SOF0) declaring ``width`` x ``height`` with one component, then ``tail``."""
    sof = b"\xff\xc0" + (11).to_bytes(2, "big") + b"\x08" + height.to_bytes(2, "big") + width.to_bytes(2, "big") \
        + b"\x01\x01\x11\x00"
    return b"\xff\xd8" + sof + tail


@FUZZ
@given(st.sampled_from(["png", "jpeg"]), st.integers(0, 2**16 - 1), st.integers(0, 2**16 - 1),
       st.binary(max_size=200), st.sampled_from([None, (64, 48), (640, 480)]))
def test_a_compressed_image_is_decoded_only_at_its_declared_allowed_size(
        fmt: str, width: int, height: int, tail: bytes, expected: tuple[int, int] | None) -> None:
    """Any declared size with any payload after the header: decoded only when the size is within the cap and
    camera_info's; then the image has exactly that size. Otherwise an ImageConversionError, and OpenCV is not
    asked to decode (a declared 65535 x 65535 would allocate 4 GB)."""
    from encoded_images import png_header

    from epi_vo.io import msgconv

    data = png_header(width, height) + tail if fmt == "png" else _sof_jpeg(width, height, tail)
    calls = []
    real = msgconv.cv2.imdecode

    def spy(buf: Any, flags: int) -> Any:
        calls.append(1)
        return real(buf, flags)

    msgconv.cv2.imdecode = spy
    try:
        gray = compressed_to_gray(SimpleNamespace(format=fmt, data=data), expected)
    except ImageConversionError as exc:
        assert str(exc).startswith("could not decode CompressedImage")
        allowed = width * height <= msgconv.MAX_DECODED_PIXELS and expected in (None, (width, height))
        assert calls == [] or allowed
        return
    finally:
        msgconv.cv2.imdecode = real
    assert gray.shape == (height, width) and width * height <= msgconv.MAX_DECODED_PIXELS
    assert expected in (None, (width, height))
