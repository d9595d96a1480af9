"""Every value a VoConfig range allows works: the pipeline runs a short real sequence with each knob at the ends
of its range (and just inside its lower end, where a sign check let 5e-324 through) and with random mixtures
of such values, raising nothing and publishing only finite poses, covariances and twists.

The sequence: the first 14 frames of bags/ground_robot (a floor, the robot starting to drive), 3 black frames
(tracking is lost or held), 7 more frames, with the bag's wheel odometry: it reaches a map, keyframes, the
scale sources and a restart.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig, allowed_range, config_fields, validate
from epi_vo.core.decisions import Decision
from epi_vo.core.errors import ConfigError
from epi_vo.core.odometry import OdometryConverter
from epi_vo.core.pipeline import VoPipeline
from epi_vo.io import bagio
from epi_vo.io.msgconv import decode_frame

BAG = Path(__file__).resolve().parents[2] / "bags" / "ground_robot" / "bag"
FIELDS = {f.name: f for f in config_fields()}
# Where the value of a knob is used: the scale source it needs to be exercised.
SOURCE_OF = {"camera_height_rel_sigma": "ground_plane", "ground_max_tilt_deg": "ground_plane",
             "ground_inlier_ratio": "ground_plane", "ground_min_points": "ground_plane",
             "wheel_odometry_rel_sigma": "wheel_odometry", "wheel_odometry_timeout_s": "wheel_odometry",
             "wheel_odometry_noise_m": "wheel_odometry", "wheel_odometry_window_m": "wheel_odometry",
             "ground_fit_min_rel_sigma": "ground_plane"}
METRIC = {"ground_plane": {"scale_source": "ground_plane", "camera_height_m": 0.45},
          "wheel_odometry": {"scale_source": "wheel_odometry", "wheel_odometry_topic": "/wheel/odom"},
          "none": {"scale_source": "none"}}
# The windowed adjustment needs its switch on to use its other knobs.
NEEDS = {"ba_every_keyframes": {"ba_window_keyframes": 3, "ba_solver": "inline"},
         "ba_wait": {"ba_window_keyframes": 3}, "ba_solver": {"ba_window_keyframes": 3}}


@dataclasses.dataclass(frozen=True)
class Sequence:
    frames: list[tuple[int, np.ndarray, CameraModel]]
    wheel: list[tuple[int, np.ndarray]]


@pytest.fixture(scope="module")
def sequence() -> Sequence:
    frames = []
    with bagio.open_camera_bag(BAG, wheel_topic="/wheel/odom") as bag:
        odom = bag.read_wheel_odometry()
        assert odom is not None
        for i, f in enumerate(bag.iter_frames()):
            if i >= 24:
                break
            gray = decode_frame(f.image_msg, bag.image_is_compressed)
            if i in (14, 15, 16):
                gray = np.zeros_like(gray)
            frames.append((f.stamp_ns, gray, CameraModel.from_camera_info(f.camera_info_msg)))
        end = frames[-1][0]
        wheel = [(int(s), np.asarray(p)) for s, p in zip(odom.stamps_ns, odom.positions, strict=True) if s <= end]
    return Sequence(frames, wheel)


def _run(cfg: VoConfig, seq: Sequence) -> None:
    """The sequence through the pipeline and the odometry converter: nothing raises, everything published
    is finite, and no frame was lost to an error inside the code."""
    pipe, conv = VoPipeline(cfg), OdometryConverter()
    for stamp, xyz in seq.wheel:
        pipe.add_wheel_odometry(stamp, xyz)
    for stamp, gray, camera in seq.frames:
        r = pipe.process(gray, camera, stamp)
        s = conv.convert_result(r)
        arrays: list[Any] = [r.T_w_c, r.covariance, r.points_w, s.position, s.quat_xyzw, s.pose_covariance,
                             s.linear_velocity, s.angular_velocity, s.twist_covariance]
        if r.step_covariance is not None:
            arrays.append(r.step_covariance)
        assert all(np.all(np.isfinite(a)) for a in arrays), (r.index, r.reason)
        assert math.isfinite(r.scale.scale) and not math.isinf(r.scale.rel_std)
        defects = {Decision.OPENCV_FAILED, Decision.POSE_NOT_FINITE, Decision.COVARIANCE_NOT_FINITE}
        assert not defects & set(r.decisions), r.reason


def _ends(name: str) -> list[Any]:
    """The values to try for one knob: the ends of its range, the least value above its lower end, its
    'off' value; every choice; both switch positions."""
    f = FIELDS[name]
    if f.metadata.get("choices"):
        return list(f.metadata["choices"])
    if isinstance(f.default, bool):
        return [True, False]
    lo, hi, off = f.metadata.get("min"), f.metadata.get("max"), f.metadata.get("off")
    if lo is None:
        return []
    if isinstance(f.default, int):
        values = [int(lo), int(hi), int(lo) + 1]
        if name in ("klt_window_px", "klt_patch_refine_px"):  # odd sizes only
            values = [v if v % 2 else v + 1 for v in values]
    else:
        values = [float(lo), float(hi), math.nextafter(float(lo), math.inf)]
    return values + ([off] if off is not None else [])


def _config(values: dict[str, Any]) -> VoConfig:
    """The defaults with ``values``, metric through the source a knob needs (ground_plane unless said)."""
    base: dict[str, Any] = {}
    for name in values:
        base.update(NEEDS.get(name, {}))
    source = values.get("scale_source", next((SOURCE_OF[n] for n in values if n in SOURCE_OF), "ground_plane"))
    if values.get("camera_height_m", 0.45) == 0.0:
        source = "none"  # 0: not set
    base.update(METRIC[source])
    return dataclasses.replace(VoConfig(), **{**base, **values})


CASES = [(name, value) for name in FIELDS for value in _ends(name)]


def test_every_numeric_knob_has_a_range_and_a_doc_line_that_says_it() -> None:
    from epi_vo.core.config import field_doc

    for f in config_fields():
        if isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            assert allowed_range(f) is not None, f.name
            lo, hi = f.metadata["min"], f.metadata["max"]
            assert field_doc(f).endswith(f"{lo:g} to {hi:g}]"), f.name
    assert len(CASES) > 3 * 60


@pytest.mark.parametrize(("name", "value"), CASES, ids=[f"{n}={v!r}" for n, v in CASES])
def test_each_knob_at_the_ends_of_its_range_works(name: str, value: Any, sequence: Sequence) -> None:
    cfg = _config({name: value})
    validate(cfg)
    _run(cfg, sequence)


def test_values_just_outside_a_range_are_refused_all_at_once() -> None:
    bad: dict[str, Any] = {}
    for f in config_fields():
        lo = f.metadata.get("min")
        if lo is None or isinstance(f.default, bool):
            continue
        below = lo - 1 if isinstance(f.default, int) else math.nextafter(float(lo), -math.inf)
        if f.metadata.get("off") is not None and below == f.metadata["off"]:
            below = lo - 2 if isinstance(f.default, int) else (lo + f.metadata["off"]) / 2
        bad[f.name] = below
    with pytest.raises(ConfigError) as info:
        validate(dataclasses.replace(VoConfig(), **bad))
    msg = str(info.value)
    assert all(f"{name}=" in msg for name in bad), [n for n in bad if f"{n}=" not in msg]


@st.composite
def mixtures(draw: st.DrawFn) -> dict[str, Any]:
    """Up to 8 knobs at once, each at one of its ends or anywhere inside its range."""
    names = draw(st.lists(st.sampled_from(sorted(n for n in FIELDS if _ends(n))), min_size=1, max_size=8,
                          unique=True))
    values: dict[str, Any] = {}
    for name in names:
        f = FIELDS[name]
        ends = _ends(name)
        if isinstance(f.default, float) and draw(st.booleans()):
            lo, hi = float(f.metadata["min"]), float(f.metadata["max"])
            values[name] = draw(st.floats(lo, hi, allow_nan=False, allow_infinity=False))
        else:
            values[name] = draw(st.sampled_from(ends))
    return values


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(values=mixtures())
def test_mixtures_of_values_inside_the_ranges_work(values: dict[str, Any], sequence: Sequence) -> None:
    cfg = _config(values)
    try:
        validate(cfg)
    except ConfigError as exc:
        # Only the cross-field rules may refuse a mixture of in-range values, and they say so.
        assert "must be odd" in str(exc) or "(0, or odd)" in str(exc), str(exc)
        return
    _run(cfg, sequence)
