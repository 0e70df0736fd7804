"""A verified target's scan, given to ``phantom daemon`` (a ``phantom.host.daemon.VerifyScanner``): the plan of
the scan the daemon takes with its own ``scan`` method, and the capture's reconstruction to a gland volume (run
by ``phantom daemon`` in the scan worker's process, ``phantom.cli.scan_worker``, as the capture is).

The plan is sized by measurement (bench/README.md, "Scanner" and "A verified target"): the fewest orbit stops
whose volume error fits in what the verify loop leaves the scanner of the target's tolerance (:func:`views_for`),
of 640x480 pictures (larger ones do not help).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from phantom import PhantomError

if TYPE_CHECKING:
    from phantom.scan.camera import Rig
    from phantom.scan.capture import CaptureFolder

#: The verify scan's plan (``scan`` params) for the default tolerance (0.3 %): 30 orbit stops at two elevations of
#: 640x480 pictures, -0.13 % at rest and +0.16 % at the 45 ml target (:data:`SCAN_ERROR_PCT_BY_VIEWS`).
VERIFY_PLAN: dict[str, Any] = {"views": 30, "elevations_deg": [0.0, 30.0], "scale": 0.5, "settle_s": 0.05}
#: The scanner's error model: the largest volume error (%, of rest and the 45 ml target's truth) of the verify
#: plan's 640x480 pictures by orbit stops per elevation (two elevations, the virtual rig's true poses, as the
#: daemon's verify scan; ``bench/scan_accuracy.py --true-poses --scales 0.5 --views 10,15,20,30``, bench/README.md
#: "Scanner"): 10 +0.65 / +1.41 %, 15 +0.29 / +0.67 %, 20 +0.03 / +0.43 %, 30 -0.13 / +0.16 %. A picture is a
#: stop of the orbit and a render (1-1.3 s at load 5-12), so the scan's time goes with the stops. Larger pictures
#: do not help (1280x960 at 30 stops: +0.06 / +0.23 %), nor more stops (60: -0.30 / -0.10 %: each view's edge
#: error trims the intersection).
SCAN_ERROR_PCT_BY_VIEWS = {10: 1.412, 15: 0.667, 20: 0.434, 30: 0.159}


def views_for(tolerance_pct: float) -> int:
    """The fewest orbit stops per elevation whose scanner error (:data:`SCAN_ERROR_PCT_BY_VIEWS`) fits in what the
    verify loop leaves the scanner of ``tolerance_pct`` (%): the tolerance less the share a round aims at
    (:data:`phantom.host.verify.VERIFY_AIM_SHARE`), so that a scan stopped within the aim is within the tolerance
    in true volume. 0.3 %: 30 (0.2 % left); 0.7-1 %: 20; 1.1 %: 15; 2.5 %: 10. A tolerance tighter than any plan
    meets takes the best measured (30)."""
    from phantom.host.verify import VERIFY_AIM_SHARE

    left_pct = tolerance_pct * (1.0 - VERIFY_AIM_SHARE)
    fitting = [views for views, error_pct in SCAN_ERROR_PCT_BY_VIEWS.items() if error_pct <= left_pct]
    return min(fitting) if fitting else min(SCAN_ERROR_PCT_BY_VIEWS, key=SCAN_ERROR_PCT_BY_VIEWS.__getitem__)


class VerifyScan:
    """The verify scan's ``plan`` and :meth:`volume` (see the module docstring). A capture without a rig
    calibration taken with the virtual camera is posed by the virtual rig's true geometry (the simulated board's
    scanner is the virtual rig), its surface (``surface_mm``) in the model's frame; one taken with a real camera
    needs the rig's (``rig`` in the plan), its surface in the rig's frame (``surface_mm`` None: the recording
    shows no scan surface it cannot place over the model's)."""

    def __init__(self, plan: dict[str, Any] | None = None):
        self.plan = dict(VERIFY_PLAN if plan is None else plan)

    def plan_for(self, tolerance_pct: float) -> dict[str, Any]:
        """The plan of a verified target's scan at ``tolerance_pct`` (%): this plan with the orbit stops the
        tolerance needs (:func:`views_for`), never more than its own."""
        return {**self.plan, "views": min(int(self.plan.get("views", VERIFY_PLAN["views"])),
                                          views_for(tolerance_pct))}

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
        return virtual_rig(float(self.plan.get("scale", 1.0)),
                           tuple(float(e) for e in self.plan.get("elevations_deg", [0.0, 30.0])))

    def volume(self, folder: str) -> dict[str, Any]:
        from phantom.scan.capture import CaptureFolder
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
        return {"volume_ml": result.volume_ml, "mesh": str(mesh), "views": result.views,
                "stage_s": result.stage_s, "surface_mm": surface, "keyed_while_taken": len(keyed)}
