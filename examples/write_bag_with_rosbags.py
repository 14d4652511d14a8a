"""Write a bag that tensegrity-gym reads, with nothing but `rosbags`: what a lab does to
bring its own robot's logs here (or what a ROS 2 robot publishes, recorded by
`ros2 bag record -s mcap`).

Usage: python examples/write_bag_with_rosbags.py OUT_DIR [ROBOT_YAML]

The robot here stands still at its nominal shape for 5 s, so every sensor reading is
exact; a real robot's driver fills in its own readings. Then:
    tensegrity-gym estimate OUT_DIR --estimator ukf --out estimate_out
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

sys.path.insert(0, str(Path(__file__).parent))  # lab_messages, beside this file
from lab_messages import ahrs, rod_orientations, typestore, uwb_round

from tensegrity_gym.model.description import dump_robot, load_robot

CONTROL_PERIOD = 0.1  # s: one command per period
JOINTS = "sensor_msgs/msg/JointState"


def main(out: Path, robot: str = "three_bar") -> None:
    d = load_robot(robot)  # a lab's own YAML in the same schema works the same way
    store = typestore()
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Point = T["geometry_msgs/msg/Point"]

    def header(ns: int, frame: str = "") -> object:
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def rest_lengths(ns: int, values: np.ndarray) -> object:
        """A JointState of the actuated cables' rest lengths (m), by cable name."""
        return T[JOINTS](
            header=header(ns), name=actuated, position=values,
            velocity=np.empty(0), effort=np.empty(0),
        )  # fmt: skip

    nodes = d.initial_positions  # (n, 3) m: the robot's pose, which a real robot measures
    anchors = d.anchors
    modules = np.vstack([nodes, anchors])
    n_modules = len(modules)
    actuated = [d.cables[k].name for k in d.actuated]
    hold = d.rest_lengths[d.actuated]
    quats = rod_orientations(d)

    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        conns: dict[str, object] = {}

        def write(topic: str, msgtype: str, msg: object, ns: int) -> None:
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=store)
            bag.write(conns[topic], ns, store.serialize_cdr(msg, msgtype))

        # Once, first: the robot and the calibration (no UWB offsets measured: zeros).
        write(
            "/tensegrity/robot_description_yaml",
            "std_msgs/msg/String",
            T["std_msgs/msg/String"](data=dump_robot(d)),
            0,
        )
        write(
            "/tensegrity/calibration",
            "tensegrity_msgs/msg/SensorCalibration",
            T["tensegrity_msgs/msg/SensorCalibration"](
                header=header(0, "world"),
                anchors=[Point(x=a[0], y=a[1], z=a[2]) for a in anchors],
                n_modules=n_modules,
                uwb_offsets=np.zeros(n_modules * n_modules),
                camera_pose=np.eye(4).reshape(16),
            ),
            0,
        )
        for step in range(50):
            t0 = round(step * CONTROL_PERIOD * 1e9)
            if step > 0:  # the command that drives the period starting at t0
                write("/commands/rest_length_targets", JOINTS, rest_lengths(t0, hold), t0)
            for k in range(1, 11):  # encoders and AHRS at 100 Hz within the period
                ns = t0 + k * 10_000_000
                write("/motors/rest_lengths", JOINTS, rest_lengths(ns, hold), ns)
                for rod, q in zip(d.rods, quats, strict=True):
                    imu = ahrs(store, header(ns, rod.name), q)
                    write(f"/{rod.name}/imu/data", "sensor_msgs/msg/Imu", imu, ns)
            # one UWB round per period: every endcap to every anchor
            ns = t0 + 100_000_000
            write(
                "/uwb/ranges",
                "tensegrity_msgs/msg/UwbRangeArray",
                uwb_round(store, header(ns), d),
                ns,
            )


if __name__ == "__main__":
    main(Path(sys.argv[1]), *sys.argv[2:3])
