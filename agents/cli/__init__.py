"""The ``tensegrity-gym`` command line: a parser per subcommand, built from the registry
:data:`COMMANDS` (each module of this package contributes its own), and the mapping of
a user's mistake to one line on stderr and exit status 2.

- :mod:`agents.cli.arguments`: the value types and options the subcommands share.
- :mod:`agents.cli.errors`: the errors that are a user's, one line each; SIGTERM.
- :mod:`agents.cli.training`: ``demo``, ``train``, ``evaluate``, ``gait``.
- :mod:`agents.cli.bench`: ``bench``.
- :mod:`agents.cli.recordings`: ``record``, ``estimate``, ``calibrate``, ``view``.
- :mod:`agents.cli.identify`: ``identify``.
- :mod:`agents.cli.link`: ``emulate``.

The handlers import what they run when they run, so ``tensegrity-gym --help`` stays fast.
"""

from __future__ import annotations

import argparse
import logging

from agents.cli import bench, identify, link, recordings, training
from agents.cli.arguments import Command, SubcommandParser
from agents.cli.errors import log, one_line, user_errors

__all__ = ["COMMANDS", "build_parser", "main"]

COMMANDS: tuple[Command, ...] = (
    *training.COMMANDS,
    *bench.COMMANDS,
    *recordings.COMMANDS,
    *identify.COMMANDS,
    *link.COMMANDS,
)
"""Every subcommand, in the order ``tensegrity-gym --help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    """The ``tensegrity-gym`` parser: ``--verbose`` and a subparser per command of
    :data:`COMMANDS` (whose ``func`` default runs it)."""
    parser = argparse.ArgumentParser(
        prog="tensegrity-gym", description="Tensegrity robots with estimated-state observations."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=SubcommandParser)
    for command in COMMANDS:
        command_parser = sub.add_parser(command.name, help=command.help)
        command.add_arguments(command_parser)
        command_parser.set_defaults(func=command.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (default: the process's arguments) names; its exit status:
    130 when interrupted, 2 for a user's mistake (one line on stderr, the traceback only
    with --verbose)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except user_errors() as err:
        if args.verbose:
            log.exception("%s failed", args.command)
        else:
            log.error("%s", one_line(err))
        return 2
