"""Tests for epi_vo.io.bagio: camera bag reading, TUM files and the MCAP output bag.

Test bags are written by fixtures into tmp_path with rosbags' Writer (MCAP and sqlite3 storage).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from epi_vo.core.diagnostics import DiagnosticLevel, DiagnosticStatusRecord
from epi_vo.core.errors import BagError
from epi_vo.io.bag_topics import is_ground_truth_name, recorded_topic_name
from epi_vo.io.bagio import BagFrame, open_camera_bag
from epi_vo.io.msgconv import image_to_gray, point_cloud2_fields, read_points_xyz
from epi_vo.io.outbag import OutputBag
from epi_vo.io.trajectory import StampedPoses
from epi_vo.io.tum import read_tum, write_tum

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
STRING = "std_msgs/msg/String"

STORAGES = [StoragePlugin.MCAP, StoragePlugin.SQLITE3]


# --- message and bag builders --------------------------------------------------------------------


def _header(stamp_ns: int, frame_id: str = "cam") -> object:
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def _image(stamp_ns: int, value: int) -> object:
    """4x6 mono8 image filled with ``value``."""
    return T[IMAGE](
        header=_header(stamp_ns),
        height=4,
        width=6,
        encoding="mono8",
        is_bigendian=0,
        step=6,
        data=np.full(24, value, dtype=np.uint8),
    )


def _compressed(stamp_ns: int) -> object:
    return T[COMPRESSED](header=_header(stamp_ns), format="jpeg", data=np.arange(5, dtype=np.uint8))


def _camera_info(stamp_ns: int, fx: float) -> object:
    """CameraInfo whose fx identifies it."""
    k = np.array([fx, 0.0, 3.0, 0.0, fx, 2.0, 0.0, 0.0, 1.0])
    return T[CAMERA_INFO](
        header=_header(stamp_ns),
        height=4,
        width=6,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=k,
        r=np.eye(3).reshape(-1),
        p=np.hstack([k.reshape(3, 3), np.zeros((3, 1))]).reshape(-1),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


def _pose(xyz: tuple[float, float, float], quat_xyzw: tuple[float, float, float, float]) -> object:
    return T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](
            x=quat_xyzw[0], y=quat_xyzw[1], z=quat_xyzw[2], w=quat_xyzw[3]
        ),
    )


def _pose_stamped(stamp_ns: int, xyz: tuple, quat_xyzw: tuple) -> object:
    return T[POSE_STAMPED](header=_header(stamp_ns, "world"), pose=_pose(xyz, quat_xyzw))


def _odometry(stamp_ns: int, xyz: tuple, quat_xyzw: tuple) -> object:
    zero3 = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T[ODOMETRY](
        header=_header(stamp_ns, "map"),
        child_frame_id="body",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose(xyz, quat_xyzw), covariance=np.zeros(36)
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero3, angular=zero3), covariance=np.zeros(36)
        ),
    )


@dataclass(frozen=True)
class Record:
    topic: str
    msgtype: str
    log_time_ns: int
    msg: object | None  # None: declare the topic, write no message


def write_bag(
    path: Path, records: list[Record], storage: StoragePlugin = StoragePlugin.MCAP
) -> Path:
    """Write a rosbag2 directory at ``path`` with ``records`` in list order."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        connections = {}
        for record in records:
            if record.topic not in connections:
                connections[record.topic] = writer.add_connection(
                    record.topic, record.msgtype, typestore=TS
                )
            if record.msg is not None:
                writer.write(
                    connections[record.topic],
                    record.log_time_ns,
                    TS.serialize_cdr(record.msg, record.msgtype),
                )
    return path


def _camera_records(
    image_topic: str = "/cam/image_raw",
    info_topic: str = "/cam/camera_info",
    frames: int = 3,
) -> list[Record]:
    records = []
    for i in range(frames):
        stamp_ns = (i + 1) * 10**8
        records.append(Record(info_topic, CAMERA_INFO, stamp_ns, _camera_info(stamp_ns, 500.0 + i)))
        records.append(Record(image_topic, IMAGE, stamp_ns, _image(stamp_ns, 10 * i)))
    return records


@pytest.fixture(params=STORAGES, ids=lambda x: x.name.lower())
def camera_bag_path(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    """Image + camera_info + PoseStamped ground truth + an unrelated String topic."""
    records = _camera_records()
    records += [Record("/rosout_text", STRING, 1, T[STRING](data="hello"))]
    records += [
        Record("/gt/pose", POSE_STAMPED, s, _pose_stamped(s, (s * 1e-9, 0.0, 0.0), (0, 0, 0, 1)))
        for s in (3 * 10**8, 10**8, 2 * 10**8)  # recorded out of stamp order
    ]
    return write_bag(tmp_path / "bag", records, request.param)


# --- opening and topic discovery ------------------------------------------------------------------


def test_auto_discovery_and_frames(camera_bag_path: Path) -> None:
    with open_camera_bag(camera_bag_path) as bag:
        assert bag.image_topic == "/cam/image_raw"
        assert bag.camera_info_topic == "/cam/camera_info"
        assert bag.gt_topic == "/gt/pose"
        assert bag.image_is_compressed is False
        assert bag.frame_count == 3
        frames = list(bag.iter_frames())
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.stamp_ns for f in frames] == [10**8, 2 * 10**8, 3 * 10**8]
    assert [f.camera_info_msg.k[0] for f in frames] == [500.0, 501.0, 502.0]
    for i, frame in enumerate(frames):
        assert isinstance(frame, BagFrame)
        np.testing.assert_array_equal(image_to_gray(frame.image_msg), np.full((4, 6), 10 * i))


