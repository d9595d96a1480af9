"""The one frame handler of both front doors (epi_vo.runner.frames): what a frame yields (skipped, rejected,
processed), the look-ahead giving the same records, a runtime change anchored at the last pose, and the
outputs each frame gives (epi_vo.runner.outputs)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from epi_vo.core.camera import CameraModel
from epi_vo.core.config import VoConfig
from epi_vo.core.decisions import Decision
from epi_vo.core.frame import FrameResult, TrackingState
from epi_vo.core.odometry import UNKNOWN_TWIST_VARIANCE
from epi_vo.io import bagio
from epi_vo.io.msgconv import decode_frame
from epi_vo.runner.frames import FrameHandler, FrameInput, HandledFrame
from epi_vo.runner.outputs import OutputFrames, OutputMaker

BAG = Path(__file__).resolve().parents[2] / "bags" / "general_motion" / "bag"


@pytest.fixture(scope="module")
def inputs() -> list[FrameInput]:
    with bagio.open_camera_bag(BAG) as bag:
        return [FrameInput(f.stamp_ns, f.image_msg, bag.image_is_compressed, f.camera_info_msg, f.problem)
                for f in bag.iter_frames()]


def _run(handler: FrameHandler, frames: list[FrameInput], ahead: bool) -> list[HandledFrame]:
    return [handler.handle(f, frames[i + 1] if ahead and i + 1 < len(frames) else None, "test")
            for i, f in enumerate(frames)]


def test_looking_ahead_gives_the_same_records_and_outputs(inputs: list[FrameInput]) -> None:
    """The next image decoded first and tracked into during the current frame: the same poses, covariances
    and odometry, bit for bit; the frames' timings say KLT ran ahead."""
    plain = _run(FrameHandler(), inputs[:25], ahead=False)
    ahead = _run(FrameHandler(), inputs[:25], ahead=True)
    assert sum("klt_ahead" in h.result.timings_ms for h in ahead) >= 15
    assert not any("klt_ahead" in h.result.timings_ms for h in plain)
    for a, b in zip(plain, ahead, strict=True):
        assert np.array_equal(a.result.T_w_c, b.result.T_w_c) and np.array_equal(a.result.covariance,
                                                                                  b.result.covariance)
        assert a.outputs.odometry is not None and b.outputs.odometry is not None
        assert np.array_equal(a.outputs.odometry.sample.position, b.outputs.odometry.sample.position)
    assert sum(h.result.state is TrackingState.TRACKING for h in plain) >= 15


def test_a_frame_is_skipped_rejected_or_processed_and_says_why(inputs: list[FrameInput]) -> None:
    """A message unusable whatever its pixels (a stamp that is no ROS time, a problem its source found) is
    skipped: a status, no odometry, tracking untouched. No camera_info or pixels that do not decode: rejected,
    a frame without a pose whose odometry says so. The next good frame tracks on."""
    handler = FrameHandler(frames=OutputFrames("odom", "base_link"))
    first = handler.handle(inputs[0])
    assert first.problem is None and first.outputs.odometry is not None and first.gray is not None
    bad_stamp = SimpleNamespace(**{k: getattr(inputs[1].image, k) for k in ("data", "format")},
                                header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=2_000_000_000)))
    skipped = handler.handle(dataclasses.replace(inputs[1], image=bad_stamp))
    assert skipped.result.skipped and skipped.outputs.odometry is None and not skipped.outputs.transforms
    assert "nanosec 2000000000 is not a valid ROS time" in (skipped.problem or "")
    assert skipped.outputs.status.level == 1 and "not a valid ROS time" in skipped.outputs.status.message
    said = handler.handle(dataclasses.replace(inputs[1], problem="bytes damaged", note="at offset 7"))
    assert said.result.skipped and said.problem == "bytes damaged" and "at offset 7" in said.result.reason
    no_info = handler.handle(dataclasses.replace(inputs[1], camera_info=None, no_camera_info="no camera_info here"))
    assert no_info.result.rejected and not no_info.result.has_pose and no_info.problem == "no camera_info here"
    assert no_info.outputs.odometry is not None and no_info.gray is None
    assert no_info.outputs.odometry.sample.pose_covariance[0, 0] >= VoConfig().lost_position_variance
    undecodable = handler.handle(dataclasses.replace(inputs[2], image=SimpleNamespace(
        header=inputs[2].image.header, format="jpeg", data=b"\xff\xd8 not a jpeg")))
    assert undecodable.result.rejected and undecodable.gray is None
    on = [handler.handle(f) for f in inputs[3:12]]
    assert [h.problem for h in on] == [None] * 9 and on[-1].result.has_pose
    assert Decision.TIME_JUMPED_BACK not in {d for h in on for d in h.result.decisions}


