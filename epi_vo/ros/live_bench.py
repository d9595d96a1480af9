"""``epi-vo latency``: live latency of vo_node (image publish -> odometry received) over DDS on loopback.

A ``vo_node`` process runs in live mode (sensor-data QoS, bounded queue). This process publishes the
bundled general-motion bag as raw mono8 640x480 ``sensor_msgs/Image`` (frames played forward, back and
forward again so the camera motion stays continuous) with camera_info at a fixed rate, and measures,
for every image, the time from its publication to the arrival of the odometry with its stamp. Frames
without odometry are drops. Rates are tried in increasing order; the fastest with no drops and p95
below the frame period is the sustained rate.

DDS stays on this machine: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a private ROS_DOMAIN_ID are set
before rclpy is imported, for this process and the node process alike.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

_DRAIN_TIMEOUT_S = 10.0  # after the last frame: bound on waiting for its odometry


@dataclass(frozen=True)
class LatencyResult:
    rate_hz: float
    published: int
    received: int
    p50_ms: float
    p95_ms: float
    max_ms: float

    @property
    def drops(self) -> int:
        return self.published - self.received


def _frames(bag: Path) -> list[tuple[np.ndarray, Any]]:
    from epi_vo.io import bagio
    from epi_vo.io.msgconv import decode_frame

    out = []
    with bagio.open_camera_bag(bag) as b:
        for f in b.iter_frames():
            out.append((decode_frame(f.image_msg, b.image_is_compressed), f.camera_info_msg))
    return out


def run_latency(rates: list[float], seconds: float = 8.0, bag: str | Path | None = None) -> list[LatencyResult]:
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 50))
    bag = Path(bag) if bag else Path(__file__).resolve().parents[2] / "bags" / "general_motion" / "bag"
    frames = _frames(bag)
    seq = frames + frames[-2:0:-1] + frames  # forward, back, forward: continuous motion
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CameraInfo, Image

    results = []
    rclpy.init()
    node = rclpy.create_node("epi_vo_latency_bench")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    # Receive on a thread of its own; the publishing loop sleeps between frames (a busy spin would
    # take one of the two cores away from the node under test).
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    pub_img = node.create_publisher(Image, "camera/image_raw", qos_profile_sensor_data)
    pub_info = node.create_publisher(CameraInfo, "camera/camera_info", qos_profile_sensor_data)
    received: dict[int, float] = {}
    node.create_subscription(Odometry, "vo/odometry",
                             lambda m: received.setdefault(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                                           time.perf_counter()), 100)
    info_msgs = [_info_msg(info, CameraInfo) for _, info in frames[:1]]
    try:
        for rate in rates:
            proc = subprocess.Popen([sys.executable, "-m", "epi_vo.ros.node"], env=dict(os.environ),
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                deadline = time.monotonic() + 20
                while node.count_subscribers("camera/image_raw") == 0 or node.count_publishers("vo/odometry") == 0:
                    time.sleep(0.05)
                    if time.monotonic() > deadline:
                        raise RuntimeError("vo_node did not start")
                time.sleep(0.5)
                received.clear()
                sent: dict[int, float] = {}
                n = int(seconds * rate)
                period = 1.0 / rate
                t0 = time.perf_counter()
                for i in range(n):
                    gray, _ = seq[i % len(seq)]
                    stamp = 1_000_000_000 + int(i * period * 1e9)
                    img = Image()
                    img.header.stamp.sec, img.header.stamp.nanosec = divmod(stamp, 10**9)
                    img.header.frame_id = "camera_optical_frame"
                    img.height, img.width = gray.shape
                    img.encoding, img.step = "mono8", gray.shape[1]
                    img.data = gray.tobytes()
                    info = info_msgs[0]
                    info.header.stamp = img.header.stamp
                    delay = t0 + i * period - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    pub_info.publish(info)
                    sent[stamp] = time.perf_counter()
                    pub_img.publish(img)
                # Live mode keeps the newest frame: its odometry ends the run (the node's queue drained),
                # however long a loaded machine takes; a node that never answers is bounded.
                last_stamp = max(sent, default=None)
                deadline = time.monotonic() + _DRAIN_TIMEOUT_S
                while last_stamp is not None and last_stamp not in received and time.monotonic() < deadline:
                    time.sleep(0.01)
                lat = np.array([(received[s] - t) * 1e3 for s, t in sent.items() if s in received])
                results.append(LatencyResult(rate, len(sent), len(lat), *(
                    (float(np.percentile(lat, 50)), float(np.percentile(lat, 95)), float(lat.max()))
                    if lat.size else (float("nan"),) * 3)))
            finally:
                proc.send_signal(2)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
    finally:
        ex.shutdown()
        spinner.join(timeout=5.0)  # a thread still inside spin() at interpreter exit aborts the process
        node.destroy_node()
        rclpy.try_shutdown()
    return results


def _info_msg(info: Any, msg_type: Any) -> Any:
    from rclpy.serialization import deserialize_message

    from epi_vo.io.bagio import to_cdr

    return deserialize_message(to_cdr(info), msg_type)


def format_results(results: list[LatencyResult]) -> str:
    lines = [f"{'rate Hz':>8} {'published':>10} {'odometry':>9} {'drops':>6} {'p50 ms':>8} {'p95 ms':>8} {'max ms':>8}"]
    for r in results:
        lines.append(f"{r.rate_hz:>8.0f} {r.published:>10} {r.received:>9} {r.drops:>6} {r.p50_ms:>8.2f} "
                     f"{r.p95_ms:>8.2f} {r.max_ms:>8.2f}")
    ok = [r for r in results if r.drops == 0 and r.p95_ms < 1e3 / r.rate_hz]
    lines.append(f"sustained (no drops, p95 < frame period): {max(r.rate_hz for r in ok):.0f} Hz" if ok
                 else "sustained: none of the tried rates")
    return "\n".join(lines)


def main(rates: list[float], seconds: float) -> int:
    print(format_results(run_latency(rates, seconds)))
    return 0