def test_compressed_image_topic(tmp_path: Path) -> None:
    records = [
        Record("/cam/image_raw/compressed", COMPRESSED, 5, _compressed(5)),
        Record("/cam/camera_info", CAMERA_INFO, 5, _camera_info(5, 400.0)),
    ]
    with open_camera_bag(write_bag(tmp_path / "bag", records)) as bag:
        assert bag.image_is_compressed is True
        assert bag.gt_topic is None
        (frame,) = bag.iter_frames()
    assert frame.image_msg.format == "jpeg"
    assert frame.camera_info_msg.k[0] == 400.0


def test_bare_mcap_file(tmp_path: Path) -> None:
    bag_dir = write_bag(tmp_path / "bag", _camera_records(frames=2))
    with open_camera_bag(bag_dir / "bag.mcap") as bag:
        assert bag.frame_count == 2
        assert [f.stamp_ns for f in bag.iter_frames()] == [10**8, 2 * 10**8]


def test_bare_db3_file(tmp_path: Path) -> None:
    bag_dir = write_bag(tmp_path / "bag", _camera_records(frames=2), StoragePlugin.SQLITE3)
    with open_camera_bag(bag_dir / "bag.db3") as bag:
        assert len(list(bag.iter_frames())) == 2


def test_ambiguous_image_topics(tmp_path: Path) -> None:
    records = _camera_records("/cam0/image_raw", "/cam0/camera_info")
    records += _camera_records("/cam1/image_raw", "/cam1/camera_info")
    path = write_bag(tmp_path / "bag", records)
    with pytest.raises(
        BagError,
        match=r"several sensor_msgs/Image or CompressedImage topics: /cam0/image_raw, "
        r"/cam1/image_raw; choose one with --image-topic",
    ):
        open_camera_bag(path)
    # Choosing the image topic also settles camera_info: the one in the same namespace.
    with open_camera_bag(path, image_topic="/cam1/image_raw") as bag:
        assert bag.camera_info_topic == "/cam1/camera_info"


def test_ambiguous_camera_info_topics(tmp_path: Path) -> None:
    records = _camera_records("/camera/image", "/left/camera_info")
    records += [Record("/right/camera_info", CAMERA_INFO, 1, _camera_info(1, 9.0))]
    path = write_bag(tmp_path / "bag", records)
    with pytest.raises(
        BagError,
        match=r"several sensor_msgs/CameraInfo topics: /left/camera_info, /right/camera_info; "
        r"choose one with --camera-info-topic",
    ):
        open_camera_bag(path)
    with open_camera_bag(path, camera_info_topic="/right/camera_info") as bag:
        assert bag.camera_info_topic == "/right/camera_info"


def test_ambiguous_ground_truth_topics(tmp_path: Path) -> None:
    records = _camera_records()
    records += [Record("/gt/pose", POSE_STAMPED, 1, _pose_stamped(1, (0, 0, 0), (0, 0, 0, 1)))]
    records += [Record("/gt/odom", ODOMETRY, 1, _odometry(1, (0, 0, 0), (0, 0, 0, 1)))]
    path = write_bag(tmp_path / "bag", records)
    with pytest.raises(BagError, match="/gt/odom, /gt/pose; choose one with --gt-topic"):
        open_camera_bag(path)
    with open_camera_bag(path, gt_topic="/gt/odom") as bag:
        assert bag.gt_topic == "/gt/odom"


def test_explicit_topic_missing_lists_topics(camera_bag_path: Path) -> None:
    with pytest.raises(
        BagError,
        match=r"--image-topic '/nope' is not in the bag; topics: .*"
        r"/cam/camera_info \(sensor_msgs/msg/CameraInfo\).*"
        r"/cam/image_raw \(sensor_msgs/msg/Image\)",
    ):
        open_camera_bag(camera_bag_path, image_topic="/nope")
    with pytest.raises(BagError, match="--gt-topic '/nope' is not in the bag"):
        open_camera_bag(camera_bag_path, gt_topic="/nope")


def test_explicit_topic_of_wrong_type(camera_bag_path: Path) -> None:
    with pytest.raises(
        BagError,
        match=r"--camera-info-topic '/cam/image_raw' has type sensor_msgs/msg/Image, "
        r"expected sensor_msgs/CameraInfo",
    ):
        open_camera_bag(camera_bag_path, camera_info_topic="/cam/image_raw")


def test_no_image_topic(tmp_path: Path) -> None:
    records = [Record("/cam/camera_info", CAMERA_INFO, 1, _camera_info(1, 1.0))]
    with pytest.raises(
        BagError,
        match=r"bag has no sensor_msgs/Image or CompressedImage topic; "
        r"topics: /cam/camera_info \(sensor_msgs/msg/CameraInfo\)",
    ):
        open_camera_bag(write_bag(tmp_path / "bag", records))


def test_no_camera_info_topic(tmp_path: Path) -> None:
    records = [Record("/cam/image_raw", IMAGE, 1, _image(1, 0))]
    with pytest.raises(
        BagError, match="bag has no sensor_msgs/CameraInfo topic; topics: /cam/image_raw"
    ):
        open_camera_bag(write_bag(tmp_path / "bag", records))


def test_image_topic_without_messages(tmp_path: Path) -> None:
    records = [
        Record("/cam/image_raw", IMAGE, 0, None),
        Record("/cam/camera_info", CAMERA_INFO, 1, _camera_info(1, 1.0)),
    ]
    with pytest.raises(BagError, match=r"image topic /cam/image_raw in bag .* has no messages"):
        open_camera_bag(write_bag(tmp_path / "bag", records))


# --- bad paths and files --------------------------------------------------------------------------


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"bag not found: .*nothing_here"):
        open_camera_bag(tmp_path / "nothing_here")


@pytest.mark.parametrize("storage", STORAGES, ids=lambda x: x.name.lower())
def test_empty_bag(tmp_path: Path, storage: StoragePlugin) -> None:
    path = write_bag(tmp_path / "bag", [], storage)
    with pytest.raises(BagError, match=r"bag .* is empty \(no messages\)"):
        open_camera_bag(path)