def test_in_vo_units_the_fusable_odometry_holds_the_position_and_the_vo_unit_one_moves(
        inputs: list[FrameInput]) -> None:
    """scale_source none: vo/odometry (odom -> base_link) holds the position where tracking started with the
    "unknown" variance and no linear velocity ("unknown" variance), with the orientation and angular velocity
    as estimated; TF follows it (no map -> odom in VO units); vo/odometry/vo_units carries the motion,
    between frames that exist in no TF tree, and the path and points are in its frame; the status's pose is
    vo/odometry's."""
    handler = FrameHandler(frames=OutputFrames("odom", "base_link", "map"), path_max_length=5)
    handled = _run(handler, inputs[:20], ahead=False)
    lengths = [len(h.outputs.path.stamps_ns) for h in handled if h.outputs.path is not None]
    assert lengths == [1, 2, 3, 4] + [5] * 16
    last = handled[-1].outputs
    assert last.odometry is not None and last.odometry_vo_units is not None and last.path is not None
    held, vo = last.odometry.sample, last.odometry_vo_units.sample
    assert (last.odometry.frame_id, last.odometry.child_frame_id) == ("odom", "base_link")
    assert (last.odometry_vo_units.frame_id, last.odometry_vo_units.child_frame_id) == (
        "odom_vo_units", "base_link_vo_units")
    assert last.estimate is last.odometry_vo_units
    np.testing.assert_array_equal(held.position, np.zeros(3))
    assert float(np.linalg.norm(vo.position)) > 0.5 and float(np.linalg.norm(vo.linear_velocity)) > 0.1
    var = VoConfig().lost_position_variance
    np.testing.assert_array_equal(held.pose_covariance[:3, :3], np.eye(3) * var)
    np.testing.assert_array_equal(held.pose_covariance[:3, 3:], np.zeros((3, 3)))
    np.testing.assert_array_equal(held.pose_covariance[3:, 3:], vo.pose_covariance[3:, 3:])
    assert np.max(np.diag(vo.pose_covariance)[:3]) < 1.0  # tight, in VO units
    np.testing.assert_array_equal(held.linear_velocity, np.zeros(3))
    np.testing.assert_array_equal(held.twist_covariance[:3, :3], np.eye(3) * UNKNOWN_TWIST_VARIANCE)
    np.testing.assert_array_equal(held.angular_velocity, vo.angular_velocity)
    np.testing.assert_array_equal(held.twist_covariance[3:, 3:], vo.twist_covariance[3:, 3:])
    np.testing.assert_array_equal(held.quat_xyzw, vo.quat_xyzw)
    assert [(t.parent, t.child) for t in last.transforms] == [("odom", "base_link")]
    np.testing.assert_array_equal(last.transforms[0].xyz, held.position)
    assert last.path.frame_id == "odom_vo_units"
    np.testing.assert_array_equal(last.path.positions[-1], vo.position)
    values = dict(last.status.values)
    assert values["position_frame"] == "odom -> base_link" and values["units"] == "vo"
    assert [float(v) for v in values["position"].split()] == [0.0, 0.0, 0.0]
    assert any(h.outputs.points is not None and h.outputs.points.frame_id == "odom_vo_units" for h in handled)


