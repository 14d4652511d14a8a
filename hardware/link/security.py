"""Who may speak on the robot link: TLS with mutual authentication and Zenoh's
user-password authentication, from a security file that each side names.

A security file is YAML; relative paths in it are relative to the file's folder::

    tls:                        # TLS, both sides prove who they are (mTLS)
      ca: ca.pem                # the lab's CA: the peer's certificate must be signed by it
      certificate: robot.pem    # this side's certificate, signed by the lab's CA
      key: robot.key            # its private key
    users_file: users.txt       # the robot's side: "user:password" lines; others are refused
    user: env                   # the env's side: the user it logs in as ...
    password_file: env.password # ... and the file whose first line is its password

The robot's side (``tensegrity-gym emulate --security FILE``) listens with its
certificate and refuses a peer whose certificate the lab's CA did not sign, or that
sends none; with ``users_file`` also one that does not log in as a listed user. The env's
side (``zenoh/tls/HOST:PORT?security=FILE``) checks that the robot's certificate is the
CA's and names ``HOST``. ``scripts/make_link_certs.py`` writes both files and what they
name. Zenoh reports a refusal only in its own log: :func:`forward_zenoh_log` brings it
into this process's log (the emulator does so).
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import stat
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import yaml

if TYPE_CHECKING:
    import zenoh

__all__ = ["LinkSecurity", "forward_zenoh_log"]

log = logging.getLogger(__name__)

_KEYS = ("tls", "users_file", "user", "password", "password_file")
_TLS_KEYS = ("ca", "certificate", "key")


class _InvalidError(ValueError):
    """A security file's problem, without the file's name (added by :meth:`load`)."""


@dataclass(frozen=True)
class LinkSecurity:
    """The credentials of one side of the link, read from a security file (see the
    module docstring). Paths are absolute; every file was found readable at load."""

    source: Path
    """The security file."""
    ca: Path | None = None
    """The lab's CA certificate (PEM); set with :attr:`certificate` and :attr:`key`."""
    certificate: Path | None = None
    key: Path | None = None
    users_file: Path | None = None
    """The listening side's ``user:password`` lines (Zenoh's dictionary file)."""
    user: str | None = None
    password: str | None = field(default=None, repr=False)

    @property
    def tls(self) -> bool:
        """Whether the link is TLS with mutual authentication."""
        return self.ca is not None

    @classmethod
    def load(cls, path: str | Path) -> LinkSecurity:
        """Read and check a security file: ValueError naming the file and what is
        wrong (a missing or unreadable file it names, an unknown key, a user without a
        password)."""
        source = Path(path).expanduser().absolute()
        try:
            raw = _read(source, "security")
        except _InvalidError as err:  # it names the security file itself
            raise ValueError(str(err)) from None
        try:
            return cls._from_mapping(source, yaml.safe_load(raw.decode("utf-8")))
        except _InvalidError as err:
            raise ValueError(f"security file {source}: {err}") from None
        except (UnicodeDecodeError, yaml.YAMLError) as err:
            first = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise ValueError(f"security file {source}: not YAML: {first}") from None

    @classmethod
    def _from_mapping(cls, source: Path, data: Any) -> LinkSecurity:
        if not isinstance(data, dict) or not data:
            raise _InvalidError(f"expected a mapping with some of {', '.join(_KEYS)}")
        unknown = sorted(set(map(str, data)) - set(_KEYS))
        if unknown:
            raise _InvalidError(f"unknown key {unknown[0]!r}; valid keys are {', '.join(_KEYS)}")
        folder = source.parent
        tls = data.get("tls")
        files: dict[str, Path | None] = dict.fromkeys(_TLS_KEYS)
        if tls is not None:
            if not isinstance(tls, dict) or sorted(map(str, tls)) != sorted(_TLS_KEYS):
                raise _InvalidError(f"tls must give exactly {', '.join(_TLS_KEYS)}")
            for name in _TLS_KEYS:
                files[name] = _pem_file(folder, f"tls.{name}", tls[name], name == "key")
        users_file = None
        if data.get("users_file") is not None:
            users_file = _file(folder, "users_file", data["users_file"])
            _check_users(users_file)
        user, password = _login(folder, data)
        ca, certificate, key = (files[name] for name in _TLS_KEYS)
        return cls(source, ca, certificate, key, users_file, user, password)

    def apply(self, config: zenoh.Config, *, listen: bool) -> None:
        """Insert these credentials into a Zenoh configuration for the listening
        (robot's) side or the connecting (env's) side; ValueError for a file that
        gives the listening side nothing to check a peer with (an env's file)."""
        if listen and not (self.tls or self.users_file is not None):
            raise ValueError(
                f"security file {self.source}: the robot's side needs tls or users_file "
                "(this is an env's file?); with neither it would let anyone in"
            )
        if self.tls:
            side = "listen" if listen else "connect"
            tls: dict[str, Any] = {
                "root_ca_certificate": str(self.ca),
                f"{side}_certificate": str(self.certificate),
                f"{side}_private_key": str(self.key),
                # Both directions: the robot checks the env's certificate, and the env
                # sends one only with this set.
                "enable_mtls": True,
            }
            if not listen:
                tls["verify_name_on_connect"] = True  # the robot's certificate names HOST
            config.insert_json5("transport/link/tls", json.dumps(tls))
        usrpwd: dict[str, str] = {}
        if self.user is not None and self.password is not None:
            usrpwd.update(user=self.user, password=self.password)
        if listen and self.users_file is not None:
            usrpwd["dictionary_file"] = str(self.users_file)
        if usrpwd:
            config.insert_json5("transport/auth/usrpwd", json.dumps(usrpwd))


