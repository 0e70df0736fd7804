"""Subcommands of ``phantom``: the daemon's clients: status, set, vent, clear-fault, zero, run-scene, watch.

Each is a few lines on the Python API (``phantom.connect``, phantom/host/client.py): one client for scripts,
notebooks and the command line. A command that finds the daemon still starting waits for it (up to
READY_TIMEOUT_S), saying on stderr what it is doing. Only argparse is imported at module load; handlers import
what they need when they run. A client's --socket is the daemon's own setting (phantom.host.config), with its help.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from phantom.cli.common import setting_field

if TYPE_CHECKING:
    from phantom.host.client import Phantom, Status

#: How long a client waits for a daemon that is still starting before it gives up (s): a first start on a busy
#: machine loads its model in seconds (the response table, if any, is built in the background).
READY_TIMEOUT_S = 300.0
#: How often ``phantom watch`` prints (s).
WATCH_PERIOD_S = 0.5


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the daemon's clients to the ``phantom`` parser."""
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
    set_target.add_argument("--wait", action="store_true",
                            help="return once the estimated volume is within --tolerance-pct of the target and the "
                            "pressures have settled (a fault or --timeout-s is an error)")
    set_target.add_argument("--tolerance-pct", type=float, metavar="PCT",
                            help="with --wait: how close the estimate must come (%% of the target, default 1)")
    set_target.add_argument("--timeout-s", type=float, default=None, metavar="S",
                            help="with --wait: how long to wait (s, default 60, and 120 more per verify round)")
    set_target.add_argument("--verify", choices=["scan", "auto"],
                            help="with --volume-ml: once reached on pressure, scan the phantom and correct until the "
                            "scanned volume is within --verify-tolerance-pct (implies --wait); auto: scan only when "
                            "the correction's 95 %% band at the target is wider than that")
    set_target.add_argument("--verify-tolerance-pct", type=float, metavar="PCT",
                            help="with --verify: how close the scanned volume must come (%% of the target, default "
                            "0.3; the rounds aim at 0.6 of it, a third where the scan's hull error could not be "
                            "taken off; the last accepts it all)")
    set_target.add_argument("--verify-rounds", type=int, metavar="N",
                            help="with --verify: the most scans (default 4)")
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
    watch.add_argument("--count", type=_count, metavar="N", help="stop after N status lines")
    _add_json(watch, "print one JSON object per line (status and events) instead of text")
    _add_socket(watch)
    watch.set_defaults(run=_run_watch)


def _count(text: str) -> int:
    """argparse's type for ``watch --count``: a whole number, at least 1 (0 would watch forever)."""
    try:
        count = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if count < 1:
        raise argparse.ArgumentTypeError(f"{count} is below 1: give how many status lines to print, or leave --count "
                                         "out to watch until interrupted")
    return count


def _add_json(parser: argparse.ArgumentParser, text: str) -> None:
    parser.add_argument("--json", action="store_true", help=text)


def _add_socket(parser: argparse.ArgumentParser) -> None:
    """A client's --socket: the daemon's own setting, with its help."""
    socket = setting_field("socket")
    parser.add_argument(socket.flag, metavar=socket.setting.metavar, help=socket.setting.help)


def _socket(args: argparse.Namespace) -> Path:
    from phantom.host.api import default_socket_path

    return Path(args.socket) if args.socket else default_socket_path()


def _connect(args: argparse.Namespace, wait_ready: bool = True) -> Phantom:
    """The daemon, through the Python API; a daemon still starting is waited for (what it is doing on stderr)."""
    import sys

    import phantom

    def tell(what: str) -> None:
        print(f"waiting for the daemon: {what}", file=sys.stderr, flush=True)

    return phantom.connect(_socket(args), ready_timeout_s=READY_TIMEOUT_S if wait_ready else 0.0, on_wait=tell)


def _labels(status: dict[str, Any]) -> list[str]:
    return status.get("chamber_labels") or status.get("chambers") or []


