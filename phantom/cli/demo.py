"""``make demo``: the daemon on the simulated board runs a BPH growth scene end to end, then verifies each of its
volumes with the scanner.

Starts ``phantom daemon --sim`` (the real firmware image in simavr, paced to the wall clock) with a recording,
waits for it to be ready (saying what it is doing: a first start on a machine answers on full solves while the
response table builds in the background), plays the scene's timeline through the Python API, prints a table of
each step's target, estimate, true volume (the simulated plant's) and its error, with the time it took: the
model's own error, uncorrected. Then each step's volume is set again with ``verify="scan"`` (issue 36: scanned,
corrected, applied again until the scanned volume is within 0.3 %) and a second table prints, per step, the
target, the model's estimate, the scanned and the true volume before the correction (the first round) and after
it (the last). ``--no-verify`` leaves the scans out. The scans and the measurements they store go to
``out/data``, emptied at each start (not the user's data directory: the simulated phantom is not theirs). It
stops the daemon with SIGTERM (it vents), reads the recording back (each scan's volume is on its volume plot)
and writes its static report (``phantom report``) beside it: ``out/demo.html``.

The recording is written to ``out/demo.running.rrd`` and becomes ``out/demo.rrd`` only when the demo succeeds:
a failed demo leaves the last good recording alone, and says which part failed (the daemon's start, the board,
the scene) with the daemon's log. Nothing waits on a fixed wall-clock limit while the daemon makes progress;
one stage of its start that takes longer than STAGE_LIMIT_S is reported as stuck.

    python -m phantom.cli.demo [--scene host/scenes/bph_growth.toml] [--time-scale 4] [--out out/]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from phantom import PhantomError

#: How long one stage of the daemon's start (loading the model, waiting for the board) may take before the demo
#: calls it stuck (s); the whole start has no limit while its stages move on.
STAGE_LIMIT_S = 600.0
#: How long the daemon may take to stop after SIGTERM (it vents and closes the recording) before it is killed (s).
STOP_LIMIT_S = 60.0
#: How often the demo repeats what the daemon is doing while a stage lasts (s).
TELL_EVERY_S = 10.0
#: A step counts as reached when its estimate ends within this of its target (%).
STEP_TOLERANCE_PCT = 1.0
#: A verified step succeeds when the simulated phantom's TRUE volume ends within this of its target (%): the
#: verify tolerance (0.3 %) is on the scanned volume, which the scanner's own error (0.03-0.16 %) separates from
#: the true one.
VERIFIED_TRUE_TOLERANCE_PCT = 0.3
#: How long a verified volume waits for the daemon's link to the board to come back before it is set (s).
LINK_WAIT_S = 60.0
#: How long one verified volume may take (s): a round (a scan of 60 pictures, its reconstruction, the pressures
#: settling again) took 1 to 5 minutes on the two cores, idle to loaded, and 8-9 minutes at load 17-30; four
#: rounds and two retaken scans fit.
VERIFY_TIMEOUT_S = 3600.0


def demo_environment(out: Path) -> dict[str, str]:
    """The daemon's environment: a data directory of its own, ``out/data``, emptied first (the scans and the
    measurements they store): the simulated phantom's scans must not correct the user's own phantom's model,
    and each demo starts from the model's own error."""
    data = out / "data"
    shutil.rmtree(data, ignore_errors=True)
    return {**os.environ, "PHANTOM_DATA_DIR": str(data.resolve())}


def daemon_command(scene: str, out: Path) -> list[str]:
    """The daemon ``make demo`` starts: on its own simulated board, recording to ``out/demo.running.rrd``."""
    phantom = Path(sys.executable).with_name("phantom")
    return [str(phantom), "daemon", "--sim", "--scene", scene, "--socket", str(out / "demo.sock"),
            "--rerun-save", str(out / "demo.running.rrd")]


def rerun_command(recording: Path) -> str:
    """How to open a recording from here: ``rerun FILE`` when the ``rerun`` on PATH is this environment's,
    else the viewer by its path (``.venv/bin/rerun``, relative when it lies below the working folder)."""
    viewer = Path(sys.executable).with_name("rerun")
    on_path = shutil.which("rerun")
    if on_path is not None and Path(on_path).resolve() == viewer.resolve():
        return f"rerun {recording}"
    try:
        shown = viewer.relative_to(Path.cwd())
    except ValueError:
        shown = viewer
    return f"{shown} {recording}"


