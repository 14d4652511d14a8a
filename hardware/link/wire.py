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
Env to robot: ``/commands/rest_length_targets`` and ``/tensegrity/heartbeat``, both
naming the env's session in their header's ``frame_id`` (:mod:`hardware.link.ownership`).

Plain TCP carries no encryption and no authentication: anyone who reaches the endpoint
may publish. ``?security=FILE`` (:mod:`hardware.link.security`) adds TLS with mutual
authentication and Zenoh's user-password authentication.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hardware.bag.messages import COMMAND_TOPIC
from hardware.link.security import LinkSecurity, without_source_line

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


_OPTIONS = ("mode", "prefix", "security")


@dataclass(frozen=True)
class LinkAddress:
    """Where the robot is: a Zenoh endpoint, the session mode, the topic prefix and the
    credentials.

    Written ``zenoh/ENDPOINT[?mode=client|peer&prefix=NAME&security=FILE]``, for example
    ``zenoh/tcp/127.0.0.1:7447``, ``zenoh/tcp/robot.local:7447?prefix=lab1`` or
    ``zenoh/tls/robot.local:7447?security=lab/env.yaml`` (a security file, see
    :mod:`hardware.link.security`; a ``tls/`` endpoint needs one with a ``tls`` section).
    """

    endpoint: str
    """A Zenoh locator, ``tcp/HOST:PORT``."""
    mode: str = "client"
    prefix: str = ""
    security: LinkSecurity | None = None
    """This side's credentials; None: no encryption, no authentication (loopback)."""

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
            if not eq or key not in _OPTIONS:
                raise ValueError(
                    f"robot address {text!r}: option {item!r}; valid options are mode=client|peer, "
                    "prefix=NAME and security=FILE"
                )
            options[key] = value
        mode = options.get("mode", "client")
        if mode not in ("client", "peer"):
            raise ValueError(f"robot address {text!r}: mode must be client or peer, not {mode!r}")
        prefix = options.get("prefix", "").strip("/")
        if prefix and not re.fullmatch(r"[A-Za-z0-9_\-/]+", prefix):
            raise ValueError(f"robot address {text!r}: prefix {prefix!r} has invalid characters")
        security = _security(text, rest, options.get("security"))
        return cls(rest, mode, prefix, security)

    def __str__(self) -> str:
        options = []
        if self.mode != "client":
            options.append(f"mode={self.mode}")
        if self.prefix:
            options.append(f"prefix={self.prefix}")
        if self.security is not None:
            options.append(f"security={self.security.source}")
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


def _security(text: str, endpoint: str, path: str | None) -> LinkSecurity | None:
    """The address's security file, loaded and checked; ValueError naming the option
    and the file when it is unusable or does not fit the endpoint's protocol."""
    protocol = endpoint.split("/", 1)[0]
    if path is None:
        if protocol == "tls":
            raise ValueError(
                f"robot address {text!r}: a tls/ endpoint needs security=FILE with a tls "
                "section (scripts/make_link_certs.py writes one)"
            )
        return None
    if not path:
        raise ValueError(f"robot address {text!r}: security= needs a file name")
    try:
        security = LinkSecurity.load(path)
    except ValueError as err:
        raise ValueError(f"robot address {text!r}: {err}") from None
    if security.tls and protocol != "tls":
        raise ValueError(
            f"robot address {text!r}: security={path} sets up TLS; the endpoint must be "
            f"tls/HOST:PORT, not {protocol}/"
        )
    return security


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
    if address.security is not None:
        address.security.apply(config, listen=listen)
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
                # Zenoh does not tell a refusal from silence on the connecting side.
                hint = (
                    "; with credentials, the robot may have refused them (its log says why)"
                    if address.security is not None and not listen
                    else ""
                )
                why = without_source_line(str(err))
                raise LinkError(
                    f"could not {verb} {address} within {timeout:g} s: {why}{hint}"
                ) from None
            time.sleep(0.1)
