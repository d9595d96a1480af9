"""The camera extrinsic follows TF (epi_vo.ros.node_tf.ExtrinsicResolver.follow): a TF that arrives after the
wait ran out replaces the parameters, a mounting that moves beyond the tolerance is followed, one that does
not is kept, and TF is never looked up when the user asked for the parameters. A fake lookup stands in for
tf2_ros (not on PyPI); no DDS here (the node's behaviour is tested live in test_node_follow.py)."""

from __future__ import annotations

import math

import numpy as np

from epi_vo.core.odometry import T_base_cam_from_params
from epi_vo.ros.node_tf import MOUNTING_TOLERANCE_RAD, ExtrinsicResolver, mounting_change

CAMERA = "camera_optical_frame"
T_PARAMS = T_base_cam_from_params([0.2, 0.0, 0.45], [0.0, 0.0, 0.0])


class FakeLookup:
    """A TransformLookup whose answer the test sets (None: TF does not have it); counts the lookups."""

    def __init__(self) -> None:
        self.T: np.ndarray | None = None
        self.calls = 0

    def lookup(self, target_frame: str, source_frame: str) -> np.ndarray | None:
        assert (target_frame, source_frame) == ("base_link", CAMERA)
        self.calls += 1
        return None if self.T is None else self.T.copy()


def _pitched(deg: float) -> np.ndarray:
    return T_base_cam_from_params([0.2, 0.0, 0.45], [0.0, math.radians(deg), 0.0])


def test_a_tf_that_arrives_after_the_fallback_replaces_the_parameters() -> None:
    fake = FakeLookup()
    res = ExtrinsicResolver(fake, "base_link", 0.5, T_PARAMS, "camera_xyz parameters")
    assert res.poll(CAMERA, 0.0) is None
    first = res.poll(CAMERA, 0.6)
    assert first is not None and first.source == "parameters" and first.warn
    assert "TF is still looked up at every frame" in first.text
    for _ in range(3):  # no TF yet: the parameters stand
        assert res.follow() is None
    fake.T = _pitched(15.0)
    switched = res.follow()
    assert switched is not None and switched.source == "tf" and not switched.warn
    np.testing.assert_allclose(switched.T_base_cam, _pitched(15.0))
    assert switched.text == ("camera extrinsic from TF base_link <- camera_optical_frame (xyz 0.200 0.000 0.450 m); "
                             "it arrived after the wait, replacing the camera_xyz parameters")
    assert switched.record() == {"source": "tf", "xyz": [0.2, 0.0, 0.45], "detail": switched.text}
    assert res.follow() is None  # the same TF: nothing to switch
    assert fake.calls == 2 + 3 + 2


def test_a_moving_mounting_is_followed_beyond_the_tolerance_only() -> None:
    fake = FakeLookup()
    fake.T = _pitched(15.0)
    res = ExtrinsicResolver(fake, "base_link", 2.0, T_PARAMS, "camera_xyz parameters")
    start = res.poll(CAMERA, 0.0)
    assert start is not None and start.source == "tf"
    fake.T = _pitched(15.0 + math.degrees(0.5 * MOUNTING_TOLERANCE_RAD))  # encoder noise: the same mounting
    assert res.follow() is None
    fake.T = _pitched(20.0)
    moved = res.follow()
    assert moved is not None and moved.source == "tf"
    np.testing.assert_allclose(moved.T_base_cam, _pitched(20.0))
    assert moved.text.endswith("; the camera moved on base by 0.0 mm, 5.00 deg")
    fake.T = None  # TF lost the transform (a publisher gone): the last one known stands
    assert res.follow() is None
    fake.T = _pitched(20.0)
    fake.T[0, 3] += 0.01
    shifted = res.follow()
    assert shifted is not None and shifted.text.endswith("; the camera moved on base by 10.0 mm, 0.00 deg")


def test_tf_is_not_followed_when_the_parameters_were_asked_for() -> None:
    fake = FakeLookup()
    fake.T = _pitched(15.0)
    res = ExtrinsicResolver(fake, "base_link", 0.0, T_PARAMS, "camera_xyz parameters")
    chosen = res.poll(CAMERA, 0.0)
    assert chosen is not None and chosen.source == "parameters"
    assert res.follow() is None and fake.calls == 0
    no_frame = ExtrinsicResolver(fake, "base_link", 2.0, T_PARAMS, "camera_xyz parameters")
    chosen = no_frame.poll("", 0.0)
    assert chosen is not None and chosen.source == "parameters"
    assert no_frame.follow() is None and fake.calls == 0


def test_mounting_change() -> None:
    moved_m, turned_rad = mounting_change(_pitched(15.0), _pitched(18.0))
    assert moved_m == 0.0 and abs(turned_rad - math.radians(3.0)) < 1e-12
