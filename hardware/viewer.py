"""The live view: a run's topics streamed to Foxglove over its WebSocket protocol.

:class:`FoxgloveSink` is a recording sink (:class:`~hardware.recording.WriterSink`)
whose episodes go to a Foxglove WebSocket server (the ``foxglove-sdk`` package, an
optional extra: ``pip install tensegrity-gym[viewer]``) instead of a bag: the very
messages a bag gets (ROS 2 types, CDR bytes, ``ros2msg`` schemas), so Foxglove shows a
live run as it shows a bag. ``gym.make(..., render_mode="foxglove")`` and the
``tensegrity-gym view`` command use it; the server stops when the env closes. Clients
speaking either name of the protocol connect (``foxglove.sdk.v1``, what the SDK's
server takes, and ``foxglove.websocket.v1``, what Lichtblick and the ws-protocol
libraries ask for): the public port is a relay (:mod:`hardware.foxglove_relay`) in
front of the SDK's server on a loopback port.

The header messages (the robot description and its URDF, run info, calibration) and
``/tf_static`` are sent again every second of run time, so that a viewer that connects
late gets them (what a bag records latched, :data:`hardware.bag.messages.LATCHED_TOPICS`).
"""

from __future__ import annotations

import logging
import socket
import time
from typing import TYPE_CHECKING, Any

from hardware.bag import messages as m
from hardware.bag.writer import MessageWriter
from hardware.foxglove_relay import TIMEOUTS, SubprotocolRelay
from hardware.recording import WriterSink
from tensegrity_gym.model.checks import check_whole
from tensegrity_gym.model.samples import seconds_to_ns

if TYPE_CHECKING:
    from collections.abc import Mapping

    from hardware.recording import Episode
    from tensegrity_gym.model.estimate import Estimate

