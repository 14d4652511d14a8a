"""How the command line fails: a user's mistake as one line and exit status 2 (a traceback
only with --verbose), and SIGTERM unwinding like Ctrl-C."""

from __future__ import annotations

import logging

__all__ = ["log", "one_line", "terminate", "user_errors"]

log = logging.getLogger("tensegrity_gym")


def one_line(err: BaseException) -> str:
    """An error's message on one line (whitespace runs, newlines among them, made one
    space), or its type's name where it has none."""
    return " ".join(str(err).split()) or type(err).__name__


def user_errors() -> tuple[type[BaseException], ...]:
    """What a user can cause (a bad id, path, bag, robot YAML or config; a robot that does
    not answer; an estimator that cannot start from the data; a missing optional
    package): one line on stderr and exit status 2, a traceback only with --verbose."""
    import gymnasium.error

    from estimation.ukf.initialise import InitialisationError
    from hardware.link.wire import LinkError
    from hardware.viewer import ViewerError

    return (ValueError, OSError, ImportError, LinkError, InitialisationError, ViewerError,
            gymnasium.error.Error)  # fmt: skip


def terminate(signum: int, frame: object) -> None:
    """A SIGTERM handler: exit with 128 + the signal's number, unwinding like Ctrl-C does
    (so open bags get closed)."""
    raise SystemExit(128 + signum)
