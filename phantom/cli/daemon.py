"""Subcommands of ``phantom``: the daemon and its clients: daemon, status, set, vent, clear-fault, run-scene, watch.

At module load only argparse and the daemon's settings (phantom.host.config, which is light) are imported;
handlers import what they need when they run. The ``phantom daemon`` flags are built from the settings'
dataclass, as are the config file's keys, so that the two cannot differ.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from phantom.host.config import ConfigError, SettingField, checked, settings

if TYPE_CHECKING:
    from phantom.hil.sim import SimulatedBoard
    from phantom.host.client import DaemonClient


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
    daemon.set_defaults(run=_run_daemon)

    sim_board = subparsers.add_parser(
        "sim-board", help="run the simulated board alone and print its port",
        description="Run the simulated board (the real firmware in simavr against the pneumatic plant) on its own "
        "until SIGTERM/SIGINT, and print its serial port: a daemon started with --port PORT drives it like a "
        "real board, and can be killed to see the board vent at its dead-host deadline.")
    speed = _setting("sim_speed")  # the daemon's own setting: the same range and help
    sim_board.add_argument(speed.flag, dest=speed.name, type=_flag_value(speed), default=speed.default,
                           metavar=speed.setting.metavar, help=_flag_help(speed))
    sim_board.add_argument("--json", action="store_true", help="print {\"port\": ...} as JSON")
    sim_board.set_defaults(run=_run_sim_board)

    status = subparsers.add_parser("status", help="show the daemon's link, pressures, volumes and faults",
                                   description="Show the daemon's link, control state, pressures and volumes per "
                                   "chamber, and latched faults.")
    _add_json(status, "print the whole status as JSON")
    _add_socket(status)
    status.set_defaults(run=_run_status)

    set_target = subparsers.add_parser("set", help="set a target: a volume, chamber volumes or raw pressures",
                                       description="Set the daemon's target: the gland volume, each chamber's "
                                       "volume, or raw pressures; the inverse gives the setpoints.")
    target = set_target.add_mutually_exclusive_group(required=True)
    target.add_argument("--volume-ml", type=float, metavar="V", help="the gland's total volume (ml)")
    target.add_argument("--chamber-volumes-ml", metavar="A,B,C",
                        help="each chamber's volume (ml); '-' leaves one free")
    target.add_argument("--pressures-kpa", metavar="A,B,C", help="raw chamber pressures (kPa)")
    set_target.add_argument("--growth-ratio", metavar="NAME=W,...",
                            help="with --volume-ml: e.g. chamber1=2,chamber2=1 (left lobe grows twice the right)")
    _add_json(set_target, "print the answer as JSON")
    _add_socket(set_target)
    set_target.set_defaults(run=_run_set)

    # the commands that send one method with no parameters and print the answer
    for name, method, help_text, description in (
            ("vent", "vent", "all blowers off now (every setpoint 0)",
             "Vent the phantom: every setpoint 0 now; the target and any scene are dropped."),
            ("clear-fault", "clear_fault", "clear the board's latched fault (if its cause is gone)",
             "Clear the board's latched faults; the daemon then restores the current target's setpoints. "
             "Refused while a fault's cause persists."),
            ("zero", "zero", "zero the pressure sensors (the phantom must be vented)",
             "Ask the board to measure each pressure sensor's zero offset. The phantom must be vented and its "
             "readings steady; a refusal says why.")):
        simple = subparsers.add_parser(name, help=help_text, description=description)
        _add_json(simple, "print the answer as JSON")
        _add_socket(simple)
        simple.set_defaults(run=_run_simple, method=method)

    scene = subparsers.add_parser("run-scene", help="play a scene's [[steps]] timeline on the daemon",
                                  description="Play a scene's [[steps]] timeline on the running daemon (the scene "
                                  "must describe the daemon's phantom, material and model).")
    scene.add_argument("scene", metavar="SCENE",
                       help="the scene TOML file (or the name of a shipped example: bph_growth, lopsided)")
    scene.add_argument("--time-scale", type=float, default=1.0, metavar="X",
                       help="play the timeline X times faster (default 1)")
    scene.add_argument("--wait", action="store_true",
                       help="wait for the end and print each step's target, reached volume and time")
    _add_json(scene, "print the answer (with --wait: the step table) as JSON")
    _add_socket(scene)
    scene.set_defaults(run=_run_scene)

    watch = subparsers.add_parser("watch", help="a live text view of pressures, volumes and events",
                                  description="Print the daemon's pressures, setpoints and volumes twice a "
                                  "second, and its events as they happen, until interrupted.")
    watch.add_argument("--count", type=int, metavar="N", help="stop after N status lines")
    _add_json(watch, "print one JSON object per line (status and events) instead of text")
    _add_socket(watch)
    watch.set_defaults(run=_run_watch)


def _add_json(parser: argparse.ArgumentParser, text: str) -> None:
    parser.add_argument("--json", action="store_true", help=text)


def _setting(name: str) -> SettingField:
    return next(item for item in settings() if item.name == name)


def _add_socket(parser: argparse.ArgumentParser) -> None:
    """A client's --socket: the daemon's own setting, with its help."""
    socket = _setting("socket")
    parser.add_argument(socket.flag, metavar=socket.setting.metavar, help=socket.setting.help)


def _socket(args: argparse.Namespace) -> Path:
    from phantom.host.api import default_socket_path

    return Path(args.socket) if args.socket else default_socket_path()


def _client(args: argparse.Namespace) -> DaemonClient:
    from phantom.host.client import DaemonClient

    return DaemonClient(_socket(args))


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
    from phantom.host.config import load_config, merged_config
    from phantom.host.daemon import run_daemon

    file_values = load_config(args.config) if args.config else {}
    config = merged_config(file_values, {item.name: getattr(args, item.name) for item in settings()})
    return run_daemon(config, simulated_board=_simulated_board if config.sim else None)


def _simulated_board(speed: float) -> SimulatedBoard:
    """The daemon's simulated board (``--sim``): the firmware image in simavr against the plant (mypy checks it
    against the host's ``SimulatedBoard`` Protocol where it is passed)."""
    from phantom.hil.sim import SimulatedBoard

    return SimulatedBoard(speed=speed)


