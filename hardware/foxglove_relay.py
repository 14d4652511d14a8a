"""A WebSocket port that speaks both names of the Foxglove protocol.

foxglove-sdk 0.30 (0.30.3, the newest release as this is written; its server is
compiled Rust with no option for it) accepts only the WebSocket subprotocol
``foxglove.sdk.v1`` and answers HTTP 400 to a client asking for
``foxglove.websocket.v1``, the name Lichtblick, older Foxglove apps and the
ws-protocol client libraries send. The two names stand for the same messages
(serverInfo, advertise, subscribe, messageData, ...): the SDK renamed the protocol and
kept it. :class:`SubprotocolRelay` therefore listens on the public port, rewrites the
one header of the opening handshake (``Sec-WebSocket-Protocol``) on the way to the SDK
server on a loopback port and back, and then copies bytes both ways untouched: frames
carry no subprotocol name, and whatever else the two ends agree on (compression)
passes through. A client asking for ``foxglove.sdk.v1`` (or both) is passed as it is.

The relay runs an asyncio loop in a thread of its own; :meth:`SubprotocolRelay.close`
stops listening, drops every connection and joins the thread. The SDK server sees each
client as a connection from 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Coroutine
    from typing import Any, TypeVar

    T = TypeVar("T")

__all__ = [
    "LEGACY_SUBPROTOCOL",
    "SDK_SUBPROTOCOL",
    "TIMEOUTS",
    "SubprotocolRelay",
    "rewrite_protocol",
]

log = logging.getLogger(__name__)

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
"""The name foxglove-sdk's server accepts."""
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
"""The name of the same protocol that Lichtblick and ws-protocol clients ask for."""
HANDSHAKE_TIMEOUT = 10.0
"""Seconds a client (and the SDK server) has to complete its half of the handshake."""
START_TIMEOUT = 5.0
"""Seconds the relay's thread has to start listening, and to stop."""
SHUTDOWN_GRACE = 0.5
"""Seconds :meth:`SubprotocolRelay.close` lets open connections end on their own."""
TIMEOUTS: tuple[type[Exception], ...] = (
    TimeoutError,
    asyncio.TimeoutError,
    concurrent.futures.TimeoutError,
)
"""What a timed-out wait raises: one class from Python 3.11, three before."""
_DROPPED: tuple[type[Exception], ...] = (OSError, EOFError, asyncio.LimitOverrunError, *TIMEOUTS)
"""What ends one client's connection without it being the relay's fault."""
_CHUNK = 64 * 1024  # bytes copied at a time
_HEADER = "sec-websocket-protocol"
_END = b"\r\n\r\n"  # the end of an HTTP head


def rewrite_protocol(head: bytes, old: str, new: str) -> tuple[bytes, bool]:
    """``head`` (an HTTP request or response head, ending in a blank line) with its
    ``Sec-WebSocket-Protocol`` header(s) made one saying ``new`` where they offer
    ``old`` and not ``new``; else ``head`` unchanged. Returns it and whether it changed."""
    lines = head.decode("latin-1").split("\r\n")
    offered = [
        token.strip()
        for line in lines[1:]
        if line.partition(":")[0].strip().lower() == _HEADER
        for token in line.partition(":")[2].split(",")
    ]
    if old not in offered or new in offered:
        return head, False
    kept = [line for line in lines if line.partition(":")[0].strip().lower() != _HEADER]
    # The head ends "\r\n\r\n": the last two lines are empty; the header goes before them.
    out = [*kept[:-2], f"Sec-WebSocket-Protocol: {new}", *kept[-2:]]
    return "\r\n".join(out).encode("latin-1"), True


