"""A verified target's scan, given to ``phantom daemon`` (a ``phantom.host.daemon.VerifyScanner``): the plan of
the scan the daemon takes with its own ``scan`` method, and the capture's reconstruction to a gland volume (run
by ``phantom daemon`` in the scan worker's process, ``phantom.cli.scan_worker``, as the capture is).

The plan is sized by measurement (bench/README.md, "Scanner" and "A verified target"): the fastest orbit stops
and elevations whose volume error fits in what the verify loop leaves the scanner of the target's tolerance
(:func:`plan_for_tolerance`), of 640x480 pictures (larger ones do not help).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from phantom import PhantomError

if TYPE_CHECKING:
    from phantom.scan.camera import Rig
    from phantom.scan.capture import CaptureFolder

#: The scanner's error model: the largest |volume error| (%, of rest's and the 45 ml target's truth) of 640x480
#: pictures carved with the virtual rig's true poses (as the daemon's verify scan), by plan: (orbit stops per
#: elevation over a whole turn, the elevations (deg)). ``bench/scan_accuracy.py --true-poses --scales 0.5 --views
#: 15,20,30 --elevations 0+30,0+15+30,0+30+45,15+45,0+45`` (bench/README.md "Scanner"; 10 stops at 0 and 30 deg
#: from the run before): at 0 and 30 deg, 10 +0.65 / +1.41 %, 15 +0.29 / +0.67 %, 20 +0.03 / +0.43 %, 30 -0.13 /
#: +0.16 %; at 15 and 45 deg, 15 +0.15 / +0.32 %, 20 -0.01 / +0.17 %, 30 -0.17 / -0.03 %; at 0 and 45 deg, 15 +0.17
#: / +0.35 %, 20 -0.02 / +0.19 %, 30 -0.17 / -0.02 %. The steeper pass sees the target's folds the 30 deg one
#: misses. Not here: three elevations (their third pass turns the orbit back a whole turn, 55-65 s a scan), a half
#: turn (+0.90 to +1.41 % at the 45 ml target: the far side's silhouettes are not the near side's), larger
#: pictures (1280x960 at 30 stops, 0 and 30 deg: +0.06 / +0.23 %), more stops (60: -0.36 / -0.14 %: each view's
#: edge error trims the intersection).
SCAN_ERROR_PCT_BY_PLAN: dict[tuple[int, tuple[float, ...]], float] = {
    (10, (0.0, 30.0)): 1.412, (15, (0.0, 30.0)): 0.666, (20, (0.0, 30.0)): 0.433, (30, (0.0, 30.0)): 0.157,
    (15, (15.0, 45.0)): 0.317, (20, (15.0, 45.0)): 0.167, (30, (15.0, 45.0)): 0.170,
    (15, (0.0, 45.0)): 0.349, (20, (0.0, 45.0)): 0.185, (30, (0.0, 45.0)): 0.169,
}
#: The most orbit stops the error model has measured: a real rig's plan (``phantom daemon --camera``) starts from
#: them, :meth:`VerifyScan.plan_for` takes fewer where its tolerance allows.
MOST_VIEWS = max(views for views, _ in SCAN_ERROR_PCT_BY_PLAN)
#: The verify plan's wait after each move (s): the simulated rig is still when its move ends.
VERIFY_SETTLE_S = 0.05


def scan_s(views: int, elevations_deg: tuple[float, ...], settle_s: float = VERIFY_SETTLE_S) -> float:
    """A verify scan's time on the board (s): its moves on the scanner's axes' profile
    (:data:`phantom.protocol.motion.SCANNER_AXES`, the move back to its first stop included) and the settle after
    each picture's."""
    from phantom.protocol.motion import SCANNER_AXES
    from phantom.scan.capture import Plan

    return Plan(views, elevations_deg, settle_s=settle_s).board_s(SCANNER_AXES)


