"""The real robot over the network: the wire (ROS 2 messages over Zenoh), who may speak
on it (credentials, the session that owns the motors), the driver behind ``Backend``,
command safety, and the robot emulator that stands in for it."""

from hardware.link.driver import DriverTimeouts, ZenohDriver
from hardware.link.safety import CommandLimiter, Watchdog
from hardware.link.security import LinkSecurity
from hardware.link.wire import LinkAddress, LinkError

__all__ = [
    "CommandLimiter",
    "DriverTimeouts",
    "LinkAddress",
    "LinkError",
    "LinkSecurity",
    "Watchdog",
    "ZenohDriver",
]
