"""Values the ``phantom`` subcommands of every part parse and print the same way: number lists, growth ratios,
output folders. A neutral module, so that no part imports another's command line."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, overload

from phantom import PhantomError


@overload
def parse_numbers(text: str, option: str, allow_free: Literal[False] = False) -> list[float]: ...


@overload
def parse_numbers(text: str, option: str, allow_free: bool) -> list[float | None]: ...


def parse_numbers(text: str, option: str, allow_free: bool = False) -> list[float] | list[float | None]:
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
            raise PhantomError(
                f"{option} takes comma-separated numbers{free} like 1,1.5,0; {item!r} is not a number"
            ) from None
        if not math.isfinite(value):
            raise PhantomError(f"{option}: {item!r} is not a finite number")
        values.append(value)
    return values


def parse_growth_ratio(text: str, option: str = "--growth-ratio") -> dict[str, float]:
    """Chamber growth weights given as ``NAME=WEIGHT`` pairs, e.g. ``chamber1=2,chamber2=1``.

    A name is a chamber's group name or its index; checking it against the scene's chambers is the caller's.
    """
    ratio: dict[str, float] = {}
    for pair in text.split(","):
        name, separator, weight = pair.partition("=")
        if not separator or not name.strip():
            raise PhantomError(f"{option} takes NAME=WEIGHT pairs like chamber1=2,chamber2=1; got {pair!r}")
        ratio[name.strip()] = parse_numbers(weight, option)[0]
    return ratio


def output_file(path: str | Path, option: str = "--out") -> Path:
    """A file to write: its missing folders are created; a one-line error when that is not possible."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise PhantomError(f"{option} {path}: cannot create the folder {path.parent} ({error.strerror})") from None
    if path.is_dir():
        raise PhantomError(f"{option} {path} is a folder: give a file name")
    return path
