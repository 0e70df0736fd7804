"""Subcommands of ``phantom``: the hardware-in-the-loop bench: phantom hil ....

Only argparse is imported at module load; handlers import what they need when they run.
"""

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add this part's subcommands to the ``phantom`` parser."""
