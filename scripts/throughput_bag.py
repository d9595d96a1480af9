"""Make the throughput bag of the README's replay figures: 640x480 raw mono8, 720+ frames.

general_motion's frames are played back and forth (0..51, 50..1, 0..51, ...) at 15 Hz, as raw
``sensor_msgs/Image`` mono8 (no decoding cost), with its camera_info and its ground-truth pose per frame
(so the replay still evaluates ATE). Only the stamps are new.

    .venv/bin/python scripts/throughput_bag.py OUT_DIR [--frames 720] [--source bags/general_motion/bag]
    .venv/bin/epi-vo replay OUT_DIR --output /tmp/tp      # end_to_end_fps is in /tmp/tp/stats.json
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

PERIOD_NS = 66_666_667  # 15 Hz
START_NS = 1_700_000_000 * 1_000_000_000


def ping_pong(n_source: int, n_frames: int) -> list[int]:
    """Source frame index of each output frame: 0..n-1, n-2..1, 0..n-1, ..."""
    cycle = list(range(n_source)) + list(range(n_source - 2, 0, -1))
    return [cycle[i % len(cycle)] for i in range(n_frames)]


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=720)
    ap.add_argument("--source", type=Path, default=Path(__file__).resolve().parents[1] / "bags/general_motion/bag")
    args = ap.parse_args(argv)
    store = get_typestore(Stores.ROS2_JAZZY)
    images: list[np.ndarray] = []
    infos: list[object] = []
    poses: list[object] = []
    with AnyReader([args.source], default_typestore=store) as reader:
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "sensor_msgs/msg/CompressedImage":
                images.append(cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE))
            elif conn.msgtype == "sensor_msgs/msg/CameraInfo":
                infos.append(msg)
            elif conn.msgtype == "geometry_msgs/msg/PoseStamped":
                poses.append(msg)
    if not images or len(infos) < len(images) or len(poses) < len(images):
        print(f"{args.source}: expected one image, camera_info and pose per frame", file=sys.stderr)
        return 1
    Image = store.types["sensor_msgs/msg/Image"]
    Time = store.types["builtin_interfaces/msg/Time"]
    if args.out.exists():
        shutil.rmtree(args.out)  # rosbags' Writer refuses to overwrite
    with Writer(args.out, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        c_img = writer.add_connection("/camera/image_raw", "sensor_msgs/msg/Image", typestore=store)
        c_info = writer.add_connection("/camera/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        c_pose = writer.add_connection("/ground_truth/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        for i, k in enumerate(ping_pong(len(images), args.frames)):
            stamp = START_NS + i * PERIOD_NS
            t = Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
            info, pose, img = infos[k], poses[k], images[k]
            info.header.stamp = t
            pose.header.stamp = t
            header = type(info.header)(stamp=t, frame_id=info.header.frame_id)
            image = Image(header=header, height=img.shape[0], width=img.shape[1], encoding="mono8",
                          is_bigendian=0, step=img.shape[1], data=np.ascontiguousarray(img).reshape(-1))
            writer.write(c_img, stamp, store.serialize_cdr(image, "sensor_msgs/msg/Image"))
            writer.write(c_info, stamp, store.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            writer.write(c_pose, stamp, store.serialize_cdr(pose, "geometry_msgs/msg/PoseStamped"))
    print(f"{args.out}: {args.frames} frames {images[0].shape[1]}x{images[0].shape[0]} mono8")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