def _run_status(args: argparse.Namespace) -> int:
    import json

    from phantom.host.client import StartingError

    try:
        with _connect(args, wait_ready=False) as daemon:
            status = daemon.status().raw
    except StartingError as error:  # before its model answers, a daemon has no status but its progress
        print(json.dumps({"ready": False, "starting": error.data}, indent=2) if args.json
              else f"starting  {error.message.removeprefix('the daemon is still starting: ')}")
        return 0
    if args.json:
        print(json.dumps(status, indent=2))
        return 0
    print(format_status(status))
    return 0


def _kpa(values: list[float] | None) -> str:
    return "-" if values is None else " ".join(f"{value:6.3f}" for value in values)


def _ml(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f} ml"


def _per_chamber(values: Sequence[float | None] | None, digits: int = 3, width: int = 11) -> str:
    if values is None:
        return "-"
    return " ".join(f"{value:>{width}.{digits}f}" if value is not None else f"{'free':>{width}}" for value in values)


def _faults(status: dict[str, Any]) -> str:
    """The board's latched faults, or, with no link to the board, that they are unknown (the last known beside)."""
    known = ", ".join(status["faults"]) or "none"
    return known if status["link"] == "online" else f"unknown while the link is {status['link']} (last known: {known})"


#: What interrupted a reached target (the status's ``target_after_interruption``'s ``after``), as ``phantom status``
#: says it.
INTERRUPTION_WORDS = {"fault": "the fault", "board restart": "the board restarted", "link loss": "the link was lost"}


def _after_interruption(held: dict[str, str] | None) -> str:
    """What became of a reached target after the board lost its setpoints (the status's
    ``target_after_interruption``), as ``phantom status`` says it after its control line; empty when nothing did."""
    if not held:
        return ""
    state, after = held.get("state"), held.get("after")
    words = INTERRUPTION_WORDS.get(str(after), str(after))
    if state == "not_held":
        again = "go again once it is cleared" if after == "fault" else "go to the board again"
        return f"; not held since {words}: its setpoints {again}"
    if state == "settling":
        return f"; settling again after {words}"
    return f"; held again after {words}" if state == "held_again" else f"; {state} after {words}"


def format_status(status: dict[str, Any]) -> str:
    """A few readable lines of a status answer, one column per chamber (named as the scene names them)."""
    link = status["link_detail"]
    board = link.get("board") or {}
    stats = link["stats"]
    rtt = "-" if stats.get("rtt_ms_mean") is None else f"{stats['rtt_ms_mean']:.1f} ms"
    error = f": {link['last_error']}" if link.get("last_error") else ""
    true_volume = f", true {_ml(status['plant_volume_ml'])} (simulated plant)" if "plant_volume_ml" in status else ""
    lines = []
    if status.get("starting"):
        lines.append(f"starting  {status['starting']['text']}")
    lines += [
        f"link      {status['link']} ({link['transport']}){error}",
        f"board     {board.get('board', '-')} firmware {board.get('firmware_version', '-')}, reset cause "
        f"{board.get('reset_cause', '-')}; rtt {rtt}, retries {stats['retries']}, bad frames {stats['bad_frames']}, "
        f"reconnects {stats['reconnects']}",
        f"control   {status['control']}" + (f" ({status['target_source']})" if status.get("target_source") else "")
        + _after_interruption(status.get("target_after_interruption")),
        f"{'chamber':<9} " + " ".join(f"{label:>11}" for label in _labels(status)),
        f"{'pressure':<9} {_per_chamber(status['pressures_kpa'])}  kPa measured",
        f"{'setpoint':<9} {_per_chamber(status['setpoints_kpa'])}  kPa",
        f"{'volume':<9} {_per_chamber(status.get('estimated_chamber_volumes_ml'), 2)}  ml estimated",
        f"gland     {_ml(status['estimated_volume_ml'])} estimated, target {_ml(status['target_volume_ml'])} "
        f"(rest {status['rest_volume_ml']:.2f} ml){true_volume}",
        f"faults    {_faults(status)}",
        "model     " + format_model(status),
    ]
    if status.get("correction"):
        lines.append("corrected " + format_correction(status["correction"]))
    web = status.get("web")
    if web:  # the browser panel (phantom daemon --http)
        token = f", tokens in {web['tokens_file']}" if web.get("token") else ", no token asked"
        lines.append(f"panel     {web['url']}{token}")
    recording = status.get("recording")
    if recording:
        where = recording.get("path") or recording.get("viewer")
        problem = f": {recording['problem']}" if recording.get("problem") else ""
        lines.append(f"recording {recording['state']} to {where}{problem}")
    if status.get("scene"):
        scene = status["scene"]
        lines.append(f"scene     {scene['name']}: {scene['time_s']:.1f} / {scene['end_s']:g} s"
                     + (f" (stopped: {scene['stopped']})" if scene.get("stopped") else
                        " (finished)" if scene["finished"] else ""))
    scan = (status.get("motion") or {}).get("scan")
    if status.get("verify"):
        lines.append(f"verify    {status['verify']['text']}")
    elif scan:
        lines.append(f"scan      {scan['text']}, started {scan['started_utc']}")
    return "\n".join(lines)