def wait_until_ready(socket: Path, process: subprocess.Popen[bytes], log_path: Path,
                     stage_limit_s: float = STAGE_LIMIT_S) -> float:
    """Wait for the daemon to be ready, telling what it does on stderr; the seconds it took. Raises PhantomError
    naming the cause: the daemon exited (with its log's end), or one stage of its start did not move on within
    ``stage_limit_s``."""
    import phantom
    from phantom.host.client import ConnectionLostError, StartingError

    started_s = time.monotonic()
    stage, stage_since_s, told_s = "starting the daemon process", started_s, started_s
    told: tuple[str, object] = ("", None)
    while True:
        if process.poll() is not None:
            raise PhantomError(f"the daemon exited with status {process.returncode} while {stage}; its log "
                               f"({log_path}) ends:\n{_tail(log_path)}")
        try:
            with phantom.connect(socket, ready_timeout_s=0) as daemon:
                status = daemon.status()
            if status.ready:
                return time.monotonic() - started_s
            starting = status.raw.get("starting") or {}
            now_stage = str(starting.get("stage", "waiting for the board"))
            text, detail = str(starting.get("text", now_stage)), starting.get("detail")
        except StartingError as error:
            now_stage, detail = str(error.data.get("stage", "starting")), error.data.get("detail")
            text = error.message.removeprefix("the daemon is still starting: ")
        except ConnectionLostError:
            now_stage = text = "starting the daemon process"
            detail = None
        if now_stage != stage:
            stage, stage_since_s = now_stage, time.monotonic()
        if (now_stage, detail) != told or time.monotonic() - told_s >= TELL_EVERY_S:
            print(f"  daemon: {text}", file=sys.stderr, flush=True)
            told, told_s = (now_stage, detail), time.monotonic()
        if time.monotonic() - stage_since_s > stage_limit_s:
            raise PhantomError(f"the daemon has been {stage} for over {stage_limit_s:g} s without moving on; its "
                               f"log ({log_path}) ends:\n{_tail(log_path)}")
        time.sleep(1.0)


def _tail(path: Path, lines: int = 15) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])


@contextlib.contextmanager
def sim_daemon(folder: Path, options: Sequence[str] = ()) -> Iterator[Path]:
    """A ``phantom daemon --sim`` of the benches' own (``options`` added to its command line): its socket, log
    (``daemon.log``) and data directory in ``folder``; ready when entered, stopped (:func:`stop_daemon`) on
    leaving. Yields its socket's path."""
    socket, log_path = folder / "d.sock", folder / "daemon.log"
    with open(log_path, "w") as log:
        process = subprocess.Popen([str(Path(sys.executable).with_name("phantom")), "daemon", "--sim",
                                    "--socket", str(socket), *options], stdout=log, stderr=subprocess.STDOUT,
                                   env={**os.environ, "PHANTOM_DATA_DIR": str(folder / "data")})
    try:
        wait_until_ready(socket, process, log_path)
        yield socket
    finally:
        stop_daemon(process)


