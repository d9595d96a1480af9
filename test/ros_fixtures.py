"""Shared helpers for tests that run rclpy: DDS on loopback, a unique domain, rclpy init and shutdown.

Every process of the test suite that uses rclpy must see ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``
and a ``ROS_DOMAIN_ID`` of its own before rclpy starts: in-process through ``rclpy_session`` (which
sets ``os.environ`` first and only then imports and initialises rclpy), in subprocesses by passing
``session.env`` (or ``ros_test_env().env``) as their environment.

Usage in a test file (pytest puts ``test/`` on sys.path)::

    from ros_fixtures import RosSession, rclpy_session, spin_until

    @pytest.fixture(scope="module")
    def ros() -> Iterator[RosSession]:
        with rclpy_session() as session:
            yield session

    def test_x(ros: RosSession) -> None:
        node = rclpy.create_node("probe", context=ros.context)
        executor = SingleThreadedExecutor(context=ros.context)
        subprocess.run([...], env=ros.env)

Import rclpy (and modules that import it) inside tests or fixtures that depend on ``ros``, not at
module level, so the environment is set before rclpy is loaded.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rclpy.context import Context

# Domains 50-99 for the test suite (the experiments of people at the machine use lower ones); Fast DDS on Linux
# accepts 0-232. A session (.ci/run, a helper) hands its own range in EPI_VO_TEST_DOMAIN_IDS ("LO-HI").
DOMAIN_IDS_ENV = "EPI_VO_TEST_DOMAIN_IDS"
DEFAULT_DOMAIN_IDS = range(50, 100)
# Every process that starts DDS for the tests claims its domain id with an exclusive flock on a file of its
# own in this directory (scripts/ros_domain.sh does the same for .ci/run and scripts/test.sh), held until the
# process ends: two concurrent sessions (two pytest runs, xdist workers, .ci/run beside a helper's tests)
# never share a domain, where a pid modulo the range can agree. The kernel drops the lock of a process that
# dies, so a crashed run leaves nothing claimed.
DOMAIN_LOCK_DIR_ENV = "EPI_VO_ROS_DOMAIN_LOCKS"


class DomainIdError(RuntimeError):
    """No ROS_DOMAIN_ID of the range is free, or the range is unusable."""


def domain_id_range(text: str | None = None) -> range:
    """The ids the test suite may claim: ``EPI_VO_TEST_DOMAIN_IDS`` ("LO-HI", inclusive, within 0-232)."""
    text = os.environ.get(DOMAIN_IDS_ENV, "") if text is None else text
    if not text.strip():
        return DEFAULT_DOMAIN_IDS
    lo, sep, hi = text.partition("-")
    try:
        ids = range(int(lo), int(hi if sep else lo) + 1)
    except ValueError:
        ids = range(0)
    if not ids or ids.start < 0 or ids.stop > 233:
        msg = f"{DOMAIN_IDS_ENV}={text!r} is not a range LO-HI of ROS domain ids within 0-232"
        raise DomainIdError(msg)
    return ids


def domain_lock_dir() -> Path:
    """Where domain ids are claimed: ``EPI_VO_ROS_DOMAIN_LOCKS``, else ``$TMPDIR`` (or /tmp)/epi_vo_ros_domains."""
    path = os.environ.get(DOMAIN_LOCK_DIR_ENV) or str(Path(os.environ.get("TMPDIR") or "/tmp") / "epi_vo_ros_domains")
    return Path(path)


def claim_domain_id(ids: range | None = None, lock_dir: Path | None = None,
                    start: int | None = None) -> tuple[int, int]:
    """Claim a free domain id of ``ids`` (default ``domain_id_range()``) under ``lock_dir``: the first free one
    from ``start`` (default: from the pid) on, wrapping. Returns the id and the open file descriptor that holds
    the claim (closing it, or the process ending, frees the id). DomainIdError when every id is taken."""
    import fcntl

    ids = domain_id_range() if ids is None else ids
    lock_dir = domain_lock_dir() if lock_dir is None else lock_dir
    lock_dir.mkdir(parents=True, exist_ok=True)
    first = os.getpid() if start is None else start
    for k in range(len(ids)):
        domain_id = ids[(first + k) % len(ids)]
        fd = os.open(lock_dir / f"ros_domain_{domain_id}.lock", os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return domain_id, fd
    msg = (f"every ROS domain id {ids.start}-{ids.stop - 1} is claimed by another test session (locks in "
           f"{lock_dir}); set {DOMAIN_IDS_ENV}=LO-HI to a free range")
    raise DomainIdError(msg)


_claimed: int | None = None  # this process's domain id, claimed once and held until it ends


def pick_domain_id() -> int:
    """This test process's ROS_DOMAIN_ID: claimed (``claim_domain_id``) at the first call, the same after."""
    global _claimed
    if _claimed is None:
        _claimed, _fd = claim_domain_id()  # the descriptor stays open: the claim lasts as long as the process
    return _claimed


