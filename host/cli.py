"""The ``phantom`` command line.

Each part of the stack registers its own subcommands from a ``cli`` module with a
``register(subparsers)`` function; those modules import only argparse at load time, so that
``phantom --help`` and every subcommand start fast. A subcommand's handler is stored as ``run``
and returns the process exit status.
"""

import argparse
import importlib
import math
import sys

import phantom

#: Modules that add subcommands, in the order they appear in ``phantom --help``.
COMMAND_MODULES: tuple[str, ...] = (
    "phantom.model.cli",
    "phantom.model.inverse_cli",
    "phantom.model.calibrate_cli",
    "phantom.hil.cli",
    "phantom.host.commands",
)


def parse_numbers(text: str, option: str, allow_free: bool = False) -> list[float | None]:
    """A comma-separated list of finite numbers given to ``option``, e.g. ``1,1.5,0``.

    With ``allow_free``, ``-`` (or an empty item) stands for "no value" and gives ``None``.
    """
    values: list[float | None] = []
    for item in text.split(","):
        item = item.strip()
        if allow_free and item in ("-", ""):
            values.append(None)
            continue
        try:
            value = float(item)
        except ValueError:
            free = " or -" if allow_free else ""
            raise phantom.PhantomError(
                f"{option} takes comma-separated numbers{free} like 1,1.5,0; {item!r} is not a number"
            ) from None
        if not math.isfinite(value):
            raise phantom.PhantomError(f"{option}: {item!r} is not a finite number")
        values.append(value)
    return values


def parse_growth_ratio(text: str, option: str = "--growth-ratio") -> dict[str, float]:
    """Chamber growth weights given as ``NAME=WEIGHT`` pairs, e.g. ``chamber1=2,chamber2=1``.

    A name is a chamber's group name or its index; checking it against the scene's chambers is the caller's.
    """
    ratio = {}
    for pair in text.split(","):
        name, separator, weight = pair.partition("=")
        if not separator or not name.strip():
            raise phantom.PhantomError(f"{option} takes NAME=WEIGHT pairs like chamber1=2,chamber2=1; got {pair!r}")
        ratio[name.strip()] = parse_numbers(weight, option)[0]
    return ratio


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
