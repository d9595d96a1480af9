"""Odometry out: reading the ``nav_msgs/Odometry`` messages of a bag back (e.g. ``/vo/odometry`` of an
``epi-vo replay`` output.mcap), with their full 6x6 covariances.

The frame record (frames.jsonl) carries only the diagonal of the pose covariance, in the pipeline's frame;
the odometry message carries the whole matrix as published, in its ``header.frame_id`` (odom), over
(x, y, z, rot_x, rot_y, rot_z). Fields are read by name, as everywhere in ``epi_vo.io``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from epi_vo.core.errors import BagError
from epi_vo.io.msgconv import stamp_to_ns

ODOMETRY_MSGTYPE = "nav_msgs/msg/Odometry"
VO_ODOMETRY_TOPIC = "/vo/odometry"
VO_UNITS_ODOMETRY_TOPIC = "/vo/odometry/vo_units"

_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_ERRORS = (AnyReaderError, ReaderError, SerdeError, OSError, UnicodeDecodeError, KeyError, TypeError, ValueError)


class OdometryTrack(NamedTuple):
    """The odometry messages of one topic, in bag order.

    ``positions`` (N, 3) and ``quats_xyzw`` (N, 4): pose of ``child_frame_id`` in ``frame_id``;
    ``pose_covariance`` (N, 6, 6) over (x, y, z, rot_x, rot_y, rot_z) in ``frame_id``;
    ``twist_covariance`` (N, 6, 6) in ``child_frame_id``; ``stamps_ns`` (N,) header stamps;
    ``linear_velocity`` / ``angular_velocity`` (N, 3) the twist in ``child_frame_id``.
    """

    stamps_ns: NDArray[np.int64]
    positions: NDArray[np.float64]
    quats_xyzw: NDArray[np.float64]
    pose_covariance: NDArray[np.float64]
    twist_covariance: NDArray[np.float64]
    frame_id: str
    child_frame_id: str
    linear_velocity: NDArray[np.float64] = np.zeros((0, 3))
    angular_velocity: NDArray[np.float64] = np.zeros((0, 3))


def read_odometry(path: str | Path, topic: str = VO_ODOMETRY_TOPIC) -> OdometryTrack:
    """Every ``nav_msgs/Odometry`` message of ``topic`` in the bag (directory or bare .mcap / .db3).

    Raises:
        BagError: the bag cannot be opened or read, or has no such topic (the message lists the
            odometry topics it has), or the topic is not of type nav_msgs/msg/Odometry.
    """
    return _read_tracks(path, topic)[topic]


def read_estimate_odometry(path: str | Path) -> OdometryTrack:
    """The motion as vo_node estimated it, in its own units, from an output bag: at each stamp the
    ``/vo/odometry/vo_units`` message when there is one (the units were VO units: ``/vo/odometry`` then held its
    position), else the ``/vo/odometry`` one (metres). A bag without the vo_units topic (written before it
    existed) gives ``/vo/odometry``. Frame ids are ``/vo/odometry``'s. BagError as :func:`read_odometry`."""
    tracks = _read_tracks(path, VO_ODOMETRY_TOPIC, VO_UNITS_ODOMETRY_TOPIC)
    fused, vo = tracks[VO_ODOMETRY_TOPIC], tracks.get(VO_UNITS_ODOMETRY_TOPIC)
    if vo is None:
        return fused
    row = {int(t): i for i, t in enumerate(vo.stamps_ns)}
    take = [(i, row[int(t)]) for i, t in enumerate(fused.stamps_ns) if int(t) in row]

    def merged(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        out = a.copy()
        for i, j in take:
            out[i] = b[j]
        return out

    return fused._replace(
        positions=merged(fused.positions, vo.positions), quats_xyzw=merged(fused.quats_xyzw, vo.quats_xyzw),
        pose_covariance=merged(fused.pose_covariance, vo.pose_covariance),
        twist_covariance=merged(fused.twist_covariance, vo.twist_covariance),
        linear_velocity=merged(fused.linear_velocity, vo.linear_velocity),
        angular_velocity=merged(fused.angular_velocity, vo.angular_velocity))


def _read_tracks(path: str | Path, topic: str, *optional: str) -> dict[str, OdometryTrack]:
    """The odometry of ``topic`` (required) and of those of ``optional`` the bag has, by topic."""
    p = Path(path)
    if not p.exists():
        msg = f"bag not found: {p}"
        raise BagError(msg)
    rows: dict[str, list[Any]] = {}
    try:
        with AnyReader([p], default_typestore=_TYPESTORE) as reader:
            types = {name: info.msgtype for name, info in reader.topics.items()}
            if topic not in types:
                odoms = sorted(t for t, ty in types.items() if ty == ODOMETRY_MSGTYPE)
                msg = f"bag {p} has no topic {topic} (odometry topics: {', '.join(odoms) or 'none'})"
                raise BagError(msg)
            wanted = [topic, *(t for t in optional if t in types)]
            for t in wanted:
                if types[t] != ODOMETRY_MSGTYPE:
                    msg = f"topic {t} in bag {p} is {types[t]}, not {ODOMETRY_MSGTYPE}"
                    raise BagError(msg)
                rows[t] = []
            connections = [c for c in reader.connections if c.topic in rows]
            for connection, _, raw in reader.messages(connections):
                rows[connection.topic].append(reader.deserialize(raw, connection.msgtype))
            return {t: _track(msgs) for t, msgs in rows.items()}
    except BagError:
        raise
    except _ERRORS as exc:
        msg = f"cannot read odometry {topic} from bag {p}: {exc}"
        raise BagError(msg) from exc


def _track(msgs: list[Any]) -> OdometryTrack:
    """The track of deserialised nav_msgs/Odometry messages, read by field name."""
    stamps: list[int] = []
    pos: list[list[float]] = []
    quat: list[list[float]] = []
    pcov: list[NDArray[np.float64]] = []
    tcov: list[NDArray[np.float64]] = []
    lin: list[list[float]] = []
    ang: list[list[float]] = []
    frame_id = child = ""
    for m in msgs:
        stamps.append(stamp_to_ns(m.header.stamp))
        frame_id, child = str(m.header.frame_id), str(m.child_frame_id)
        pp, q = m.pose.pose.position, m.pose.pose.orientation
        pos.append([float(pp.x), float(pp.y), float(pp.z)])
        quat.append([float(q.x), float(q.y), float(q.z), float(q.w)])
        pcov.append(np.asarray(m.pose.covariance, dtype=np.float64).reshape(6, 6))
        tcov.append(np.asarray(m.twist.covariance, dtype=np.float64).reshape(6, 6))
        v, w = m.twist.twist.linear, m.twist.twist.angular
        lin.append([float(v.x), float(v.y), float(v.z)])
        ang.append([float(w.x), float(w.y), float(w.z)])
    n = len(stamps)
    return OdometryTrack(np.asarray(stamps, dtype=np.int64).reshape(n), np.asarray(pos, np.float64).reshape(n, 3),
                         np.asarray(quat, np.float64).reshape(n, 4), np.asarray(pcov, np.float64).reshape(n, 6, 6),
                         np.asarray(tcov, np.float64).reshape(n, 6, 6), frame_id, child,
                         np.asarray(lin, np.float64).reshape(n, 3), np.asarray(ang, np.float64).reshape(n, 3))
