"""Values the ``phantom`` subcommands of every part parse and print the same way: number lists, growth ratios,
output folders, input files' sizes. A neutral module, so that no part imports another's command line."""

from __future__ import annotations

import math
import stat
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Literal, overload

from phantom import PhantomError

if TYPE_CHECKING:
    import argparse

    from phantom.host.client import DaemonClient
    from phantom.host.config import SettingField
    from phantom.model.scene import Scene
    from phantom.scan.capture import CaptureFolder, FrameSource, Plan, Progress


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


#: The largest mesh file a command reads (a scene's mesh, a scan, a photogrammetry tool's mesh): a binary STL of
#: about 5 million triangles. The readers (meshio, trimesh) hold a whole file and several copies of its arrays.
MAX_MESH_BYTES = 256 * 2**20
#: What to do with a mesh over :data:`MAX_MESH_BYTES`.
MESH_TOO_LARGE = "decimate it first (e.g. MeshLab's Quadric Edge Collapse Decimation, to under a million triangles)"
#: The largest picture of a capture folder read (a 1280x960 PNG is about 2 MB).
MAX_PICTURE_BYTES = 64 * 2**20
#: The largest JSON file of ours read (a rig calibration, a capture folder's capture.json of thousands of frames).
MAX_JSON_BYTES = 16 * 2**20


def check_input_size(path: str | Path, max_bytes: int | None, what: str, error: type[PhantomError] = PhantomError,
                     hint: str = "that is not one of ours (give the right file)", *, give: str | None = None,
                     required: bool = False) -> None:
    """Refuse, before a library reads it whole, a file a user named that is larger than ``max_bytes`` (a 2 GB
    sparse file took 4-6 GB of memory to refuse) or not a file at all (/dev/zero, a pipe: endless).

    A missing file, or a folder, is left to the reader, whose message says what to do; unless ``give`` says what
    the command reads there (e.g. "a mesh file (.obj, .ply or .stl)"): then a folder is refused, saying to give
    that; and with ``required``, a missing file too (for a file named and kept, not read). ``max_bytes`` None:
    no size is refused (a file only referred to). Raises ``error`` with a one-line message that starts with
    ``what`` and the path, and ends with ``hint`` for a file too large.
    """
    path = Path(path)
    try:
        info = path.stat()
    except (FileNotFoundError, NotADirectoryError):
        if required:
            raise error(f"{what} {path} does not exist: check the path") from None
        return
    except OSError as problem:
        if required:
            raise error(f"{what} {path} cannot be read: {problem.strerror}") from None
        return
    if stat.S_ISDIR(info.st_mode):
        if give is not None:
            raise error(f"{what} {path} is a folder: give {give}")
        return
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{what} {path} is not a regular file (a device or a pipe): give a file")
    if max_bytes is not None and info.st_size > max_bytes:
        raise error(f"{what} {path} is {info.st_size / 2**20:.0f} MiB, more than the {max_bytes / 2**20:g} MiB "
                    f"read: {hint}")


def check_output_file(path: str | Path, option: str, example: str, error: type[PhantomError] = PhantomError) -> Path:
    """A file a command writes at the end of its work, refused in one line before it starts: a folder (``example``
    names a file in it), a path under a file, or one in a folder this user cannot write (folders that are missing
    are made when it is written)."""
    import os

    file = Path(path)
    if file.is_dir():
        raise error(f"{option} {path} is a folder: give the file to write, e.g. {file / example}")
    folder = file.parent
    while not folder.exists() and folder != folder.parent:  # the nearest folder there is: the rest is made
        folder = folder.parent
    if not folder.is_dir():
        raise error(f"{option} {path}: {folder} is not a folder: give a path in a folder")
    if not os.access(folder, os.W_OK | os.X_OK) or (file.exists() and not os.access(file, os.W_OK)):
        what = f"{file} is" if file.exists() else f"the folder {folder} is"
        raise error(f"{option} {path}: {what} not writable: give a path you can write")
    return file