def _read(path: Path, what: str) -> bytes:
    """The bytes of ``path``; _InvalidError naming ``what`` and the file when it is missing,
    not a file, or unreadable."""
    if not path.exists():
        raise _InvalidError(f"{what} file {path} does not exist")
    if not path.is_file():
        raise _InvalidError(f"{what} {path} is not a file")
    try:
        return path.read_bytes()
    except OSError as err:
        raise _InvalidError(f"{what} file {path} cannot be read: {err.strerror}") from None


def _file(folder: Path, what: str, value: Any) -> Path:
    if not isinstance(value, str) or not value:
        raise _InvalidError(f"{what} must be a file name, not {value!r}")
    path = (folder / Path(value).expanduser()).absolute()
    _read(path, what)
    return path


def _pem_file(folder: Path, what: str, value: Any, private: bool) -> Path:
    """A PEM file's path; _InvalidError when it holds no PEM block of the expected kind."""
    path = _file(folder, what, value)
    text = _read(path, what)
    marker = b"PRIVATE KEY-----" if private else b"-----BEGIN CERTIFICATE-----"
    if marker not in text:
        kind = "private key" if private else "certificate"
        raise _InvalidError(f"{what} file {path} holds no PEM {kind}")
    if private and os.name == "posix" and path.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        # Not refused (a lab may share a test key), but whoever reads it can be this side.
        log.warning("robot link: the private key %s is readable by others (chmod 600 it)", path)
    return path


def _check_users(path: Path) -> None:
    lines = [s.strip() for s in _read(path, "users_file").decode("utf-8", "replace").splitlines()]
    entries = [s for s in lines if s and not s.startswith("#")]
    if not entries:
        raise _InvalidError(f"users_file {path} lists no user")
    for number, line in enumerate(lines, start=1):
        if line and not line.startswith("#") and not re.fullmatch(r"[^:\s]+:\S+", line):
            raise _InvalidError(f"users_file {path}, line {number}: expected user:password")


def _login(folder: Path, data: dict[str, Any]) -> tuple[str | None, str | None]:
    """(user, password) of the connecting side, or (None, None)."""
    user, password = data.get("user"), data.get("password")
    password_file = data.get("password_file")
    if user is None:
        if password is not None or password_file is not None:
            raise _InvalidError("a password needs a user")
        return None, None
    if not isinstance(user, str) or not re.fullmatch(r"[^:\s]+", user):
        raise _InvalidError(f"user {user!r} must be a name without ':' or spaces")
    if (password is None) == (password_file is None):
        raise _InvalidError(f"user {user!r} needs one of password or password_file")
    if password_file is not None:
        path = _file(folder, "password_file", password_file)
        lines = _read(path, "password_file").decode("utf-8", "replace").splitlines()
        password = lines[0].strip() if lines else ""
        if not password:
            raise _InvalidError(f"password_file {path} is empty")
    if not isinstance(password, str) or not password:
        raise _InvalidError("password must be a non-empty string")
    return user, password


# ---------------------------------------------------------------------- Zenoh's log

_ZENOH_LINE = re.compile(
    r"^\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?ThreadId\(\d+\)\s+"
    r"(?P<target>[\w:]+):\s*(?P<message>.*)$"
)
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LEVELS = {"TRACE": logging.DEBUG, "DEBUG": logging.DEBUG, "INFO": logging.INFO}
_REFUSALS = (  # (Zenoh's message, why, whether Zenoh logged the connection before)
    (r"Invalid password", "wrong user or password", True),
    (r"UsrPwd extension - Recv InitSyn\. Expected extension", "no user or password", True),
    (r"peer sent no certificates", "it sent no certificate", False),
    (r"invalid peer certificate: (\w+)", "its certificate is not the lab CA's ({0})", False),
    (
        r"received fatal alert: (\w+)",
        "it broke off the TLS handshake ({0}): it does not trust this side's certificate",
        False,
    ),
    (r"received corrupt message of type InvalidContentType", "it does not speak TLS", False),
)
_SOURCE_LINE = re.compile(r"\s*at /\S+\.rs:\d+\.?\s*$")
"""Where in Zenoh's source a message was raised: noise in a lab's log."""