def _run_sim_board(args: argparse.Namespace) -> int:
    import json
    import signal
    import threading

    from phantom.hil.sim import SimulatedBoard

    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    with SimulatedBoard(speed=args.sim_speed) as board:
        if args.json:
            print(json.dumps({"port": board.port, "speed": args.sim_speed}), flush=True)
        else:
            print(f"simulated board on {board.port} (speed {args.sim_speed:g}); drive it with "
                  f"`phantom daemon --port {board.port}`; Ctrl-C stops it", flush=True)
        while not stop.wait(0.5):
            pass
    return 0


def _labels(status: dict[str, Any]) -> list[str]:
    return status.get("chamber_labels") or status.get("chambers") or []


def _run_status(args: argparse.Namespace) -> int:
    import json

    with _client(args) as client:
        status = client.call("status")
    if args.json:
        print(json.dumps(status, indent=2))
        return 0
    print(format_status(status))
    return 0


def _kpa(values: list[float] | None) -> str:
    return "-" if values is None else " ".join(f"{value:6.3f}" for value in values)


def _ml(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} ml"


def _per_chamber(values: list[float | None] | None, digits: int = 3, width: int = 11) -> str:
    if values is None:
        return "-"
    return " ".join(f"{value:>{width}.{digits}f}" if value is not None else f"{'free':>{width}}" for value in values)


