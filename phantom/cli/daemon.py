"""Subcommands of ``phantom``: the daemon and its simulated board: daemon, sim-board.

At module load only argparse and the daemon's settings (phantom.host.config, which is light) are imported;
handlers import what they need when they run. The ``phantom daemon`` flags are built from the settings'
dataclass, as are the config file's keys, so that the two cannot differ. The daemon's clients are in client.py.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from phantom.cli.common import setting_field
from phantom.host.config import ConfigError, SettingField, checked, settings

if TYPE_CHECKING:
    from pathlib import Path

    from phantom.hil.sim import SimulatedBoard
    from phantom.hil.simulated_truth import SimulatedTruth


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add this part's subcommands to the ``phantom`` parser."""
    daemon = subparsers.add_parser("daemon", help="run the host daemon (link, control, scenes, Rerun, local API)",
                                   description="Run the host daemon in the foreground until SIGTERM/SIGINT, "
                                   "which vent the phantom and close the recording. A start-up error (the socket "
                                   "taken, an unwritable recording) is one line on stderr and exit status 2. "
                                   "Every flag is also a key of the config file's [daemon] table (--mesh-hz: "
                                   "mesh_hz); flags win.")
    add_setting_flags(daemon)
    daemon.add_argument("--config", metavar="FILE", help="a TOML config file with a [daemon] table (flags win)")
    daemon.add_argument("--sim-truth", metavar="SCENE",
                        help="with --sim: the simulated phantom is this scene (another geometry, material or mesh) "
                        "instead of the shipped one (the measured phantom); its plant is built on first use (the "
                        "scene's chambers and 64 solves, with progress) and cached")
    daemon.add_argument("--sim-truth-modulus-factor", type=float, metavar="F", default=1.0,
                        help="with --sim-truth: the simulated phantom's modulus over the scene's (default 1)")
    daemon.set_defaults(run=_run_daemon)

    sim_board = subparsers.add_parser(
        "sim-board", help="run the simulated board alone and print its port",
        description="Run the simulated board (the real firmware in simavr against the pneumatic plant) on its own "
        "until SIGTERM/SIGINT, and print its serial port: a daemon started with --port PORT drives it like a "
        "real board, and can be killed to see the board vent at its dead-host deadline.")
    speed = setting_field("sim_speed")  # the daemon's own setting: the same range and help
    sim_board.add_argument(speed.flag, dest=speed.name, type=_flag_value(speed), default=speed.default,
                           metavar=speed.setting.metavar, help=_flag_help(speed))
    sim_board.add_argument("--json", action="store_true", help="print {\"port\": ...} as JSON")
    sim_board.add_argument("--camera-stream", metavar="HOST:PORT",
                           help="serve the simulated rig's camera as MJPEG over HTTP (/phantom.mjpg, /target0.mjpg, "
                                "/target1.mjpg) rendered at the rig's true angles, for `phantom daemon --port ... "
                                "--camera http://HOST:PORT/phantom.mjpg` (port 0: any free one); /truth.json is the "
                                "simulated phantom's truth, for a test to judge a scan by")
    sim_board.add_argument("--stream-scale", type=float, default=0.5,
                           help="the stream's picture size as a fraction of 1280x960 (default 0.5)")
    sim_board.add_argument("--stream-look", choices=("ideal", "real"), default="ideal",
                           help="the stream's pictures: ideal, or as a real rig sees the phantom hung by its tubes")
    sim_board.set_defaults(run=_run_sim_board)


