"""Subcommands of ``phantom``: the scanner's stepper axes on the phantom's board: phantom motion ....

``check`` runs the bench's motion check against the firmware in simavr (``--sim``, where the simulated drivers
count every pulse) or a board on a serial port (``--port``); ``move``, ``home`` and ``status`` drive a board by
hand. The board does not keep an axis's configuration across a reset: every command sends it first (the
options below, whose defaults are the orbit of docs/hardware.md).
Only argparse is imported at module load; handlers import what they need when they run. The connection is
``phantom hil``'s (its ``_Bench``), with the same target options.
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from phantom.cli.hil import _Bench
    from phantom.hil.motion import AxisConfig, MotionStatus


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add this part's subcommands to the ``phantom`` parser."""
    motion = subparsers.add_parser(
        "motion",
        help="the scanner's stepper axes on the phantom's board: check, move, home, status",
        description="Check or drive the scanner's stepper axes (0 orbit, 1 elevation) through the phantom's board, "
                    "in simavr (--sim) or on a serial port (--port).",
    )
    commands = motion.add_subparsers(dest="motion_command", metavar="COMMAND", required=True)

    def add(name: str, help_text: str, handler: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
        parser: argparse.ArgumentParser = commands.add_parser(name, help=help_text, description=help_text)
        target = parser.add_mutually_exclusive_group(required=True)
        target.add_argument("--sim", action="store_true", help="run the firmware image in simavr")
        target.add_argument("--port", help="serial port of a real board, e.g. /dev/ttyACM0")
        parser.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
        parser.add_argument("--boot-delay-s", type=float, help="--port: seconds of silence after opening the port, "
                                                               "while the bootloader runs (default 2)")
        parser.add_argument("--elf", help="--sim: firmware image (default firmware/build/uno-bench/phantom.elf)")
        parser.add_argument("--plant", help="--sim: plant parameter file (default hil/plant.toml)")
        parser.add_argument("--sim-speed", dest="speed", type=float, default=1.0,
                            help="--sim: simulated time per wall-clock time (default 1)")
        parser.add_argument("--seed", type=int, default=0, help="--sim: seed of the sensor and line noise")
        parser.add_argument("--axis", type=int, default=0, choices=(0, 1), help="0 orbit (default), 1 elevation")
        parser.add_argument("--steps-per-rev", type=float, default=28800,
                            help="steps per turn of the axis: full steps x microsteps x gear ratio (default 28800)")
        parser.add_argument("--max-speed", type=float, default=30.0, help="deg/s (default 30)")
        parser.add_argument("--max-accel", type=float, default=240.0, help="deg/s^2 (default 240)")
        parser.add_argument("--limits", default="-190,190", help="soft limits MIN,MAX in deg (default -190,190)")
        parser.add_argument("--home-speed", type=float, default=10.0,
                            help="switch search speed in deg/s, with --home-switch (default 10)")
        parser.add_argument("--home-switch", action="store_true", help="a home switch is wired to the axis")
        parser.add_argument("--home-positive", action="store_true", help="search the switch towards + angles")
        parser.add_argument("--switch-active-low", action="store_true", help="the switch input reads low when active")
        parser.add_argument("--reverse", action="store_true", help="the motor turns the other way: invert DIR")
        parser.add_argument("--json", action="store_true", help="print the result as JSON")
        parser.set_defaults(run=handler)
        return parser

    check = add("check", "configure an axis, move it and back; in simavr also count its pulses, check their "
                         "timing and limits, and home it on a simulated switch", _run_check)
    check.add_argument("--move-deg", type=float, default=90.0, help="how far to move and back (default 90)")
    move = add("move", "move an axis to an absolute angle and wait until it is there", _run_move)
    move.add_argument("--deg", type=float, required=True, help="the target angle in deg")
    home = add("home", "set an axis's position: here (default) or by searching its home switch", _run_home)
    home.add_argument("--deg", type=float, default=0.0, help="the angle of the position now, or of the switch's "
                                                              "edge (default 0)")
    home.add_argument("--search", action="store_true", help="search the home switch (needs --home-switch)")
    add("status", "print where each axis is", _run_status)


def _config(args: argparse.Namespace) -> AxisConfig:
    from phantom.cli.common import parse_numbers
    from phantom.hil.motion import AxisConfig, MotionError

    limits = parse_numbers(args.limits, "--limits")
    if len(limits) != 2:
        raise MotionError(f"--limits takes MIN,MAX in deg like -190,190, got {args.limits!r}")
    config = AxisConfig(
        steps_per_rev=args.steps_per_rev, max_speed_deg_s=args.max_speed, max_accel_deg_s2=args.max_accel,
        min_angle_deg=limits[0], max_angle_deg=limits[1], home_speed_deg_s=args.home_speed if args.home_switch else 0.0,
        reverse=args.reverse, home_switch=args.home_switch, switch_active_low=args.switch_active_low,
        home_positive=args.home_positive,
    )
    problems = config.problems()
    if problems:
        raise MotionError(f"axis {args.axis} configuration: {'; '.join(problems)}")
    return config


@contextlib.contextmanager
def _configured(args: argparse.Namespace, config: AxisConfig) -> Iterator[_Bench]:
    """The bench's link (phantom hil's, and the simulated board with --sim), its session open and the axis
    configured."""
    from phantom.cli.hil import _Bench
    from phantom.hil import bench, motion

    with _Bench(args) as b:
        bench.start_session(b.link)
        motion.configure(b.link, args.axis, config)
        yield b


def _report(args: argparse.Namespace, status: MotionStatus) -> int:
    from phantom.cli.hil import _emit

    return _emit(args, _status_result(status), [_axis_line(n, a) for n, a in enumerate(status.axes)])


def _axis_line(n: int, axis: Any) -> str:
    return (f"axis {n}: {axis.state} ({axis.result}) at {axis.position_deg:g} deg ({axis.position_steps} steps), "
            f"target {axis.target_deg:g} deg, {axis.velocity_deg_s:g} deg/s, driver "
            f"{'enabled' if axis.enabled else 'released'}, position {'known' if axis.referenced else 'lost'}"
            f"{', home switch active' if axis.switch_active else ''}")


def _status_result(status: MotionStatus) -> dict[str, Any]:
    from dataclasses import asdict

    return {"board_time_s": status.board_time_s, "axes": [asdict(axis) for axis in status.axes]}


def _run_check(args: argparse.Namespace) -> int:
    from phantom.cli.hil import _Bench, _emit
    from phantom.hil import motion

    config = _config(args)
    with _Bench(args) as b:
        report = motion.check_motion(b.link, b.board, config, move_deg=args.move_deg, axis=args.axis)
    lines = [f"{name}: {'PASS' if ok else 'FAIL'}" for name, ok in report["checks"].items()]
    lines += [f"{key}: {value:.6g}" if isinstance(value, float) else f"{key}: {value}"
              for key, value in report.items() if key not in ("checks", "passed", "config")]
    return _emit(args, report, lines)


def _run_move(args: argparse.Namespace) -> int:
    from phantom.hil import motion

    config = _config(args)
    with _configured(args, config) as b:
        status = motion.move_to(b.link, args.axis, args.deg)
    return _report(args, status)


def _run_home(args: argparse.Namespace) -> int:
    from phantom.hil import motion

    config = _config(args)
    with _configured(args, config) as b:
        status = motion.home(b.link, args.axis, "switch" if args.search else "here", angle_deg=args.deg)
    return _report(args, status)


def _run_status(args: argparse.Namespace) -> int:
    from phantom.hil import motion

    config = _config(args)
    with _configured(args, config) as b:
        status = motion.status(b.link)
    return _report(args, status)
