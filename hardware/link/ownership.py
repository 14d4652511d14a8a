"""Which env drives the motors: a session identity on every command and heartbeat, and
the robot's side rule that obeys only the env that took the motors.

Each driver names its session (:func:`new_session_id`) in the ``header.frame_id`` of its
commands (``sensor_msgs/JointState``) and heartbeats (``std_msgs/Header``): a ROS field
that a plain ROS robot ignores, so the wire stays ROS's. On the robot's side
(:class:`MotorOwner`), the first session whose heartbeats arrive owns the motors until
its heartbeats stop for the watchdog time; meanwhile the commands and heartbeats of any
other session, and any command without a session, are refused, counted and logged,
naming the session. It keeps a second env (or a stray test, or a script left running)
from fighting the first over the motors; it is no defence against a peer that means
harm, which the link's credentials keep out (:mod:`hardware.link.security`).
"""

from __future__ import annotations

import os
import secrets
import socket
import threading
import time
from collections import Counter
from typing import TYPE_CHECKING, Any

from hardware.link.safety import Watchdog

if TYPE_CHECKING:
    import logging
    from collections.abc import Callable

__all__ = ["MotorOwner", "frame_id_of", "new_session_id"]

LOG_EVERY = 5.0
"""Seconds between two log lines about one kind of message refused from one session
(all are counted)."""
NO_SESSION = "(none)"
"""How a message without a session identity is named in counts and logs."""


def new_session_id() -> str:
    """A session identity: ``env@HOST:PID/TOKEN``, so that a robot's log names the
    machine and process of a refused sender; the token tells apart two sessions of one
    process."""
    host = socket.gethostname().split(".")[0] or "host"
    return f"env@{host}:{os.getpid()}/{secrets.token_hex(4)}"


def frame_id_of(raw: bytes) -> str | None:
    """The ``header.frame_id`` of a CDR message that begins with a std_msgs/Header
    (JointState, Header itself); None if the bytes are too short or not CDR.

    Read in place: the robot's side checks the sender of every heartbeat (20 Hz) before
    it decodes anything else."""
    # CDR: 4 bytes of encapsulation, stamp sec (4) and nanosec (4), then the string's
    # length (4, the terminating NUL included) and its bytes.
    if len(raw) < 16 or raw[0] != 0 or raw[1] not in (0, 1):
        return None
    size = int.from_bytes(raw[12:16], "little" if raw[1] == 1 else "big")
    if size < 1 or 16 + size > len(raw) or raw[15 + size] != 0:
        return None
    try:
        return raw[16 : 15 + size].decode("utf-8")
    except UnicodeDecodeError:
        return None


class MotorOwner:
    """The robot's side rule for who drives the motors (thread-safe; times are seconds
    of any monotonic clock).

    Args:
        timeout: seconds without the owner's heartbeat after which the motors hold and
            another session may take them (the watchdog time).
        log: where refusals and changes of owner are logged.
        clock: the monotonic clock the log's rate limit reads.
    """

    def __init__(
        self, timeout: float, log: logging.Logger, clock: Callable[[], float] | None = None
    ) -> None:
        self.watchdog = Watchdog(timeout)
        self.owner: str | None = None
        """The session that owns (or last owned) the motors."""
        self.refused: Counter[str] = Counter()
        """Refused messages by ``"command"``/``"heartbeat"``."""
        self.refused_by: Counter[str] = Counter()
        """Refused messages by session."""
        self._log = log
        self._clock = clock or time.monotonic
        self._logged_at: dict[str, float] = {}  # "kind session" -> when last logged
        self._lock = threading.Lock()

    def heartbeat(self, session: str | None, now: float) -> bool:
        """A heartbeat from ``session`` at ``now``: True if it feeds the watchdog (the
        owner's, or a session taking motors nobody holds)."""
        with self._lock:
            if session and (session == self.owner or self.watchdog.tripped(now)):
                if session != self.owner:
                    before = self.owner
                    self.owner = session
                    self._log.info(
                        "session %s owns the motors%s",
                        session,
                        "" if before is None else f" ({before}'s heartbeats stopped)",
                    )
                self.watchdog.feed(now)
                return True
            self._refuse("heartbeat", session)
            return False

    def may_command(self, session: str | None, now: float) -> bool:
        """Whether a command from ``session`` at ``now`` is kept rather than refused:
        the owner's, or any session's while nobody owns the motors (an env's first
        command goes out just before its first heartbeat: no refusal to log). Whether a
        kept command moves the motors is :meth:`obeys`'s to say, tick by tick."""
        with self._lock:
            if session and (session == self.owner or self.watchdog.tripped(now)):
                return True
            self._refuse("command", session)
            return False

    def obeys(self, session: str | None, now: float) -> bool:
        """Whether a command of ``session`` moves the motors at ``now``."""
        with self._lock:
            return bool(session) and session == self.owner and not self.watchdog.tripped(now)

    def _refuse(self, kind: str, session: str | None) -> None:
        name = session or NO_SESSION
        self.refused[kind] += 1
        self.refused_by[name] += 1
        now = self._clock()
        if now - self._logged_at.get(f"{kind} {name}", -float("inf")) >= LOG_EVERY:
            self._logged_at[f"{kind} {name}"] = now
            why = f"session {self.owner} owns the motors" if session else "it names no session"
            self._log.warning(
                "refused a %s from %s: %s (%d refused from it so far)",
                kind,
                name,
                why,
                self.refused_by[name],
            )

    def counts(self) -> dict[str, Any]:
        """Refused messages by kind and by session, for stats and tests."""
        with self._lock:
            return {"refused": dict(self.refused), "refused_by": dict(self.refused_by)}
