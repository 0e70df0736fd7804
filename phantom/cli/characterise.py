"""Subcommand of ``phantom``: ``characterise`` (the phantom scanned over its pressure box, the model corrected).

Through the running daemon (its socket, as every client command): for each pressure state of the design, set the
pressures and wait until the daemon says they are reached, scan (the daemon's ``scan`` method, into
``DIR/scans/NNN``), reconstruct the scan here, and store the scanned gland volume in the phantom's CorrectionStore
and in ``DIR``'s record (``phantom.scan.characterise``); then vent, fit the correction to the run's scans, and
write the report. Only argparse is imported at module load.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from phantom.host.client import Phantom
    from phantom.model.corrections import ModelGrid
    from phantom.model.measurements import CorrectionStore
    from phantom.scan.camera import Rig
    from phantom.scan.characterise import CharacterisationRecord, PointResult

#: How much the daemon's model may differ from --scene's at rest (ml) before the run is refused as another model.
SAME_MODEL_ML = 0.05


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``characterise`` to the ``phantom`` parser."""
    from phantom.cli.client import _add_socket
    from phantom.cli.scan_verify import VERIFY_SETTLE_S

    parser = subparsers.add_parser(
        "characterise", help="scan the phantom over its pressure box through the daemon, store the scans and fit "
        "the model's correction (report.md, report.png)",
        description="Through the running daemon: set each pressure state of the design (--path N: rest and N-1 "
        "states along the model's inverse, where volume targets are set; --grid: every combination of the given kPa "
        "on every chamber; --points N: a Latin hypercube of N states in the daemon's pressure box), scan the phantom "
        "there and reconstruct the scan, and store each scanned volume as a measurement of "
        "the phantom (`phantom corrections list`) and in DIR; then vent, fit the correction to the scans and "
        "write DIR/report.md and DIR/report.png. A stopped run goes on with --resume, without scanning a finished "
        "point again. The rig's calibration comes from `phantom scan calibrate` (on the simulated rig: `phantom "
        "scan calibrate --sim --scale 0.5 --out rig.json`).")
    design = parser.add_mutually_exclusive_group()
    design.add_argument("--path", type=int, metavar="N", help="rest and N-1 states the model's inverse gives for "
                        "volumes evenly across its range: the states volume targets are set at, so the targets "
                        "land where the scans measured (the design for volume targets)")
    design.add_argument("--grid", metavar="KPA,KPA,...", help="the pressures (kPa) combined on every chamber, e.g. "
                        "0,1.5,3 (27 states on three chambers)")
    design.add_argument("--points", type=int, metavar="N", help="N states of a space-filling design (a Latin "
                        "hypercube, its centred discrepancy lowered) in the daemon's pressure box")
    parser.add_argument("--resume", action="store_true", help="go on with the run in --out where it stopped")
    parser.add_argument("--out", required=True, metavar="DIR", help="the run's folder: its record, scans and report")
    parser.add_argument("--phantom", default="default", metavar="NAME",
                        help="which phantom's measurements to add to (default 'default', as the daemon's)")
    parser.add_argument("--rig", metavar="RIG.json", help="the scanner's calibration (phantom scan calibrate); "
                        "required to start, kept in DIR")
    parser.add_argument("--scene", default="builtin:converged",
                        help="the daemon's model scene (default builtin:converged, the daemon's default)")
    parser.add_argument("--views", type=int, default=30,
                        help="pictures per turn of the orbit (default 30: at two elevations, 60 pictures of 640x480 "
                        "read the simulated phantom -0.13 %% at rest and +0.16 %% at 45 ml, bench/README.md "
                        "\"Scanner\"; the elevations a rig from `phantom scan calibrate --sim` has)")
    parser.add_argument("--elevations", default="0,30", help="the passes' elevations (deg, default 0,30)")
    parser.add_argument("--scale", type=float, default=0.5,
                        help="the virtual camera's picture size, of 1280x960 (default 0.5: 640x480)")
    parser.add_argument("--camera", default=None,
                        help="the daemon's camera (default): its --camera on a real board, else the simulated "
                        "board's virtual one; or 'virtual', a device number, a stream's URL")
    parser.add_argument("--settle-s", type=float, default=VERIFY_SETTLE_S,
                        help=f"wait after each move of the orbit (s, default {VERIFY_SETTLE_S:g}, the verify scan's)")
    parser.add_argument("--voxel-mm", type=float, default=0.3, help="the reconstruction's finest voxel (mm)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the design and of the sensor noise")
    parser.add_argument("--reach-timeout-s", type=float, default=120.0,
                        help="how long a state may take to be reached before it is skipped (s)")
    parser.add_argument("--calibrate", action="store_true",
                        help="then run `phantom calibrate` on the run's measurements (DIR/measurements.csv)")
    parser.add_argument("--json", action="store_true", help="print one JSON object at the end")
    _add_socket(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Handler of ``phantom characterise``."""
    import sys

    import phantom
    from phantom.host.client import ConnectionLostError
    from phantom.model.measurements import CorrectionStore
    from phantom.scan.characterise import CharacterisationError, CharacterisationRecord

    out = Path(args.out)
    if args.resume:
        record = CharacterisationRecord.load(out)
        _check_same_run(record, args)
    else:
        if args.grid is None and args.points is None and args.path is None:
            raise CharacterisationError("give the design: --path N, --grid KPA,KPA,... or --points N (or --resume "
                                        "to go on with a stopped run)")
        if CharacterisationRecord.exists(out):
            done = len(CharacterisationRecord.load(out).results)
            raise CharacterisationError(f"{out} holds a characterisation already ({done} point(s) done): give "
                                        f"--resume to go on with it, or another --out")
        if args.rig is None:
            raise CharacterisationError("give the scanner's calibration: --rig RIG.json (from `phantom scan "
                                        "calibrate`; on the simulated rig `phantom scan calibrate --sim --scale "
                                        f"{args.scale:g} --out rig.json`)")
    store = CorrectionStore.for_phantom(record.phantom if args.resume else args.phantom)
    scene = record.model if args.resume else args.scene
    say = _teller()
    say(f"loading the model {scene} ...")
    grid = _grid(scene)
    try:
        client = phantom.connect(_socket(args), request_timeout_s=3600.0, ready_timeout_s=60.0,
                                 on_wait=lambda what: say(f"waiting for the daemon: {what}"))
    except ConnectionLostError as error:
        raise CharacterisationError(f"{error.message}; `phantom daemon --sim` runs it on the simulated board") from None
    with client:
        _check_daemon(client, grid)
        if not args.resume:
            record = _new_record(args, out, grid)
        rig = _rig(record)
        _store_unstored(record, store, say, grid, lambda folder: _reconstructed_ml(folder, rig, record, client))
        started = time.monotonic()
        session: dict[str, Any] = {"started_utc": _utc_now(), "points": 0, "elapsed_s": 0.0}
        record.sessions.append(session)
        try:
            with _terminate_as_interrupt():
                _visit(client, record, store, grid, rig, args, say, session, started)
        except KeyboardInterrupt:
            say(f"stopped: {len(record.results)} of {len(record.points_kpa)} points done and stored; `phantom "
                f"characterise --resume --out {out}` goes on")
            return 130
        finally:
            session["elapsed_s"] = time.monotonic() - started
            record.save()
        say("venting")
        client.vent()
    if not record.results:
        raise CharacterisationError(f"no point was scanned ({len(record.skipped)} skipped): see {record.path}")
    return _finish(record, grid, args, say, sys.stdout)


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM stops the run as Ctrl-C does: the session's time and points saved in the record, `--resume` said.
    A run in the background (`nohup phantom characterise ... &`) ignores SIGINT, and a kill left the session's time
    out of the report's total (2 of 4 sessions of the real run on the simulated rig)."""
    import signal

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _socket(args: argparse.Namespace) -> Path:
    from phantom.cli.client import _socket as client_socket

    return client_socket(args)


def _teller() -> Any:
    import sys

    started = time.monotonic()

    def say(text: str) -> None:
        print(f"[{time.monotonic() - started:7.1f} s] {text}", file=sys.stderr, flush=True)
    return say


def _utc_now() -> str:
    import datetime

    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _grid(scene: str) -> ModelGrid:
    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import model_grid
    from phantom.model.fidelity.levels import VolumeEstimator

    return model_grid(VolumeEstimator(PhantomModel.from_scene(load_scene(scene))), scene)


def _check_same_run(record: CharacterisationRecord, args: argparse.Namespace) -> None:
    """--resume goes on with the record's run: a design, phantom or rig given that differs is refused."""
    from phantom.cli.common import parse_numbers
    from phantom.scan.characterise import CharacterisationError

    design = record.design
    asked: dict[str, Any] = {}
    if args.grid is not None:
        asked = {"kind": "grid", "values_kpa": parse_numbers(args.grid, "--grid")}
    elif args.points is not None:
        asked = {"kind": "points", "count": args.points, "seed": args.seed}
    elif args.path is not None:
        asked = {"kind": "path", "count": args.path}
    if asked and any(design.get(key) != value for key, value in asked.items()):
        raise CharacterisationError(f"{record.folder} holds another design ({design}): --resume goes on with it "
                                    f"(give no --path, --grid or --points), or start another --out")
    if args.phantom != "default" and args.phantom != record.phantom:
        raise CharacterisationError(f"{record.folder} characterises phantom {record.phantom!r}, not "
                                    f"{args.phantom!r}: --resume goes on with it")


def _check_daemon(client: Phantom, grid: ModelGrid) -> None:
    """Refuse, before anything moves, a daemon that cannot scan, has a fault latched, or holds another model."""
    from phantom.host.client import DaemonError
    from phantom.scan.characterise import CharacterisationError

    status = client.status()
    if status.faults:
        raise CharacterisationError(f"the board has faults latched ({', '.join(status.faults)}): remove the cause "
                                    f"and `phantom clear-fault` first")
    try:
        client.call("scan", {})
    except DaemonError as error:
        if error.code == "unknown_method":
            raise CharacterisationError("this daemon has no scanner (no `scan` method): run the one `phantom daemon` "
                                        "starts (`phantom daemon --sim` on the simulated board)") from None
        # the scanner's own refusal of a scan without a folder: it is there
    import numpy as np

    rest_ml = grid.gland_ml(np.zeros(grid.chamber_ml.shape[-1]))
    daemon_rest = status.raw.get("rest_volume_ml")
    if daemon_rest is not None and abs(float(daemon_rest) - rest_ml) > SAME_MODEL_ML:
        raise CharacterisationError(f"the daemon's model rests at {float(daemon_rest):.3f} ml, {grid.description} at "
                                    f"{rest_ml:.3f} ml: give --scene the daemon's scene")


def _new_record(args: argparse.Namespace, out: Path, grid: ModelGrid) -> CharacterisationRecord:
    import shutil

    import numpy as np

    from phantom.cli.common import parse_numbers
    from phantom.scan.camera import Rig
    from phantom.scan.characterise import CharacterisationRecord, grid_design, path_design, space_filling_design

    pressure_max_kpa = float(grid.points_kpa[-1])
    chambers = grid.chamber_ml.shape[-1]
    design: dict[str, Any]
    if args.grid is not None:
        values = parse_numbers(args.grid, "--grid")
        points = grid_design(values, pressure_max_kpa, chambers)
        design = {"kind": "grid", "values_kpa": values}
    elif args.path is not None:
        points = path_design(args.path, _model_inverse(grid.description), grid.gland_ml(np.zeros(chambers)),
                             grid.gland_ml(np.full(chambers, pressure_max_kpa)))
        design = {"kind": "path", "count": args.path}
    else:
        points = space_filling_design(args.points, pressure_max_kpa, chambers, args.seed)
        design = {"kind": "points", "count": args.points, "seed": args.seed}
    Rig.load(args.rig)  # a bad rig file is refused before the run starts
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(args.rig, out / "rig.json")
    scan = {"views": args.views, "elevations_deg": parse_numbers(args.elevations, "--elevations"),
            "scale": args.scale, "settle_s": args.settle_s, "voxel_mm": args.voxel_mm, "seed": args.seed,
            "camera": args.camera}
    _check_plan(scan)
    record = CharacterisationRecord(out, args.phantom, grid.description, design, pressure_max_kpa,
                                    points.tolist(), scan, "rig.json")
    record.save()
    return record


def _model_inverse(scene: str) -> Any:
    """The model's own inverse (gland volume in ml -> pressures in kPa), as the daemon's model worker answers a
    volume target without a correction (and with one: it asks this inverse for other volumes)."""
    import numpy as np

    from phantom.model import PhantomModel, load_scene
    from phantom.model.inverse import InverseSolver
    from phantom.model.target import Target

    solver = InverseSolver(PhantomModel.from_scene(load_scene(scene)))

    def inverse_kpa(volume_ml: float) -> np.ndarray:
        return np.asarray(solver.pressures_for(Target(gland_volume_m3=volume_ml * 1e-6)).pressures_pa) / 1e3
    return inverse_kpa


def _check_plan(scan: dict[str, Any]) -> None:
    """The scan's plan and voxel checked here, before the daemon is asked to move."""
    from phantom.scan.capture import Plan
    from phantom.scan.characterise import CharacterisationError
    from phantom.scan.reconstruct import MAX_VOXEL_MM, MIN_VOXEL_MM

    Plan(scan["views"], tuple(scan["elevations_deg"]), settle_s=scan["settle_s"])
    if not MIN_VOXEL_MM <= scan["voxel_mm"] <= MAX_VOXEL_MM:
        raise CharacterisationError(f"--voxel-mm must be from {MIN_VOXEL_MM:g} to {MAX_VOXEL_MM:g}, got "
                                    f"{scan['voxel_mm']!r}")


def _rig(record: CharacterisationRecord) -> Rig:
    from phantom.scan.camera import Rig

    rig: Rig = Rig.load(str(record.folder / record.rig))
    return rig


def _store_unstored(record: CharacterisationRecord, store: CorrectionStore, say: Any, grid: ModelGrid,
                    volume_of: Any) -> None:
    """Store the finished points a stopped run recorded but had not stored yet (a stop between the two), each once
    verified (:func:`phantom.scan.characterise.verified_row`: its scan is this run's and gives its volume): a row
    refused is said why and scanned again; an implausible one is stored unconfirmed."""
    from phantom.scan.characterise import CharacterisationError, check_same_folder, verified_row

    check_same_folder(record)
    stored_files = {entry.scan_file for entry in store.entries()}
    for result in list(record.results):
        if not result.stored:
            if result.scan_folder not in stored_files:
                try:
                    measurement = verified_row(record, result, grid, store.confirmed(), volume_of)
                except CharacterisationError as refused:
                    record.forget(result.index)
                    say(f"{refused}; it is scanned again")
                    continue
                store.add(measurement)
                say(f"point {result.index}: stored its scan now (the run stopped before it was)"
                    + ("" if measurement.status == "confirmed" else f", UNCONFIRMED: {measurement.reason}"))
            record.mark_stored(result.index)


def _reconstructed_ml(folder: Path, rig: Rig, record: CharacterisationRecord, client: Phantom) -> float:
    """The gland volume (ml) of the complete scan in ``folder`` reconstructed as the run does (the hull's error
    on the model's surface at its held pressures taken off)."""
    from phantom.scan.capture import CaptureFolder
    from phantom.scan.characterise import CharacterisationError, held_pressures_kpa, scanned_ml

    capture = CaptureFolder.open(folder)
    if capture.status != "complete":
        raise CharacterisationError(f"the scan ended {capture.status}, not complete")
    pressures = held_pressures_kpa([frame.pressures_kpa for frame in capture.frames if frame.pressures_kpa])
    return scanned_ml(capture, rig, record.scan["voxel_mm"], pressures,
                      _model_surface_at(client, record.pressure_max_kpa))[0]


def _model_surface_at(client: Phantom, pressure_max_kpa: float) -> Any:
    """The model's outer surface at pressures (kPa), asked of the daemon: positions (mm) and triangles. A point held
    at the box's edge reads an ADC count or two past it (3.005 kPa), which the daemon refuses: its shape is the
    edge's."""
    def surface_at(pressures_kpa: list[float]) -> tuple[Any, Any]:
        surface = client.surface([min(max(p, 0.0), pressure_max_kpa) for p in pressures_kpa])
        return surface.vertices_mm, surface.faces
    return surface_at


def _visit(client: Phantom, record: CharacterisationRecord, store: CorrectionStore, grid: ModelGrid, rig: Rig,
           args: argparse.Namespace, say: Any, session: dict[str, Any], started: float) -> None:
    """Set, scan, reconstruct and store each pending point (see the module docstring)."""
    import shutil

    from phantom.cli.common import format_duration
    from phantom.host.client import (
        DaemonError,
        TargetReplacedError,
        UnreachableError,
        WaitTimeoutError,
    )
    from phantom.model.corrections import judged
    from phantom.scan.characterise import CharacterisationError

    pending = record.pending()
    total = len(record.points_kpa)
    say(f"{total - len(pending)} of {total} points done; {len(pending)} to scan into {record.folder / 'scans'}")
    for number, index in enumerate(pending, start=1):
        point_started = time.monotonic()
        asked = record.points_kpa[index]
        label = f"[{total - len(pending) + number}/{total}] point {index} ({_kpa(asked)} kPa)"
        folder = record.scan_folder(index)
        if folder.exists():
            say(f"{label}: removing the unfinished scan a stopped run left in {folder}")
            shutil.rmtree(folder)
        try:
            client.set_pressures(asked, wait=True, timeout_s=args.reach_timeout_s)
        except TargetReplacedError as error:
            raise CharacterisationError(f"{label}: {error.message}: another client moved the phantom; run again "
                                        f"with --resume when it is free") from None
        except (UnreachableError, WaitTimeoutError) as error:
            record.skip(index, error.message)
            say(f"{label}: skipped, not reached: {error.message}")
            continue
        except DaemonError as error:  # a fault while reaching, or latched since the last point (the board refuses)
            raise CharacterisationError(f"{label}: {error.message}; then `phantom characterise --resume --out "
                                        f"{record.folder}` goes on from this point") from None
        say(f"{label}: reached; scanning")
        result = _scan_point(client, record, index, folder, rig, grid, point_started, label)
        measurement = result.measurement(record.model)  # checked before it is recorded: a record holds only these
        record.finish(result)
        measurement = judged(measurement, grid, store.confirmed(), record.model)
        store.add(measurement)
        if measurement.status != "confirmed":
            say(f"{label}: stored UNCONFIRMED, left out of the fits: {measurement.reason} (`phantom corrections "
                f"confirm N` if it is right)")
        record.mark_stored(index)
        session["points"] += 1
        elapsed = time.monotonic() - started
        left = (len(pending) - number) * elapsed / number
        truth = "" if result.true_ml is None else (
            f", truth {result.true_ml:.3f} ml (scan {(result.volume_ml / result.true_ml - 1) * 100:+.2f} %)")
        hull = ("the hull's error not taken off (the model's surface fit no motion onto the scan)"
                if result.hull_error_pct is None else f"the hull's {result.hull_error_pct:+.3f} % taken off")
        say(f"{label}: scan {result.volume_ml:.3f} ml ({hull}), model {result.model_ml:.3f} ml "
            f"({(result.model_ml / result.volume_ml - 1) * 100:+.2f} %){truth}; {result.seconds:.0f} s; "
            f"{format_duration(elapsed)} elapsed, about {format_duration(left)} left")


def _scan_point(client: Phantom, record: CharacterisationRecord, index: int, folder: Path, rig: Rig, grid: ModelGrid,
                point_started: float, label: str) -> PointResult:
    """Scan point ``index`` with the daemon's ``scan`` and measure it (``phantom.scan.characterise``)."""
    from phantom.host.client import DaemonError
    from phantom.scan.characterise import CharacterisationError, measured_point, scan_params

    try:
        client.call("scan", scan_params(record, index, folder))
    except DaemonError as error:
        faults = client.status().faults
        why = f" (faults latched: {', '.join(faults)}: remove the cause and `phantom clear-fault`)" if faults else ""
        raise CharacterisationError(f"{label}: {error.message}{why}; the point is not stored: `phantom characterise "
                                    f"--resume --out {record.folder}` scans it again") from None
    true_ml = client.status().true_volume_ml
    return measured_point(record, index, folder, rig, grid, _utc_now(), time.monotonic() - point_started, true_ml,
                          label, _model_surface_at(client, record.pressure_max_kpa))


def _kpa(pressures: Any) -> str:
    return ", ".join(f"{p:.2f}" for p in pressures)


def _finish(record: CharacterisationRecord, grid: ModelGrid, args: argparse.Namespace, say: Any, stdout: Any) -> int:
    """Fit the correction to the run's scans, write the measurements CSV, optionally calibrate, and report."""
    import json
    import tempfile

    from phantom import written_atomically
    from phantom.model.measurements import CorrectionStore
    from phantom.scan.characterise import CharacterisationError, fit_run, write_report

    held_out = {entry.scan_file for entry in CorrectionStore.for_phantom(record.phantom).entries()
                if entry.status != "confirmed"}
    measurements = [m for m in record.measurements() if m.scan_file not in held_out]  # the confirmed ones
    if not measurements:
        raise CharacterisationError(f"every scan of the run is stored unconfirmed (`phantom corrections list "
                                    f"--phantom {record.phantom}`): confirm those that are right, then run again")
    say(f"fitting the correction to {len(measurements)} scans (each kind left out in turn) ...")
    correction, note = fit_run(measurements, grid)
    if note:
        say(note)
    with tempfile.TemporaryDirectory(prefix="phantom-characterise-") as scratch:
        export = CorrectionStore(Path(scratch) / "run.json")
        for measurement in record.measurements():
            export.add(measurement)
        csv_text = export.to_csv()
    csv_path = record.folder / "measurements.csv"
    with written_atomically(csv_path, CharacterisationError) as temporary:
        temporary.write_text(csv_text)
    extra = [note, "", f"The measurements: {csv_path.name} (`phantom calibrate --measurements {csv_path.name}` reads "
             "it)."]
    if args.calibrate:
        extra += _calibrate(record, csv_path, say)
    markdown, plot = write_report(record, grid, correction, extra)
    summary = {"report": str(markdown), "plot": str(plot), "measurements": str(csv_path),
               "points": len(record.results), "skipped": len(record.skipped), "correction": correction.to_json()}
    if args.json:
        print(json.dumps(summary), file=stdout)
    else:
        loo = ", ".join(f"{kind} {error:.2f} %" for kind, error in correction.leave_one_out_pct.items())
        print(f"{len(record.results)} scans; the model misses them by {correction.uncorrected_pct:.2f} % on average; "
              f"leave-one-out {loo or '-'}; in force: {correction.kind}\nreport {markdown}, plot {plot}", file=stdout)
    return 0


def _calibrate(record: CharacterisationRecord, csv_path: Path, say: Any) -> list[str]:
    """`phantom calibrate` on the run's measurements, its output kept in DIR/calibrate.log; the report's lines."""
    import subprocess
    import sys

    output = record.folder / "calibrated.toml"
    command = [str(Path(sys.executable).with_name("phantom")), "calibrate", "--scene", record.model,
               "--measurements", str(csv_path), "--output", str(output)]
    say("$ " + " ".join(command))
    with open(record.folder / "calibrate.log", "w") as log:
        code = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode
    text = (record.folder / "calibrate.log").read_text().strip().splitlines()
    say(f"phantom calibrate exited {code}: see {record.folder / 'calibrate.log'}")
    return ["", "## phantom calibrate", "", f"Exit {code}; the last lines of calibrate.log:", "", "```",
            *text[-15:], "```"]