def test_truncated_mcap(tmp_path: Path) -> None:
    bag_dir = write_bag(tmp_path / "bag", _camera_records(frames=20))
    data = (bag_dir / "bag.mcap").read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError, match=r"cannot open bag .*truncated\.mcap: .+") as info:
        open_camera_bag(truncated)
    assert "\n" not in str(info.value)


def test_not_a_bag_file(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    with pytest.raises(BagError, match=r"is not a rosbag2 bag: expected a bag directory, a \.mcap"):
        open_camera_bag(path)
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"\x00" * 100)
    with pytest.raises(BagError, match=r"cannot open bag .*garbage\.mcap"):
        open_camera_bag(garbage)


def test_directory_without_metadata_points_to_files(tmp_path: Path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "output.mcap").write_bytes(b"")
    with pytest.raises(
        BagError, match=r"directory without metadata\.yaml, not a rosbag2 bag; .*: output\.mcap"
    ):
        open_camera_bag(tmp_path / "out")


# --- camera_info association ----------------------------------------------------------------------


def _association_bag(tmp_path: Path, info_stamps_ns: list[int], image_stamps_ns: list[int]) -> Path:
    """camera_info with fx = its stamp; log times follow list order (not stamp order)."""
    records = [Record("/cam/camera_info", CAMERA_INFO, 0, None)]
    records += [
        Record("/cam/camera_info", CAMERA_INFO, 1000 + i, _camera_info(s, float(s)))
        for i, s in enumerate(info_stamps_ns)
    ]
    records += [
        Record("/cam/image_raw", IMAGE, 2000 + i, _image(s, 0))
        for i, s in enumerate(image_stamps_ns)
    ]
    return write_bag(tmp_path / "bag", records)


def test_camera_info_association(tmp_path: Path) -> None:
    # Images at 50 (before any info: earliest), 200 (exact), 250 (latest before), 400 (latest).
    path = _association_bag(tmp_path, [300, 100, 200], [50, 200, 250, 400])
    with open_camera_bag(path) as bag:
        chosen = {f.stamp_ns: f.camera_info_msg.k[0] for f in bag.iter_frames()}
    assert chosen == {50: 100.0, 200: 200.0, 250: 200.0, 400: 300.0}


def test_camera_info_association_prefers_exact_stamp(tmp_path: Path) -> None:
    path = _association_bag(tmp_path, [100, 199, 200, 201], [200])
    with open_camera_bag(path) as bag:
        (frame,) = bag.iter_frames()
    assert frame.camera_info_msg.k[0] == 200.0


def test_camera_info_topic_without_messages(tmp_path: Path) -> None:
    path = _association_bag(tmp_path, [], [10, 20])
    with open_camera_bag(path) as bag:
        assert [f.camera_info_msg for f in bag.iter_frames()] == [None, None]


# --- ground truth ---------------------------------------------------------------------------------


def test_ground_truth_pose_stamped_sorted_by_stamp(camera_bag_path: Path) -> None:
    with open_camera_bag(camera_bag_path) as bag:
        gt = bag.read_ground_truth()
    assert gt is not None
    assert gt.topic == "/gt/pose"
    assert gt.frame_id == "world"
    np.testing.assert_array_equal(gt.stamps_ns, [10**8, 2 * 10**8, 3 * 10**8])
    np.testing.assert_allclose(gt.positions, [[0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]])
    np.testing.assert_array_equal(gt.quats_xyzw, np.tile([0.0, 0.0, 0.0, 1.0], (3, 1)))
    assert not gt.positions.flags.writeable


