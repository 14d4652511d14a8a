"""ROS 2 bags in the sqlite3 storage (``.db3``), the default of ROS 2 before Iron, read
through rosbags' public :class:`rosbags.rosbag2.Reader`.

They open as :class:`~hardware.bag.salvage.McapBag` does, so that
:class:`~hardware.bag.reader.BagReader` reads both the same way. A ``.db3`` file is a
database written transaction by transaction: what a crash leaves is what sqlite itself
recovers, so there is no chunk-level salvage here and no span is ever reported lost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rosbags.rosbag2 import Reader

from hardware.bag.salvage import Topic

if TYPE_CHECKING:
    from collections.abc import Callable, Collection, Iterator
    from pathlib import Path

    from hardware.bag.salvage import LostSpan

__all__ = ["Sqlite3Bag", "is_sqlite3_bag"]


def is_sqlite3_bag(path: Path, storage: object) -> bool:
    """Whether the bag folder ``path`` (its ``metadata.yaml`` naming ``storage``) is a
    sqlite3 bag: so named, or holding ``.db3`` files and no ``.mcap``."""
    if storage == "sqlite3":
        return True
    return path.is_dir() and any(path.glob("*.db3")) and not any(path.glob("*.mcap"))


class Sqlite3Bag:
    """The sqlite3 bag at the folder ``path``: its topics and its messages in log-time
    order, with the attributes of :class:`~hardware.bag.salvage.McapBag`.

    Raises:
        ValueError: rosbags cannot open it (its message names the reason).
    """

    recovered = False
    """A sqlite3 bag is never read past damage: sqlite recovers what it can itself."""

    def __init__(self, path: Path) -> None:
        try:
            self._reader = Reader(path)  # no metadata.yaml: FileNotFoundError
            self._reader.open()
        except Exception as err:  # rosbags raises its own ReaderError and sqlite3's errors
            raise ValueError(" ".join(str(err).split()) or type(err).__name__) from None
        self.topics = [
            Topic(c.topic, c.msgtype, c.digest, c.msgcount) for c in self._reader.connections
        ]
        self.known_lost: list[LostSpan] = []
        self.message_count = int(self._reader.message_count)
        self.start_ns = int(self._reader.start_time) if self.message_count else 0

    def set_on_damage(self, on_damage: Callable[[LostSpan], None]) -> None:
        """Nothing to hand on: no chunk of a sqlite3 bag is ever found damaged."""

    def messages(self, topics: Collection[str]) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log time ns, CDR bytes) of every message on ``topics``, in log-time
        order."""
        wanted = [c for c in self._reader.connections if c.topic in topics]
        for connection, ns, raw in self._reader.messages(connections=wanted):
            yield connection.topic, ns, bytes(raw)

    def close(self) -> None:
        self._reader.close()