def add_setting_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per setting of the daemon (phantom.host.config): ``--mesh-hz HZ`` for ``mesh_hz``, a switch as
    ``--vent-on-exit`` / ``--no-vent-on-exit`` (in a group, as the group's choice: ``--sim``); the settings of a
    group are mutually exclusive. A flag not given is None, so that the config file's value stands."""
    groups: dict[str, argparse._MutuallyExclusiveGroup] = {}
    for item in settings():
        group = item.setting.group
        if group is not None and group not in groups:
            groups[group] = parser.add_mutually_exclusive_group()
        target: Any = parser if group is None else groups[group]
        if item.kind is bool and group is not None:
            target.add_argument(item.flag, dest=item.name, action="store_true", default=None, help=_flag_help(item))
        elif item.kind is bool:
            target.add_argument(item.flag, dest=item.name, action=argparse.BooleanOptionalAction, default=None,
                                help=_flag_help(item))
        else:
            target.add_argument(item.flag, dest=item.name, type=_flag_value(item), default=None,
                                metavar=item.setting.metavar, help=_flag_help(item))


def _flag_help(item: SettingField) -> str:
    """A setting's help with its default (unless it is in a group, or has none) and its range."""
    notes = [item.setting.range_text()]
    if item.kind is bool and item.setting.group is None:
        notes.insert(0, f"default {'yes' if item.default else 'no'}")
    elif item.kind is not bool and item.default is not None:
        notes.insert(0, f"default {item.default:g}" if isinstance(item.default, (int, float)) else
                     f"default {item.default}")
    notes = [note for note in notes if note]
    return item.setting.help + (f" ({', '.join(notes)})" if notes else "")


def _flag_value(item: SettingField) -> Callable[[str], Any]:
    """argparse's ``type`` for a setting's flag: the text as the setting's type, checked against its range."""
    def convert(text: str) -> Any:
        try:
            value = item.kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not {'an integer' if item.kind is int else 'a number'}") from None
        try:
            return checked(item.name, value, "the value")
        except ConfigError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    return convert


def _run_daemon(args: argparse.Namespace) -> int:
    import functools
    import os

    # The daemon's worker processes (scan, model, link) read it when they import numpy: numpy asks the kernel for
    # huge pages on its large arrays, and where transparent huge pages are "madvise" (Debian's and Ubuntu's
    # default) the kernel compacts memory for them on the spot. The scan worker sits idle while the rig moves and
    # then carves: its carve took 2.7-4.0 s after each capture with that advice and 0.8-0.9 s without
    # (bench/carve_after_idle.py). A value the daemon was started with is kept.
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")

    from phantom import PhantomError
    from phantom.host.config import load_config, merged_config
    from phantom.host.service import run_daemon

    file_values = load_config(args.config) if args.config else {}
    config = merged_config(file_values, {item.name: getattr(args, item.name) for item in settings()})
    from phantom.cli.scan_verify import MOST_VIEWS, VERIFY_PLAN, VerifyScan
    from phantom.hil.simulated_truth import SimulatedTruth
    from phantom.scan.daemon_scan import DaemonScanner

    truth = SimulatedTruth()
    if args.sim_truth is not None:
        if not config.sim:
            raise PhantomError("--sim-truth sets the simulated phantom: give --sim too")
        truth = _simulated_truth(args.sim_truth, args.sim_truth_modulus_factor)
    elif args.sim_truth_modulus_factor != 1.0:
        raise PhantomError("--sim-truth-modulus-factor is the --sim-truth scene's: give --sim-truth SCENE too")
    from phantom.host.presets import DEFAULT_PRESETS, load_presets

    presets = (load_presets(args.config) if args.config else None) or DEFAULT_PRESETS
    verify = VerifyScan({**VERIFY_PLAN, "look": config.look})
    if config.camera is not None or config.rig is not None:
        from phantom.scan.daemon_scan import camera_plan

        verify = VerifyScan(camera_plan(config.camera, config.rig, MOST_VIEWS))
    from phantom.host.scan_worker import ScanWorker

    # the scans' capture and reconstruction in a process of their own: they hold the GIL for long stretches,
    # which in the daemon's process held up its loops past the board's dead-host deadline on a busy machine
    # the simulated phantom's truth shape is built in the worker's process, on its first virtual picture; a real
    # board has none for the virtual camera to photograph
    scans = ScanWorker(DaemonScanner(truth.shape if config.sim else None, config.look, config.camera), verify,
                       getattr(args, "log_level", "info"))
    try:
        scans.start()
        return run_daemon(config, simulated_board=functools.partial(_simulated_board, plant=truth.plant_path)
                          if config.sim else None, scanner=scans, verify_scanner=scans, presets=presets)
    finally:
        scans.close()


def _simulated_truth(scene: str, modulus_factor: float) -> SimulatedTruth:
    """The simulated phantom of ``--sim-truth``: its plant built (with progress on stderr) or found in the cache."""
    import sys

    from phantom.hil.plant import truth_plant_path, truth_shapes_path
    from phantom.hil.simulated_truth import SimulatedTruth
    from phantom.model.cluster import stderr_progress

    print(f"the simulated phantom: {scene} with E x {modulus_factor:g} (its plant and shapes are built once: the "
          f"scene's chambers and 64 solves, then cached)", file=sys.stderr, flush=True)
    path = truth_plant_path(scene, modulus_factor, progress=stderr_progress("simulated phantom's truth"))
    print(f"the simulated phantom's plant: {path}", file=sys.stderr, flush=True)
    return SimulatedTruth(scene, modulus_factor, path, truth_shapes_path(path))


def _simulated_board(speed: float, plant: Path | None = None) -> SimulatedBoard:
    """The daemon's simulated board (``--sim``): the firmware image in simavr against the plant (the shipped
    one, or ``--sim-truth``'s), its stepper drivers turning the scanner's simulated mechanism (mypy checks it
    against the host's ``SimulatedBoard`` Protocol where it is passed)."""
    from phantom.hil.truth_shape import ScannerBoard

    return ScannerBoard(speed=speed, plant=plant)


def _run_sim_board(args: argparse.Namespace) -> int:
    import faulthandler
    import json
    import signal
    import threading

    from phantom import PhantomError
    from phantom.hil.sim import SimulatedBoard

    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    stream_at = None
    if args.camera_stream is not None:
        host, _, port = args.camera_stream.rpartition(":")
        if not host or not port.isdigit() or not 0 <= int(port) < 65536:
            raise PhantomError(f"--camera-stream must be HOST:PORT (e.g. 127.0.0.1:8080), got {args.camera_stream!r}")
        stream_at = (host, int(port))
    board_type: type[SimulatedBoard] = SimulatedBoard
    if stream_at is not None:
        from phantom.hil.truth_shape import ScannerBoard

        board_type = ScannerBoard
    with board_type(speed=args.sim_speed) as board:
        stream = None
        if stream_at is not None:
            from phantom.cli.sim_stream import CameraStream

            stream = CameraStream(board, *stream_at, scale=args.stream_scale, look=args.stream_look).start()
        try:
            urls = {} if stream is None else {"streams": stream.urls()}
            # the board counts its dead-host deadline on its own clock: faster than real time, a daemon that
            # drives it as a real board gives it as many times the real 500 ms (at speed 0 no one factor holds)
            deadline_ms = min(10000, round(500 * args.sim_speed))
            deadline = "" if args.sim_speed in (0, 1) else f" --host-deadline-ms {deadline_ms}"
            if args.json:
                print(json.dumps({"port": board.port, "speed": args.sim_speed, **urls}), flush=True)
            else:
                camera = "" if stream is None else f" --camera {stream.urls()['phantom']} --rig RIG.json"
                print(f"simulated board on {board.port} (speed {args.sim_speed:g}); drive it with "
                      f"`phantom daemon --port {board.port}{deadline}{camera}`; Ctrl-C stops it", flush=True)
                if stream is not None:
                    # the rig is calibrated first, from the target's two placements (README.md, "A verified
                    # volume on a real rig")
                    streams = stream.urls()
                    truth, timing = streams.pop("truth"), streams.pop("board")
                    print("camera streams: " + ", ".join(f"{name} {url}" for name, url in streams.items())
                          + f"; the simulated phantom's truth (a test's, never the daemon's): {truth}; the simulated "
                          f"board's timing: {timing}", flush=True)
            while not stop.wait(0.5):
                pass
            # an end that hangs says where: every thread's stack on stderr (a test's board did not end within
            # 30 s of its SIGTERM once in a clean clone's make test, 2026-11-29)
            faulthandler.dump_traceback_later(20.0)
        finally:
            if stream is not None:
                stream.close()
    return 0