def format_status(status: dict[str, Any]) -> str:
    """A few readable lines of a status answer, one column per chamber (named as the scene names them)."""
    link = status["link_detail"]
    board = link.get("board") or {}
    stats = link["stats"]
    rtt = "-" if stats.get("rtt_ms_mean") is None else f"{stats['rtt_ms_mean']:.1f} ms"
    error = f": {link['last_error']}" if link.get("last_error") else ""
    true_volume = f", true {_ml(status['plant_volume_ml'])} (simulated plant)" if "plant_volume_ml" in status else ""
    lines = [
        f"link      {status['link']} ({link['transport']}){error}",
        f"board     {board.get('board', '-')} firmware {board.get('firmware_version', '-')}, reset cause "
        f"{board.get('reset_cause', '-')}; rtt {rtt}, retries {stats['retries']}, bad frames {stats['bad_frames']}, "
        f"reconnects {stats['reconnects']}",
        f"control   {status['control']}" + (f" ({status['target_source']})" if status.get("target_source") else ""),
        f"{'chamber':<9} " + " ".join(f"{label:>11}" for label in _labels(status)),
        f"{'pressure':<9} {_per_chamber(status['pressures_kpa'])}  kPa measured",
        f"{'setpoint':<9} {_per_chamber(status['setpoints_kpa'])}  kPa",
        f"{'volume':<9} {_per_chamber(status.get('estimated_chamber_volumes_ml'), 2)}  ml estimated",
        f"gland     {_ml(status['estimated_volume_ml'])} estimated, target {_ml(status['target_volume_ml'])} "
        f"(rest {status['rest_volume_ml']:.2f} ml){true_volume}",
        f"faults    {', '.join(status['faults']) or 'none'}",
    ]
    if status.get("scene"):
        scene = status["scene"]
        lines.append(f"scene     {scene['name']}: {scene['time_s']:.1f} / {scene['end_s']:g} s"
                     + (" (finished)" if scene["finished"] else ""))
    return "\n".join(lines)


def _run_set(args: argparse.Namespace) -> int:
    import json

    from phantom import PhantomError
    from phantom.cli.common import parse_growth_ratio, parse_numbers

    if args.volume_ml is not None:
        params = {"volume_ml": args.volume_ml}
    elif args.chamber_volumes_ml is not None:
        params = {"chamber_volumes_ml": parse_numbers(args.chamber_volumes_ml, "--chamber-volumes-ml", allow_free=True)}
    else:
        params = {"pressures_kpa": parse_numbers(args.pressures_kpa, "--pressures-kpa")}
    if args.growth_ratio:
        if args.volume_ml is None:
            raise PhantomError("--growth-ratio goes with --volume-ml")
        params["growth_ratio"] = parse_growth_ratio(args.growth_ratio)
    with _client(args) as client:
        result = client.call("set_target", params)
        labels = _labels(client.call("status"))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{'chamber':<9} " + " ".join(f"{label:>11}" for label in labels))
        print(f"{'setpoint':<9} {_per_chamber(result['pressures_kpa'])}  kPa")
        print(f"{'volume':<9} {_per_chamber(result['predicted_chamber_volumes_ml'], 2)}  ml predicted")
        print(f"gland     {result['predicted_volume_ml']:.2f} ml predicted (inverse {result['iterations']} "
              f"iteration(s), {result['solve_time_s'] * 1e3:.1f} ms)")
    return 0


def format_simple(method: str, result: dict[str, Any]) -> str:
    """The text answer of vent, clear-fault and zero."""
    if method == "vent":
        return "vented: every setpoint is 0; the target and any scene are dropped"
    if method == "zero":
        return "sensors zeroed"
    cleared = ", ".join(result.get("cleared", [])) or "none were latched"
    restored = "; the target's setpoints restored" if result.get("setpoints_restored") else ""
    return f"faults cleared: {cleared}{restored}"


def _run_simple(args: argparse.Namespace) -> int:
    import json

    with _client(args) as client:
        result = client.call(args.method)
    print(json.dumps(result) if args.json else format_simple(args.method, result))
    return 0


