"""The bundled ``static_mover`` and ``moving_mover`` bags: an independently moving object in view.

``static_mover``: a camera that never moves while a large textured panel sweeps across a third to a half
of the image; ``moving_mover``: a walking camera and a cart crossing its path. Read back with rosbags only
(no ROS) and checked against what bags/README.md documents, including the per-frame mover coverage file
``mover_coverage.txt`` (frame, share of the pixels on the mover, bounding box x0 y0 x1 y1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

REPO = Path(__file__).resolve().parents[2]
BAGS = REPO / "bags"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

IMAGE_TOPIC = "/camera/image_raw/compressed"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/ground_truth/pose"
WIDTH, HEIGHT = 640, 480
MAX_BAG_BYTES = 8_000_000
# name: (frames, mover name)
EXPECTED = {"static_mover": (120, "panel"), "moving_mover": (105, "cart")}


def _quat_to_matrix(x: float, y: float, z: float, w: float) -> NDArray[np.float64]:
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _se3(R: NDArray[np.float64], t: tuple[float, ...] | NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _stamp(header: object) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _stamp_text(stamp: int) -> str:
    return f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}"


@dataclass
class MoverBag:
    name: str
    root: Path
    msgtypes: dict[str, str]
    image_stamps: list[int]
    image_formats: set[str]
    jpegs: list[bytes]
    info_stamps: list[int]
    infos: list[object]
    gt_stamps: list[int]
    gt_frames: set[str]
    gt_raw: list[tuple[float, ...]]  # x y z qx qy qz qw as written
    T_c0_ci: NDArray[np.float64]  # (N, 4, 4)
    record_equals_header: bool
    record_times: list[int]
    coverage: NDArray[np.float64]  # (N, 6): frame, fraction, x0, y0, x1, y1

    @property
    def fraction(self) -> NDArray[np.float64]:
        return self.coverage[:, 1]

    @property
    def bbox(self) -> NDArray[np.float64]:
        return self.coverage[:, 2:]

    def image(self, i: int) -> NDArray[np.uint8]:
        return cv2.imdecode(np.frombuffer(self.jpegs[i], np.uint8), cv2.IMREAD_UNCHANGED)


def _read(name: str) -> MoverBag:
    root = BAGS / name
    bag_dir = root / "bag"
    if not bag_dir.is_dir():
        pytest.fail(f"{bag_dir} is missing: regenerate it with .venv/bin/python bags/make_bags.py --only {name}")
    image_stamps, info_stamps, gt_stamps, infos, poses, raw, jpegs = [], [], [], [], [], [], []
    formats, gt_frames = set(), set()
    record_equals_header, record_times = True, []
    with AnyReader([bag_dir], default_typestore=TYPESTORE) as reader:
        msgtypes = {c.topic: c.msgtype for c in reader.connections}
        for con, timestamp, data in reader.messages():
            msg = reader.deserialize(data, con.msgtype)
            stamp = _stamp(msg.header)
            record_equals_header &= stamp == timestamp
            record_times.append(timestamp)
            if con.topic == IMAGE_TOPIC:
                image_stamps.append(stamp)
                formats.add(msg.format)
                jpegs.append(bytes(msg.data))
            elif con.topic == CAMERA_INFO_TOPIC:
                info_stamps.append(stamp)
                infos.append(msg)
            elif con.topic == GROUND_TRUTH_TOPIC:
                gt_stamps.append(stamp)
                gt_frames.add(msg.header.frame_id)
                p, q = msg.pose.position, msg.pose.orientation
                raw.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
                poses.append(_se3(_quat_to_matrix(q.x, q.y, q.z, q.w), (p.x, p.y, p.z)))
    coverage = np.loadtxt(root / "mover_coverage.txt", comments="#", ndmin=2)
    return MoverBag(
        name, root, msgtypes, image_stamps, formats, jpegs, info_stamps, infos, gt_stamps, gt_frames, raw,
        np.array(poses), record_equals_header, record_times, coverage,
    )


@pytest.fixture(scope="module", params=sorted(EXPECTED))
def bag(request: pytest.FixtureRequest) -> MoverBag:
    return _read(request.param)


@pytest.fixture(scope="module")
def static_bag() -> MoverBag:
    return _read("static_mover")


@pytest.fixture(scope="module")
def moving_bag() -> MoverBag:
    return _read("moving_mover")


def _fully_in_view(bbox: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Frames whose mover bounding box touches no image border."""
    return (bbox[:, 0] > 0) & (bbox[:, 1] > 0) & (bbox[:, 2] < WIDTH - 1) & (bbox[:, 3] < HEIGHT - 1)


