"""``phantom scan validate --sim``: the paper's validation on the simulated rig, joined here (the measurement and
the report are ``phantom.scan.validation``'s): the rig calibrated from rendered pictures of the target, a daemon
on the simulated board with the scene, and at each target volume the target set, a capture through the daemon
with the virtual camera (the simulated rig's true angles and the truth's surface) and its measurement."""

from __future__ import annotations

import time
from typing import Any

from phantom import PhantomError


def run_validate(args: Any) -> int:
    """Handler of ``phantom scan validate --sim``."""
    import json
    import shlex
    import signal
    import subprocess
    import sys
    from pathlib import Path

    import numpy as np

    import phantom
    from phantom.cli.common import capture_through_daemon, frame_progress, parse_numbers, plan_of
    from phantom.cli.demo import wait_until_ready
    from phantom.hil.truth_shape import TruthShape
    from phantom.host.client import DaemonClient
    from phantom.host.scan_client import DaemonOrbit
    from phantom.host.scenes import example_scene_path, load_timeline_scene
    from phantom.model import PhantomModel
    from phantom.model.mesh.surface import TriangleMesh
    from phantom.scan.calibrate import calibrate_rig, target_views
    from phantom.scan.camera import Rig, virtual_pose_at, virtual_rig
    from phantom.scan.capture import CaptureFolder
    from phantom.scan.reconstruct import VOXEL_MM
    from phantom.scan.validation import (
        TargetResult,
        frame_map,
        measure_target,
        scene_targets_ml,
        write_recording,
        write_report,
    )
    from phantom.scan.virtual import VirtualCamera, render_target_captures, truth_scene

    if not args.sim:
        raise PhantomError("validate runs on the simulated rig: give --sim (with a real board, scan with `phantom "
                           "scan capture`, `reconstruct` and `compare-scan`)")
    plan = plan_of(args, args.settle_s)
    elevations = plan.elevations_deg
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = args.scene or str(example_scene_path("bph_growth"))
    targets = parse_numbers(args.targets, "--targets") if args.targets else scene_targets_ml(scene)
    true_rig = virtual_rig(args.scale, elevations)
    started = time.monotonic()

    def say(text: str) -> None:
        print(f"[{time.monotonic() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    # the rig's calibration, from rendered pictures of the target, as a real rig's from photographs of it
    if args.rig:
        rig = Rig.load(args.rig)
    else:
        say("calibrating the virtual rig from pictures of the ChArUco target ...")
        folders = render_target_captures(true_rig, out / "target", args.target_views)
        rig = calibrate_rig(target_views(folders), true_rig.camera.width, true_rig.camera.height)
        rig.save(out / "rig.json")
        say(f"rig calibrated: reprojection RMS {rig.calibration['rms_px']:.3f} px")
    to_truth = frame_map(rig, true_rig, elevations[0])
    truth = TruthShape()
    controller = PhantomModel.from_scene(load_timeline_scene(scene))
    socket = out / "daemon.sock"
    command = [str(Path(sys.executable).with_name("phantom")), "daemon", "--sim", "--scene", scene, "--socket",
               str(socket), "--sim-speed", f"{args.sim_speed:g}"]
    say("$ " + shlex.join(command))
    log = open(out / "daemon.log", "w")
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    results: list[TargetResult] = []
    captures: list[Path] = []
    models: list[tuple[TriangleMesh, np.ndarray]] = []
    try:
        wait_until_ready(socket, process, out / "daemon.log", stage_limit_s=args.daemon_timeout_s)
        say("daemon ready")
        with DaemonClient(socket) as client, phantom.connect(socket) as daemon:
            for target_ml in targets:
                # reached and settled by the control core's rule (the client's wait), as every client waits
                reached = daemon.set_volume(target_ml, wait=True)
                answer: dict[str, Any] = {"pressures_kpa": list(reached.pressures_kpa),
                                          "predicted_volume_ml": reached.predicted_volume_ml,
                                          "iterations": reached.iterations}
                measured = list(reached.measured_pressures_kpa or reached.pressures_kpa)
                say(f"{target_ml:g} ml: inverse {', '.join(f'{p:.3f}' for p in answer['pressures_kpa'])} kPa, "
                    f"held at {', '.join(f'{p:.3f}' for p in measured)} kPa; capturing {len(plan.stops())} pictures")
                folder = CaptureFolder.create(out / f"capture_{target_ml:g}ml", {}, plan.to_json(), {
                    "scene": scene, "target_ml": target_ml, "inverse": answer}, rig)
                camera = VirtualCamera(true_rig, truth_scene(DaemonOrbit(client).simulated, truth), args.seed,
                                       pose_at=virtual_pose_at(args.scale))
                folder.camera = camera.describe()
                capture_through_daemon(client, camera, plan, folder, frame_progress(f"  {target_ml:g} ml"))
                last, model = measure_target(target_ml, answer, folder, rig, to_truth, controller, truth, out,
                                             args.voxel_mm or VOXEL_MM)
                results.append(last)
                captures.append(folder.path)
                models.append(model)
                say(f"{target_ml:g} ml: scan {last.scan_ml:.2f} ml ({last.scan_vs_target_pct:+.2f} % of the target, "
                    f"{last.scan_vs_model_pct:+.2f} % of the model, {last.scan_vs_truth_pct:+.2f} % of the truth); "
                    f"mean distance to the model {last.model_distance_mm['mean']:.3f} mm, to the truth "
                    f"{last.truth_distance_mm['mean']:.3f} mm")
            client.call("vent")
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            process.wait(30)
        log.close()
    meta = {"command": shlex.join(["phantom", *args.argv]), "scene": scene,
            "truth": truth.description, "rig": rig.calibration, "elapsed_s": time.monotonic() - started}
    report = write_report(results, out, meta)
    recording = write_recording(results, rig, captures, models, out / "validation.rrd") if args.rerun else None
    if args.json:
        print(json.dumps({"report": str(report), "recording": None if recording is None else str(recording),
                          "targets": [r.to_json() for r in results]}))
    else:
        print(report.read_text())
        print(f"report {report}" + (f", recording {recording}" if recording else ""))
    return 0