@dataclass(frozen=True)
class RosTestEnv:
    """The DDS settings of a test: ``env`` is a copy of os.environ with them, for subprocesses."""

    domain_id: int
    env: dict[str, str]


@contextmanager
def ros_test_env(domain_id: int | None = None) -> Iterator[RosTestEnv]:
    """Set ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST in os.environ; restore on exit.

    Also clears ROS_STATIC_PEERS (peers would widen discovery) and the deprecated ROS_LOCALHOST_ONLY.
    """
    domain_id = pick_domain_id() if domain_id is None else domain_id
    settings: dict[str, str | None] = {
        "ROS_DOMAIN_ID": str(domain_id),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_STATIC_PEERS": "",
        "ROS_LOCALHOST_ONLY": None,
    }
    saved = {key: os.environ.get(key) for key in settings}
    try:
        for key, value in settings.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        yield RosTestEnv(domain_id, dict(os.environ))
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@dataclass(frozen=True)
class RosSession:
    """An initialised rclpy context on a loopback-only domain; ``env`` is for subprocesses."""

    domain_id: int
    env: dict[str, str]
    context: Context


@contextmanager
def rclpy_session(domain_id: int | None = None) -> Iterator[RosSession]:
    """``ros_test_env`` + rclpy initialised in a context of its own (no signal handlers: pytest keeps Ctrl-C)."""
    with ros_test_env(domain_id) as ros_env:
        import rclpy
        from rclpy.context import Context
        from rclpy.signals import SignalHandlerOptions

        context = Context()
        rclpy.init(context=context, domain_id=ros_env.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        try:
            yield RosSession(ros_env.domain_id, ros_env.env, context)
        finally:
            rclpy.try_shutdown(context=context)


# Waiting for another process (or DDS) to do something: wait on the condition itself, bounded by a generous
# deadline, never sleep a fixed time and hope. The bound only matters when the condition never comes (the
# test then fails after it); on a loaded machine it must be far beyond the usual time (tens of seconds).
def spin_until(executor: Any, predicate: Callable[[], bool], timeout_s: float, step_s: float = 0.01) -> bool:
    """Spin ``executor`` until ``predicate()`` is true (True) or ``timeout_s`` passes (False)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        executor.spin_once(timeout_sec=step_s)
    return True


def wait_until(predicate: Callable[[], bool], timeout_s: float, step_s: float = 0.02) -> bool:
    """Poll ``predicate()`` until it is true (True) or ``timeout_s`` passes (False); no executor spun."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        time.sleep(step_s)
    return True


class NodeProcess:
    """A node (``vo_node``, or another ``module``) as a child process with ``--ros-args``; stopped (SIGINT,
    then kill) when the block ends; ``stderr`` and ``proc.returncode`` after."""

    def __init__(self, env: dict[str, str], *ros_args: str, module: str = "epi_vo.ros.node") -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", module, "--ros-args", *ros_args], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.stderr = ""

    def __enter__(self) -> NodeProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.stderr = self.proc.communicate()[1]


def odom_pose(msg: Any) -> Any:
    """x y z qx qy qz qw of a nav_msgs/Odometry message's pose."""
    import numpy as np

    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    return np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])


def replay_odometry(bag: Any, out: Any, topic: str = "/vo/odometry", run: bool = True) -> dict[int, Any]:
    """The offline replay's ``topic`` poses (x y z qx qy qz qw) by header stamp (ns); ``run``: replay first."""
    import numpy as np

    from epi_vo.io.odometry_bag import read_odometry
    from epi_vo.tools.replay import run_replay

    if run:
        run_replay(bag, out)
    odo = read_odometry(out / "output.mcap", topic)
    return {int(t): np.concatenate([p, q]) for t, p, q in zip(odo.stamps_ns, odo.positions, odo.quats_xyzw,
                                                             strict=True)}


PROBE_WAIT_S = 120.0  # bound on a probe's wait for another process or DDS (only matters if it never comes)

# A service call unanswered for this long is asked again. DDS can lose a response: the server sends it only
# once it has matched the client's response reader, and Fast DDS waits 100 ms for that match
# (rmw_fastrtps "client will not receive response"); on a loaded machine discovery can take longer, though
# the client already saw the service (wait_for_service). Resending is then the only way to an answer.
RESEND_S = 10.0


def call_service(executor: Any, client: Any, request: Any, timeout_s: float = PROBE_WAIT_S,
                 took_effect: Callable[[], bool] | None = None) -> Any:
    """Call a service and return its response, asking again every RESEND_S while none came (the first
    response to come is taken). For a request that must not run twice, ``took_effect`` tells whether the
    server already acted on it: if it did, no second request is sent and None is returned when no response
    comes. Fails the test if no response (and no effect) comes within ``timeout_s``."""
    assert client.wait_for_service(timeout_sec=timeout_s), client.srv_name
    deadline = time.monotonic() + timeout_s
    futures = [client.call_async(request)]

    def answered() -> bool:
        return any(f.done() for f in futures)

    while not spin_until(executor, answered, min(RESEND_S, max(0.0, deadline - time.monotonic()))):
        if time.monotonic() >= deadline:
            raise AssertionError(f"{client.srv_name}: no response in {timeout_s:.0f} s")
        if took_effect is not None and took_effect():
            return None
        futures.append(client.call_async(request))
    return next(f for f in futures if f.done()).result()


