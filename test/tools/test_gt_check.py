"""The ground-truth check (epi_vo.tools.gt_check): a ground truth the images confirm passes, one they
contradict is found where it is wrong, and a mover that dominates the matches is not taken for the
ground truth's error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from exact_calibration import exact
from scipy.spatial.transform import Rotation

from epi_vo.cli import main
from epi_vo.core.errors import EpiVoError
from epi_vo.io import tum
from epi_vo.tools.benchmark import BenchRow, format_checks
from epi_vo.tools.gt_check import AGREE_EXCESS_PX, agrees, check_ground_truth, excess_px

BAGS = Path(__file__).resolve().parents[2] / "bags"


def tilted_before(gt: tuple[np.ndarray, np.ndarray, np.ndarray], frame: int, deg_per_frame: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ground truth with the camera of each frame k < ``frame`` turned by (frame - k) x
    ``deg_per_frame`` about its own y axis (a heading that drifts and is right again from ``frame``)."""
    s, p, q = (np.array(a, dtype=np.float64) for a in gt)
    for k in range(frame):
        R = Rotation.from_quat(q[k]) * Rotation.from_rotvec([0.0, np.radians((frame - k) * deg_per_frame), 0.0])
        q[k] = R.as_quat()
    return s, p, q


def test_excess_is_what_the_ground_truth_adds_in_quadrature() -> None:
    assert excess_px(0.5, 0.3) == pytest.approx(0.4)
    assert excess_px(0.1, 0.2) == 0.0
    assert agrees(0.5, 0.3) and agrees(0.1, 0.2)
    assert not agrees(np.hypot(AGREE_EXCESS_PX + 0.01, 0.1), 0.1)


def test_a_rendered_ground_truth_agrees_with_its_images() -> None:
    check = check_ground_truth(BAGS / "general_motion" / "bag", tum.read_tum(BAGS / "general_motion" /
                                                                                "groundtruth_tum.txt"))
    assert [(p.first, p.second) for p in check.pairs] == [(k, k + 4) for k in range(0, 48, 4)]
    assert all(p.agrees for p in check.pairs) and check.confirmed_from == 0
    for p in check.pairs:
        assert p.model == "epipolar" and p.motion == 1 and p.matches > 500
        assert p.gt_px < 0.1 and excess_px(p.gt_px, p.image_px) < 0.05  # exact poses: at the image noise
        assert p.rotation_deg < 0.05 and p.direction_deg < 0.5
    assert check.summary().startswith("agrees with the images at all 12 pairs")


def test_a_ground_truth_wrong_over_the_first_frames_is_found_there() -> None:
    """0.1 deg of heading per frame before frame 12 (as much as the KITTI clip's ground truth is off
    there): the three pairs before frame 12 disagree by far more than the threshold, the rest agree."""
    gt = tilted_before(tum.read_tum(BAGS / "general_motion" / "groundtruth_tum.txt"), 12, 0.1)
    check = check_ground_truth(BAGS / "general_motion" / "bag", gt)
    assert [(p.first, p.second) for p in check.disagreeing] == [(0, 4), (4, 8), (8, 12)]
    for p in check.disagreeing:
        assert excess_px(p.gt_px, p.image_px) > 2 * AGREE_EXCESS_PX
        assert p.rotation_deg == pytest.approx(0.4, abs=0.05)
    assert check.confirmed_from == 12
    assert check.confirmed_from_ns == next(p.first_ns for p in check.pairs if p.first == 12)
    assert "contradicts the images at 3 of 12 pairs (0-4, 4-8, 8-12" in check.summary()
    assert check.summary().endswith("confirmed from frame 12")


def test_a_mover_that_dominates_the_matches_is_not_the_ground_truths_error() -> None:
    """static_mover: a still camera and a mover in view. On some pairs the mover has the most matches; the
    still background is the second motion, and the ground truth agrees with it (judged against the mover
    it would be 21 px off). A camera that does not translate is judged by the rotation's homography."""
    check = check_ground_truth(BAGS / "static_mover" / "bag", tum.read_tum(BAGS / "static_mover" /
                                                                             "groundtruth_tum.txt"))
    assert all(p.agrees for p in check.pairs) and len(check.pairs) == 29
    assert all(p.model == "rotation" for p in check.pairs)
    second = [p for p in check.pairs if p.motion == 2]
    assert len(second) >= 5
    assert all(p.gt_px < 0.2 and p.rotation_deg < 0.05 for p in second)


def test_gtcheck_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["gtcheck", str(BAGS / "moving_mover" / "bag")]) == 0
    out = capsys.readouterr().out
    assert "ground truth agrees with the images at all 26 pairs" in out
    bad = tmp_path / "gt.txt"
    tum.write_tum(bad, *tilted_before(tum.read_tum(BAGS / "moving_mover" / "groundtruth_tum.txt"), 12, 0.1))
    assert main(["gtcheck", str(BAGS / "moving_mover" / "bag"), "--gt", str(bad)]) == 1
    out = capsys.readouterr().out
    assert "confirmed from frame 12" in out and out.count("  NO") == 3
    assert main(["gtcheck", str(BAGS / "planar" / "bag"), "--gap", "0"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "epi-vo: error: ground-truth check: gap must be at least 1 frame, not 0"
    assert main(["gtcheck", str(tmp_path)]) == 2
    assert "no --gt given and no" in capsys.readouterr().err


def test_the_check_needs_two_poses() -> None:
    with pytest.raises(EpiVoError, match="fewer than two ground-truth poses"):
        check_ground_truth(BAGS / "planar" / "bag", (np.zeros(1), np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]])))


