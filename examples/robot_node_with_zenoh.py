"""The robot's side of the wire, written with nothing but `eclipse-zenoh` and `rosbags`:
what a lab runs on (or beside) its robot so that `gym.make(..., driver="zenoh/...")`
drives it. A ROS 2 robot needs none of this: zenoh-bridge-ros2dds forwards its topics.

Usage: python examples/robot_node_with_zenoh.py [tcp/127.0.0.1:7447] [SECONDS] [ZENOH.json5]

This robot stands still at its nominal shape: its motors follow the rest-length
commands at their maximum speed, its encoders report them at 100 Hz, the AHRS of each
rod reports the rod's orientation at 100 Hz, and the UWB modules range every endcap to
every anchor at 10 Hz. It holds its motors before the first heartbeat and when none has
come for 0.15 s. A real robot fills in its own readings.

It obeys one env at a time: each env names its session in the header.frame_id of its
heartbeats and commands; the first session whose heartbeats arrive owns the motors until
its heartbeats stop for 0.15 s, and the commands and heartbeats of any other session (or
of none) are refused, counted and logged. A Zenoh configuration file (the third
argument) adds TLS with mutual authentication and user-password authentication:
scripts/make_link_certs.py writes one (robot_zenoh.json5), with the endpoint tls/HOST:PORT.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).parent))  # lab_messages, beside this file
from lab_messages import ahrs, rod_orientations, typestore, uwb_round

from tensegrity_gym.model.description import dump_robot, load_robot

JOINTS = "sensor_msgs/msg/JointState"
WATCHDOG = 0.15  # s without a heartbeat before the motors hold
log = logging.getLogger("robot_node")


class Owner:
    """The session that owns the motors: the first whose heartbeats arrive, until they
    stop for WATCHDOG seconds. Others are refused and counted (``refused``, by kind and
    sender), and logged (the 1st, 10th, 100th, then every 1000th of each)."""

    def __init__(self) -> None:
        self.session = ""
        self.last_heartbeat = -1.0  # monotonic s
        self.refused: dict[str, int] = {}

    def alive(self, now: float) -> bool:
        return bool(self.session) and now - self.last_heartbeat < WATCHDOG

    def heartbeat(self, session: str, now: float) -> None:
        if session and (session == self.session or not self.alive(now)):
            if session != self.session:
                log.info("session %s owns the motors", session)
            self.session, self.last_heartbeat = session, now
        else:
            self.refuse("heartbeat", session)

    def obeys(self, session: str, now: float) -> bool:
        alive = self.alive(now)
        if session and session == self.session and alive:
            return True
        # Nobody owning the motors, they hold: an env's first command, which goes out
        # just before its first heartbeat, is not a refusal worth a log line.
        if not session or alive:
            self.refuse("command", session)
        return False

    def refuse(self, kind: str, session: str) -> None:
        name = session or "(no session)"
        key = f"{kind} from {name}"
        self.refused[key] = self.refused.get(key, 0) + 1
        if self.refused[key] in (1, 10, 100) or self.refused[key] % 1000 == 0:
            log.warning("refused a %s (%d so far): %s owns the motors",
                        key, self.refused[key], self.session or "nobody")  # fmt: skip


def listen(endpoint: str, zenoh_config: str | None = None) -> zenoh.Session:
    """A Zenoh session listening at ``endpoint`` (``tcp/HOST:PORT``), as a peer, with no
    multicast scouting; ``zenoh_config``: a Zenoh JSON5 file with the lab's TLS and
    users (``robot_zenoh.json5`` of scripts/make_link_certs.py)."""
    config = zenoh.Config.from_file(zenoh_config) if zenoh_config else zenoh.Config()
    config.insert_json5("mode", json.dumps("peer"))
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def latched(store: Any, d: Any, header: object) -> tuple[object, object]:
    """The messages a late joiner needs, republished about once a second: the robot
    description (YAML) and the calibration (the anchors of the layout, no offsets)."""
    T = store.types
    Point = T["geometry_msgs/msg/Point"]
    n_modules = len(d.initial_positions) + len(d.anchors)
    calibration = T["tensegrity_msgs/msg/SensorCalibration"](
        header=header,
        anchors=[Point(x=a[0], y=a[1], z=a[2]) for a in d.anchors],
        n_modules=n_modules,
        uwb_offsets=np.zeros(n_modules * n_modules),  # no offsets measured
        camera_pose=np.eye(4).reshape(16),
    )
    return T["std_msgs/msg/String"](data=dump_robot(d)), calibration


def serve(
    endpoint: str = "tcp/127.0.0.1:7447",
    seconds: float = 1e9,
    robot: str = "three_bar",
    zenoh_config: str | None = None,
) -> Owner:
    d = load_robot(robot)
    store = typestore()
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]

    def header(frame: str = "") -> object:
        ns = time.time_ns()  # the robot's clock, synchronised with the env's machine
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    actuated = [d.cables[k].name for k in d.actuated]
    lo = np.array([d.cables[k].motor.min_rest_length for k in d.actuated])
    hi = np.array([d.cables[k].motor.max_rest_length for k in d.actuated])
    speed = np.array([d.cables[k].motor.max_speed for k in d.actuated])
    rest = d.rest_lengths[d.actuated].copy()  # the motors' present rest lengths (m)
    target = rest.copy()
    owner = Owner()
    lock = threading.Lock()

    session = listen(endpoint, zenoh_config)

    def put(topic: str, msgtype: str, msg: object) -> None:
        # ROS topic /a/b is Zenoh key a/b; the payload is the message's CDR bytes.
        session.put(topic.lstrip("/"), bytes(store.serialize_cdr(msg, msgtype)))

    def on_command(sample: zenoh.Sample) -> None:
        msg = store.deserialize_cdr(sample.payload.to_bytes(), JOINTS)
        values = dict(zip(msg.name, np.asarray(msg.position), strict=True))
        with lock:
            if not owner.obeys(msg.header.frame_id, time.monotonic()):
                return
            if set(values) == set(actuated) and np.all(np.isfinite(list(values.values()))):
                target[:] = np.clip([values[n] for n in actuated], lo, hi)

    def on_heartbeat(sample: zenoh.Sample) -> None:
        msg = store.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/Header")
        with lock:
            owner.heartbeat(msg.frame_id, time.monotonic())

    subscribers = [
        session.declare_subscriber("commands/rest_length_targets", on_command),
        session.declare_subscriber("tensegrity/heartbeat", on_heartbeat),
    ]
    description, calibration = latched(store, d, header("world"))
    quats = rod_orientations(d)

    start = time.monotonic()
    tick = 0
    while time.monotonic() - start < seconds:
        if tick % 100 == 0:  # about once a second, for late joiners
            put("/tensegrity/robot_description_yaml", "std_msgs/msg/String", description)
            put("/tensegrity/calibration", "tensegrity_msgs/msg/SensorCalibration", calibration)
        with lock:
            alive = owner.alive(time.monotonic())
            goal = target.copy() if alive else rest.copy()  # hold without heartbeats
            target[:] = goal
        rest += np.clip(goal - rest, -speed * 0.01, speed * 0.01)
        put(
            "/motors/rest_lengths",
            JOINTS,
            T[JOINTS](
                header=header(), name=actuated, position=rest.copy(),
                velocity=np.empty(0), effort=np.empty(0),
            ),
        )  # fmt: skip
        for rod, q in zip(d.rods, quats, strict=True):
            put(f"/{rod.name}/imu/data", "sensor_msgs/msg/Imu", ahrs(store, header(rod.name), q))
        if tick % 10 == 0:  # a UWB round: every endcap to every anchor
            put("/uwb/ranges", "tensegrity_msgs/msg/UwbRangeArray", uwb_round(store, header(), d))
        tick += 1
        time.sleep(max(start + 0.01 * tick - time.monotonic(), 0.0))  # 100 Hz
    for subscriber in subscribers:
        subscriber.undeclare()
    session.close()
    return owner


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    zenoh.init_log_from_env_or("warn")  # Zenoh's own log: peers refused by TLS, say
    config_file = sys.argv[3] if len(sys.argv) > 3 else None
    serve(*sys.argv[1:2], *[float(s) for s in sys.argv[2:3]], zenoh_config=config_file)
