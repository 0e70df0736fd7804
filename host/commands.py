"""Subcommands of ``phantom``: the daemon and its clients: daemon, status, set, vent, clear-fault, run-scene, watch.

Only argparse is imported at module load; handlers import what they need when they run.
"""

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add this part's subcommands to the ``phantom`` parser."""