def _mover_pose_file(bag: MoverBag) -> NDArray[np.float64]:
    return np.loadtxt(bag.root / f"{EXPECTED[bag.name][1]}_pose_tum.txt", comments="#", ndmin=2)


# --- both bags: stream layout ----------------------------------------------------------------------------


def test_topics_types_and_record_times(bag: MoverBag) -> None:
    assert bag.msgtypes == {
        IMAGE_TOPIC: "sensor_msgs/msg/CompressedImage",
        CAMERA_INFO_TOPIC: "sensor_msgs/msg/CameraInfo",
        GROUND_TRUTH_TOPIC: "geometry_msgs/msg/PoseStamped",
    }
    assert bag.record_equals_header, "bag record time must equal the header stamp"
    assert bag.record_times == sorted(bag.record_times)


def test_frames_at_15_hz_each_with_camera_info_and_ground_truth(bag: MoverBag) -> None:
    n = EXPECTED[bag.name][0]
    assert len(bag.image_stamps) == n
    assert bag.image_stamps[0] == 1_000_000_000_000
    assert bag.image_stamps == sorted(set(bag.image_stamps))
    assert bag.info_stamps == bag.image_stamps
    assert bag.gt_stamps == bag.image_stamps
    assert np.allclose(np.diff(bag.image_stamps), 1e9 / 15, atol=1)
    assert bag.image_formats == {"jpeg"}
    assert bag.gt_frames == {"world"}
    for i in (0, n - 1):
        assert bag.image(i).shape == (HEIGHT, WIDTH)
        assert bag.image(i).dtype == np.uint8


def test_camera_info_is_the_documented_pinhole(bag: MoverBag) -> None:
    K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    for info in bag.infos:
        assert (info.width, info.height) == (WIDTH, HEIGHT)
        assert info.distortion_model == "plumb_bob"
        assert info.header.frame_id == "camera_optical_frame"
        assert np.array_equal(np.asarray(info.k).reshape(3, 3), K)
        assert not np.any(np.asarray(info.d))


def test_bag_is_small(bag: MoverBag) -> None:
    size = sum(f.stat().st_size for f in (bag.root / "bag").iterdir())
    assert size <= MAX_BAG_BYTES


def test_groundtruth_tum_file_matches_the_topic(bag: MoverBag) -> None:
    lines = [line for line in (bag.root / "groundtruth_tum.txt").read_text().splitlines() if line.strip()]
    assert lines[0].startswith("#")
    rows = [line.split() for line in lines[1:]]
    assert [row[0] for row in rows] == [_stamp_text(s) for s in bag.image_stamps]
    values = np.array([[float(v) for v in row[1:]] for row in rows])
    assert np.allclose(values, np.array(bag.gt_raw), atol=2e-9)
    assert np.all(values[:, 6] >= 0.0)


def test_ground_truth_starts_at_identity(bag: MoverBag) -> None:
    assert np.all(np.isfinite(bag.T_c0_ci))
    assert np.allclose(bag.T_c0_ci[0], np.eye(4), atol=1e-12)


# --- both bags: the coverage file ------------------------------------------------------------------------


def test_coverage_file_has_one_row_per_frame(bag: MoverBag) -> None:
    header = (bag.root / "mover_coverage.txt").read_text().splitlines()[0]
    assert header.startswith("# frame fraction x0 y0 x1 y1")
    n = len(bag.image_stamps)
    assert bag.coverage.shape == (n, 6)
    assert np.array_equal(bag.coverage[:, 0], np.arange(n))
    assert np.all((bag.fraction >= 0.0) & (bag.fraction <= 1.0))


def test_coverage_bounding_boxes_are_consistent(bag: MoverBag) -> None:
    """A box for every frame with a visible mover (inside the image, holding the mover's pixels), and
    -1 -1 -1 -1 for frames without one."""
    for fraction, (x0, y0, x1, y1) in zip(bag.fraction, bag.bbox, strict=True):
        if x0 < 0:
            assert (x0, y0, x1, y1) == (-1, -1, -1, -1)
            assert fraction < 0.001  # at most slivers of pixels less than half on the mover
            continue
        assert 0 <= x0 <= x1 <= WIDTH - 1
        assert 0 <= y0 <= y1 <= HEIGHT - 1
        box_area = (x1 - x0 + 1) * (y1 - y0 + 1)
        # the box holds the mover's pixels (up to its one-pixel soft edge), and the mover fills much of it
        assert fraction * WIDTH * HEIGHT <= box_area + 2 * (x1 - x0 + y1 - y0 + 2)
        assert fraction * WIDTH * HEIGHT >= 0.4 * box_area


