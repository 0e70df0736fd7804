"""A verified target's scan, given to ``phantom daemon`` (a ``phantom.host.daemon.VerifyScanner``): the plan of
the scan the daemon takes with its own ``scan`` method, and the capture's reconstruction to a gland volume (run
by ``phantom daemon`` in the scan worker's process, ``phantom.cli.scan_worker``, as the capture is).

The plan was chosen by measurement (bench/README.md, "Scanner" and "A verified target"): the fewest pictures
and the smallest picture whose volume error stays well under the verified targets' 0.3 %.
"""

from __future__ import annotations

from typing import Any

from phantom import PhantomError

#: The verify scan's plan (``scan`` params): 30 orbit stops at two elevations of 640x480 pictures, +0.16 %
#: on the 43 ml truth (bench/README.md's table: "60 views"), a few seconds to capture and reconstruct.
VERIFY_PLAN: dict[str, Any] = {"views": 30, "elevations_deg": [0.0, 30.0], "scale": 0.5, "settle_s": 0.05}


class VerifyScan:
    """The verify scan's ``plan`` and :meth:`volume` (see the module docstring). A capture without a rig
    calibration taken with the virtual camera is posed by the virtual rig's true geometry (the simulated board's
    scanner is the virtual rig), its surface (``surface_mm``) in the model's frame; one taken with a real camera
    needs the rig's (``rig`` in the plan), its surface in the rig's frame (``surface_mm`` None: the recording
    shows no scan surface it cannot place over the model's)."""

    def __init__(self, plan: dict[str, Any] | None = None):
        self.plan = dict(VERIFY_PLAN if plan is None else plan)

    def volume(self, folder: str) -> dict[str, Any]:
        from phantom.scan.camera import virtual_rig
        from phantom.scan.capture import CaptureFolder
        from phantom.scan.reconstruct import reconstruct, write_mesh

        capture = CaptureFolder.open(folder)
        rig = capture.rig()
        # the virtual rig's world is the simulated phantom's frame, the model's; a calibrated rig's is its own
        in_model_frame = rig is None
        if rig is None:
            if capture.camera.get("kind") != "virtual":
                raise PhantomError(f"{folder} keeps no rig calibration: a real camera's scan needs the rig's (give "
                                   "the verify plan a rig, from phantom scan calibrate)")
            rig = virtual_rig(float(self.plan.get("scale", 1.0)),
                              tuple(float(e) for e in self.plan.get("elevations_deg", [0.0, 30.0])))
        result = reconstruct(capture, rig)
        if result.touching_edge:
            raise PhantomError(f"the phantom touches the picture's edge in {result.touching_edge} of {result.views} "
                               "pictures: it is not wholly in view, its volume would be wrong")
        mesh = write_mesh(result.mesh, capture.path / "scan.ply")
        surface = (result.mesh.vertices_mm, result.mesh.triangles) if in_model_frame else None
        return {"volume_ml": result.volume_ml, "mesh": str(mesh), "views": result.views,
                "stage_s": result.stage_s, "surface_mm": surface}
