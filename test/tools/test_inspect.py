"""``epi-vo inspect``: the residual data of one frame pair, the reference keyframe, the PNG, the CLI errors.

Bags are the bundled ones; the expected keyframes come from a replay's frames.jsonl. Synthetic scenes
(conftest.py) give known answers for the residuals.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import pytest

from epi_vo.cli import main
from epi_vo.core import geometry as geo
from epi_vo.core.debug_image import mover_mask
from epi_vo.core.errors import BagError
from epi_vo.core.frame import FrameResult, Matches, Model
from epi_vo.tools.inspect_frame import (
    MAX_LINES,
    Inspection,
    draw_inspection,
    inspect_bag,
    line_in_box,
    nearest_frame,
    pair_data,
    record_lines,
    summary_line,
)
from epi_vo.tools.replay import run_replay

if TYPE_CHECKING:
    from conftest import TwoViewScene

REPO = Path(__file__).resolve().parents[2]
GENERAL = REPO / "bags" / "general_motion" / "bag"
ROTATION = REPO / "bags" / "pure_rotation" / "bag"
SIGMA_PX = 1.0  # VoConfig().score_sigma_px


@pytest.fixture(scope="module")
def records(tmp_path_factory: pytest.TempPathFactory) -> list[dict]:
    out = tmp_path_factory.mktemp("replay_general")
    run_replay(GENERAL, out)
    return [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def general20() -> Inspection:
    return inspect_bag(GENERAL, 20)


def _expected_reference(records: list[dict], n: int) -> int:
    """The keyframe frame n was measured against: the last keyframe strictly before n."""
    return max(r["index"] for r in records[:n] if r["is_keyframe"])


def _point_line_px(line: np.ndarray, uv: np.ndarray) -> float:
    a, b, c = line
    return abs(a * uv[0] + b * uv[1] + c) / math.hypot(a, b)


def _with_matches(result: FrameResult, model: Model, uv_kf: np.ndarray, uv_cur: np.ndarray,
                  inliers: np.ndarray, F: np.ndarray, H: np.ndarray) -> FrameResult:
    m = Matches(uv_kf.copy(), uv_cur.copy(), uv_kf.copy(), uv_cur.copy(), inliers.copy(), F, H)
    return replace(result, model=model, matches=m, n_inliers=int(np.count_nonzero(inliers)),
                   n_tracked=uv_kf.shape[0])


# -------------------------------------------------------------------------------------------------
# The bundled bags


def test_cli_writes_a_legible_png(general20: Inspection, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["inspect", str(GENERAL), "--frame", "20"]) == 0
    out = capsys.readouterr().out.splitlines()
    png = tmp_path / "frame_20.png"
    assert out[0] == "frame_20.png"
    assert out[1].startswith("frame 20 ") and "vs keyframe" in out[1] and "model E" in out[1]
    img = cv2.imread(str(png))
    assert img is not None
    h, w = img.shape[:2]
    assert 1200 <= w <= 3000 and 700 <= h <= 2000  # side-by-side 640x480 pair over histogram + record
    assert float(img.std()) > 20.0  # an image, not a blank canvas


def test_e_residuals_gate_the_inliers(general20: Inspection) -> None:
    r, d = general20.result, general20.data
    assert r.model is Model.ESSENTIAL and d.model is Model.ESSENTIAL
    assert d.residual_px.shape == (r.n_tracked,)
    assert d.gate_px == pytest.approx(SIGMA_PX * math.sqrt(geo.CHI2_1DOF))
    assert d.n_inliers == r.n_inliers
    assert np.all(d.residual_px[d.inliers] <= d.gate_px)
    assert 0 < d.line_idx.size <= MAX_LINES
    assert np.all(np.diff(d.line_idx) > 0)
    # The drawn epipolar lines are those of inliers, and pass within the residual of their points.
    assert d.epi_idx.size > 0 and np.all(d.inliers[d.epi_idx])
    for k, i in enumerate(d.epi_idx):
        assert _point_line_px(d.lines_cur[k], d.uv_cur[i]) <= d.residual_px[i] + 1e-9
        assert _point_line_px(d.lines_kf[k], d.uv_kf[i]) <= d.residual_px[i] + 1e-9
    assert d.transfer_cur.shape == (0, 2)


def test_reference_keyframe_is_the_one_in_use(records: list[dict], general20: Inspection) -> None:
    assert general20.keyframe_index == _expected_reference(records, 20)
    assert general20.result.n_inliers == records[20]["n_inliers"]
    assert general20.gray_kf is not None and general20.gray_kf.shape == general20.gray_cur.shape
    # A frame that itself becomes a keyframe was still measured against the previous one.
    n = next(r["index"] for r in records[3:] if r["is_keyframe"])
    insp = inspect_bag(GENERAL, n)
    assert insp.result.is_keyframe
    assert insp.keyframe_index == _expected_reference(records, n) < n
    assert insp.result.n_inliers == records[n]["n_inliers"]


def test_stamp_picks_the_nearest_frame(records: list[dict]) -> None:
    s20, s21 = records[20]["stamp"], records[21]["stamp"]
    insp = inspect_bag(GENERAL, stamp_s=s20 + 0.3 * (s21 - s20))
    assert insp.frame_index == 20
    assert insp.result.stamp_ns == records[20]["stamp_ns"]
    stamps = [r["stamp_ns"] for r in records]
    assert nearest_frame(stamps, s21 - 0.3 * (s21 - s20)) == 21
    assert nearest_frame(stamps, records[0]["stamp"] - 100.0) == 0
    assert nearest_frame(stamps, records[-1]["stamp"] + 100.0) == len(records) - 1


def test_cli_stamp_option(records: list[dict], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "sub" / "at_stamp.png"
    assert main(["inspect", str(GENERAL), "--stamp", f"{records[5]['stamp'] + 0.01:.6f}", "-o", str(png)]) == 0
    out = capsys.readouterr().out
    assert str(png) in out and "frame 5 " in out
    assert cv2.imread(str(png)) is not None


@pytest.mark.parametrize("frame", [52, -1])
def test_frame_out_of_range_is_a_clear_error(frame: int, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(GENERAL), "--frame", str(frame)]) == 2
    err = capsys.readouterr().err
    assert f"frame {frame} is out of range" in err and "52 frames (0..51)" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    with pytest.raises(BagError, match=r"out of range: .* 52 frames \(0\.\.51\)"):
        inspect_bag(GENERAL, frame)


def test_frame_or_stamp_exactly_one() -> None:
    with pytest.raises(ValueError, match="exactly one"):
        inspect_bag(GENERAL)
    with pytest.raises(ValueError, match="exactly one"):
        inspect_bag(GENERAL, 3, stamp_s=1000.0)


def test_h_residuals_under_pure_rotation(tmp_path: Path) -> None:
    insp = inspect_bag(ROTATION, 20)
    r, d = insp.result, insp.data
    assert r.model is Model.HOMOGRAPHY and d.model is Model.HOMOGRAPHY
    assert d.gate_px == pytest.approx(SIGMA_PX * math.sqrt(geo.CHI2_2DOF))
    assert "transfer" in d.residual_label
    e_cur_sq, e_kf_sq = geo.transfer_errors_sq(r.matches.H, r.matches.uv_kf, r.matches.uv_cur)
    np.testing.assert_allclose(d.residual_px, np.sqrt(np.maximum(e_cur_sq, e_kf_sq)))
    assert d.n_inliers == r.n_inliers
    assert np.all(d.residual_px[d.inliers] <= d.gate_px)
    # H-transferred points are drawn instead of epipolar lines; they land near the observed points.
    assert d.lines_cur.shape == (0, 3) and d.transfer_cur.shape == (d.epi_idx.size, 2) and d.epi_idx.size > 0
    assert np.all(np.linalg.norm(d.transfer_cur - d.uv_cur[d.epi_idx], axis=1) <= d.gate_px)
    assert np.all(np.linalg.norm(d.transfer_kf - d.uv_kf[d.epi_idx], axis=1) <= d.gate_px)
    assert cv2.imread(str(draw_inspection(insp, tmp_path / "rot.png"))) is not None


def test_first_frame_has_no_reference(tmp_path: Path) -> None:
    insp = inspect_bag(ROTATION, 0)
    assert insp.keyframe_index is None and insp.gray_kf is None
    assert insp.data.model is Model.NONE and insp.data.residual_px.size == 0 and insp.data.line_idx.size == 0
    assert cv2.imread(str(draw_inspection(insp, tmp_path / "f0.png"))) is not None


# -------------------------------------------------------------------------------------------------
# The pure function on synthetic scenes (known answers)


def test_pair_data_e_known_answer(general20: Inspection, general_scene_outliers: TwoViewScene) -> None:
    s = general_scene_outliers
    F = geo.fundamental_from_essential(geo.essential_from_pose(s.R_cur_ref, s.t_cur_ref), s.K)
    res = _with_matches(general20.result, Model.ESSENTIAL, s.uv_ref_obs, s.uv_cur_obs, ~s.is_outlier, F,
                        np.zeros((3, 3)))
    d = pair_data(res, SIGMA_PX)
    x_ref = np.c_[s.uv_ref_obs, np.ones(s.n)]
    x_cur = np.c_[s.uv_cur_obs, np.ones(s.n)]
    expected = [max(_point_line_px(F @ x_ref[i], s.uv_cur_obs[i]), _point_line_px(F.T @ x_cur[i], s.uv_ref_obs[i]))
                for i in range(s.n)]
    np.testing.assert_allclose(d.residual_px, expected, rtol=1e-9)
    assert np.median(d.residual_px[~s.is_outlier]) < 0.5  # 0.3 px noise
    assert np.median(d.residual_px[s.is_outlier]) > 5.0 * d.gate_px


def test_pair_data_h_known_answer(general20: Inspection, rotation_scene: TwoViewScene) -> None:
    s = rotation_scene
    assert s.H_true is not None
    H = s.H_true
    res = _with_matches(general20.result, Model.HOMOGRAPHY, s.uv_ref_obs, s.uv_cur_obs, np.ones(s.n, bool),
                        np.zeros((3, 3)), H)
    d = pair_data(res, SIGMA_PX)

    def mapped(M: np.ndarray, uv: np.ndarray) -> np.ndarray:
        p = M @ np.r_[uv, 1.0]
        return p[:2] / p[2]

    H_inv = np.linalg.inv(H)
    expected = [max(np.linalg.norm(mapped(H, s.uv_ref_obs[i]) - s.uv_cur_obs[i]),
                    np.linalg.norm(mapped(H_inv, s.uv_cur_obs[i]) - s.uv_ref_obs[i])) for i in range(s.n)]
    np.testing.assert_allclose(d.residual_px, expected, rtol=1e-9)
    assert np.max(d.residual_px) < d.gate_px  # 0.3 px noise, exact H


def test_pair_data_degenerate_cases(general20: Inspection) -> None:
    # No model chosen: nothing to gate, nothing to draw.
    d = pair_data(replace(general20.result, model=Model.NONE, matches=Matches.empty()), SIGMA_PX)
    assert d.model is Model.NONE and d.residual_px.size == 0 and d.line_idx.size == 0 and d.epi_idx.size == 0
    assert math.isnan(d.gate_px)
    # E named but no F estimated (zero matrix): treated as no model, not as zero residuals.
    d = pair_data(replace(general20.result, matches=replace(general20.result.matches, F=np.zeros((3, 3)))),
                  SIGMA_PX)
    assert d.model is Model.NONE and d.residual_px.size == 0


def test_line_subsampling_keeps_outliers_visible(general20: Inspection) -> None:
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 400, (500, 2))
    inliers = np.ones(500, bool)
    inliers[::5] = False  # 100 outliers
    res = _with_matches(general20.result, Model.ESSENTIAL, uv, uv + 1.0, inliers, general20.result.matches.F,
                        np.zeros((3, 3)))
    d = pair_data(res, SIGMA_PX)
    assert d.line_idx.size == MAX_LINES and np.unique(d.line_idx).size == MAX_LINES
    assert np.count_nonzero(~inliers[d.line_idx]) == MAX_LINES // 3
    d = pair_data(res, SIGMA_PX, max_lines=1000)
    assert d.line_idx.size == 500


def test_line_in_box() -> None:
    assert line_in_box(np.array([0.0, 1.0, -100.0]), 640, 480) == ((0.0, 100.0), (639.0, 100.0))  # v = 100
    (u0, v0), (u1, v1) = line_in_box(np.array([1.0, -1.0, 0.0]), 640, 480)  # u = v: corner to bottom edge
    assert (u0, v0) == pytest.approx((0.0, 0.0)) and (u1, v1) == pytest.approx((479.0, 479.0))
    assert line_in_box(np.array([0.0, 1.0, 1000.0]), 640, 480) is None  # v = -1000: outside


# -------------------------------------------------------------------------------------------------
# Movers: coloured like the debug image, counted in the summary


def test_static_mover_frame_colours_the_movers(tmp_path: Path) -> None:
    insp = inspect_bag(REPO / "bags" / "static_mover" / "bag", 40)
    r, d = insp.result, insp.data
    assert r.state.value == "static" and r.n_moving >= 0.25 * r.n_tracked
    # In front of a still camera every feature the static hypothesis did not explain moved.
    assert d.n_movers == r.n_moving
    assert np.array_equal(d.movers, ~d.inliers)
    x0, y0, x1, y1 = r.moving_region
    assert d.moving_region == r.moving_region
    line = summary_line(insp)
    assert f"moving {r.n_moving} ({r.moving_fraction:.0%}) in x {x0}-{x1}, y {y0}-{y1} px, static score " in line
    assert any(s.startswith("moving features") and f"moving {r.n_moving}" in s for s in record_lines(insp))
    png = cv2.imread(str(draw_inspection(insp, tmp_path / "f40.png")))
    magenta = np.all(png == (230, 0, 230), axis=2)  # BGR of #e600e6
    assert int(magenta.sum()) > 500


def test_moving_mover_frame_colours_exactly_the_pipelines_movers() -> None:
    insp = inspect_bag(REPO / "bags" / "moving_mover" / "bag", 56)
    r, d = insp.result, insp.data
    assert r.state.value == "tracking" and r.n_moving > 0 and r.moving_region is not None
    assert r.matches.moving is not None and np.array_equal(d.movers, r.matches.moving)
    assert d.n_movers == r.n_moving
    assert not np.any(d.movers & d.inliers)
    x0, y0, x1, y1 = r.moving_region
    inside = (d.uv_cur[:, 0] >= x0) & (d.uv_cur[:, 0] <= x1) & (d.uv_cur[:, 1] >= y0) & (d.uv_cur[:, 1] <= y1)
    assert np.all(inside[d.movers])  # the box is the movers' own


def test_no_movers_no_magenta(general20: Inspection, tmp_path: Path) -> None:
    assert general20.result.n_moving == 0 and general20.data.n_movers == 0
    assert "moving 0 (0%), static score" in summary_line(general20)
    png = cv2.imread(str(draw_inspection(general20, tmp_path / "f20.png")))
    assert int(np.all(png == (230, 0, 230), axis=2).sum()) == 0


def test_mover_mask_known_answer(general20: Inspection) -> None:
    r = general20.result
    uv = np.array([[10.0, 10.0], [50.0, 50.0], [55.0, 45.0], [200.0, 200.0], [52.0, 52.0]])
    m = Matches(uv, uv, uv, uv, np.array([False, False, False, False, True]), np.zeros((3, 3)), np.zeros((3, 3)))
    moving = replace(r, matches=m, n_moving=2, moving_fraction=0.4, moving_region=(45, 40, 60, 55),
                     model=Model.ESSENTIAL)
    # Matches without the pipeline's mask (older records): the outliers in the box; the inlier in it is none.
    assert mover_mask(moving).tolist() == [False, True, True, False, False]
    exact = replace(moving, matches=replace(m, moving=np.array([False, True, False, False, False])))
    assert mover_mask(exact).tolist() == [False, True, False, False, False]  # the pipeline's mask wins
    static = replace(moving, model=Model.STATIC)
    assert mover_mask(static).tolist() == [True, True, True, True, False]
    assert mover_mask(replace(moving, n_moving=0, moving_region=None)).tolist() == [False] * 5
