"""Subcommand of ``phantom``: ``corrections`` (the measured volumes that correct a phantom's model).

``list``, ``add`` (a water-displacement or other measurement by hand: refused outside the model's pressure box,
stored unconfirmed when implausible, :func:`phantom.model.corrections.judged`), ``confirm N`` and ``remove N`` (one
entry), ``clear``, ``export`` (the CSV ``phantom calibrate --measurements`` reads) and ``fit`` (the correction they
give a scene's model, with every candidate's leave-one-out error). The store is ``phantom.model.measurements``; only
argparse is imported at module load.
"""

from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``corrections`` to the ``phantom`` parser."""
    corrections = subparsers.add_parser(
        "corrections", help="the scans and measurements that correct a phantom's model (list, add, confirm, remove, "
        "clear, export, fit)",
        description="Each scan of the phantom at known pressures is a measured gland volume that corrects the "
        "model; they are kept per phantom in the user's data directory ($PHANTOM_DATA_DIR, else "
        "$XDG_DATA_HOME/phantom, else ~/.local/share/phantom: corrections/NAME.json).")
    actions = corrections.add_subparsers(dest="action", metavar="ACTION", required=True)
    listing = actions.add_parser("list", help="the stored measurements, oldest first")
    add = actions.add_parser("add", help="store a measured volume by hand (a water displacement, a scan measured "
                             "elsewhere)")
    add.add_argument("--pressures-kpa", required=True, help="the chamber pressures (kPa), comma-separated")
    add.add_argument("--volume-ml", type=float, required=True, help="the measured gland volume (ml)")
    add.add_argument("--method", choices=("scan", "water_displacement"), default="water_displacement",
                     help="how it was measured (default water_displacement)")
    add.add_argument("--scan-file", help="the scan's file (kept as a reference)")
    add.add_argument("--scene", default="builtin:converged", help="the model the volume is checked against (default "
                     "builtin:converged): a volume implausible against it, corrected by the confirmed measurements, "
                     "is stored unconfirmed and left out of the fit until `confirm N`")
    confirm = actions.add_parser("confirm", help="confirm measurement N (as listed): it is right though implausible, "
                                 "and the fit uses it from now on")
    remove = actions.add_parser("remove", help="remove measurement N (as listed)")
    for parser in (confirm, remove):
        parser.add_argument("number", type=int, metavar="N", help="the measurement's number in `phantom corrections "
                            "list` (1 = the oldest)")
    clear = actions.add_parser("clear", help="remove every stored measurement of the phantom")
    clear.add_argument("--yes", action="store_true", help="do it (without --yes: say how many would go)")
    export = actions.add_parser("export", help="write the measurements as the CSV `phantom calibrate` reads")
    export.add_argument("--out", help="the CSV file to write (default: stdout); never the store itself")
    export.add_argument("--replace", action="store_true", help="write over a file already at --out")
    fit = actions.add_parser("fit", help="the correction the measurements give a scene's model, and each "
                             "candidate's leave-one-out error")
    fit.add_argument("--scene", default="builtin:converged", help="the model's scene (default builtin:converged)")
    for parser in (listing, add, confirm, remove, clear, export, fit):
        parser.add_argument("--phantom", default="default", metavar="NAME",
                            help="which phantom's measurements (default 'default')")
        parser.add_argument("--json", action="store_true", help="print JSON")
    corrections.set_defaults(run=_run)


def _run(args: argparse.Namespace) -> int:
    from phantom.model.measurements import CorrectionStore

    store = CorrectionStore.for_phantom(args.phantom)
    handler = {"list": _list, "add": _add, "confirm": _confirm, "remove": _remove, "clear": _clear,
               "export": _export, "fit": _fit}[args.action]
    return handler(store, args)


def _print(args: argparse.Namespace, data: Any, text: str) -> int:
    import json

    print(json.dumps(data) if args.json else text)
    return 0


def _list(store: Any, args: argparse.Namespace) -> int:
    from dataclasses import asdict

    entries = store.entries()
    lines = [f"{len(entries)} measurement(s) of phantom {args.phantom!r} in {store.path}"]
    for number, entry in enumerate(entries, start=1):
        pressures = ", ".join(f"{p:.3f}" for p in entry.pressures_kpa)
        model = "" if entry.model_volume_ml is None else (
            f", model {entry.model_volume_ml:.3f} ml ({(entry.model_volume_ml / entry.volume_ml - 1) * 100:+.2f} %)")
        lines.append(f"{number:3d}  {entry.time_utc or '-':25s}  {pressures} kPa  {entry.volume_ml:.3f} ml "
                     f"({entry.method}){model}" + (f"  {entry.scan_file}" if entry.scan_file else ""))
        if entry.status == "unconfirmed":
            lines.append(f"     UNCONFIRMED, left out of the fit: {entry.reason} (`phantom corrections confirm "
                         f"{number}` if it is right, `remove {number}` if not)")
        elif entry.status == "refused":
            lines.append(f"     REFUSED, left out of the fit: {entry.reason} (`phantom corrections remove {number}`, "
                         f"then add the volume again in ml)")
    return _print(args, {"path": str(store.path), "measurements": [asdict(e) for e in entries]}, "\n".join(lines))


def _checked_add(args: argparse.Namespace) -> list[float]:
    """``add``'s numbers and scan file refused in the command line's terms (its flags) before any model is built
    (the store's own messages name its fields, for library callers): the pressures, as a list of kPa."""

    from phantom.cli.common import check_input_size, parse_numbers
    from phantom.model.measurements import MAX_CHAMBERS, MAX_PRESSURE_KPA, CorrectionError, gland_volume_problem

    pressures = parse_numbers(args.pressures_kpa, "--pressures-kpa")
    if len(pressures) > MAX_CHAMBERS or not all(0 <= value <= MAX_PRESSURE_KPA for value in pressures):
        raise CorrectionError(f"--pressures-kpa takes the chamber pressures in kPa, each 0 or more (gauge: the "
                              f"blowers only push) and at most {MAX_PRESSURE_KPA:g}, one per chamber (at most "
                              f"{MAX_CHAMBERS}); got {args.pressures_kpa}")
    if problem := gland_volume_problem(args.volume_ml, "--volume-ml (the measured gland volume)"):
        raise CorrectionError(problem)
    if args.scan_file is not None:
        check_input_size(args.scan_file, None, "--scan-file", CorrectionError,
                         give="the scan's mesh file (.obj, .ply or .stl)", required=True)
    return pressures


def _add(store: Any, args: argparse.Namespace) -> int:
    import sys

    import numpy as np

    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import judged, model_grid, pressures_in_box
    from phantom.model.fidelity.levels import VolumeEstimator
    from phantom.model.measurements import CorrectionError, Measurement

    measurement = Measurement.now(_checked_add(args), args.volume_ml, args.method, args.scan_file)
    grid = model_grid(VolumeEstimator(PhantomModel.from_scene(load_scene(args.scene))), args.scene)
    chambers = grid.chamber_ml.shape[-1]
    if len(measurement.pressures_kpa) != chambers:
        raise CorrectionError(f"--pressures-kpa has {len(measurement.pressures_kpa)} values; the model {args.scene} "
                              f"has {chambers} chambers: give {chambers} pressures, one per chamber")
    on_box = pressures_in_box(measurement.pressures_kpa, float(grid.points_kpa[-1]), "--pressures-kpa")
    confirmed = store.confirmed()
    if confirmed and not args.json:  # a fit of many measurements not fitted before takes seconds
        print(f"checking {args.volume_ml:g} ml against {args.scene} corrected by the {len(confirmed)} confirmed "
              f"measurement(s) ...", file=sys.stderr, flush=True)
    measurement = judged(Measurement(measurement.pressures_kpa, measurement.volume_ml, measurement.method,
                                     measurement.time_utc, measurement.scan_file, args.scene,
                                     float(grid.gland_ml(np.asarray(on_box)))),
                         grid, confirmed, args.scene)
    count = store.add(measurement)
    text = f"stored ({count} measurement(s) of phantom {args.phantom!r} in {store.path})"
    if measurement.status != "confirmed":
        text = (f"stored UNCONFIRMED as measurement {count}, left out of the fit: {measurement.reason}. If it is "
                f"right: `phantom corrections confirm {count} --phantom {args.phantom}`; if not: `phantom "
                f"corrections remove {count} --phantom {args.phantom}`")
    return _print(args, {"path": str(store.path), "measurements": count, "status": measurement.status,
                         "reason": measurement.reason}, text)


def _confirm(store: Any, args: argparse.Namespace) -> int:
    confirmed = store.confirm(args.number)
    return _print(args, {"path": str(store.path), "confirmed": args.number},
                  f"measurement {args.number} ({confirmed.volume_ml:.3f} ml) of phantom {args.phantom!r} confirmed: "
                  f"the fit uses it")


def _remove(store: Any, args: argparse.Namespace) -> int:
    removed = store.remove(args.number)
    return _print(args, {"path": str(store.path), "removed": args.number},
                  f"removed measurement {args.number} ({removed.volume_ml:.3f} ml at "
                  f"{', '.join(f'{p:g}' for p in removed.pressures_kpa)} kPa) of phantom {args.phantom!r}")


def _clear(store: Any, args: argparse.Namespace) -> int:
    if not args.yes:
        count = len(store.entries())
        return _print(args, {"path": str(store.path), "would_remove": count},
                      f"{count} measurement(s) of phantom {args.phantom!r} would be removed: add --yes to do it "
                      f"(`phantom corrections export --out FILE` keeps a copy)")
    removed = store.clear()
    return _print(args, {"path": str(store.path), "removed": removed},
                  f"removed {removed} measurement(s) of phantom {args.phantom!r}")


def _check_out(store: Any, args: argparse.Namespace) -> None:
    """Refuse an --out that is the store itself (also through a link or another path to it: the CSV would replace
    the measurements), a folder, or a file already there without ``--replace``, before the store is read."""
    import os
    from pathlib import Path

    from phantom.model.measurements import CorrectionError

    out = Path(args.out)
    same = os.path.realpath(out) == os.path.realpath(store.path)  # realpath: a link loop raises nothing
    if not same and out.exists() and store.path.exists():
        same = os.path.samefile(out, store.path)  # a hard link to it
    if same:
        raise CorrectionError(f"--out {args.out} is the correction store of phantom {args.phantom!r} "
                              f"({store.path}): the CSV would replace the measurements; give another --out")
    if out.is_dir():
        raise CorrectionError(f"--out {args.out} is a folder: give the CSV file to write, e.g. "
                              f"{out / f'{args.phantom}.csv'}")
    if (out.exists() or out.is_symlink()) and not args.replace:
        raise CorrectionError(f"--out {args.out} exists already: give another --out, or --replace to write over it")


def _export(store: Any, args: argparse.Namespace) -> int:
    from pathlib import Path

    from phantom import written_atomically
    from phantom.model.measurements import CorrectionError

    if args.out is not None:
        _check_out(store, args)
    entries = store.entries()  # read once: the file and the count said are of the same measurements
    text = store.to_csv(entries)
    if args.out is None:
        print(text, end="")
        return 0
    with written_atomically(Path(args.out), CorrectionError) as temporary:
        temporary.write_text(text)
    unconfirmed = [number for number, entry in enumerate(entries, start=1) if entry.status == "unconfirmed"]
    refused = [number for number, entry in enumerate(entries, start=1) if entry.status == "refused"]
    left_out = "" if not unconfirmed else (
        f"; the unconfirmed measurement(s) {', '.join(map(str, unconfirmed))} as comment lines, left out as from "
        "every fit (`phantom corrections confirm N` if one is right)")
    if refused:
        left_out += (f"; the refused measurement(s) {', '.join(map(str, refused))} (a volume no gland has) as comment "
                     "lines, left out as from every fit (`phantom corrections list` says why)")
    written = len(entries) - len(unconfirmed) - len(refused)
    return _print(args, {"out": args.out, "measurements": written, "unconfirmed": unconfirmed, "refused": refused},
                  f"wrote {written} measurement(s) to {args.out} (`phantom calibrate --measurements {args.out}` reads "
                  f"it){left_out}")


def _fit(store: Any, args: argparse.Namespace) -> int:
    import numpy as np

    from phantom.model import PhantomModel, load_scene
    from phantom.model.corrections import CorrectedModel, cached_fit, model_grid
    from phantom.model.fidelity.levels import VolumeEstimator

    entries = store.confirmed()
    model = PhantomModel.from_scene(load_scene(args.scene))
    grid = model_grid(VolumeEstimator(model), args.scene)
    correction = cached_fit(entries, grid)
    summary = correction.summary(grid)
    corrected = CorrectedModel(grid, correction)
    bands = [corrected.gland_band_ml(entry.pressures_kpa) for entry in entries]
    summary["band_at_measured"] = [{"pressures_kpa": list(entry.pressures_kpa), "measured_ml": entry.volume_ml,
                                    "model_ml": grid.gland_ml(np.asarray(entry.pressures_kpa)), "corrected_ml": mean,
                                    "band_ml": half} for entry, (mean, half) in zip(entries, bands, strict=True)]
    lines = [f"{correction.count} measurement(s) of phantom {args.phantom!r}; the model {args.scene} misses them by "
             f"{correction.uncorrected_pct:.2f} % on average",
             "leave-one-out (mean abs error of the volume left out): "
             + (", ".join(f"{kind} {error:.2f} %" for kind, error in correction.leave_one_out_pct.items())
                or "none (fewer than two measurements)"),
             f"correction in force: {correction.kind}, a Gaussian process: {correction.hyperparameters()}; its "
             f"largest size over the pressure box {summary['size_ml']:.3f} ml",
             "at the measured pressures (kPa): measured, model, corrected +- its 95 % band (ml)"]
    lines += [f"  {', '.join(f'{p:.3f}' for p in entry.pressures_kpa)}: {entry.volume_ml:.3f}, "
              f"{band['model_ml']:.3f}, {band['corrected_ml']:.3f} +- {band['band_ml']:.3f}"
              for entry, band in zip(entries, summary["band_at_measured"], strict=True)]
    return _print(args, summary, "\n".join(lines))
