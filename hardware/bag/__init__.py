"""Runs as ROS 2 bags (MCAP storage): writing, reading, and replay behind ``Backend``."""

from hardware.bag.reader import BagError, BagPeriod, BagReader, LostSpan, find_bags, read_run
from hardware.bag.replay import ReplayBackend
from hardware.bag.writer import BagWriter

__all__ = [
    "BagError",
    "BagPeriod",
    "BagReader",
    "BagWriter",
    "LostSpan",
    "ReplayBackend",
    "find_bags",
    "read_run",
]