async def _pump(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    """Copy ``src`` to ``dst`` until ``src`` ends, then end ``dst`` for writing; a peer
    that resets takes the other side down with it."""
    try:
        while data := await src.read(_CHUNK):
            dst.write(data)
            await dst.drain()
        if dst.can_write_eof():
            dst.write_eof()
    except OSError:
        dst.transport.abort()


class SubprotocolRelay:
    """Listens on ``host:port`` and relays each WebSocket client to the Foxglove server
    at ``upstream_host:upstream_port``, asking it for :data:`SDK_SUBPROTOCOL` where the
    client asked for :data:`LEGACY_SUBPROTOCOL` (see the module docstring).

    Args:
        upstream_port: the SDK server's port.
        host: the address to listen on.
        port: the port to listen on (0: a free one; :attr:`port` says which; a host
            name of several addresses, ``localhost`` on a dual-stack machine, then gets
            one port per address, and :attr:`port` is the first's).
        upstream_host: the SDK server's address.

    Raises:
        OSError: the port cannot be listened on (taken, a bad address).
    """

    def __init__(
        self,
        upstream_port: int,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        upstream_host: str = "127.0.0.1",
    ) -> None:
        self.upstream = (upstream_host, upstream_port)
        self._connections: set[asyncio.Task[None]] = set()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="foxglove-relay", daemon=True
        )
        self._thread.start()
        try:
            self._server = self._call(asyncio.start_server(self._serve, host, port))
        except BaseException:
            self._stop_loop()
            raise
        self.port: int = self._server.sockets[0].getsockname()[1]

    def _call(self, coroutine: Coroutine[Any, Any, T]) -> T:
        """Run ``coroutine`` on the relay's loop and wait for its result."""
        future = asyncio.run_coroutine_threadsafe(coroutine, self._loop)
        return future.result(START_TIMEOUT)

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(START_TIMEOUT)
        if self._thread.is_alive():
            log.warning("the Foxglove relay's thread did not stop")
            return
        self._loop.close()

    @property
    def closed(self) -> bool:
        return self._loop.is_closed() or not self._thread.is_alive()

    def close(self) -> None:
        """Stop listening and drop every connection; on return nothing listens on
        :attr:`port`. Safe to call twice."""
        if self.closed:
            return
        try:
            self._call(self._shutdown())
        finally:
            self._stop_loop()

    async def _shutdown(self) -> None:
        """Stop listening; give the connections :data:`SHUTDOWN_GRACE` to end (the SDK
        server, stopped first, closes them with a close frame), then drop the rest."""
        self._server.close()
        if self._connections:
            _, pending = await asyncio.wait(list(self._connections), timeout=SHUTDOWN_GRACE)
            for task in pending:
                task.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        await self._server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One client's connection, from its handshake to its end."""
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        peer = writer.get_extra_info("peername")
        try:
            await self._relay(reader, writer)
        except _DROPPED as err:
            # A client that goes away mid-handshake, or an SDK server that is stopping.
            log.debug("Foxglove relay: dropped %s: %s", peer, err or type(err).__name__)
        except asyncio.CancelledError:
            # close() dropped it; ending quietly spares asyncio's "exception in callback"
            # report (the start_server callback asks a cancelled task for its exception).
            log.debug("Foxglove relay: dropped %s on close", peer)
        finally:
            self._connections.discard(task)
            writer.transport.abort()

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Pass the handshake on with its subprotocol rewritten, then copy both ways."""
        request = await asyncio.wait_for(reader.readuntil(_END), HANDSHAKE_TIMEOUT)
        request, legacy = rewrite_protocol(request, LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL)
        up_reader, up_writer = await asyncio.wait_for(
            asyncio.open_connection(*self.upstream), HANDSHAKE_TIMEOUT
        )
        try:
            up_writer.write(request)
            response = await asyncio.wait_for(up_reader.readuntil(_END), HANDSHAKE_TIMEOUT)
            if legacy:  # the client is told the name it asked for
                response, _ = rewrite_protocol(response, SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL)
            writer.write(response)
            await asyncio.gather(_pump(reader, up_writer), _pump(up_reader, writer))
            # Both ends are done: let the last bytes (a close frame) out before closing.
            for w in (writer, up_writer):
                w.close()
            await asyncio.wait_for(
                asyncio.gather(writer.wait_closed(), up_writer.wait_closed()), HANDSHAKE_TIMEOUT
            )
        finally:
            up_writer.transport.abort()