def stop_daemon(process: subprocess.Popen[bytes]) -> int:
    """SIGTERM (the daemon vents and closes its recording), then a kill if it has not ended in STOP_LIMIT_S."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(STOP_LIMIT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return int(process.returncode)


def verified_steps(daemon: Any, targets_ml: list[float]) -> list[dict[str, Any]]:
    """Each volume set with ``verify="scan"``: per target, the first and the last round (the model's estimate,
    the scanned and the true volume) and the rounds taken; a target that was not verified says why."""
    from phantom.cli.common import progress_printer
    from phantom.host.client import DaemonError, FaultError

    rows: list[dict[str, Any]] = []
    for index, target_ml in enumerate(targets_ml):
        print(f"  verifying {target_ml:g} ml: reach on pressure, scan, correct ...", file=sys.stderr, flush=True)
        started_s = time.monotonic()
        try:
            wait_for_link(daemon)
            result = daemon.set_volume(target_ml, verify="scan", timeout_s=VERIFY_TIMEOUT_S,
                                       on_progress=progress_printer("    "))
        except FaultError as error:
            # a fault stops the blowers until it is cleared: the volumes after it are not tried (each was refused
            # at once, FAULT_LATCHED), and the error says which round it came in and what to do
            rows.append({"target_ml": target_ml, "rounds": list(getattr(error, "rounds", [])), "error": str(error),
                         "took_s": time.monotonic() - started_s})
            rows += [{"target_ml": later_ml, "rounds": [], "error": f"not tried: {', '.join(error.faults)} latched "
                      f"while verifying {target_ml:g} ml", "took_s": 0.0} for later_ml in targets_ml[index + 1:]]
            print(f"  {target_ml:g} ml: not verified: {error}; the rest are not tried", file=sys.stderr)
            break
        except DaemonError as error:
            rounds = list(getattr(error, "rounds", []))
            rows.append({"target_ml": target_ml, "rounds": rounds, "error": str(error),
                         "took_s": time.monotonic() - started_s})
            print(f"  {target_ml:g} ml: not verified: {error}", file=sys.stderr)
            continue
        rows.append({"target_ml": target_ml, "rounds": list(result.rounds), "error": None,
                     "took_s": time.monotonic() - started_s})
        last = result.rounds[-1] if result.rounds else {}
        true_ml = last.get("true_volume_ml")
        true = "" if true_ml is None else f", true {true_ml:.3f} ml ({100.0 * (true_ml / target_ml - 1.0):+.3f} %)"
        print(f"  {target_ml:g} ml: scanned {result.scanned_volume_ml:.3f} ml{true} after {len(result.rounds)} "
              f"round(s), {rows[-1]['took_s']:.0f} s", file=sys.stderr, flush=True)
    return rows


def wait_for_link(daemon: Any, limit_s: float = LINK_WAIT_S) -> None:
    """Wait (at most ``limit_s``) until the daemon's link to the board is online: a target set while it is down
    is refused (``link_down``), and the simulated board on a loaded machine loses it for a second now and then."""
    deadline_s = time.monotonic() + limit_s
    while daemon.status().link != "online" and time.monotonic() < deadline_s:
        time.sleep(0.5)


def format_verified(rows: list[dict[str, Any]]) -> str:
    """The verified table: per target, before the correction (round 1) and after it (the last round): the model's
    estimate, the scanned volume, the TRUE volume (the simulated phantom's) and its error; the rounds and the
    time. Under it the mean true error after."""
    def number(value: Any, digits: int = 2, signed: bool = False) -> str:
        return "-" if value is None else f"{value:{'+' if signed else ''}.{digits}f}"

    def true_pct(entry: dict[str, Any], target_ml: float) -> float | None:
        true_ml = entry.get("true_volume_ml")
        return None if true_ml is None else 100.0 * (true_ml - target_ml) / target_ml

    lines = [f"{'target':>7} | {'before: estimate':>16} {'scanned':>8} {'true':>7} {'true err %':>10} | "
             f"{'after: estimate':>15} {'band +-':>7} {'scanned':>8} {'true':>7} {'true err %':>10} | {'rounds':>6} "
             f"{'s':>5}"]
    after_errors = []
    for row in rows:
        target_ml, rounds = row["target_ml"], row["rounds"]
        first = rounds[0] if rounds else {}
        last = rounds[-1] if rounds else {}
        error = true_pct(last, target_ml)
        if error is not None and row["error"] is None:
            after_errors.append(abs(error))
        lines.append(f"{target_ml:>7.2f} | {number(first.get('estimated_volume_ml')):>16} "
                     f"{number(first.get('scanned_volume_ml'), 3):>8} {number(first.get('true_volume_ml'), 3):>7} "
                     f"{number(true_pct(first, target_ml), 3, True):>10} | "
                     f"{number(last.get('estimated_volume_ml')):>15} {number(last.get('band_ml'), 3):>7} "
                     f"{number(last.get('scanned_volume_ml'), 3):>8} "
                     f"{number(last.get('true_volume_ml'), 3):>7} {number(error, 3, True):>10} | {len(rounds):>6} "
                     f"{row['took_s']:>5.0f}" + ("" if row["error"] is None else f"  NOT VERIFIED: {row['error']}"))
    if after_errors:
        lines.append(f"after the scans: mean |true error| {sum(after_errors) / len(after_errors):.3f} % (largest "
                     f"{max(after_errors):.3f} %), {sum(len(row['rounds']) for row in rows) / len(rows):.1f} rounds "
                     "on average; the estimate is the model's at the pressures held (corrected by the scans stored "
                     "before the round's own), the band its correction's 95 % half-width there (ml; - without one), "
                     "the scanned volume what the scanner measured, the true one the simulated phantom's")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import phantom
    from phantom.cli.client import format_steps, scene_progress
    from phantom.cli.report import MESH_SKIPPED, write_report
    from phantom.host.client import SceneRun
    from phantom.host.recording import read_rrd
    from phantom.host.scenes import example_scene_path

    parser = argparse.ArgumentParser(prog="python -m phantom.cli.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=str(example_scene_path("bph_growth")))
    parser.add_argument("--time-scale", type=float, default=4.0, help="play the timeline this much faster")
    parser.add_argument("--out", default="out", help="folder for the recording, socket and log")
    parser.add_argument("--no-verify", dest="verify", action="store_false",
                        help="leave out the scans that verify each step's volume")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    running, recording = out / "demo.running.rrd", out / "demo.rrd"
    command = daemon_command(args.scene, out)
    print("$ " + " ".join(command), file=sys.stderr)
    log_path = out / "daemon.log"
    demo_started_s = time.monotonic()
    with open(log_path, "w") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=demo_environment(out))
    succeeded = False
    try:
        ready_s = wait_until_ready(out / "demo.sock", process, log_path)
        with phantom.connect(out / "demo.sock") as daemon:
            status = daemon.status()
            building = f", the {status.fidelity_pending} level building" if status.fidelity_pending else ""
            print(f"daemon ready in {ready_s:.1f} s (the model on {status.fidelity}{building}; the board online)",
                  file=sys.stderr)
            run = daemon.run_scene(Path(args.scene), time_scale=args.time_scale)
            assert isinstance(run, SceneRun)  # without wait
            print(f"running {run.name}: {run.steps} steps, {run.end_s:g} s of timeline in about "
                  f"{run.wall_duration_s:.0f} s", file=sys.stderr)
            scene = daemon.follow_scene(run, on_progress=scene_progress(args.time_scale))
            steps = [dataclasses.asdict(step) for step in scene.steps]
            print(f"BPH growth on the simulated board (firmware in simavr), timeline x{args.time_scale:g}, without "
                  "verify (the model's error, uncorrected); 'time to 1 %' counts from the step's start (ramp "
                  "included), in wall seconds:", flush=True)
            print(format_steps(steps), flush=True)
            verified: list[dict[str, Any]] = []
            if args.verify:
                targets = list(dict.fromkeys(step["target_volume_ml"] for step in steps
                                             if step["target_volume_ml"] is not None))
                verified = verified_steps(daemon, targets)
            faults = daemon.status().faults
        code = stop_daemon(process)
        if verified:
            print("\nthe same volumes verified by the scanner (set_volume(v, verify=\"scan\")), before and after the "
                  "correction:")
            print(format_verified(verified))
        entities = read_rrd(running, skip=MESH_SKIPPED)  # every row's time, not the surfaces: 1 s, not 5
        logged = sum(len(columns.get("time", [])) for columns in entities.values())
        missed = [step for step in steps if step["error_pct"] is None or abs(step["error_pct"]) > STEP_TOLERANCE_PCT]
        unverified = [row for row in verified if row["error"] is not None or not row["rounds"]
                      or row["rounds"][-1].get("true_volume_ml") is None
                      or abs(row["rounds"][-1]["true_volume_ml"] - row["target_ml"]) > (
                          VERIFIED_TRUE_TOLERANCE_PCT / 100.0 * row["target_ml"])]
        succeeded = not missed and not unverified and not faults and code == 0
        if succeeded:
            os.replace(running, recording)
        shown = recording if succeeded else running
        report = write_report(shown, shown.with_suffix(".html"))
        print(f"\nrecording {shown}: {len(entities)} entities, {logged} logged rows; faults: "
              f"{', '.join(faults) or 'none'}; daemon exit status {code}\n"
              f"report {report}: plots, steps{', the verified scans' if verified else ''} and pictures of the "
              "gland in one HTML file (any browser, mailable)\n"
              f"open the recording with `{rerun_command(shown)}` on a display; without one (over SSH) "
              f"`{rerun_command(shown)} --serve-web --bind 127.0.0.1` serves it to a browser (README.md, "
              "\"Viewing a recording\")\n"
              f"the demo took {(time.monotonic() - demo_started_s) / 60.0:.1f} min (the daemon's start, the scene"
              f"{', the verified volumes' if verified else ''})")
        if not succeeded:
            why = [f"step {step['index']} missed its target by {step['error_pct']}" for step in missed]
            why += [f"{row['target_ml']:g} ml did not end within {VERIFIED_TRUE_TOLERANCE_PCT:g} % true"
                    for row in unverified]
            why += [f"faults latched: {', '.join(faults)}"] if faults else []
            why += [f"the daemon exited with status {code}"] if code else []
            print(f"make demo: failed: {'; '.join(why)}; the last good recording ({recording}) is kept; the daemon's "
                  f"log is {log_path}", file=sys.stderr)
        return 0 if succeeded else 1
    finally:
        stop_daemon(process)
        if not succeeded:
            print(f"daemon log ({log_path}), its end:\n{_tail(log_path, 30)}", file=sys.stderr)


if __name__ == "__main__":
    try:
        sys.exit(main())
    except PhantomError as error:
        print(f"make demo: error: {error}", file=sys.stderr)
        sys.exit(2)