def test_ground_truth_odometry(tmp_path: Path) -> None:
    records = _camera_records()
    records += [Record("/odom", ODOMETRY, 7, _odometry(7, (1.0, 2.0, 3.0), (0.0, 0.6, 0.0, 0.8)))]
    with open_camera_bag(write_bag(tmp_path / "bag", records), gt_topic="/odom") as bag:
        gt = bag.read_ground_truth()
    assert gt is not None
    assert gt.frame_id == "map"
    np.testing.assert_array_equal(gt.stamps_ns, [7])
    np.testing.assert_array_equal(gt.positions, [[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(gt.quats_xyzw, [[0.0, 0.6, 0.0, 0.8]])


def test_ground_truth_is_only_a_topic_named_so(tmp_path: Path) -> None:
    """An Odometry / PoseStamped topic is ground truth only when named so or chosen: a robot's own odometry
    (/wheel/odom, /odom) or a sensor's pose is not taken for it; the wheel odometry topic (the scale source)
    never, not even when chosen; no_ground_truth takes none."""
    records = _camera_records()
    records += [Record("/wheel/odom", ODOMETRY, 7, _odometry(7, (1.0, 2.0, 3.0), (0, 0, 0, 1)))]
    records += [Record("/camera/pose", POSE_STAMPED, 7, _pose_stamped(7, (0, 0, 0), (0, 0, 0, 1)))]
    path = write_bag(tmp_path / "bag", records)
    with open_camera_bag(path) as bag:
        assert bag.gt_topic is None and bag.read_ground_truth() is None
    with open_camera_bag(path, gt_topic="/camera/pose") as bag:
        assert bag.gt_topic == "/camera/pose"
    with pytest.raises(BagError, match="'/wheel/odom' is the wheel odometry topic, the scale source"):
        open_camera_bag(path, gt_topic="/wheel/odom", wheel_topic="/wheel/odom")
    records += [Record("/mocap/pose_gt", POSE_STAMPED, 7, _pose_stamped(7, (0, 0, 0), (0, 0, 0, 1)))]
    path = write_bag(tmp_path / "bag2", records)
    with open_camera_bag(path) as bag:
        assert bag.gt_topic == "/mocap/pose_gt"
    with open_camera_bag(path, no_ground_truth=True) as bag:
        assert bag.gt_topic is None


@pytest.mark.parametrize(("topic", "named"), [
    ("/ground_truth/pose", True), ("/gt/odom", True), ("/mocap/pose_gt", True), ("/GroundTruth", True),
    ("/robot/ground-truth/odom", True), ("/wheel/odom", False), ("/odom", False), ("/vicon/pose", False),
    ("/lgtm/pose", False), ("/ground/pose", False), ("/truth", False)])
def test_ground_truth_names(topic: str, named: bool) -> None:
    assert is_ground_truth_name(topic) is named


@pytest.mark.parametrize(("name", "recorded"), [
    ("odom", "/odom"), ("wheel/odom", "/wheel/odom"), ("/robot1/odom", "/robot1/odom"), ("~/odom", "/vo_node/odom"),
    ("~", "/vo_node")])
def test_a_node_topic_parameter_is_found_in_a_bag_as_the_root_namespace_resolves_it(name: str, recorded: str) -> None:
    assert recorded_topic_name(name) == recorded


def test_no_ground_truth(tmp_path: Path) -> None:
    with open_camera_bag(write_bag(tmp_path / "bag", _camera_records())) as bag:
        assert bag.gt_topic is None
        assert bag.read_ground_truth() is None


def test_closed_bag_raises(camera_bag_path: Path) -> None:
    bag = open_camera_bag(camera_bag_path)
    bag.close()
    bag.close()  # idempotent
    with pytest.raises(BagError, match="is closed"):
        next(bag.iter_frames())


# --- TUM files ------------------------------------------------------------------------------------


def test_tum_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    stamps_s = 1_700_000_000.0 + np.cumsum(rng.uniform(0.01, 0.1, size=20))
    positions = rng.normal(scale=100.0, size=(20, 3))
    quats_xyzw = rng.normal(size=(20, 4))
    quats_xyzw /= np.linalg.norm(quats_xyzw, axis=1, keepdims=True)
    path = tmp_path / "traj.tum"
    write_tum(path, stamps_s, positions, quats_xyzw)
    assert path.read_text().startswith("# timestamp tx ty tz qx qy qz qw\n")
    stamps_back, positions_back, quats_back = read_tum(path)
    np.testing.assert_array_equal(stamps_back, stamps_s)
    np.testing.assert_array_equal(positions_back, positions)
    np.testing.assert_array_equal(quats_back, quats_xyzw)


def test_read_tum_skips_comments_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "traj.txt"
    path.write_text("# comment\n\n1.5 1 2 3 0 0 0 1\n  # indented comment\n2.5 4 5 6 0 0 1 0\n")
    poses = read_tum(path)
    assert isinstance(poses, StampedPoses)  # named fields, and unpacks as (stamps, positions, quaternions)
    np.testing.assert_array_equal(poses.stamps_s, [1.5, 2.5])
    np.testing.assert_array_equal(poses.positions_xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(poses.quats_xyzw, [[0, 0, 0, 1], [0, 0, 1, 0]])


def test_read_tum_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.txt"
    path.write_text("# nothing\n")
    stamps_s, positions, quats_xyzw = read_tum(path)
    assert stamps_s.shape == (0,)
    assert positions.shape == (0, 3)
    assert quats_xyzw.shape == (0, 4)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1 2 3 4 5 6 7 8\n1 2 3\n", r"traj.txt:2: expected 8 values .*, got 3"),
        ("# header\n1 2 3 4 5 6 7 x\n", r"traj.txt:2: not a number in '1 2 3 4 5 6 7 x'"),
        ("\n\n1 2 3 nan 5 6 7 8\n", r"traj.txt:3: non-finite value"),
    ],
)
def test_read_tum_malformed(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "traj.txt"
    path.write_text(text)
    with pytest.raises(BagError, match=match):
        read_tum(path)


def test_read_tum_missing_file(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"cannot read TUM file .*missing\.txt"):
        read_tum(tmp_path / "missing.txt")


def test_write_tum_shape_mismatch(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"quats_xyzw has shape \(2, 3\), expected \(2, 4\)"):
        write_tum(tmp_path / "t.txt", [0.0, 1.0], np.zeros((2, 3)), np.zeros((2, 3)))


# --- OutputBag ------------------------------------------------------------------------------------


def _read_back(path: Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log time ns, message)] read with rosbags' AnyReader."""
    messages: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([path]) as reader:
        for connection, log_time_ns, rawdata in reader.messages():
            messages.setdefault(connection.topic, []).append(
                (log_time_ns, reader.deserialize(rawdata, connection.msgtype))
            )
    return messages


def _write_everything(out: OutputBag, stamp_ns: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(stamp_ns)
    values = {
        "position": rng.normal(size=3),
        "quat_xyzw": np.array([0.0, 0.0, 0.6, 0.8]),
        "pose_covariance": rng.normal(size=(6, 6)),
        "linear_velocity": rng.normal(size=3),
        "angular_velocity": rng.normal(size=3),
        "twist_covariance": rng.normal(size=(6, 6)),
        "points_xyz": rng.normal(size=(50, 3)),
    }
    out.write_odometry(
        stamp_ns,
        "odom",
        "camera",
        values["position"],
        values["quat_xyzw"],
        values["pose_covariance"],
        values["linear_velocity"],
        values["angular_velocity"],
        values["twist_covariance"],
    )
    out.write_points(stamp_ns, "odom", values["points_xyz"])
    out.write_tf(stamp_ns, [("odom", "camera", values["position"], values["quat_xyzw"]),
                            ("map", "odom", np.array([1.0, -2.0, 0.5]), np.array([0.0, 0.6, 0.0, 0.8]))])
    out.write_path(
        stamp_ns,
        "odom",
        np.array([stamp_ns - 10, stamp_ns]),
        np.array([[0.0, 0.0, 0.0], values["position"]]),
        np.array([[0.0, 0.0, 0.0, 1.0], values["quat_xyzw"]]),
    )
    out.write_diagnostics(
        stamp_ns,
        [
            DiagnosticStatusRecord(
                DiagnosticLevel.WARN,
                "epi_vo: tracking",
                "low parallax",
                "camera",
                (("inliers", "42"), ("state", "tracking")),
            ),
            DiagnosticStatusRecord(0, "epi_vo: timing", "ok", "camera"),
        ],
    )
    return values


def test_output_bag_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "out" / "output.mcap"
    with OutputBag(path) as out:
        written = {stamp: _write_everything(out, stamp) for stamp in (1_000_000_000, 1_500_000_000)}

    messages = _read_back(path)
    assert sorted(messages) == ["/tf", "/vo/frame_status", "/vo/odometry", "/vo/path", "/vo/points"]
    assert all(len(v) == 2 for v in messages.values())

    for log_time_ns, tf in messages["/tf"]:  # tf2_msgs/TFMessage: one TransformStamped per transform
        values = written[log_time_ns]
        first, second = tf.transforms
        for t in (first, second):
            assert (t.header.stamp.sec, t.header.stamp.nanosec) == divmod(log_time_ns, 10**9)
        assert (first.header.frame_id, first.child_frame_id, second.header.frame_id, second.child_frame_id) == (
            "odom", "camera", "map", "odom")
        r, q = first.transform.translation, first.transform.rotation
        np.testing.assert_array_equal([r.x, r.y, r.z, q.x, q.y, q.z, q.w],
                                      [*values["position"], *values["quat_xyzw"]])
        r, q = second.transform.translation, second.transform.rotation
        assert [r.x, r.y, r.z, q.x, q.y, q.z, q.w] == [1.0, -2.0, 0.5, 0.0, 0.6, 0.0, 0.8]

    for log_time_ns, odom in messages["/vo/odometry"]:
        values = written[log_time_ns]
        assert odom.header.stamp.sec == log_time_ns // 10**9
        assert odom.header.stamp.nanosec == log_time_ns % 10**9
        assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "camera")
        p, q = odom.pose.pose.position, odom.pose.pose.orientation
        np.testing.assert_array_equal([p.x, p.y, p.z], values["position"])
        np.testing.assert_array_equal([q.x, q.y, q.z, q.w], values["quat_xyzw"])
        np.testing.assert_array_equal(odom.pose.covariance.reshape(6, 6), values["pose_covariance"])
        np.testing.assert_array_equal(
            odom.twist.covariance.reshape(6, 6), values["twist_covariance"]
        )
        v, w = odom.twist.twist.linear, odom.twist.twist.angular
        np.testing.assert_array_equal([v.x, v.y, v.z], values["linear_velocity"])
        np.testing.assert_array_equal([w.x, w.y, w.z], values["angular_velocity"])

    for log_time_ns, cloud in messages["/vo/points"]:
        assert cloud.width == 50
        assert cloud.header.frame_id == "odom"
        np.testing.assert_array_equal(
            read_points_xyz(cloud), written[log_time_ns]["points_xyz"].astype(np.float32)
        )

    for log_time_ns, path_msg in messages["/vo/path"]:
        assert len(path_msg.poses) == 2
        last = path_msg.poses[-1]
        assert last.header.stamp.nanosec == log_time_ns % 10**9
        assert last.pose.position.x == written[log_time_ns]["position"][0]

    _, diagnostics = messages["/vo/frame_status"][0]
    warn, ok = diagnostics.status
    assert (warn.level, warn.name, warn.message, warn.hardware_id) == (
        1,
        "epi_vo: tracking",
        "low parallax",
        "camera",
    )
    assert [(kv.key, kv.value) for kv in warn.values] == [("inliers", "42"), ("state", "tracking")]
    assert (ok.level, ok.values) == (0, [])


def test_output_bag_is_a_ros2_mcap(tmp_path: Path) -> None:
    """Profile ros2, cdr channels with QoS entry and type hash, ros2msg schemas with full text."""
    path = tmp_path / "output.mcap"
    with OutputBag(path) as out:
        _write_everything(out, 15)  # the path's first pose is 10 ns earlier: still a valid ROS time
    with path.open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    assert summary is not None
    assert summary.statistics.message_count == 5
    schemas = {s.name: s for s in summary.schemas.values()}
    assert set(schemas) == {
        "nav_msgs/msg/Odometry",
        "sensor_msgs/msg/PointCloud2",
        "nav_msgs/msg/Path",
        "diagnostic_msgs/msg/DiagnosticArray",
        "tf2_msgs/msg/TFMessage",
    }
    assert all(s.encoding == "ros2msg" for s in schemas.values())
    assert "MSG: geometry_msgs/PoseWithCovariance" in schemas["nav_msgs/msg/Odometry"].data.decode()
    for channel in summary.channels.values():
        assert channel.message_encoding == "cdr"
        assert channel.metadata["offered_qos_profiles"] == ""
        assert channel.metadata["topic_type_hash"].startswith("RIHS01_")
    with path.open("rb") as stream:
        assert len(list(make_reader(stream).iter_messages())) == 5


def test_output_bag_stays_readable_after_interrupt(tmp_path: Path) -> None:
    path = tmp_path / "output.mcap"
    with pytest.raises(KeyboardInterrupt), OutputBag(path) as out:
        out.write_points(10, "odom", np.ones((3, 3)))
        raise KeyboardInterrupt
    messages = _read_back(path)
    assert list(messages) == ["/vo/points"]
    assert messages["/vo/points"][0][1].width == 3


def test_output_bag_drops_non_finite_points(tmp_path: Path) -> None:
    path = tmp_path / "output.mcap"
    with OutputBag(path) as out:
        out.write_points(1, "odom", np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0]]))
    ((_, cloud),) = _read_back(path)["/vo/points"]
    np.testing.assert_array_equal(read_points_xyz(cloud), [[1.0, 2.0, 3.0]])