def plan_for_tolerance(tolerance_pct: float, elevations_deg: tuple[float, ...] | None = None
                       ) -> tuple[int, tuple[float, ...]] | None:
    """The fastest plan (orbit stops per elevation, elevations; :func:`scan_s`) whose scanner error
    (:data:`SCAN_ERROR_PCT_BY_PLAN`) fits in what the verify loop leaves the scanner of ``tolerance_pct`` (%): the
    tolerance less the share a round aims at (:data:`phantom.host.verify.VERIFY_AIM_SHARE`), so that a scan
    stopped within the aim is within the tolerance in true volume. 0.3 % (0.2 % left): 20 stops at 15 and 45 deg
    (0.17 %, 30.6 s; 30 at 0 and 30 deg 34.4 s); 0.5-1 %: 15 at 15 and 45 deg; 2.5 %: 10 at 0 and 30 deg. A
    tolerance tighter than any plan meets takes the most accurate. ``elevations_deg`` keeps to plans at those (a
    calibrated rig's); None when none is measured there. The plan is sized for the hull's error left in (this
    table), so a round whose scan could not have it taken off (``phantom.scan.hull_bias``: the model's surface did
    not fit) still stops within the tolerance in true volume; one that had (within 0.083 %, bench/README.md) stops
    within 0.6 of it (``phantom.host.verify.aim_share``)."""
    from phantom.host.verify import VERIFY_AIM_SHARE

    left_pct = tolerance_pct * (1.0 - VERIFY_AIM_SHARE)
    measured = {plan: error_pct for plan, error_pct in SCAN_ERROR_PCT_BY_PLAN.items()
                if elevations_deg is None or plan[1] == tuple(float(e) for e in elevations_deg)}
    if not measured:
        return None
    fitting = [plan for plan, error_pct in measured.items() if error_pct <= left_pct]
    if not fitting:
        return min(measured, key=measured.__getitem__)
    return min(fitting, key=lambda plan: (scan_s(*plan), measured[plan]))


_VIEWS, _ELEVATIONS = plan_for_tolerance(0.3) or (MOST_VIEWS, (0.0, 30.0))
#: The verify scan's plan (``scan`` params) for the default tolerance (0.3 %): :func:`plan_for_tolerance`'s (20
#: orbit stops at 15 and 45 deg of 640x480 pictures, -0.01 % at rest and +0.17 % at the 45 ml target).
VERIFY_PLAN: dict[str, Any] = {"views": _VIEWS, "elevations_deg": list(_ELEVATIONS), "scale": 0.5,
                               "settle_s": VERIFY_SETTLE_S}