def test_mover_moves_across_the_image(bag: MoverBag) -> None:
    seen = bag.bbox[:, 0] >= 0
    centre_x = 0.5 * (bag.bbox[seen, 0] + bag.bbox[seen, 2])
    assert centre_x.max() - centre_x.min() > 300.0
    # left to right, smoothly: the box centre never jumps by more than 20 px between frames
    steps = np.diff(centre_x)
    assert np.all(steps > -5.0)
    assert np.all(np.abs(steps) < 20.0)


def test_image_changes_where_the_mover_is(bag: MoverBag) -> None:
    """Between two frames the image changes inside the mover boxes: the mover is drawn where the file says."""
    a, b = 30, 60
    img_a, img_b = bag.image(a).astype(np.float64), bag.image(b).astype(np.float64)
    union = np.zeros((HEIGHT, WIDTH), bool)
    for x0, y0, x1, y1 in bag.bbox[[a, b]].astype(int):
        union[y0 : y1 + 1, x0 : x1 + 1] = True
    assert float(np.median(np.abs(img_a - img_b)[union])) > 10.0


# --- static_mover -----------------------------------------------------------------------------------------


def test_static_camera_ground_truth_is_exactly_constant(static_bag: MoverBag) -> None:
    assert all(pose == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) for pose in static_bag.gt_raw)
    assert np.array_equal(static_bag.T_c0_ci, np.broadcast_to(np.eye(4), static_bag.T_c0_ci.shape))


def test_static_mover_covers_a_quarter_of_most_frames(static_bag: MoverBag) -> None:
    fraction = static_bag.fraction
    assert np.all(fraction > 0.15)  # always in view
    assert np.mean(fraction >= 0.25) >= 0.80
    assert fraction.max() <= 0.5  # the static background stays the larger part of every frame


def test_static_background_does_not_change(static_bag: MoverBag) -> None:
    """Outside the mover (its boxes widened by 3 px for the optics), two frames differ only by the sensor
    noise and JPEG: nothing but the mover moves."""
    a, b = 0, len(static_bag.image_stamps) - 1
    mask = np.ones((HEIGHT, WIDTH), bool)
    for x0, y0, x1, y1 in static_bag.bbox[[a, b]].astype(int):
        mask[max(y0 - 3, 0) : y1 + 4, max(x0 - 3, 0) : x1 + 4] = False
    assert mask.mean() > 0.15
    diff = np.abs(static_bag.image(a).astype(np.float64) - static_bag.image(b).astype(np.float64))[mask]
    assert float(np.mean(diff)) < 3.0
    assert float(np.percentile(diff, 99)) < 10.0


def test_static_mover_pose_is_plausible(static_bag: MoverBag) -> None:
    """The panel stays 3-4.5 m in front of the camera and moves at 0.5-1 m/s, mostly sideways."""
    poses = _mover_pose_file(static_bag)
    assert [_stamp_text(s) for s in static_bag.image_stamps] == [f"{t:.9f}" for t in poses[:, 0]]
    xyz = poses[:, 1:4]
    assert np.all((xyz[:, 2] > 3.0) & (xyz[:, 2] < 4.5))
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=1) * 15.0
    assert np.all((speed > 0.5) & (speed < 1.0))
    assert xyz[-1, 0] - xyz[0, 0] > 4.0


# --- moving_mover -----------------------------------------------------------------------------------------