def format_correction(correction: dict[str, Any]) -> str:
    """The correction of the model by the phantom's measured volumes in force, or why there is none."""
    name = f"phantom {correction['phantom']!r}"
    fitting = " (fitting again)" if correction.get("fitting") else ""
    fitted = correction.get("correction")
    if fitted is None:
        why = correction.get("error") or f"no measured volumes in {correction['store']}"
        return f"no ({name}: {why}){fitting}"
    errors = ", ".join(f"{kind} {error:.2f} %" for kind, error in fitted["leave_one_out_pct"].items()) or "none"
    return (f"yes: {fitted['kind']} from {fitted['count']} measurement(s) of {name}, up to {fitted['size_ml']:.3f} "
            f"ml over the pressure box; leave-one-out {errors}{fitting}")


def format_model(status: dict[str, Any]) -> str:
    """The fidelity the model answers on, and the level being built meanwhile with its progress."""
    from phantom.host.client import Progress

    text = f"fidelity {status.get('fidelity', '-')}"
    build = status.get("model_build")
    if status.get("fidelity_pending") and build and not build.get("finished"):
        text += f" until the {status['fidelity_pending']} level is built ({Progress.from_json(build)})"
    elif build and build.get("error"):
        text += f" (the {status.get('fidelity_pending')} level could not be built: {build['error']})"
    return text


def _check_set_numbers(args: argparse.Namespace) -> None:
    """``phantom set``'s numbers against the daemon's bounds, before connecting, naming the flags (the daemon's
    refusals name its params); the number of chamber volumes is the daemon's to check (it knows its chambers)."""
    from phantom import PhantomError, is_finite_number
    from phantom.cli.common import parse_numbers
    from phantom.host.control import MAX_TOLERANCE_PCT
    from phantom.host.scenes import MIN_VOLUME_ML
    from phantom.host.verify import MAX_VERIFY_ROUNDS, VERIFY_TOLERANCE_PCT

    if args.volume_ml is not None and not (is_finite_number(args.volume_ml) and args.volume_ml >= MIN_VOLUME_ML):
        raise PhantomError(f"--volume-ml must be a number of at least {MIN_VOLUME_ML:g} ml, got {args.volume_ml:g}")
    if args.chamber_volumes_ml is not None:
        volumes = [value for value in parse_numbers(args.chamber_volumes_ml, "--chamber-volumes-ml",
                                                    allow_free=True) if value is not None]
        if not volumes:
            raise PhantomError("--chamber-volumes-ml needs at least one number: give a volume (ml) for one chamber "
                               "or more, '-' for the free ones")
        if min(volumes) < MIN_VOLUME_ML:
            raise PhantomError(f"--chamber-volumes-ml: each volume must be at least {MIN_VOLUME_ML:g} ml, got "
                               f"{args.chamber_volumes_ml}")
    if args.tolerance_pct is not None and not (is_finite_number(args.tolerance_pct)
                                               and 0 < args.tolerance_pct <= MAX_TOLERANCE_PCT):
        raise PhantomError(f"--tolerance-pct must be a number more than 0 and at most {MAX_TOLERANCE_PCT:g} (% of the "
                           f"target), got {args.tolerance_pct:g}")
    if args.timeout_s is not None and not (is_finite_number(args.timeout_s) and args.timeout_s > 0):
        raise PhantomError(f"--timeout-s must be a positive number of seconds, got {args.timeout_s:g}")
    low_pct, high_pct = VERIFY_TOLERANCE_PCT
    if args.verify_tolerance_pct is not None and not (is_finite_number(args.verify_tolerance_pct)
                                                      and low_pct <= args.verify_tolerance_pct <= high_pct):
        raise PhantomError(f"--verify-tolerance-pct must be a number from {low_pct:g} to {high_pct:g} (% of the "
                           f"target), got {args.verify_tolerance_pct:g}")
    if args.verify_rounds is not None and not 1 <= args.verify_rounds <= MAX_VERIFY_ROUNDS:
        raise PhantomError(f"--verify-rounds must be a whole number from 1 to {MAX_VERIFY_ROUNDS}, got "
                           f"{args.verify_rounds}")


