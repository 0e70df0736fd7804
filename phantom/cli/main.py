"""The ``phantom`` command line.

Each part of the stack registers its own subcommands from a ``cli`` module with a
``register(subparsers)`` function; those modules import only argparse at load time, so that
``phantom --help`` and every subcommand start fast. A subcommand's handler is stored as ``run``
and returns the process exit status.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

import phantom

#: Modules that add subcommands, in the order they appear in ``phantom --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "phantom.cli.model",
    "phantom.cli.inverse",
    "phantom.cli.scan",
    "phantom.cli.shape",
    "phantom.cli.design",
    "phantom.cli.calibrate",
    "phantom.cli.corrections",
    "phantom.cli.characterise",
    "phantom.cli.hil",
    "phantom.cli.motion",
    "phantom.cli.daemon",
    "phantom.cli.client",
    "phantom.cli.report",
)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, with every part's subcommands registered."""
    parser = argparse.ArgumentParser(
        prog="phantom",
        description="Drive and model the active prostate phantom. Offline commands need no daemon.",
    )
    parser.add_argument("--version", action="version", version=f"phantom {phantom.__version__}")
    parser.add_argument("--log-level", choices=("debug", "info", "warning", "error"), default="info",
                        help="what the log on stderr shows (default info; under systemd, levels are journald "
                        "priorities)")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module_name in COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def join_list_values(argv: list[str]) -> list[str]:
    """``--option -,3.5,3.5`` as ``--option=-,3.5,3.5``: argparse takes a value that starts with '-' for an
    option, but a comma-separated list whose first item is free ('-') is a value (no option has a comma)."""
    joined: list[str] = []
    for argument in argv:
        if joined and joined[-1].startswith("--") and "=" not in joined[-1] and argument.startswith("-") and (
                "," in argument):
            joined[-1] = f"{joined[-1]}={argument}"
        else:
            joined.append(argument)
    return joined


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``phantom`` console script; returns the exit status."""
    from phantom.host.logs import configure_logging

    parser = build_parser()
    args = parser.parse_args(join_list_values(sys.argv[1:] if argv is None else list(argv)))
    configure_logging(getattr(args, "log_level", "info"))
    try:
        return int(args.run(args) or 0)
    except phantom.PhantomError as error:
        print(f"phantom {args.command}: error: {error}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # whoever read our output has gone (`phantom ... --json | head`): not an error; stdout goes nowhere now
        # so that the interpreter's final flush does not raise again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception:
        # a bug: logged with its traceback (journald keeps it under systemd), then the usual exit status 1
        logging.getLogger("phantom").exception("phantom %s failed unexpectedly", args.command)
        return 1
    except KeyboardInterrupt:
        print(f"phantom {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
