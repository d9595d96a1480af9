"""Bags with a modified wheel odometry stream, for the tests of the one wheel rule (replay and node alike).

``write_wheel_variant(src, dst, modify)`` copies a bag message for message (same log times, so the same
arrival order) with each ``nav_msgs/Odometry`` message of ``topic`` passed through ``modify(k, msg)``, which
changes the deserialized message in place (its header stamp, its position). ``n_images`` keeps the first
images only (and the other messages logged up to the last of them).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
NS = 1_000_000_000


def shift_stamp(msg: Any, delta_ns: int) -> None:
    """Move a message's header stamp by ``delta_ns``."""
    t = msg.header.stamp.sec * NS + msg.header.stamp.nanosec + delta_ns
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, NS)


def every_third_early(k: int, msg: Any) -> None:
    """Every third message stamped 0.3 s early (a driver that stamps some messages with a stale clock)."""
    if k % 3 == 2:
        shift_stamp(msg, -300_000_000)


def write_wheel_variant(src: Path, dst: Path, modify: Callable[[int, Any], None], *, topic: str = "/wheel/odom",
                        n_images: int | None = None) -> Path:
    with AnyReader([src], default_typestore=TYPESTORE) as reader:
        msgs = list(reader.messages())
        if n_images is not None:
            images = [t for con, t, _ in msgs if con.msgtype.endswith("Image")][:n_images]
            msgs = [m for m in msgs if m[1] <= images[-1]]
        with Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            out = {c.id: w.add_connection(c.topic, c.msgtype, typestore=TYPESTORE) for c in reader.connections}
            k = 0
            for con, t, raw in msgs:
                if con.topic == topic:
                    msg = reader.deserialize(raw, con.msgtype)
                    modify(k, msg)
                    k += 1
                    raw = TYPESTORE.serialize_cdr(msg, con.msgtype)
                w.write(out[con.id], t, raw)
    return dst