def test_output_bag_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "output.mcap"
    OutputBag(path).close()
    with pytest.raises(BagError, match="exists already"):
        OutputBag(path)
    with OutputBag(path, overwrite=True) as out:
        out.write_points(1, "odom", np.zeros((1, 3)))
    assert len(_read_back(path)["/vo/points"]) == 1


def test_output_bag_bad_use(tmp_path: Path) -> None:
    with pytest.raises(BagError, match=r"must be a \.mcap file"):
        OutputBag(tmp_path / "output")
    out = OutputBag(tmp_path / "output.mcap")
    with pytest.raises(BagError, match=r"pose_covariance has shape \(36,\), expected \(6, 6\)"):
        out.write_odometry(
            1,
            "odom",
            "cam",
            np.zeros(3),
            [0, 0, 0, 1],
            np.zeros(36),
            np.zeros(3),
            np.zeros(3),
            np.zeros((6, 6)),
        )
    with pytest.raises(BagError, match=r"positions has shape \(2, 3\), expected \(3, 3\)"):
        out.write_path(1, "odom", [1, 2, 3], np.zeros((2, 3)), np.zeros((3, 4)))
    with pytest.raises(BagError, match=r"/vo/points: stamp -5 ns is not a valid ROS time"):
        out.write_points(-5, "odom", np.zeros((1, 3)))
    out.close()
    with pytest.raises(BagError, match="is closed"):
        out.write_points(1, "odom", np.zeros((1, 3)))


