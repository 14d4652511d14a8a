"""The emulator as a child process: for tests, benchmarks and notebooks."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from hardware.link.security import LinkSecurity
from hardware.link.wire import LinkError

if TYPE_CHECKING:
    from collections.abc import Sequence
    from types import TracebackType

__all__ = ["EmulatorProcess", "free_port"]


def free_port() -> int:
    """A TCP port on the loopback interface that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class EmulatorProcess:
    """``python -m hardware.link.emulator`` in a child process, on a loopback port.

    Args:
        robot: robot preset or YAML.
        port: TCP port to listen on; a free one by default (kept across restarts).
        options: more command-line options (``["--latency", "0.01"]``).
        start_timeout: seconds to wait for the emulator to listen.
        security: the robot side's security file (``--security``); with a ``tls``
            section the emulator listens on ``tls/`` (its certificate must name
            127.0.0.1, as ``scripts/make_link_certs.py``'s do by default).
        log: a file the emulator's log (its standard error) is appended to; by default
            it is discarded.
    """

    def __init__(
        self,
        robot: str = "three_bar",
        *,
        port: int | None = None,
        options: Sequence[str] = (),
        start_timeout: float = 30.0,
        security: str | Path | None = None,
        log: str | Path | None = None,
    ) -> None:
        self.robot = robot
        self.port = port or free_port()
        self.options = list(options)
        self.start_timeout = start_timeout
        self.security = None if security is None else Path(security)
        # Checked here, so that a bad file is one line now, not a silent child later.
        tls = self.security is not None and LinkSecurity.load(self.security).tls
        self.protocol = "tls" if tls else "tcp"
        self.log = None if log is None else Path(log)
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def address(self) -> str:
        """The driver address without the env's credentials: ``zenoh/tcp/127.0.0.1:PORT``
        (``tls/`` with a TLS security file; add ``?security=ENV_FILE``)."""
        return f"zenoh/{self.protocol}/127.0.0.1:{self.port}"

    def start(self) -> EmulatorProcess:
        """Start and wait until it listens; :class:`LinkError` if it does not."""
        if self.process is not None and self.process.poll() is None:
            return self
        args = [sys.executable, "-m", "hardware.link.emulator", "--robot", self.robot]
        args += ["--listen", f"{self.protocol}/127.0.0.1:{self.port}", *self.options]
        args += ["--exit-with", str(os.getpid())]  # never outlives this process
        if self.security is not None:
            args += ["--security", str(self.security)]
        log: BinaryIO | int = subprocess.DEVNULL
        if self.log is not None:
            log = self.log.open("ab")  # the child holds its own descriptor
        try:
            self.process = subprocess.Popen(
                args, stdout=subprocess.PIPE, stderr=log, env=dict(os.environ)
            )
        finally:
            if not isinstance(log, int):
                log.close()
        assert self.process.stdout is not None
        deadline = time.monotonic() + self.start_timeout
        line = b""
        while time.monotonic() < deadline:
            ready, _, _ = select.select([self.process.stdout], [], [], 0.1)
            if ready:
                line = self.process.stdout.readline()
                if line.startswith(b"ready") or not line:
                    break
            if self.process.poll() is not None:
                break
        if not line.startswith(b"ready"):
            self.kill()
            raise LinkError(
                f"the emulator of {self.robot} did not start listening on port {self.port} "
                f"within {self.start_timeout:g} s"
            )
        return self

    def kill(self) -> None:
        """SIGKILL, as a robot losing power; waits so that no zombie is left."""
        if self.process is not None:
            if self.process.poll() is None:
                self.process.kill()
            self.process.wait()
            if self.process.stdout is not None:
                self.process.stdout.close()

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM and wait (SIGKILL after ``timeout``); the exit status."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self.process.stdout is not None:
            self.process.stdout.close()
        return self.process.returncode

    def __enter__(self) -> EmulatorProcess:
        return self.start()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        value: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()