def scene_pressures_kpa(text: str, scene: Scene, option: str = "--pressures-kpa",
                        pressure_max_kpa: float | None = None) -> list[float]:
    """Chamber pressures (kPa) given for a scene on the command line: one per chamber, each within what the daemon
    allows, refused in its words (:func:`phantom.model.scene.pressure_limit_error`), before any model is built.
    ``pressure_max_kpa``: the bound to check them against where the command line gives one (None: the scene's)."""
    from phantom.model.scene import describe_chambers, pressure_limit_error

    pressures = parse_numbers(text, option)
    labels = scene.chamber_labels
    if len(pressures) != len(labels):
        raise PhantomError(f"{option} has {len(pressures)} values; the scene has {len(labels)} chambers "
                           f"({describe_chambers(labels)}): give one pressure per chamber, in that order")
    if pressure_max_kpa is None:
        pressure_max_kpa = scene.model_settings.pressure_max_pa / 1e3
    refused = pressure_limit_error(pressures, labels, pressure_max_kpa)
    if refused:
        raise PhantomError(f"{option}: {refused}")
    return pressures


def progress_reporter(label: str, every_s: float = 10.0,
                      clock_s: Callable[[], float] | None = None) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that shows ``label done/total, elapsed, time left`` on stderr: one
    line rewritten in place on a terminal; on a file or a pipe a line every ``every_s`` and at the end, so that a
    log holds lines (carriage returns made a log one line). The time left is from the rate since the first call,
    so set-up before it (imports, compiling, starting workers) does not count; unknown until something is done.
    ``clock_s`` is the clock it reads (``time.monotonic`` unless given).
    """
    import sys
    import time

    clock_s = clock_s or time.monotonic
    terminal = sys.stderr.isatty()
    first: list[tuple[float, int]] = []
    shown_s = [-math.inf]

    def report(done: int, total: int) -> None:
        now = clock_s()
        if not first:
            first.append((now, done))
        started_s, done_at_start = first[0]
        elapsed_s = now - started_s
        rate = (done - done_at_start) / elapsed_s if elapsed_s > 0 and done > done_at_start else 0.0
        left = f", about {format_duration((total - done) / rate)} left" if rate > 0 and done < total else ""
        line = f"{label} {done}/{total}, {format_duration(elapsed_s)}{left}"
        finished = done >= total
        if terminal:
            sys.stderr.write(f"\r{line}   " + ("\n" if finished else ""))
        elif finished or now - shown_s[0] >= every_s:
            sys.stderr.write(line + "\n")
            shown_s[0] = now
        sys.stderr.flush()
    return report


def progress_printer(indent: str = "  ", clock_s: Callable[[], float] | None = None) -> Callable[[str], None]:
    """A verified target's ``on_progress`` (``DaemonClient.set_volume``): each of the daemon's texts on stderr as
    it comes, after the seconds since the printer was made (when the target was set): a round takes a minute or
    two. ``clock_s`` is the clock it reads (``time.monotonic`` unless given)."""
    import sys
    import time

    clock_s = clock_s or time.monotonic
    started_s = clock_s()

    def tell(text: str) -> None:
        print(f"{indent}{clock_s() - started_s:4.0f} s  {text}", file=sys.stderr, flush=True)
    return tell


def format_duration(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``, ``2 h 10 min``: a duration as people read it."""
    seconds = max(0, int(round(seconds)))
    if seconds < 60:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {seconds:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


def frame_progress(what: str) -> Callable[[int, int, object], None]:
    """:func:`progress_reporter` for a capture's ``progress(done, total, frame)`` callbacks (the frame unused)."""
    report = progress_reporter(what)

    def show(done: int, total: int, frame: object) -> None:
        report(done, total)
    return show


def plan_of(args: argparse.Namespace, settle_s: float = 0.0) -> Plan:
    """The plan of ``--views`` and ``--elevations``, at most MAX_FRAMES pictures in all."""
    from phantom.scan.capture import Plan

    return Plan(args.views, tuple(parse_numbers(args.elevations, "--elevations")), settle_s=settle_s)


def capture_through_daemon(client: DaemonClient, camera: FrameSource, plan: Plan, folder: CaptureFolder,
                           progress: Progress | None = None) -> CaptureFolder:
    """Configure the scanner's axes and take the plan's pictures through the daemon's API (the capture loop of
    ``phantom.scan.capture`` in this process, the rig through ``phantom.host.scan_client``)."""
    from phantom.host.scan_client import DaemonOrbit, DaemonPhantom
    from phantom.scan.capture import capture

    orbit = DaemonOrbit(client)
    orbit.configure()
    return capture(orbit, camera, DaemonPhantom(client), plan, folder, progress)


def setting_field(name: str) -> SettingField:
    """The daemon's setting ``name`` (its flag, type, default, help and range)."""
    from phantom.host.config import settings

    return next(item for item in settings() if item.name == name)
