"""The emulator as a child process: for tests, benchmarks and notebooks."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import time
from typing import TYPE_CHECKING

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
    """

    def __init__(
        self,
        robot: str = "three_bar",
        *,
        port: int | None = None,
        options: Sequence[str] = (),
        start_timeout: float = 30.0,
    ) -> None:
        self.robot = robot
        self.port = port or free_port()
        self.options = list(options)
        self.start_timeout = start_timeout
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def address(self) -> str:
        """The driver address: ``zenoh/tcp/127.0.0.1:PORT``."""
        return f"zenoh/tcp/127.0.0.1:{self.port}"

    def start(self) -> EmulatorProcess:
        """Start and wait until it listens; :class:`LinkError` if it does not."""
        if self.process is not None and self.process.poll() is None:
            return self
        args = [sys.executable, "-m", "hardware.link.emulator", "--robot", self.robot]
        args += ["--listen", f"tcp/127.0.0.1:{self.port}", *self.options]
        self.process = subprocess.Popen(
            args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=dict(os.environ)
        )
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
