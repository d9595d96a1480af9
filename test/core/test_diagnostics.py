"""Tests for epi_vo.core.diagnostics: the DiagnosticStatusRecord checks and level coercion."""

from __future__ import annotations

import dataclasses

import pytest

from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.errors import EpiVoError


def test_int_level_becomes_enum() -> None:
    record = DiagnosticStatusRecord(2, "epi_vo: tracking", "lost", "camera", (("inliers", "3"),))
    assert record.level is DiagnosticLevel.ERROR
    assert int(record.level) == 2
    assert record.values == (("inliers", "3"),)


def test_values_default_empty_and_list_becomes_tuple() -> None:
    assert DiagnosticStatusRecord(0, "n", "m", "h").values == ()
    record = DiagnosticStatusRecord(0, "n", "m", "h", [("k", "v")])  # type: ignore[arg-type]
    assert record.values == (("k", "v"),)


def test_record_is_frozen() -> None:
    record = DiagnosticStatusRecord(DiagnosticLevel.OK, "n", "m", "h")
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.level = DiagnosticLevel.WARN  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"level": 7}, r"diagnostic level 7 is not one of \[0, 1, 2, 3\]"),
        ({"name": None}, "diagnostic name must be str, got None"),
        ({"values": (("k", 1),)}, r"values must be \(key, value\) pairs of str, got \('k', 1\)"),
        ({"values": ("kv",)}, "values must be"),
    ],
)
def test_bad_fields_raise(kwargs: dict, match: str) -> None:
    fields = {"level": 0, "name": "n", "message": "m", "hardware_id": "h", "values": ()}
    fields.update(kwargs)
    with pytest.raises(EpiVoError, match=match):
        DiagnosticStatusRecord(**fields)


def test_debug_image_marks_what_moved_in_front_of_a_static_camera() -> None:
    import dataclasses as dc

    import numpy as np

    from epi_vo.core.debug_image import draw_matches
    from epi_vo.core.frame import FrameResult, Matches, Model, TrackingState

    pts_kf = np.array([[100.0, 100.0], [300.0, 200.0], [500.0, 300.0]])
    pts_cur = pts_kf + np.array([[0.0, 0.0], [0.0, 0.0], [20.0, 5.0]])
    inl = np.array([True, True, False])
    m = Matches(pts_kf, pts_cur, pts_kf, pts_cur, inl, np.zeros((3, 3)), np.zeros((3, 3)))
    base = FrameResult(index=0, stamp_ns=1, state=TrackingState.STATIC, has_pose=True, is_keyframe=False,
                       model=Model.STATIC, rh=0.5, n_features=3, n_tracked=3, n_inliers=2, inlier_ratio=2 / 3,
                       median_parallax_deg=0.0, n_triangulated=0, positive_depth_ratio=float("nan"),
                       median_reproj_err_px=float("nan"), relative_scale=float("nan"), n_keyframes=1,
                       T_w_c=np.eye(4), covariance=np.eye(6), points_w=np.zeros((0, 3)), timings_ms={}, reason="",
                       matches=m, n_moving=1, moving_fraction=1 / 3, moving_region=(480, 280, 540, 330))
    img = draw_matches(base, np.zeros((480, 640), np.uint8))
    magenta = np.all(img == (230, 0, 230), axis=2)
    assert magenta[280, 480:541].all()  # the box around the movers
    near = img[298:309, 500:524].astype(int)
    assert ((near[..., 0] > 100) & (near[..., 2] > 100) & (near[..., 1] < 60)).any()  # the mover's track
    assert not magenta[95:105, 95:105].any()  # a still feature stays green
    tracking = draw_matches(dc.replace(base, state=TrackingState.TRACKING, model=Model.ESSENTIAL, moving_region=None),
                            np.zeros((480, 640), np.uint8))
    assert not np.all(tracking == (230, 0, 230), axis=2).any()  # an ordinary outlier is red
