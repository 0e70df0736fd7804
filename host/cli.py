"""The ``phantom`` command line.

Each part of the stack registers its own subcommands from a ``cli`` module with a
``register(subparsers)`` function; those modules import only argparse at load time, so that
``phantom --help`` and every subcommand start fast. A subcommand's handler is stored as ``run``
and returns the process exit status.
"""

import argparse
import importlib
import sys

import phantom

#: Modules that add subcommands, in the order they appear in ``phantom --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "phantom.model.cli",
    "phantom.model.inverse_cli",
    "phantom.hil.cli",
    "phantom.host.commands",
)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, with every part's subcommands registered."""
    parser = argparse.ArgumentParser(
        prog="phantom",
        description="Drive and model the active prostate phantom. Offline commands need no daemon.",
    )
    parser.add_argument("--version", action="version", version=f"phantom {phantom.__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module_name in COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``phantom`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except phantom.PhantomError as error:
        print(f"phantom {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"phantom {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