def _run_set(args: argparse.Namespace) -> int:
    import json

    from phantom import PhantomError
    from phantom.cli.common import parse_growth_ratio, parse_numbers, progress_printer

    if args.growth_ratio and args.volume_ml is None:
        raise PhantomError("--growth-ratio goes with --volume-ml")
    if args.verify is None and (args.verify_tolerance_pct is not None or args.verify_rounds is not None):
        raise PhantomError("--verify-tolerance-pct and --verify-rounds go with --verify scan or auto")
    if args.verify is not None and args.volume_ml is None:
        raise PhantomError(f"--verify {args.verify} compares the scanned gland volume with the target: give "
                           "--volume-ml")
    options: dict[str, Any] = {"wait": args.wait or args.verify is not None}
    if not options["wait"] and (args.tolerance_pct is not None or args.timeout_s is not None):
        raise PhantomError("--tolerance-pct and --timeout-s go with --wait: add --wait (without it, set returns as "
                           "soon as the setpoints are sent)")
    _check_set_numbers(args)
    if args.tolerance_pct is not None:
        options["tolerance_pct"] = args.tolerance_pct
    if args.timeout_s is not None:
        options["timeout_s"] = args.timeout_s
    with _connect(args) as daemon:
        try:
            if args.volume_ml is not None:
                result = daemon.set_volume(args.volume_ml, growth_ratio=parse_growth_ratio(args.growth_ratio)
                                           if args.growth_ratio else None, verify=args.verify,
                                           verify_tolerance_pct=args.verify_tolerance_pct,
                                           verify_rounds=args.verify_rounds, on_progress=progress_printer(),
                                           **options)
            elif args.chamber_volumes_ml is not None:
                result = daemon.set_chamber_volumes(
                    parse_numbers(args.chamber_volumes_ml, "--chamber-volumes-ml", allow_free=True), **options)
            else:
                result = daemon.set_pressures(parse_numbers(args.pressures_kpa, "--pressures-kpa"), **options)
        except KeyboardInterrupt:
            _tell_what_goes_on(args)
            raise
        labels = daemon.status().chamber_labels
    if args.json:
        print(json.dumps(dataclasses.asdict(result), indent=2))
        return 0
    print(f"{'chamber':<9} " + " ".join(f"{label:>11}" for label in labels))
    print(f"{'setpoint':<9} {_per_chamber(result.pressures_kpa)}  kPa")
    print(f"{'volume':<9} {_per_chamber(result.predicted_chamber_volumes_ml, 2)}  ml predicted")
    band = "" if result.band_ml is None else (f", +-{result.band_ml:.3f} ml (95 %) from {result.measurements} "
                                              "stored measurement(s)")
    print(f"gland     {result.predicted_volume_ml:.2f} ml predicted{band} (inverse {result.iterations} "
          f"iteration(s), {result.solve_time_s * 1e3:.1f} ms)")
    if result.waited_s is not None:
        true_volume = "" if result.true_volume_ml is None else (
            f", true {result.true_volume_ml:.2f} ml (simulated plant)")
        print(f"reached   {_ml(result.estimated_volume_ml)} estimated after {result.waited_s:.1f} s, pressures "
              f"settled{true_volume}")
    if result.scanned is False:
        print("verify auto: the correction's band is within the tolerance: not scanned")
    if result.rounds:
        print(f"{'round':<6} {'pressures (kPa)':>24} {'asked ml':>9} {'scanned ml':>11} {'error %':>8}")
        for entry in result.rounds:
            scanned = entry.get("scanned_volume_ml")
            print(f"{entry['round']:<6} {_per_chamber(entry['pressures_kpa'], 3, 7):>24} {entry['asked_ml']:>9.2f} "
                  f"{'-' if scanned is None else f'{scanned:.3f}':>11} "
                  f"{'-' if scanned is None else format(entry['scanned_error_pct'], '+.2f'):>8}")
        print(f"MEASURED  {_ml(result.scanned_volume_ml)} scanned (verified within the tolerance) after "
              f"{len(result.rounds)} round(s)")
    return 0


