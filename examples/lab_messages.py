"""Messages of a robot standing still at its nominal shape, built with `rosbags` alone:
shared by the two lab examples (a bag written by hand, a robot node on Zenoh)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from hardware.bag.messages import CUSTOM_MESSAGES  # the same text as tensegrity_msgs/msg/*.msg

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

    from tensegrity_gym.model.description import RobotDescription

UNKNOWN = np.r_[-1.0, np.zeros(8)]  # covariance[0] = -1: the field is not provided


def typestore() -> Typestore:
    """ROS 2 Jazzy's types and the tensegrity_msgs ones."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in CUSTOM_MESSAGES.items():
        store.register(get_types_from_msg(text, name))
    return store


def rod_orientations(d: RobotDescription) -> list[np.ndarray]:
    """Per rod, the quaternion (x, y, z, w) taking the body z axis onto the rod's axis."""
    nodes, quats = d.initial_positions, []
    for i, j in d.rod_nodes:
        axis = (nodes[j] - nodes[i]) / np.linalg.norm(nodes[j] - nodes[i])
        q = np.array([*np.cross([0.0, 0.0, 1.0], axis), 1.0 + axis[2]])
        quats.append(q / np.linalg.norm(q))
    return quats


def ahrs(store: Typestore, header: Any, q: np.ndarray) -> Any:
    """A sensor_msgs/Imu that carries only an orientation."""
    T = store.types
    vector = T["geometry_msgs/msg/Vector3"]
    return T["sensor_msgs/msg/Imu"](
        header=header,
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        orientation_covariance=np.zeros(9),
        angular_velocity=vector(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=UNKNOWN,
        linear_acceleration=vector(x=0.0, y=0.0, z=0.0),
        linear_acceleration_covariance=UNKNOWN,
    )


def uwb_round(store: Typestore, header: Any, d: RobotDescription) -> Any:
    """A tensegrity_msgs/UwbRangeArray: every endcap ranged to every anchor, exactly."""
    T = store.types
    nodes, anchors = d.initial_positions, d.anchors
    ranges = [
        T["tensegrity_msgs/msg/UwbRange"](
            stamp=header.stamp,
            initiator=i,
            responder=len(nodes) + a,
            range=float(np.linalg.norm(anchors[a] - nodes[i])),
        )
        for i in range(len(nodes))
        for a in range(len(anchors))
    ]
    return T["tensegrity_msgs/msg/UwbRangeArray"](header=header, ranges=ranges)