def _metres(result: FrameResult, at: int) -> FrameResult:
    """``result`` as a metric scale source would give it from frame ``at`` on."""
    if result.index < at:
        return result
    return dataclasses.replace(result, scale=dataclasses.replace(result.scale, metric=True))


def test_once_metres_are_established_the_odometry_is_metric_and_starts_afresh(inputs: list[FrameInput]) -> None:
    """Before metres vo/odometry holds the position; from the first metric frame on it is the pose (metres),
    TF carries map -> odom too, nothing is published in VO units, and the change of units starts the twist,
    the path and map -> odom afresh."""
    pipeline = FrameHandler().pipeline
    results = [_metres(pipeline.process(*_decoded(f)), 10) for f in inputs[:20]]
    maker = OutputMaker(OutputFrames("odom", "base_link", "map"))
    outs = [maker.outputs(r, "epi_vo", "test") for r in results]
    before, first, after = outs[9], outs[10], outs[19]
    assert before.odometry is not None and before.odometry_vo_units is not None
    np.testing.assert_array_equal(before.odometry.sample.position, np.zeros(3))
    assert first.odometry_vo_units is None and after.odometry_vo_units is None and after.odometry is not None
    assert first.odometry is not None and first.estimate is first.odometry
    # a new converter at the change: the first metric frame has no twist yet, the next one has
    np.testing.assert_array_equal(first.odometry.sample.linear_velocity, np.zeros(3))
    assert first.odometry.sample.twist_covariance[0, 0] == UNKNOWN_TWIST_VARIANCE
    assert float(np.linalg.norm(outs[11].odometry.sample.linear_velocity)) > 0.1  # type: ignore[union-attr]
    assert after.odometry.sample.pose_covariance[0, 0] < 1.0
    assert first.path is not None and first.path.frame_id == "odom" and len(first.path.stamps_ns) == 1
    assert [(t.parent, t.child) for t in after.transforms] == [("odom", "base_link"), ("map", "odom")]
    np.testing.assert_array_equal(after.transforms[0].xyz, after.odometry.sample.position)
    assert dict(after.status.values)["units"] == "m"


def _decoded(frame: FrameInput) -> tuple[np.ndarray, CameraModel, int]:
    camera = CameraModel.from_camera_info(frame.camera_info)
    return decode_frame(frame.image, frame.compressed, (camera.width, camera.height)), camera, frame.stamp_ns


def test_a_runtime_change_continues_from_the_last_pose(inputs: list[FrameInput]) -> None:
    """A new pipeline anchored at the pose the old one reached: the first frame after the change is there
    (its covariance at least the anchor's), the frame index continues, its reason says why; the map
    starts afresh."""
    handler = FrameHandler()
    before = _run(handler, inputs[:15], ahead=False)[-1].result
    handler.apply_config(dataclasses.replace(VoConfig(), max_features=150), "parameters changed (max_features=150)")
    after = [handler.handle(f) for f in inputs[15:25]]
    first = after[0].result
    assert first.index == before.index + 1 and first.reason.startswith("parameters changed (max_features=150)")
    np.testing.assert_allclose(first.T_w_c, before.T_w_c, atol=1e-12)
    assert np.all(np.diag(first.covariance) >= np.diag(before.covariance) - 1e-12)
    assert handler.cfg.max_features == 150 and handler.pipeline.cfg.max_features == 150
    moved = float(np.linalg.norm(after[-1].result.position - before.position))
    assert after[-1].result.has_pose and moved > 0.0
    assert [h.result.index for h in after] == list(range(before.index + 1, before.index + 11))


def test_an_internal_error_is_recorded_and_tracking_restarts(inputs: list[FrameInput]) -> None:
    handler = FrameHandler()
    _run(handler, inputs[:5], ahead=False)
    failed = handler.internal_error(inputs[5], RuntimeError("simulated"))
    assert failed.problem == "internal error: RuntimeError('simulated')" and not failed.result.has_pose
    nxt = handler.handle(inputs[6])
    assert "internal error in the previous frame (RuntimeError)" in nxt.result.reason