# --- damaged messages, invalid stamps, bad metadata -------------------------------------------------------------


def _write_raw_bag(
    path: Path, records: list[Record], damage: dict[int, bytes], storage: StoragePlugin = StoragePlugin.MCAP
) -> Path:
    """``write_bag`` where the CDR bytes of record ``i`` are replaced by ``damage[i]``."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        connections = {}
        for i, record in enumerate(records):
            if record.topic not in connections:
                connections[record.topic] = writer.add_connection(record.topic, record.msgtype, typestore=TS)
            data = damage.get(i)
            if data is None:
                data = bytes(TS.serialize_cdr(record.msg, record.msgtype))
            writer.write(connections[record.topic], record.log_time_ns, data)
    return path


@pytest.mark.parametrize("storage", STORAGES, ids=lambda x: x.name.lower())
def test_undecodable_messages_are_reported_one_by_one(tmp_path: Path, storage: StoragePlugin) -> None:
    """An image whose CDR cannot be decoded is a frame with a problem; a camera_info or ground-truth message is
    skipped with a line saying so; every other message is read as usual."""
    records = _camera_records(frames=4)  # info 0, image 0, info 1, image 1, ...
    records += [Record("/gt/pose", POSE_STAMPED, s, _pose_stamped(s, (0.0, 0.0, 0.0), (0, 0, 0, 1)))
                for s in (10**8, 2 * 10**8)]
    image_1 = bytes(TS.serialize_cdr(records[3].msg, IMAGE))
    damage = {3: image_1[:40], 4: b"\x00\x01\x00\x00\xff\xff", 8: b"\x00\x01\x00\x00" + bytes(3)}
    path = _write_raw_bag(tmp_path / "bag", records, damage, storage)
    with open_camera_bag(path) as bag:
        assert bag.problems == [
            f"camera_info message at log time {3 * 10**8} ns skipped: it cannot be decoded: its 6 bytes of CDR "
            f"are no valid {CAMERA_INFO} ({bag.problems[0].split('(', 1)[1]}"
        ]
        frames = list(bag.iter_frames())
        gt = bag.read_ground_truth()
        assert len(bag.problems) == 2 and bag.problems[1].startswith(
            f"ground-truth message on /gt/pose at log time {10**8} ns skipped: it cannot be decoded: its 7 bytes")
    assert [f.index for f in frames] == [0, 1, 2, 3]
    bad = frames[1]
    assert bad.image_msg is None and bad.camera_info_msg is None
    assert bad.problem is not None and bad.problem.startswith(
        f"image message cannot be decoded: its 40 bytes of CDR are no valid {IMAGE} (")
    assert bad.stamp_ns == bad.log_time_ns == 2 * 10**8  # no header: filed under its log time
    assert all(f.problem is None for f in (frames[0], frames[2], frames[3]))
    # Frame 2's own camera_info (fx 502) was skipped: the latest one before it (fx 501) is used.
    assert [f.camera_info_msg.k[0] for f in (frames[0], frames[2], frames[3])] == [500.0, 501.0, 503.0]
    assert gt is not None and gt.stamps_ns.tolist() == [2 * 10**8]


def test_image_stamps_that_are_no_ros_time_give_frames_with_a_problem(tmp_path: Path) -> None:
    records = _camera_records(frames=4)
    Time = T["builtin_interfaces/msg/Time"]
    bad = {1: Time(sec=-3, nanosec=5), 3: Time(sec=1, nanosec=1_500_000_000), 5: Time(sec=2**31 - 1,
                                                                                          nanosec=4_000_000_000)}
    for i, stamp in bad.items():
        records[i].msg.header.stamp = stamp
    with open_camera_bag(write_bag(tmp_path / "bag", records)) as bag:
        frames = list(bag.iter_frames())
    assert [f.problem is None for f in frames] == [False, False, False, True]
    assert frames[0].problem == ("image header stamp sec -3 nanosec 5 is not a valid ROS time (sec 0..2147483647, "
                                 "nanosec 0..999999999)")
    assert "sec 1 nanosec 1500000000 is not a valid ROS time" in frames[1].problem
    assert "sec 2147483647 nanosec 4000000000 is not a valid ROS time" in frames[2].problem
    # Filed under the header stamp clamped into the ROS time range.
    assert [f.stamp_ns for f in frames[:3]] == [0, 2_500_000_000, (2**31 - 1) * 10**9 + 999_999_999]
    assert all(f.image_msg is not None for f in frames)


MAX_NS = (2**31 - 1) * 10**9 + 999_999_999


@pytest.mark.parametrize("stamp", [-1, MAX_NS + 1, 2**63])
def test_output_bag_refuses_times_that_are_no_ros_time(tmp_path: Path, stamp: int) -> None:
    """Nothing of a message with an invalid stamp is written (no struct.error from the serialiser, no wrapped
    time); the file stays valid, and the largest ROS time is written exactly."""
    path = tmp_path / "output.mcap"
    pattern = rf"stamp {stamp} ns is not a valid ROS time \(0\.\.{MAX_NS} ns\): message not written"
    with OutputBag(path) as out:
        with pytest.raises(BagError, match=r"/vo/odometry: " + pattern):
            out.write_odometry(stamp, "odom", "cam", np.zeros(3), [0, 0, 0, 1], np.eye(6), np.zeros(3),
                               np.zeros(3), np.eye(6))
        with pytest.raises(BagError, match=r"/vo/points: " + pattern):
            out.write_points(stamp, "odom", np.zeros((1, 3)))
        with pytest.raises(BagError, match=r"/vo/frame_status: " + pattern):
            out.write_diagnostics(stamp, [])
        with pytest.raises(BagError, match=r"/vo/path: " + pattern):  # one pose of the path
            out.write_path(5, "odom", [4, stamp], np.zeros((2, 3)), np.tile([0.0, 0, 0, 1], (2, 1)))
        out.write_points(MAX_NS, "odom", np.zeros((1, 3)))
        out.write_path(MAX_NS, "odom", [0, MAX_NS], np.zeros((2, 3)), np.tile([0.0, 0, 0, 1], (2, 1)))
    messages = _read_back(path)
    assert sorted(messages) == ["/vo/path", "/vo/points"]
    ((log_time, cloud),) = messages["/vo/points"]
    assert log_time == MAX_NS and (cloud.header.stamp.sec, cloud.header.stamp.nanosec) == (2**31 - 1, 999_999_999)
    ((_, path_msg),) = messages["/vo/path"]
    assert [(p.header.stamp.sec, p.header.stamp.nanosec) for p in path_msg.poses] == [(0, 0),
                                                                                       (2**31 - 1, 999_999_999)]


def _bag_dir_with_metadata(tmp_path: Path, edit: bytes | None = None, old: bytes = b"", new: bytes = b"") -> Path:
    path = write_bag(tmp_path / "bag", _camera_records())
    metadata = path / "metadata.yaml"
    data = metadata.read_bytes()
    metadata.write_bytes(data + edit if edit is not None else data.replace(old, new, 1))
    return path


def test_metadata_that_is_not_utf8(tmp_path: Path) -> None:
    path = _bag_dir_with_metadata(tmp_path, edit=b"\n# \xff\xfe\n")
    offset = (path / "metadata.yaml").read_bytes().index(b"\xff")
    with pytest.raises(BagError, match=rf"metadata.yaml is not UTF-8 text \(byte 0xff at offset {offset}\)"):
        open_camera_bag(path)


@pytest.mark.parametrize(("old", "new"), [(b"message_count: 3", b"message_count: 3x"),
                                          (b"message_count: 3", b"message_count: [3]")])
def test_metadata_with_a_count_that_is_no_number(tmp_path: Path, old: bytes, new: bytes) -> None:
    path = _bag_dir_with_metadata(tmp_path, old=old, new=new)
    assert new in (path / "metadata.yaml").read_bytes()
    with pytest.raises(BagError, match=rf"bag {path} has malformed metadata"):
        open_camera_bag(path)


def test_output_bag_writes_the_bytes_rosbags_would(tmp_path: Path) -> None:
    """The hand-written CDR of the four output types equals rosbags' serialize_cdr byte for byte, for frame ids
    of every length mod 8 (the alignment of what follows), empty and non-ASCII strings, empty sequences."""
    types = T

    def header(stamp: int, frame_id: str) -> object:
        return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame_id)

    def pose(p: np.ndarray, q: np.ndarray) -> object:
        return types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](*map(float, p)),
                                               orientation=types["geometry_msgs/msg/Quaternion"](*map(float, q)))

    rng = np.random.default_rng(7)
    expected: list[bytes] = []
    path = tmp_path / "out.mcap"

    def want(message: object, msgtype: str) -> None:
        expected.append(bytes(TS.serialize_cdr(message, msgtype, little_endian=True)))

    with OutputBag(path) as out:
        for frame_id in ("", "o", "od", "odo", "odom", "odom_", "ödöm", "odom_frame"):
            stamp = 1_000_000_000 + int(rng.integers(0, 10**9))
            for m in (0, 1, 2, 5):
                stamps, xyz, quats = stamp - 1000 * np.arange(m)[::-1], rng.normal(size=(m, 3)), rng.normal(size=(m, 4))
                out.write_path(stamp, frame_id, stamps, xyz, quats)
                want(types["nav_msgs/msg/Path"](header=header(stamp, frame_id), poses=[
                    types["geometry_msgs/msg/PoseStamped"](header=header(int(s), frame_id), pose=pose(p, q))
                    for s, p, q in zip(stamps, xyz, quats, strict=True)]), "nav_msgs/msg/Path")
            v = [rng.normal(size=3), rng.normal(size=4), rng.normal(size=(6, 6)), rng.normal(size=3),
                 rng.normal(size=3), rng.normal(size=(6, 6))]
            out.write_odometry(stamp, frame_id, frame_id[:3], *v)
            vector3 = types["geometry_msgs/msg/Vector3"]
            want(types["nav_msgs/msg/Odometry"](
                header=header(stamp, frame_id), child_frame_id=frame_id[:3],
                pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose(v[0], v[1]), covariance=v[2].ravel()),
                twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=types["geometry_msgs/msg/Twist"](
                    linear=vector3(*map(float, v[3])), angular=vector3(*map(float, v[4]))), covariance=v[5].ravel())),
                "nav_msgs/msg/Odometry")
            for n in (0, 3):
                points = rng.normal(size=(n, 3))
                out.write_points(stamp, frame_id, points)
                cloud = point_cloud2_fields(points)
                want(types["sensor_msgs/msg/PointCloud2"](
                    header=header(stamp, frame_id), height=cloud["height"], width=cloud["width"],
                    fields=[types["sensor_msgs/msg/PointField"](*f) for f in cloud["fields"]],
                    is_bigendian=cloud["is_bigendian"], point_step=cloud["point_step"], row_step=cloud["row_step"],
                    data=cloud["data"], is_dense=cloud["is_dense"]), "sensor_msgs/msg/PointCloud2")
            records = [DiagnosticStatusRecord(DiagnosticLevel.WARN, "a" + frame_id, "é", "",
                                              (("k", frame_id), ("", ""))),
                       DiagnosticStatusRecord(0, frame_id, "m", "hw")]
            out.write_diagnostics(stamp, records)
            want(types["diagnostic_msgs/msg/DiagnosticArray"](header=header(stamp, ""), status=[
                types["diagnostic_msgs/msg/DiagnosticStatus"](
                    level=int(r.level), name=r.name, message=r.message, hardware_id=r.hardware_id,
                    values=[types["diagnostic_msgs/msg/KeyValue"](key=k, value=x) for k, x in r.values])
                for r in records]), "diagnostic_msgs/msg/DiagnosticArray")
    with path.open("rb") as stream:
        got = [m.data for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]
    assert len(got) == len(expected)
    for i, (g, e) in enumerate(zip(got, expected, strict=True)):
        assert g == e, f"message {i}"


def test_a_growing_and_sliding_path_is_written_as_rosbags_would(tmp_path: Path) -> None:
    """/vo/path as replay writes it, a path that grows, then drops its oldest poses at its length limit,
    changes its frame id, or has an old pose changed: the bytes of rosbags' serialisation every time."""
    types = T

    def header(stamp: int, frame_id: str) -> object:
        return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=frame_id)

    rng = np.random.default_rng(11)
    n = 40
    stamps_all = 10**9 + 10**7 * np.arange(n)
    xyz_all, quats_all = rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
    calls: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]] = []
    for i in range(1, n):  # grows to 12 poses, then slides
        lo = max(0, i - 12)
        calls.append((int(stamps_all[i]), "odom", stamps_all[lo:i + 1], xyz_all[lo:i + 1], quats_all[lo:i + 1]))
    last = calls[-1]
    calls.append((last[0] + 1, "odom_frame", last[2], last[3], last[4]))  # another frame id
    changed = last[3].copy()
    changed[3] += 1.0
    calls.append((last[0] + 2, "odom_frame", last[2], changed, last[4]))  # an old pose moved
    calls.append((last[0] + 3, "odom_frame", last[2][5:], changed[5:], last[4][5:]))  # 5 dropped at once
    path = tmp_path / "out.mcap"
    expected = []
    with OutputBag(path) as out:
        for stamp, frame_id, stamps, xyz, quats in calls:
            out.write_path(stamp, frame_id, stamps, xyz, quats)
            expected.append(bytes(TS.serialize_cdr(types["nav_msgs/msg/Path"](header=header(stamp, frame_id), poses=[
                types["geometry_msgs/msg/PoseStamped"](header=header(int(s), frame_id), pose=types[
                    "geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](*map(float, p)),
                                              orientation=types["geometry_msgs/msg/Quaternion"](*map(float, q))))
                for s, p, q in zip(stamps, xyz, quats, strict=True)]), "nav_msgs/msg/Path", little_endian=True)))
    with path.open("rb") as stream:
        got = [m.data for _, _, m in make_reader(stream).iter_messages(log_time_order=False)]
    assert len(got) == len(expected) == n + 2
    for i, (g, e) in enumerate(zip(got, expected, strict=True)):
        assert g == e, f"message {i}"