def test_benchmark_prints_the_verdict_and_the_nees_from_the_confirmed_frame() -> None:
    good = check_ground_truth(BAGS / "planar" / "bag", tum.read_tum(BAGS / "planar" / "groundtruth_tum.txt"))
    row = BenchRow("kitti", "epi_vo", 51, 100.0, 0.1, 0.01, 0.3, 10.0, 50, 40.0, gt_checked_from=12,
                   nees_pos_checked=34.57, nees_pos_checked_inside_percent=2.6, nees_rot_checked=1.48,
                   nees_rot_checked_inside_percent=100.0)
    text = format_checks([("planar", good, ""), ("kitti", good, ""), ("x", None, "no camera_info")], [row])
    lines = text.splitlines()
    assert lines[1].startswith("  planar: ground truth agrees with the images at all 14 pairs")
    assert lines[3] == ("    epi_vo from frame 12 (anchored there): NEES pos 34.57 (2.6 % in 3σ), rot 1.48 "
                        "(100.0 %)")
    assert lines[4] == "  x: not checked: no camera_info"


def test_benchmark_row_gets_the_nees_from_the_confirmed_frame() -> None:
    """A check that found the ground truth contradicted before frame 12: the row's ``nees_*_checked`` are the
    NEES from frame 12's stamp on (anchored there); a check that agrees everywhere adds nothing."""
    from epi_vo.core.config import VoConfig
    from epi_vo.tools.benchmark import bench_epi_vo
    from epi_vo.tools.gt_check import GroundTruthCheck, PairCheck

    d = BAGS / "general_motion"
    stamps = tum.read_tum(d / "groundtruth_tum.txt")[0]
    ns = [round(s * 1e9) for s in stamps]
    bad = PairCheck(8, 12, ns[8], ns[12], 500, 2.0, 0.05, 0.4, 0.3, "epipolar", False)
    good = PairCheck(12, 16, ns[12], ns[16], 500, 0.05, 0.05, 0.01, 0.3, "epipolar", True)
    row = bench_epi_vo("general_motion", d / "bag", d / "groundtruth_tum.txt", exact(),  # an exact camera
                       checked=GroundTruthCheck([bad, good], 12, ns[12]))
    assert row.gt_checked_from == 12
    # the NEES from the checked frame given above (2.84 / 3.37), not over all frames (1.65 / 5.27)
    assert row.nees_pos_checked == pytest.approx(2.84, abs=0.02)
    assert row.nees_rot_checked == pytest.approx(3.37, abs=0.02)
    assert row.nees_pos == pytest.approx(1.65, abs=0.02)
    assert row.nees_rot == pytest.approx(5.27, abs=0.01)
    plain = bench_epi_vo("general_motion", d / "bag", d / "groundtruth_tum.txt", VoConfig(),
                         checked=GroundTruthCheck([good], 0, ns[0]))
    assert plain.gt_checked_from is None and np.isnan(plain.nees_rot_checked)


def _shifted(gt: tuple[np.ndarray, np.ndarray, np.ndarray], seconds: float) -> tuple[np.ndarray, ...]:
    return gt[0] + seconds, gt[1], gt[2]


@pytest.mark.parametrize(("change", "said"), ids=["shifted", "two poses", "zero quaternion"], argvalues=[
    (lambda gt: _shifted(gt, 1000.0), "no image of {bag} is within 0.01 s of a ground-truth pose (images "
                                      "1000.000-1003.733 s, ground truth 2000.000-2003.933 s)"),
    (lambda gt: tuple(a[:2] for a in gt), "no two frames 4 apart both have a ground-truth pose and a decodable "
                                          "image (1 of the 15 frames looked at, every 4th, have)"),
    (lambda gt: (gt[0], gt[1], np.zeros_like(gt[2])),
     "the ground-truth pose at 1000.000000 s has a zero quaternion (no orientation)"),
])
def test_unusable_ground_truth_says_why_and_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                    change: object, said: str) -> None:
    """Ground truth that cannot judge anything is never "agrees" or "not judged" with exit 0: one line says
    what is wrong with it (time ranges that do not meet, too few poses, no orientation)."""
    bag = BAGS / "planar" / "bag"
    gt_file = tmp_path / "gt.txt"
    tum.write_tum(gt_file, *change(tum.read_tum(BAGS / "planar" / "groundtruth_tum.txt")))  # type: ignore[operator]
    assert main(["gtcheck", str(bag), "--gt", str(gt_file)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"epi-vo: error: ground-truth check: {said.format(bag=bag)}"


def test_ground_truth_in_any_order_is_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    s, p, q = tum.read_tum(BAGS / "planar" / "groundtruth_tum.txt")
    gt_file = tmp_path / "gt.txt"
    tum.write_tum(gt_file, s[::-1], p[::-1], q[::-1])
    assert main(["gtcheck", str(BAGS / "planar" / "bag"), "--gt", str(gt_file)]) == 0
    assert "agrees with the images at all 14 pairs" in capsys.readouterr().out


def test_no_pair_judged_is_no_verdict(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Pairs with too few matches to judge: the table is printed, but the exit status is not "agrees"."""
    import epi_vo.tools.gt_check as gt_check

    monkeypatch.setattr(gt_check, "MIN_MATCHES", 10**6)
    assert main(["gtcheck", str(BAGS / "planar" / "bag")]) == 2
    captured = capsys.readouterr()
    assert captured.out.count("n/a") == 14
    assert captured.err.strip() == ("epi-vo: error: ground-truth check: not judged: no pair of frames with enough "
                                    "matches")