def test_moving_camera_walks(moving_bag: MoverBag) -> None:
    t = moving_bag.T_c0_ci[:, :3, 3]
    steps = np.linalg.norm(np.diff(t, axis=0), axis=1)
    assert np.all(steps * 15.0 > 0.7)
    assert np.all(steps * 15.0 < 1.6)
    assert 6.0 < steps.sum() < 9.0
    cosines = np.clip((np.trace(moving_bag.T_c0_ci[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    angles = np.degrees(np.arccos(cosines))
    assert 1.0 < max(angles) < 10.0


def test_moving_mover_coverage_while_visible(moving_bag: MoverBag) -> None:
    fraction, bbox = moving_bag.fraction, moving_bag.bbox
    visible = bbox[:, 0] >= 0
    assert visible.mean() >= 0.5
    inside = _fully_in_view(bbox)
    assert inside.sum() >= 20
    assert np.all((fraction[inside] >= 0.24) & (fraction[inside] <= 0.40))
    assert fraction.max() <= 0.40


def test_moving_mover_pose_is_plausible(moving_bag: MoverBag) -> None:
    """The cart crosses the camera's path from left to right, 3.4-4.6 m ahead, at 1-2 m/s, in front of
    the camera at mid sequence."""
    poses = _mover_pose_file(moving_bag)
    assert len(poses) == len(moving_bag.image_stamps)
    xyz_c0 = poses[:, 1:4]
    speed = np.linalg.norm(np.diff(xyz_c0, axis=0), axis=1) * 15.0
    assert np.all((speed > 1.0) & (speed < 2.0))
    # the cart in each frame's camera: ahead, and from left to right
    in_cam = []
    for T_c0_ci, p in zip(moving_bag.T_c0_ci, xyz_c0, strict=True):
        R, t = T_c0_ci[:3, :3], T_c0_ci[:3, 3]
        in_cam.append(R.T @ (p - t))
    in_cam = np.array(in_cam)
    assert np.all(in_cam[:, 2] > 3.0)
    assert in_cam[0, 0] < -3.0 < 3.0 < in_cam[-1, 0]


# --- the generator (needs scikit-image, bags/requirements.txt) --------------------------------------------------


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_spec_is_deterministic_and_matches_the_bag(make_bags: object, name: str) -> None:
    spec, again = make_bags.SPECS[name](), make_bags.SPECS[name]()
    assert np.array_equal(spec.T_w_c, again.T_w_c)
    assert spec.quads == again.quads
    assert [m.name for m in spec.movers] == [EXPECTED[name][1]]
    assert np.array_equal(spec.movers[0].T_w_o, again.movers[0].T_w_o)
    assert len(spec.T_w_c) == EXPECTED[name][0]
    assert np.allclose(make_bags.poses_relative_to_first(spec.T_w_c), _read(name).T_c0_ci, atol=1e-12)
    # the mover is kept 1.5 m from the camera, the static scene too
    assert make_bags.mover_clearance_m(spec) >= 1.5
    assert make_bags.min_clearance_m(spec.quads, spec.T_w_c) >= 1.5


def test_static_spec_camera_never_moves(make_bags: object) -> None:
    spec = make_bags.static_mover_spec()
    assert all(np.array_equal(T, spec.T_w_c[0]) for T in spec.T_w_c)
    assert np.array_equal(spec.T_w_c[0][:3, :3], np.eye(3))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_rendered_coverage_matches_the_file(make_bags: object, name: str) -> None:
    """Re-render two frames: the mover's share of the pixels and its box are those in the file."""
    spec = make_bags.SPECS[name]()
    coverage = _read(name).coverage
    renderer = make_bags.Renderer(spec.quads, spec.camera)
    for i in (0, len(spec.T_w_c) // 2):
        result = renderer.render_ideal(spec.T_w_c[i], spec.moving_quads_at(i))
        fraction, box = make_bags.mover_stats(result.mover_coverage)
        assert fraction == pytest.approx(coverage[i, 1], abs=2e-6)
        assert box == tuple(int(v) for v in coverage[i, 2:])
        assert float(result.coverage.min()) == 1.0


def test_moving_quads_are_z_buffered_against_the_scene(make_bags: object) -> None:
    """A mover behind a static wall is hidden; in front of it, it is drawn and counted."""
    camera = make_bags.make_camera()
    wall = make_bags.wall_quad((0.0, 0.0, 5.0), (0, 0, -1), 20.0, 20.0, "brick")
    panel = make_bags.wall_quad((0.0, 0.0, 0.0), (0, 0, -1), 1.0, 1.0, make_bags.MOVER_TEXTURE)
    renderer = make_bags.Renderer((wall,), camera)
    for z, expected_visible in ((3.0, True), (7.0, False)):
        moved = make_bags.transform_quad(panel, make_bags.se3(np.eye(3), (0.0, 0.0, z)))
        result = renderer.render_ideal(np.eye(4), (moved,))
        fraction, _ = make_bags.mover_stats(result.mover_coverage)
        if expected_visible:
            assert fraction == pytest.approx((500.0 / z) ** 2 / (WIDTH * HEIGHT), rel=0.02)
        else:
            assert fraction == 0.0
    assert make_bags.Renderer((wall,), camera).render_ideal(np.eye(4)).mover_coverage is None