#: How long (s) an interrupted ``phantom set`` waits for the daemon's status to say what goes on.
TELL_TIMEOUT_S = 5.0


def _tell_what_goes_on(args: argparse.Namespace) -> None:
    """``phantom set`` interrupted while it waited: the target is the daemon's, which goes on with it (a verified
    one's rounds too). Says so, from the daemon's status, so that nobody takes the interrupt for a stop."""
    import sys

    import phantom
    from phantom.host.client import describe_target

    try:  # a few seconds at most: the person pressed Ctrl-C to get the terminal back
        with phantom.connect(_socket(args), request_timeout_s=TELL_TIMEOUT_S, ready_timeout_s=0.0) as daemon:
            status = daemon.status()
    except Exception:  # the daemon gone too: nothing goes on that it could say
        return
    if status.target is None:
        return
    target = (f"{status.target_volume_ml:.2f} ml" if status.target_volume_ml is not None
              else describe_target(status.target))
    verify = f"; verify: {status.verify['text']}" if status.verify else ""
    print(f"phantom set: the daemon goes on with the target ({target}{verify}): `phantom status` shows it, "
          "`phantom vent` stops it", file=sys.stderr, flush=True)


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

    with _connect(args, wait_ready=args.method != "vent") as daemon:  # vent never waits
        if args.method == "vent":
            daemon.vent()
            result: dict[str, Any] = {"vented": True}
        elif args.method == "zero":
            daemon.zero()
            result = {"zeroed": True}
        else:
            cleared = daemon.clear_fault()
            result = {"cleared": list(cleared.faults), "setpoints_restored": cleared.setpoints_restored,
                      "target": cleared.target}
    print(json.dumps(result) if args.json else format_simple(args.method, result))
    return 0


def format_steps(steps: list[dict[str, Any]]) -> str:
    """The table ``make demo`` and ``run-scene --wait`` print: each step's target, the estimate at the end of its
    hold and the time it took to come within 1 %; where the steps have a true volume (the simulated plant's),
    that volume, its error against the target and, under the table, the mean of those errors. The estimate's own
    error is left out: it is what the controller drives to zero, and it hid how far off the phantom was."""
    def number(value: float | None, digits: int = 2, signed: bool = False) -> str:
        return "-" if value is None else f"{value:{'+' if signed else ''}.{digits}f}"

    def true_error_pct(step: dict[str, Any]) -> float | None:
        target, true = step["target_volume_ml"], step.get("true_volume_ml")
        return None if target is None or true is None else (true - target) / target * 100.0

    with_true = any(step.get("true_volume_ml") is not None for step in steps)
    lines = [f"{'step':>4} {'at (s)':>7} {'target':<28} {'estimate ml':>11}"
             + (f" {'true ml':>8} {'true error %':>12}" if with_true else "") + f" {'time to 1 % (s)':>15}"]
    for step in steps:
        target = step["target"] if step["target_volume_ml"] is None else f"{step['target_volume_ml']:.2f} ml"
        lines.append(f"{step['index']:>4} {step['at_s']:>7.1f} {target:<28} {number(step['reached_volume_ml']):>11}"
                     + (f" {number(step.get('true_volume_ml')):>8} {number(true_error_pct(step), signed=True):>12}"
                        if with_true else "") + f" {number(step['reached_after_s'], 1):>15}")
    errors = [abs(error) for step in steps if (error := true_error_pct(step)) is not None]
    if errors:
        lines.append(f"mean |true error| {sum(errors) / len(errors):.2f} % (largest {max(errors):.2f} %): the "
                     "phantom's own volume against the target, which the estimate cannot see")
    return "\n".join(lines)