def format_steps(steps: list[dict[str, Any]]) -> str:
    """The table ``make demo`` prints: each step's target, reached volume, error and time to reach it; a true
    (simulated plant) volume column when the steps have one."""
    with_true = any(step.get("true_volume_ml") is not None for step in steps)
    lines = [f"{'step':>4} {'at (s)':>7} {'target':<34} {'target ml':>9} {'reached ml':>10} {'error %':>8} "
             f"{'time to 1 % (s)':>15}" + (f" {'true ml':>8}" if with_true else "")]
    for step in steps:
        def number(value: float | None, digits: int = 2) -> str:
            return "-" if value is None else f"{value:.{digits}f}"
        lines.append(f"{step['index']:>4} {step['at_s']:>7.1f} {step['target']:<34} "
                     f"{number(step['target_volume_ml']):>9} {number(step['reached_volume_ml']):>10} "
                     f"{number(step['error_pct']):>8} {number(step['reached_after_s'], 1):>15}"
                     + (f" {number(step.get('true_volume_ml')):>8}" if with_true else ""))
    return "\n".join(lines)


def follow_scene(client: DaemonClient, name: str, time_scale: float, poll_s: float = 0.5) -> dict[str, Any]:
    """Poll the daemon's status until the scene ``name`` has finished, showing its progress on stderr.

    Returns the last status (its ``scene`` holds each step's record). Raises when another request replaced
    the scene before it finished.
    """
    import sys
    import time

    from phantom import PhantomError

    while True:
        status: dict[str, Any] = client.call("status")
        scene = status["scene"]
        if scene is None or scene["name"] != name:
            raise PhantomError("the scene was replaced by another request before it finished")
        print(f"\r  {scene['time_s']:6.1f} / {scene['end_s']:g} s of scene (x{time_scale:g})   volume "
              f"{_ml(status['estimated_volume_ml'])}   target {_ml(status['target_volume_ml'])} ",
              end="", file=sys.stderr, flush=True)
        if scene["finished"]:
            print(file=sys.stderr)
            return status
        time.sleep(poll_s)


def _run_scene(args: argparse.Namespace) -> int:
    import json
    import sys
    from pathlib import Path

    from phantom.host.scenes import example_scene_path

    path = Path(args.scene)
    if not path.exists() and "/" not in args.scene and not args.scene.endswith(".toml"):
        path = example_scene_path(args.scene)
    with _client(args) as client:
        started = client.call("run_scene", {"path": str(path.resolve()), "time_scale": args.time_scale})
        print(f"scene {started['name']}: {started['steps']} steps, {started['end_s']:g} s of timeline, about "
              f"{started['wall_duration_s']:.0f} s at time scale {args.time_scale:g}", file=sys.stderr)
        if not args.wait:
            if args.json:
                print(json.dumps(started))
            return 0
        scene = follow_scene(client, started["name"], args.time_scale)["scene"]
    if args.json:
        print(json.dumps(scene["steps"], indent=2))
    else:
        print(format_steps(scene["steps"]))
    return 0


def watch_header(labels: list[str]) -> str:
    """The column names of ``phantom watch``'s status lines."""
    per_chamber = " ".join(f"{label[:6]:>6}" for label in labels)
    return (f"{'time (s)':>9}  {'link':<12} p (kPa) {per_chamber}  set (kPa) {per_chamber}  "
            "gland volume -> target  faults")


def _run_watch(args: argparse.Namespace) -> int:
    import json

    printed = 0
    last_s = -1.0
    header_shown = False
    with _client(args) as client:
        for message in client.events(["status", "events"]):
            if message["event"] == "events":
                event = message["data"]
                print(json.dumps(message) if args.json else
                      f"{event['time_s']:9.2f}  [{event['level']}] {event['text']}", flush=True)
                continue
            status = message["data"]
            if status["uptime_s"] - last_s < 0.5:
                continue
            last_s = status["uptime_s"]
            if args.json:
                print(json.dumps(message), flush=True)
            else:
                if not header_shown:
                    print(watch_header(_labels(status)), flush=True)
                    header_shown = True
                print(f"{status['uptime_s']:9.2f}  {status['link']:<12} p (kPa) {_kpa(status['pressures_kpa'])}  "
                      f"set (kPa) {_kpa(status['setpoints_kpa'])}  {_ml(status['estimated_volume_ml'])} "
                      f"-> {_ml(status['target_volume_ml'])}  faults {','.join(status['faults']) or 'none'}",
                      flush=True)
            printed += 1
            if args.count and printed >= args.count:
                return 0
    return 0