def without_source_line(message: str) -> str:
    """A Zenoh error or log message without its trailing ``at /path/file.rs:N``."""
    return _SOURCE_LINE.sub("", message)


LOG_EVERY = 5.0
"""Seconds between two log lines of one kind of refusal or Zenoh warning."""
_ACCEPTED = re.compile(
    r"Accepted (?:TLS|TCP) connection on \S+: (?P<peer>\S+?)\.?(?: Common Name: (?P<cn>\S+?)\.?)?$"
)
ZENOH_LOG_FILTER = ",".join(
    (
        "warn",
        # Each connection, and a peer refused by the user-password check: Zenoh logs
        # both at debug level only.
        "zenoh_link_tcp::unicast=debug",
        "zenoh_link_tls::unicast=debug",
        "zenoh_transport::unicast::establishment::accept=debug",
    )
)
"""Which of Zenoh's messages :func:`forward_zenoh_log` asks for (RUST_LOG overrides)."""


class _ZenohLog:
    """Turns Zenoh's log lines into records of ``logger``: a refused peer as a warning
    naming it (the address of the connection it came on, where Zenoh logged it) and why,
    a peer let in as an info line. A warning that repeats (a client retrying ten times a
    second) is logged at most every :data:`LOG_EVERY` seconds, with how many were
    left out."""

    def __init__(self, logger: logging.Logger) -> None:
        self.logger = logger
        self.peer: str | None = None  # the connection being accepted (one at a time)
        self._last: dict[str, tuple[float, int]] = {}  # warning -> (logged at, left out)

    def line(self, raw: str) -> None:
        text = _ANSI.sub("", raw).strip()
        match = _ZENOH_LINE.match(text)
        if match is None:
            if text:
                self.logger.info("%s", text)  # not Zenoh's (a library printing to stdout)
            return
        message = match["message"].replace(" Hint: increase the system open file limit.", "")
        message = without_source_line(message)
        accepted = _ACCEPTED.search(message)
        if accepted:
            cn = accepted["cn"]
            self.peer = accepted["peer"] + (f" (certificate {cn})" if cn else "")
            self.logger.debug("connection from %s", self.peer)
            return
        if message.startswith("New transport link accepted"):
            self.logger.info("let in %s", self.peer or "a peer")
            self.peer = None
            return
        for pattern, why, connected in _REFUSALS:
            found = re.search(pattern, message)
            if found:
                # A TLS handshake fails before Zenoh logs the connection: no address.
                peer = (self.peer if connected else None) or "a peer"
                self.peer = None
                self._warn(f"refused {peer}: {why.format(*found.groups())}", key=why)
                return
        level = _LEVELS.get(match["level"], logging.WARNING)
        if level < logging.WARNING:
            self.logger.log(level, "zenoh: %s: %s", match["target"], message)
        else:
            self._warn(f"zenoh: {match['target']}: {message}", key=message)

    def _warn(self, text: str, key: str) -> None:
        now = time.monotonic()
        logged_at, left_out = self._last.get(key, (-math.inf, 0))
        if now - logged_at < LOG_EVERY:
            self._last[key] = (logged_at, left_out + 1)
            return
        more = f" ({left_out} more like it since the last such line)" if left_out else ""
        self.logger.warning("%s%s", text, more)
        self._last[key] = (now, 0)


def forward_zenoh_log(logger: logging.Logger) -> TextIO:
    """Log Zenoh's messages (:data:`ZENOH_LOG_FILTER`) through ``logger``, refusals of
    peers as warnings; returns a stream on this process's original standard output.

    Zenoh writes its log to file descriptor 1; this points that descriptor at a pipe
    that a daemon thread reads, so ``sys.stdout`` is replaced by the returned stream:
    only the caller's own output (the emulator's ``ready`` line) goes there."""
    import zenoh

    original = os.fdopen(os.dup(1), "w", buffering=1)
    read_end, write_end = os.pipe()
    sys.stdout.flush()
    os.dup2(write_end, 1)
    os.close(write_end)
    sys.stdout = original
    sink = _ZenohLog(logger)

    def pump() -> None:
        with os.fdopen(read_end, "r", errors="replace") as lines:
            for raw in lines:
                try:
                    sink.line(raw)
                except Exception:  # a log line must never end the process
                    logger.debug("zenoh: could not log %r", raw, exc_info=True)

    threading.Thread(target=pump, name="zenoh-log", daemon=True).start()
    zenoh.init_log_from_env_or(ZENOH_LOG_FILTER)
    return original
