"""Subcommands of ``phantom``: the hardware-in-the-loop bench: phantom hil ....

The same checks run against the firmware in simavr (``--sim``) or a real board (``--port /dev/ttyACM0``);
``phantom hil plant`` writes the simulated plant's parameters from the model. Only argparse is imported at module
load; handlers import what they need when they run.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from phantom.hil.link import BoardLink
    from phantom.hil.sim import SimulatedBoard


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add this part's subcommands to the ``phantom`` parser."""
    hil = subparsers.add_parser(
        "hil",
        help="hardware-in-the-loop bench: the firmware in simavr (--sim) or a real board (--port)",
        description="Run bench checks against the firmware image in simavr (--sim) or a board on a serial port.",
    )
    checks = hil.add_subparsers(dest="check", metavar="COMMAND", required=True)

    def add_check(name: str, help_text: str, handler: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
        parser = checks.add_parser(name, help=help_text, description=help_text)
        target = parser.add_mutually_exclusive_group(required=True)
        target.add_argument("--sim", action="store_true", help="run the firmware image in simavr against the plant")
        target.add_argument("--port", help="serial port of a real board, e.g. /dev/ttyACM0")
        parser.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
        parser.add_argument("--elf", help="firmware image for --sim (default firmware/build/uno-bench/phantom.elf)")
        parser.add_argument("--plant", help="plant parameter file for --sim (default hil/plant.toml)")
        parser.add_argument(
            "--sim-speed", dest="speed", type=float, default=1.0,
            help="--sim: simulated time per wall-clock time (default 1 = real time)",
        )
        parser.add_argument(
            "--boot-delay-s", type=float,
            help="--port: seconds to stay silent after opening the port while the bootloader runs "
                 "(default 2, enough for the Uno's Optiboot and the Mega's stk500v2)",
        )
        parser.add_argument("--seed", type=int, default=0, help="--sim: seed of the sensor and line noise")
        parser.add_argument("--json", action="store_true", help="print the result as JSON")
        parser.set_defaults(run=handler)
        return parser

    add_check("handshake", "HELLO: the board's identity, and a foreign spec hash refused", _run_handshake)
    step = add_check("step", "step response of one chamber: rise, overshoot, settling, steady-state error", _run_step)
    step.add_argument("--chamber", type=int, default=0, choices=(0, 1, 2), help="chamber to step (default 0)")
    step.add_argument("--kpa", type=float, default=2.0, help="step height in kPa (default 2)")
    step.add_argument("--duration-s", type=float, default=3.0, help="how long to record after the step (default 3)")
    step.add_argument("--plot", help="write the response as a PNG to this path")
    step.add_argument("--pid", help="KP,KI,KD gains (per kPa, per kPa s, s per kPa) to send with SET_PID first")
    add_check("faults", "each fault trips the latch and the blowers stop in the stated time", _run_faults)
    add_check("noise", "the link survives line noise: no corrupted command applied", _run_noise)
    add_check("watchdog", "a watchdog reset is reported by the next HELLO", _run_watchdog)
    report = add_check("report", "every check, with a Markdown/JSON report and PNG plots", _run_report)
    report.add_argument("--out", default="out/hil-report", help="output folder (default ./out/hil-report)")
    report.add_argument("--kpa", type=float, default=2.0, help="step height in kPa (default 2)")
    cycles = add_check("cycles", "CPU use of the firmware from simavr's cycle counter (--sim only)", _run_cycles)
    cycles.add_argument("--duration-s", type=float, default=5.0, help="measurement time (default 5 s)")
    cycles.add_argument("--telemetry-ms", type=int, default=20, help="telemetry period (default 20 ms = 50 Hz)")
    cycles.add_argument("--kpa", type=float, default=2.0, help="setpoint of all three chambers (default 2)")

    plant = checks.add_parser(
        "plant", help="write the model's chamber volumes and compliance (and a truth table) into a plant file",
        description="Regenerate the simulated plant's parameters from a scene's FEM: --from-scene rewrites the "
        "chambers' rest volumes and compliance (at rest), --truth-from-scene the truth table of chamber volumes "
        "over the three pressures that the simulated board's plant interpolates (64 full solves, each from its "
        "grid neighbour, on every core). Everything else in the file is kept; the result is checked before it is "
        "written.")
    plant.add_argument("--from-scene", metavar="SCENE",
                       help="scene TOML (or 'builtin', 'builtin:converged') whose FEM gives the chambers")
    plant.add_argument("--truth-from-scene", metavar="SCENE",
                       help="scene whose model, with its modulus times --truth-modulus-factor, is the plant's truth")
    plant.add_argument("--truth-modulus-factor", type=float, metavar="X",
                       help="the truth's modulus over the scene's (default: the calibration's leave-one-out "
                       "uncertainty, TRUTH_MODULUS_FACTOR in hil/plant.py)")
    plant.add_argument("--truth-through", metavar="CSV",
                       help="--truth-from-scene: add the smoothest residual that takes the truth's gland volume "
                       "through these measured volumes (the shipped truth: model/data/forward_measurements.csv, "
                       "the paper's Table I)")
    plant.add_argument("--workers", type=int, metavar="N", help="--truth-from-scene: worker processes "
                       "(default: one per core, at most 4)")
    plant.add_argument("--scheduler", metavar="ADDRESS", help="--truth-from-scene: address of a running Dask "
                       "scheduler (tcp://HOST:8786) to run the solves on, instead of --workers on this machine")
    plant.add_argument("--plant", metavar="FILE", help="the plant file to rewrite (default hil/plant.toml)")
    plant.add_argument("--mesh-size-mm", type=float, metavar="MM",
                       help="--from-scene: mesh size of the built-in mesh (default: the model's)")
    plant.set_defaults(run=_run_plant)


class _Bench:
    """The link (and the simulated board, with --sim) for one command."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.board: SimulatedBoard | None = None
        self._link: BoardLink | None = None

    @property
    def link(self) -> BoardLink:
        """The link to the board (inside the ``with``)."""
        if self._link is None:
            raise RuntimeError("the bench's link is open only inside its with block")
        return self._link

    def __enter__(self) -> _Bench:
        from phantom.hil.link import BoardLink
        from phantom.hil.sim import SimulatedBoard
        from phantom.protocol.link import BOOT_DELAY_S

        port, scale = self.args.port, 1.0
        boot_delay_s = self.args.boot_delay_s
        if boot_delay_s is None:
            boot_delay_s = max(BOOT_DELAY_S.values())
        if self.args.sim:
            _progress("starting the firmware in simavr")
            board = self.board = SimulatedBoard(self.args.elf, self.args.plant, speed=self.args.speed,
                                                seed=self.args.seed)
            board.start()
            port, scale = board.port, (self.args.speed or 1.0)
            boot_delay_s = BOOT_DELAY_S["sim"]
        self._link = BoardLink(port, baudrate=self.args.baud, time_scale=scale, boot_delay_s=boot_delay_s)
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._link is not None:
            self._link.close()
        if self.board is not None:
            self.board.stop()


def _fault_line(result: dict[str, Any]) -> str:
    """One line of `phantom hil faults` for one fault check's result."""
    if "skipped" in result:
        return f"{result['fault']}: skipped ({result['skipped']})"
    verdict = "PASS" if result["passed"] else "FAIL"
    if result["fault"] == "mild_leak":
        return f"mild_leak: {verdict}, held {result.get('held_kpa')} kPa at drive {result.get('drive_level', 0.0):.2f}"
    stop_time_s = result.get("stop_time_s")
    stopped = "blowers not stopped" if stop_time_s is None else f"blowers off after {stop_time_s:.3f} s"
    line = f"{result['fault']}: {verdict}, latched {result['latched']}, {stopped} (limit {result.get('limit_s')} s)"
    if result.get("chamber") is not None and "peak_true_kpa" in result:
        line += f", true pressure at most {result['peak_true_kpa'][result['chamber']]:.2f} kPa"
    return line


def _progress(message: str) -> None:
    import sys

    print(f"phantom hil: {message}", file=sys.stderr, flush=True)


def _emit(args: argparse.Namespace, result: dict[str, Any], lines: list[str]) -> int:
    import json

    print(json.dumps(result, indent=1) if args.json else "\n".join(lines))
    return 0 if result.get("passed", True) else 1


def _run_handshake(args: argparse.Namespace) -> int:
    from phantom.hil import bench

    with _Bench(args) as b:
        result = bench.check_handshake(b.link)
    lines = [f"{key}: {value}" for key, value in result.items()]
    return _emit(args, result, lines)


def _run_step(args: argparse.Namespace) -> int:
    from pathlib import Path

    from phantom import PhantomError
    from phantom.hil import bench

    gains = None
    if args.pid is not None:
        try:
            gains = [float(value) for value in args.pid.split(",")]
        except ValueError:
            gains = []
        if len(gains) != 3 or any(g < 0 for g in gains):
            raise PhantomError(f"--pid takes three gains >= 0 as KP,KI,KD (e.g. 4,15,0), got {args.pid!r}")
    with _Bench(args) as b:
        _progress(f"step 0 -> {args.kpa} kPa on chamber {args.chamber}")
        result = bench.check_step(b.link, args.chamber, args.kpa, duration_s=args.duration_s, gains=gains)
    if args.plot:
        bench.plot_steps([result], Path(args.plot), board="simulated (simavr)" if args.sim else args.port)
    result.pop("trace")
    lines = [f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}" for key, value in result.items()]
    return _emit(args, result, lines)


def _run_faults(args: argparse.Namespace) -> int:
    from phantom.hil import bench

    results = []
    with _Bench(args) as b:
        for fault, chamber in bench.FAULT_CHECKS:
            _progress(f"fault: {fault}")
            results.append(bench.check_fault(b.link, b.board, fault, chamber))
    passed = all(r.get("passed", True) for r in results)
    lines = [_fault_line(result) for result in results]
    return _emit(args, {"passed": passed, "faults": results}, lines)


def _run_noise(args: argparse.Namespace) -> int:
    from phantom.hil import bench

    with _Bench(args) as b:
        result = bench.check_line_noise(b.link, b.board)
    return _emit(args, result, [f"{key}: {value}" for key, value in result.items()])


def _run_watchdog(args: argparse.Namespace) -> int:
    from phantom.hil import bench

    with _Bench(args) as b:
        result = bench.check_watchdog(b.link, b.board)
    return _emit(args, result, [f"{key}: {value}" for key, value in result.items()])


def _run_report(args: argparse.Namespace) -> int:
    from pathlib import Path

    from phantom.hil import bench

    out = Path(args.out)
    with _Bench(args) as b:
        report = bench.run_report(b.link, b.board, out, target_kpa=args.kpa)
    passed = (
        report["handshake"]["passed"]
        and all(f.get("passed", True) for f in report["faults"])
        and report["line_noise"].get("passed", True)
        and report["watchdog"]["passed"]
    )
    _progress(f"report written to {out}/report.md (plots: {out}/steps.png)")
    if args.json:
        for step in report["steps"]:
            step.pop("trace")
    return _emit(args, {"passed": passed, **report}, [(out / "report.md").read_text()])


def _run_cycles(args: argparse.Namespace) -> int:
    from phantom import PhantomError
    from phantom.hil import bench

    if not args.sim:
        raise PhantomError("cycle counts need the simulator: use `phantom hil cycles --sim`")
    with _Bench(args) as b:
        result = bench.measure_cycles(b.link, b.board, args.duration_s, args.telemetry_ms, args.kpa)
    lines = [f"{key}: {value:.6g}" if isinstance(value, float) else f"{key}: {value}" for key, value in result.items()]
    return _emit(args, result, lines)


def _run_plant(args: argparse.Namespace) -> int:
    from phantom import PhantomError
    from phantom.hil import plant

    if args.truth_through and not args.truth_from_scene:
        raise PhantomError("--truth-through adds a residual to a truth table: give --truth-from-scene SCENE too")
    if not args.from_scene and not args.truth_from_scene:
        raise PhantomError("give --from-scene, --truth-from-scene or both")
    path = args.plant or plant.DEFAULT_PLANT_PATH
    if args.scheduler and args.workers is not None:
        raise PhantomError("give --workers (this machine) or --scheduler (a cluster), not both")
    if args.truth_from_scene:
        from phantom.model.cluster import stderr_progress

        factor = plant.TRUTH_MODULUS_FACTOR if args.truth_modulus_factor is None else args.truth_modulus_factor
        table = plant.truth_table_from_scene(args.truth_from_scene, factor, args.workers,
                                             stderr_progress("truth table"), args.scheduler)
        if args.truth_through:
            from phantom.model.calibration.calibrate import load_measurements

            measured = load_measurements(args.truth_through, plant.N_CHAMBERS)
            table = plant.truth_through_measurements(table, measured.pressures_pa / 1e3, measured.volumes_m3 * 1e6,
                                                     str(args.truth_through))
        plant.write_truth(table, path)
        print(f"wrote the truth table into {path}: {table.description}")
    if args.from_scene:
        _progress(f"FEM of {args.from_scene} (meshing first if not cached)")
        chambers = plant.chambers_from_scene(args.from_scene, args.mesh_size_mm)
        written = plant.write_chambers(chambers, path)
        print(f"wrote {written.path}: {chambers.description}")
        print(f"cavity_volume_ml = {plant.toml_list(chambers.cavity_volume_ml)}")
        print(f"rest air volume (with the tubes) ml = {plant.toml_list(1e6 * written.rest_volume_m3)}")
        for row in chambers.compliance_ml_per_kpa:
            print(f"compliance_ml_per_kpa row = {plant.toml_list(row)}")
    return 0