def scene_progress(time_scale: float) -> Callable[[Status], None]:
    """Shows a playing scene's progress on stderr: one line rewritten in place on a terminal, else a line every
    ten seconds of scene time."""
    import sys

    terminal = sys.stderr.isatty()
    shown_s = [-1e9]

    def show(status: Status) -> None:
        scene = status.scene
        if scene is None:
            return
        line = (f"  {scene.time_s:6.1f} / {scene.end_s:g} s of scene (x{time_scale:g})   volume "
                f"{_ml(status.estimated_volume_ml)}   target {_ml(status.target_volume_ml)} ")
        if terminal:
            print("\r" + line, end="\n" if scene.finished else "", file=sys.stderr, flush=True)
        elif scene.finished or scene.time_s - shown_s[0] >= 10.0:
            shown_s[0] = scene.time_s
            print(line, file=sys.stderr, flush=True)
    return show


def _run_scene(args: argparse.Namespace) -> int:
    import json
    import sys

    from phantom.host.client import SceneRun, resolve_scene

    path = resolve_scene(args.scene)  # a name that is no shipped scene is refused before connecting
    with _connect(args) as daemon:
        started = daemon.run_scene(path, time_scale=args.time_scale)
        assert isinstance(started, SceneRun)  # without wait
        print(f"scene {started.name}: {started.steps} steps, {started.end_s:g} s of timeline, about "
              f"{started.wall_duration_s:.0f} s at time scale {args.time_scale:g}", file=sys.stderr)
        if not args.wait:
            if args.json:
                print(json.dumps(dataclasses.asdict(started)))
            return 0
        finished = daemon.follow_scene(started, on_progress=scene_progress(args.time_scale))
    steps = [dataclasses.asdict(step) for step in finished.steps]
    print(json.dumps(steps, indent=2) if args.json else format_steps(steps))
    missed = unreachable_steps(steps)
    if missed:
        print(f"phantom run-scene: error: {missed}", file=sys.stderr)
        return 1
    return 0


def unreachable_steps(steps: list[dict[str, Any]]) -> str | None:
    """The steps of a finished scene (the status's step records) whose target, or a point of its ramp, the daemon
    found beyond the phantom's range (``unreachable``), in one line; None when there were none."""
    missed = [step for step in steps if step.get("unreachable")]
    if not missed:
        return None
    said = "; ".join(f"{step['index']} (at {step['at_s']:g} s): {step['unreachable']}" for step in missed)
    return f"{'step' if len(missed) == 1 else 'steps'} {said}"


def watch_header(labels: Sequence[str]) -> str:
    """The column names of ``phantom watch``'s status lines."""
    per_chamber = " ".join(f"{label[:6]:>6}" for label in labels)
    return (f"{'time (s)':>9}  {'link':<12} p (kPa) {per_chamber}  set (kPa) {per_chamber}  "
            "gland volume -> target  faults")


def _run_watch(args: argparse.Namespace) -> int:
    """Twice a second the status, and the events that came since, through the API."""
    import json
    import time

    printed = 0
    seen: set[tuple[float, str]] = set()
    with _connect(args) as daemon:
        status = daemon.status()
        seen.update((event["time_s"], event["text"]) for event in status.raw.get("events", []))
        if not args.json:
            print(watch_header(status.chamber_labels), flush=True)
        while True:
            status = daemon.status()
            for event in status.raw.get("events", []):
                if (event["time_s"], event["text"]) in seen:
                    continue
                seen.add((event["time_s"], event["text"]))
                print(json.dumps({"event": "events", "data": event}) if args.json else
                      f"{event['time_s']:9.2f}  [{event['level']}] {event['text']}", flush=True)
            if args.json:
                print(json.dumps({"event": "status", "data": status.raw}), flush=True)
            else:
                print(f"{status.uptime_s:9.2f}  {status.link:<12} p (kPa) {_kpa(status.raw['pressures_kpa'])}  "
                      f"set (kPa) {_kpa(status.raw['setpoints_kpa'])}  {_ml(status.estimated_volume_ml)} "
                      f"-> {_ml(status.target_volume_ml)}  faults {','.join(status.faults) or 'none'}", flush=True)
            printed += 1
            if args.count is not None and printed >= args.count:
                return 0
            time.sleep(WATCH_PERIOD_S)