class ProbeBase:
    """A test-side node with its own executor, subscribed to the VO's odometry, its per-frame statuses and
    /diagnostics (reliable, deep queues: nothing may be lost). The tests' probes add the publishers,
    subscriptions and clients they need, with ``self.qos``."""

    def __init__(self, ros: RosSession, name: str, namespace: str = "") -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node(name, namespace=namespace or None, context=ros.context)
        self.executor = SingleThreadedExecutor(context=ros.context)
        self.executor.add_node(self.node)
        self.qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.odom: list[Any] = []
        self.odom_vo_units: list[Any] = []  # vo/odometry/vo_units: the motion in VO units
        self.diag: list[Any] = []  # /diagnostics: the node's health, once a second
        self.frame_status: list[Any] = []  # vo/frame_status: one array per frame
        self.node.create_subscription(Odometry, "vo/odometry", self.odom.append, self.qos)
        self.node.create_subscription(Odometry, "vo/odometry/vo_units", self.odom_vo_units.append, self.qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, self.qos)
        self.node.create_subscription(DiagnosticArray, "vo/frame_status", self.frame_status.append, self.qos)

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float = PROBE_WAIT_S) -> bool:
        return spin_until(self.executor, predicate, timeout_s)

    def publish_pairs(self, pub_img: Any, pub_info: Any, frames: list[tuple[Any, Any]]) -> None:
        """Publish (image, camera_info) pairs once both publishers are matched, spinning between them."""
        assert self.spin_until(lambda: pub_img.get_subscription_count() > 0 and pub_info.get_subscription_count() > 0)
        for img, info in frames:
            pub_info.publish(info)
            pub_img.publish(img)
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def bag_frame_count(bag: Path) -> int:
    """How many camera frames the bag holds."""
    from epi_vo.io import bagio

    with bagio.open_camera_bag(bag) as b:
        return b.frame_count


def bag_frames_rclpy(bag: Path, n: int, shift_s: int = 0) -> list[tuple[Any, Any]]:
    """The first n (CompressedImage, CameraInfo) pairs of the bag as rclpy messages (via CDR), header stamps
    shifted by ``shift_s`` seconds."""
    from rclpy.serialization import deserialize_message
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import CameraInfo, CompressedImage

    from epi_vo.io import bagio

    ts = get_typestore(Stores.ROS2_JAZZY)

    def conv(msg: Any, kind: Any) -> Any:
        out = deserialize_message(bytes(ts.serialize_cdr(msg, msg.__msgtype__)), kind)
        out.header.stamp.sec += shift_s
        return out

    frames = []
    with bagio.open_camera_bag(bag) as b:
        for f in b.iter_frames():
            if f.index >= n:
                break
            frames.append((conv(f.image_msg, CompressedImage), conv(f.camera_info_msg, CameraInfo)))
    return frames


def send_calibration(probe: ProbeBase, bag: Path, timeout_s: float = PROBE_WAIT_S) -> Any:
    """Give a VO node the bag's calibration before the bag is played into it: a copy of the bag's first
    camera_info, stamped one frame period before its first image, published reliably until the node
    acknowledged it; the publisher (on ``camera/camera_info``) is returned.

    What the node promises: an image waits for the first camera_info at most 2 s (NO_CAMERA_INFO_WAIT_S) or
    30 images, and is then rejected for having none; once one has been received, an image waits
    camera_info_wait_s for its own and then takes the latest one received. The player's camera_info reaches
    the node only once the node's side of discovery of the player has completed, which on a loaded machine can
    be seconds after the images do: the first frames were rejected and tracking started later than in the
    offline replay (frame 1 held at identity instead of at its rotation). With the bag's own calibration
    received, such a frame is processed with it, as offline: for a bag whose calibration is constant the
    outputs are the replay's whenever the player's copy arrives.
    """
    from rclpy.duration import Duration
    from sensor_msgs.msg import CameraInfo

    from epi_vo.io.msgconv import stamp_to_ns

    (img0, info), (img1, _) = bag_frames_rclpy(bag, 2)
    stamp_ns = 2 * stamp_to_ns(img0.header.stamp) - stamp_to_ns(img1.header.stamp)
    info.header.stamp.sec, info.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    pub = probe.node.create_publisher(CameraInfo, "camera/camera_info", probe.qos)
    assert probe.spin_until(lambda: pub.get_subscription_count() > 0, timeout_s)
    pub.publish(info)
    # Acknowledged: the node's reader has matched this publisher and holds the message.
    assert pub.wait_for_all_acked(Duration(seconds=timeout_s))
    return pub
