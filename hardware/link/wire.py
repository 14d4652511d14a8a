"""The wire between the env and a robot: ROS 2 messages in CDR over Zenoh.

Topics and types are the bag's (:mod:`hardware.bag.messages`). A ROS topic maps to a
Zenoh key expression as zenoh-bridge-ros2dds maps it: the leading ``/`` dropped, after
an optional namespace prefix (``/rod_0/imu/data_raw`` -> ``rod_0/imu/data_raw``, or
``lab1/rod_0/imu/data_raw`` with the prefix ``lab1``). Payloads are the CDR bytes of
the message, encapsulation header included, exactly what the bridge forwards, so a
ROS 2 robot reaches the env through the bridge with no code of ours on it.

Robot to env: every sensor topic, ``/tensegrity/robot_description_yaml`` (the robot
description the env checks; an older robot's YAML on ``/robot_description`` is taken
too), ``/robot_description`` (the URDF, for viewers), ``/tensegrity/calibration`` and
``/camera/camera_info`` (republished about once a second, the way a latched topic
reaches late joiners over the bridge), and optionally ground truth from motion capture.
Env to robot: ``/commands/rest_length_targets`` and ``/tensegrity/heartbeat``.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hardware.bag.messages import COMMAND_TOPIC

if TYPE_CHECKING:
    import zenoh

__all__ = [
    "COMMAND_TOPIC",
    "HEARTBEAT_TOPIC",
    "LinkAddress",
    "LinkError",
    "open_session",
]

HEARTBEAT_TOPIC = "/tensegrity/heartbeat"
"""std_msgs/Header at a fixed rate; the robot holds its motors when they stop."""
HEARTBEAT_TYPE = "std_msgs/msg/Header"

_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws)/(\[[0-9a-fA-F:]+\]|[A-Za-z0-9_.\-]+):(\d{1,5})$")


class LinkError(RuntimeError):
    """The robot link failed: no connection, no data, or the robot went quiet."""


@dataclass(frozen=True)
class LinkAddress:
    """Where the robot is: a Zenoh endpoint, the session mode and the topic prefix.

    Written ``zenoh/ENDPOINT[?mode=client|peer&prefix=NAME]``, for example
    ``zenoh/tcp/127.0.0.1:7447`` or ``zenoh/tcp/robot.local:7447?prefix=lab1``.
    """

    endpoint: str
    """A Zenoh locator, ``tcp/HOST:PORT``."""
    mode: str = "client"
    prefix: str = ""

    @classmethod
    def parse(cls, text: str) -> LinkAddress:
        if not text.startswith("zenoh/"):
            raise ValueError(f"robot address {text!r} must start with 'zenoh/'")
        rest, _, query = text[len("zenoh/") :].partition("?")
        if not _ENDPOINT.match(rest):
            raise ValueError(
                f"robot address {text!r}: {rest!r} is not an endpoint like 'tcp/127.0.0.1:7447'"
            )
        port = int(rest.rsplit(":", 1)[1])
        if not 0 < port < 65536:
            raise ValueError(f"robot address {text!r}: port {port} is out of range")
        options: dict[str, str] = {}
        for item in filter(None, query.split("&")):
            key, eq, value = item.partition("=")
            if not eq or key not in ("mode", "prefix"):
                raise ValueError(
                    f"robot address {text!r}: option {item!r}; valid options are mode=client|peer "
                    "and prefix=NAME"
                )
            options[key] = value
        mode = options.get("mode", "client")
        if mode not in ("client", "peer"):
            raise ValueError(f"robot address {text!r}: mode must be client or peer, not {mode!r}")
        prefix = options.get("prefix", "").strip("/")
        if prefix and not re.fullmatch(r"[A-Za-z0-9_\-/]+", prefix):
            raise ValueError(f"robot address {text!r}: prefix {prefix!r} has invalid characters")
        return cls(rest, mode, prefix)

    def __str__(self) -> str:
        options = []
        if self.mode != "client":
            options.append(f"mode={self.mode}")
        if self.prefix:
            options.append(f"prefix={self.prefix}")
        return f"zenoh/{self.endpoint}" + ("?" + "&".join(options) if options else "")

    def key(self, topic: str) -> str:
        """The Zenoh key of a ROS topic."""
        return f"{self.prefix}/{topic.lstrip('/')}" if self.prefix else topic.lstrip("/")

    def topic(self, key: str) -> str | None:
        """The ROS topic of a Zenoh key; None if the key is outside the prefix."""
        if self.prefix:
            head = self.prefix + "/"
            if not key.startswith(head):
                return None
            key = key[len(head) :]
        return "/" + key

    @property
    def everything(self) -> str:
        """The key expression that matches every topic under the prefix."""
        return f"{self.prefix}/**" if self.prefix else "**"


def session_config(
    address: LinkAddress, *, listen: bool, open_timeout: float = 10.0
) -> zenoh.Config:
    """A Zenoh configuration that talks to ``address`` only: multicast scouting off, so
    that robots and tests on one network do not find each other by accident.

    ``open_timeout`` (s) bounds one attempt to open the transport, the handshake
    included: a port that accepts connections and never answers (a silent listener)
    holds an attempt this long (Zenoh's own default is 10 s)."""
    import zenoh

    config = zenoh.Config()
    open_ms = max(1, math.ceil(open_timeout * 1000.0))
    config.insert_json5("transport/unicast/open_timeout", json.dumps(open_ms))
    config.insert_json5("mode", json.dumps("peer" if listen else address.mode))
    config.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        config.insert_json5("listen/endpoints", json.dumps([address.endpoint]))
    else:
        config.insert_json5("connect/endpoints", json.dumps([address.endpoint]))
        # Come back quickly when the robot restarts.
        config.insert_json5(
            "connect/retry",
            json.dumps(
                {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 1.5}
            ),
        )
    return config


def open_session(address: LinkAddress, *, listen: bool, timeout: float) -> zenoh.Session:
    """A Zenoh session to (or, with ``listen``, serving at) ``address``; retries for up
    to ``timeout`` seconds, then raises :class:`LinkError` naming the address.

    Each attempt may block (a silent listener holds the handshake), so each is bounded
    by the time left, not only checked between attempts."""
    import zenoh

    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        try:
            return zenoh.open(session_config(address, listen=listen, open_timeout=left))
        except zenoh.ZError as err:
            if time.monotonic() >= deadline - 0.1:  # no time for another attempt
                verb = "listen at" if listen else "reach the robot at"
                raise LinkError(f"could not {verb} {address} within {timeout:g} s: {err}") from None
            time.sleep(0.1)
