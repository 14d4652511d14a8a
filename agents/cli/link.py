"""``emulate``: the simulated robot served over the robot wire (the emulator's own options)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from agents.cli.arguments import Command

if TYPE_CHECKING:
    import argparse

__all__ = ["COMMANDS"]


def add_emulate(emu: argparse.ArgumentParser) -> None:
    """``emulate``'s options: the emulator's own."""
    from hardware.link.emulator import add_arguments

    add_arguments(emu)


def run_emulate(args: argparse.Namespace) -> int:
    """``emulate``: serve the simulated robot until stopped."""
    from hardware.link.emulator import run_from_args

    return run_from_args(args)


COMMANDS = (
    Command(
        "emulate",
        "serve the simulated robot over the robot wire (Zenoh), in real time",
        add_emulate,
        run_emulate,
    ),
)
"""The subcommands of this module."""