__all__ = ["DEFAULT_PORT", "INSTALL_HINT", "FoxgloveSink", "ViewerError", "foxglove_module"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port: ws://localhost:8765."""
INSTALL_HINT = "the live view needs foxglove-sdk: pip install tensegrity-gym[viewer]"
HEADER_PERIOD = 1.0
"""Seconds of run time between repeats of the header messages."""
STOP_TIMEOUT = 2.0
"""Seconds ``close`` waits for the server to let go of its port."""
_START_FAILURES: tuple[type[Exception], ...] = (OSError, *TIMEOUTS)
"""What a server that cannot open its port raises."""


class ViewerError(RuntimeError):
    """The live view cannot start: no foxglove-sdk, or the port is taken."""


def foxglove_module() -> Any:
    """The ``foxglove`` package; :class:`ViewerError` with the install hint without it."""
    try:
        import foxglove
    except ImportError:
        raise ViewerError(INSTALL_HINT) from None
    return foxglove


class _LiveWriter(MessageWriter):
    """One episode's messages, handed to the sink's channels; the header again every
    :data:`HEADER_PERIOD` seconds of run time."""

    def __init__(self, sink: FoxgloveSink, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._sink = sink
        # What a bag records latched; a WebSocket has no such thing, hence the repeats.
        self._header: dict[str, bytes] = {}
        self._header_ns = 0
        self._period_ns = seconds_to_ns(HEADER_PERIOD)

    def __str__(self) -> str:
        return "the live view"

    def _emit(self, topic: str, ns: int, raw: bytes) -> None:
        if topic in m.LATCHED_TOPICS and topic not in self._header:
            self._header[topic] = raw  # the first ones: the episode's header, /tf_static
        self._sink.publish(topic, self.codec.topics.types[topic], ns, raw)

    def _opened(self, ns: int) -> None:
        self._header_ns = ns

    def _written(self, ns: int) -> None:
        if ns - self._header_ns >= self._period_ns:
            self._header_ns = ns
            for topic, raw in self._header.items():
                self._sink.publish(topic, self.codec.topics.types[topic], ns, raw)


class FoxgloveSink(WriterSink):
    """Streams each episode to a Foxglove WebSocket server at ``ws://HOST:PORT``.

    Args:
        port: the server's port (0: a free one; :attr:`port` says which).
        host: the address it listens on (``127.0.0.1``: this machine only).
        speed: run time per wall-clock time: 1 streams in real time (each estimate
            waits for its moment), 0 as fast as the run goes.
        run_info, markers, wall_clock: as :class:`~hardware.recording.WriterSink`
            takes them.

    Raises:
        ViewerError: foxglove-sdk is not installed, or the server cannot listen there.
    """

    def __init__(
        self,
        port: int = DEFAULT_PORT,
        *,
        host: str = "127.0.0.1",
        speed: float = 1.0,
        run_info: Mapping[str, Any] | None = None,
        markers: bool = True,
        wall_clock: bool = True,
    ) -> None:
        check_whole("port", port, 0, 65535, where="FoxgloveSink")
        if not speed >= 0:
            raise ValueError(f"viewer speed must be 0 (no pacing) or positive, got {speed}")
        super().__init__(run_info, markers=markers, wall_clock=wall_clock)
        foxglove = foxglove_module()
        self._foxglove = foxglove
        self._context = foxglove.Context()
        self._server, self._relay = _start(foxglove, self._context, host, port)
        self.port: int = self._relay.port
        self.host = host
        self.url = f"ws://{'localhost' if host == '127.0.0.1' else host}:{self.port}"
        self.speed = speed
        self._channels: dict[str, Any] = {}
        self._clock: tuple[float, float] | None = None  # (run time, monotonic time) at start
        log.info("Foxglove live view at %s", self.url)

    def _open(self, episode: Episode) -> MessageWriter:
        self._clock = None
        return _LiveWriter(
            self,
            episode.description,
            episode.calibration,
            episode.run_info,
            clock_origin_ns=episode.clock_origin_ns,
            markers=self.markers,
        )

    def publish(self, topic: str, msgtype: str, ns: int, raw: bytes) -> None:
        """Log one message's CDR bytes on its channel (made on first use)."""
        channel = self._channels.get(topic)
        if channel is None:
            text, _ = m.typestore().generate_msgdef(msgtype, ros_version=2)
            schema = self._foxglove.Schema(name=msgtype, encoding="ros2msg", data=text.encode())
            channel = self._foxglove.Channel(
                topic, schema=schema, message_encoding="cdr", context=self._context
            )
            self._channels[topic] = channel
        channel.log(raw, log_time=ns)

    def estimate(self, estimate: Estimate, t_log: float) -> None:
        self._pace(t_log)
        super().estimate(estimate, t_log)

    def _pace(self, t: float) -> None:
        """Wait until run time ``t`` (s) is due on the wall clock (at :attr:`speed`)."""
        if not self.speed:
            return
        now = time.monotonic()
        if self._clock is None:
            self._clock = (t, now)
            return
        due = self._clock[1] + (t - self._clock[0]) / self.speed
        if due > now:
            time.sleep(due - now)

    def close(self) -> None:
        """Stop the server; on return nothing listens on its port (the server lets go
        of it a moment after ``stop``). Safe to call twice."""
        self.end()
        server, self._server = self._server, None
        if server is None:
            return
        try:
            server.stop()  # it sends its clients a close frame, through the relay
        finally:
            try:
                self._relay.close()
            finally:
                for channel in self._channels.values():
                    channel.close()
                self._channels.clear()
        _wait_until_closed(self.host, self.port, STOP_TIMEOUT)
        log.info("Foxglove live view at %s stopped", self.url)


def _start(foxglove: Any, context: Any, host: str, port: int) -> tuple[Any, SubprotocolRelay]:
    """The SDK's server on a free loopback port and the relay in front of it on
    ``host:port`` (both subprotocol names: :mod:`hardware.foxglove_relay`);
    :class:`ViewerError` where either cannot listen."""
    try:
        server = foxglove.start_server(
            name="tensegrity-gym", host="127.0.0.1", port=0, context=context
        )
    except RuntimeError as err:
        raise ViewerError(f"cannot start the Foxglove server: {err}") from None
    try:
        relay = SubprotocolRelay(server.port, host=host, port=port)
    except _START_FAILURES as err:
        server.stop()
        raise ViewerError(f"cannot start the Foxglove server on {host}:{port}: {err}") from None
    return server, relay


def _wait_until_closed(host: str, port: int, timeout: float) -> None:
    """Return once a connection to ``host:port`` is refused, or after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            if s.connect_ex((host, port)) != 0:
                return
        time.sleep(0.005)
    log.warning("the Foxglove server at %s:%d still accepts connections", host, port)
