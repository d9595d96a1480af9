"""Small bags for tests, written into tmp_path from the bundled ones: the first frames of a bag, some topics
left out, image messages changed on the way (pytest puts ``test/`` on sys.path: ``from bag_copies import ...``).
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def copy_frames(src: Path, dst: Path, n_images: int, *, repeat: int = 1, drop_topics: Collection[str] = (),
                image: Callable[[Any], Any] | None = None, camera_info: Callable[[Any], Any] | None = None) -> Path:
    """The first ``n_images`` images of ``src`` with the messages of the other topics up to the last of them
    (but ``drop_topics``) into a new MCAP bag directory ``dst`` (``dst/<dst name>.mcap`` + metadata.yaml).
    ``repeat`` > 1 plays the images forward, backward, ... with increasing stamps (images and camera_info
    only). ``image`` / ``camera_info`` change each message of that kind (deserialised) before it is written."""
    with AnyReader([src], default_typestore=TYPESTORE) as reader:
        msgs = [m for m in reader.messages() if m[0].topic not in drop_topics]
        conns = {c.id: c for c in reader.connections if c.topic not in drop_topics}
        images = [m for m in msgs if m[0].msgtype.endswith("Image")][:n_images]
        t_end = images[-1][1]
        kept = [m for m in msgs if m[1] <= t_end]

        def changed(con: Any, raw: bytes, restamp: int | None = None) -> bytes:
            fn = image if con.msgtype.endswith("Image") else camera_info if con.msgtype.endswith("CameraInfo") \
                else None
            if fn is None and restamp is None:
                return raw
            msg = reader.deserialize(raw, con.msgtype)
            if restamp is not None:
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(restamp, 10**9)
            if fn is not None:
                msg = fn(msg)
            return TYPESTORE.serialize_cdr(msg, con.msgtype)

        with Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            out_conns = {cid: w.add_connection(c.topic, c.msgtype, typestore=TYPESTORE) for cid, c in conns.items()}
            if repeat == 1:
                for con, t, raw in kept:
                    w.write(out_conns[con.id], t, changed(con, raw))
                return dst
            info = next(m for m in kept if m[0].msgtype.endswith("CameraInfo"))
            order = [*range(len(images)), *range(len(images) - 2, 0, -1)]
            t0, period = images[0][1], images[1][1] - images[0][1]
            for i in range(len(order) * repeat):
                con, _, raw = images[order[i % len(order)]]
                t = t0 + i * period
                w.write(out_conns[con.id], t, changed(con, raw, t))
                w.write(out_conns[info[0].id], t, changed(info[0], info[2], t))
    return dst


def storage_file(bag_dir: Path) -> Path:
    """The one storage file of a bag directory written by :func:`copy_frames`."""
    (path,) = bag_dir.glob("*.mcap")
    return path