class VerifyScan:
    """The verify scan's ``plan`` and :meth:`volume` (see the module docstring). A capture without a rig
    calibration taken with the virtual camera is posed by the virtual rig's true geometry (the simulated board's
    scanner is the virtual rig), its surface (``surface_mm``) in the model's frame; one taken with a real camera
    needs the rig's (``rig`` in the plan), its surface in the rig's frame (``surface_mm`` None: the recording
    shows no scan surface it cannot place over the model's)."""

    def __init__(self, plan: dict[str, Any] | None = None):
        self.plan = dict(VERIFY_PLAN if plan is None else plan)

    def plan_for(self, tolerance_pct: float) -> dict[str, Any]:
        """The plan of a verified target's scan at ``tolerance_pct`` (%): this plan with the orbit stops and
        elevations the tolerance needs (:func:`plan_for_tolerance`); a calibrated rig's plan keeps its own
        elevations and never takes more stops than its own."""
        rig = self.plan.get("rig")
        chosen = plan_for_tolerance(tolerance_pct, tuple(self.plan["elevations_deg"]) if rig else None)
        if chosen is None:
            return dict(self.plan)
        views, elevations_deg = chosen
        if rig:
            views = min(int(self.plan["views"]), views)
        return {**self.plan, "views": views, "elevations_deg": list(elevations_deg)}

    def rig_for(self, capture: CaptureFolder) -> Rig:
        """The rig posing ``capture``'s pictures: the calibration kept with it, else (a virtual camera's) the
        virtual rig's true geometry at this plan's scale and elevations; PhantomError for a real camera's without."""
        from phantom.scan.camera import virtual_rig

        rig = capture.rig()
        if rig is not None:
            return rig
        if capture.camera.get("kind") != "virtual":
            raise PhantomError(f"{capture.path} keeps no rig calibration: a real camera's scan needs the rig's (give "
                               "the verify plan a rig, from phantom scan calibrate)")
        return virtual_rig(float(self.plan.get("scale", 1.0)), tuple(
            float(e) for e in capture.plan.get("elevations_deg", self.plan.get("elevations_deg", [0.0, 30.0]))))

    def expect_surface(self, model_surface_mm: tuple[Any, Any] | None) -> None:
        """The model's outer surface (positions mm, triangles) at the next verify scan's pressures, given before its
        capture (None: none): the capture renders its silhouettes while the rig moves, for :meth:`volume`'s hull
        error (``phantom.scan.hull_bias.ModelSilhouettes``)."""
        from phantom.scan.hull_bias import MODEL_SILHOUETTES

        MODEL_SILHOUETTES.expect(model_surface_mm)

    def volume(self, folder: str, model_surface_mm: tuple[Any, Any] | None = None) -> dict[str, Any]:
        """The capture in ``folder`` reconstructed: ``volume_ml`` (with the visual hull's error on the model's
        surface at the scan's pressures, ``model_surface_mm`` (positions mm, triangles), taken off:
        ``phantom.scan.hull_bias``), ``scanned_raw_ml`` (the hull's own volume), ``hull_error_pct`` (None: no
        surface given, or none could be placed on the scan, ``hull_note`` says why), ``mesh``, ``views``,
        ``stage_s``, ``surface_mm``, ``keyed_while_taken`` (the pictures whose silhouettes were keyed while the
        capture ran) and ``hull_rendered_while_taken`` (those whose model silhouette for the hull's error was
        rendered then). PhantomError for a scan that cannot be read."""
        from phantom.scan.capture import CaptureFolder
        from phantom.scan.hull_bias import MODEL_SILHOUETTES, measured_hull_bias
        from phantom.scan.keying import KEYED
        from phantom.scan.reconstruct import reconstruct, write_mesh

        capture = CaptureFolder.open(folder)
        rig = self.rig_for(capture)
        # the virtual rig's world is the simulated phantom's frame, the model's; a calibrated rig's is its own
        in_model_frame = not capture.rig_file
        # the silhouettes keyed while the capture ran in this process (key_silhouettes), the rest keyed here
        keyed = KEYED.take(capture)
        result = reconstruct(capture, rig, keyed=keyed)
        if result.touching_edge:
            raise PhantomError(f"the phantom touches the picture's edge in {result.touching_edge} of {result.views} "
                               "pictures: it is not wholly in view, its volume would be wrong")
        mesh = write_mesh(result.mesh, capture.path / "scan.ply")
        surface = (result.mesh.vertices_mm, result.mesh.triangles) if in_model_frame else None
        volume_ml, hull_error_pct, note, rendered = result.volume_ml, None, "no model surface given", 0
        if model_surface_mm is not None:
            hull = measured_hull_bias(capture, rig, result, model_surface_mm,
                                      MODEL_SILHOUETTES.take(capture, model_surface_mm))
            if isinstance(hull, str):
                note = hull
            else:
                volume_ml, hull_error_pct, note = hull.corrected_ml(result.volume_ml), hull.error_pct, ""
                rendered = hull.rendered_while_taken
                result.stage_s["hull_bias"] = hull.seconds
        return {"volume_ml": volume_ml, "scanned_raw_ml": result.volume_ml, "hull_error_pct": hull_error_pct,
                "hull_note": note, "mesh": str(mesh), "views": result.views, "stage_s": result.stage_s,
                "surface_mm": surface, "keyed_while_taken": len(keyed), "hull_rendered_while_taken": rendered}