def test_output_bag_path_stamps_are_checked(tmp_path: Path) -> None:
    with OutputBag(tmp_path / "output.mcap") as out:
        with pytest.raises(BagError, match=r"/vo/path: stamp -5 ns is not a valid ROS time"):
            out.write_path(10, "odom", np.array([1, -5]), np.zeros((2, 3)), np.zeros((2, 4)))
        with pytest.raises(BagError, match=r"/vo/path: stamp 10{25} ns is not a valid ROS time"):
            out.write_path(10, "odom", [1, 10**25], np.zeros((2, 3)), np.zeros((2, 4)))
        with pytest.raises(BagError, match=r"positions has shape \(1, 3\), expected \(2, 3\)"):
            out.write_path(10, "odom", np.array([1, 2]), np.zeros((1, 3)), np.zeros((2, 4)))
        out.write_path(10, "odom", np.array([1.9, 2.0]), np.zeros((2, 3)), np.zeros((2, 4)))  # floats: as ints
    ((_, msg),) = _read_back(tmp_path / "output.mcap")["/vo/path"]
    assert [p.header.stamp.nanosec for p in msg.poses] == [1, 2]


def test_usable_gray_is_the_pixels_of_a_frame_the_replay_would_process(tmp_path: Path) -> None:
    bad = _image(2 * 10**8, 7)
    bad.encoding = "no_such_encoding"
    records = [Record("/cam/camera_info", CAMERA_INFO, 10**8, _camera_info(10**8, 500.0)),
               Record("/cam/image_raw", IMAGE, 10**8, _image(10**8, 42)),
               Record("/cam/image_raw", IMAGE, 2 * 10**8, bad)]
    with open_camera_bag(write_bag(tmp_path / "bag", records)) as bag:
        frames = list(bag.iter_frames())
        good = bag.usable_gray(frames[0])
        assert good is not None and good.shape == (4, 6) and np.all(good == 42)
        assert bag.usable_gray(frames[1]) is None
        assert bag.usable_gray(dataclasses.replace(frames[0], camera_info_msg=None)) is None
        assert bag.usable_gray(dataclasses.replace(frames[0], problem="image message not decodable")) is None
