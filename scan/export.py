"""A capture folder with its known camera poses for the photogrammetry tools, and their mesh back.

Both exports give every picture its pose from the rig's calibration (``Rig.pose`` at the frame's angles), so the
tools need not find the cameras themselves and their result comes out in the rig's frame, in millimetres:

- COLMAP (text model: ``cameras.txt``, ``images.txt``, an empty ``points3D.txt``): one OPENCV camera (fx, fy, cx,
  cy, k1, k2, p1, p2; FULL_OPENCV when k3 is not 0), in COLMAP's pixel convention (the first pixel's centre at
  0.5, 0.5); each image's world-to-camera rotation as a quaternion (w, x, y, z) and its translation. Use it
  with the pictures of the capture folder::

      colmap feature_extractor --database_path db.db --image_path CAPTURE/images
      colmap exhaustive_matcher --database_path db.db
      colmap point_triangulator --database_path db.db --image_path CAPTURE/images \\
          --input_path EXPORT/colmap --output_path sparse
      colmap image_undistorter ... ; colmap patch_match_stereo ... ; colmap stereo_fusion ... ;
      colmap poisson_mesher ...                      (then phantom scan import meshed.ply)

  (the feature extractor must give the images the camera of cameras.txt: ``--ImageReader.single_camera 1``
  after importing it, or match the ids; COLMAP's documentation, "Reconstruct sparse/dense model from known
  camera poses").
- Meshroom (AliceVision's SfMData JSON, ``cameras.sfm``): one intrinsic of type ``brown`` (k1, k2, k3, t1, t2 =
  p1, p2), its focal length in mm on a nominal 1 mm-per-1000-px sensor and its principal point as an offset from
  the picture's centre (SfMData 1.2.1 and later), locked; each view's pose (rotation world to camera, stored
  column by column as AliceVision writes its matrices; the camera's centre), locked. Load it in Meshroom's
  CameraInit, or start the pipeline after StructureFromMotion with it.

Neither tool runs on the machine the project is tested on: the files follow the tools' documented formats, and
the COLMAP text model is read back in the tests.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from phantom.model.arrays import FloatArray
from phantom.model.mesh.surface import TriangleMesh
from phantom.scan.camera import Rig
from phantom.scan.capture import CaptureError, CaptureFolder
from phantom.scan.compare import clean_scan, read_scan

#: Pixels per millimetre of the nominal sensor the Meshroom export gives its focal length on.
NOMINAL_PX_PER_MM = 1000.0


def quaternion(rotation: FloatArray) -> FloatArray:
    """The unit quaternion (w, x, y, z), w >= 0, of a rotation matrix."""
    m = rotation
    trace = float(np.trace(m))
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        k = int(np.argmax(np.diag(m)))
        i, j = (k + 1) % 3, (k + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[k, k] - m[i, i] - m[j, j])
        q = np.zeros(4)
        q[0] = (m[j, i] - m[i, j]) / s
        q[1 + k] = 0.25 * s
        q[1 + i] = (m[i, k] + m[k, i]) / s
        q[1 + j] = (m[j, k] + m[k, j]) / s
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _rig(folder: CaptureFolder, rig: Rig | None) -> Rig:
    rig = rig if rig is not None else folder.rig()
    if rig is None:
        raise CaptureError(f"{folder.path} keeps no rig calibration: give the rig's (--rig RIG.json)")
    return rig


def export_colmap(folder: CaptureFolder, out: str | Path, rig: Rig | None = None) -> Path:
    """COLMAP's text model of the capture's cameras (see the module docstring) in ``out``; returns ``out``."""
    rig = _rig(folder, rig)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    camera = rig.camera
    k1, k2, p1, p2, k3 = camera.distortion
    head = [camera.fx, camera.fy, camera.cx + 0.5, camera.cy + 0.5]
    if k3 == 0.0:
        model, parameters = "OPENCV", head + [k1, k2, p1, p2]
    else:
        model, parameters = "FULL_OPENCV", head + [k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    (out / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 {model} {camera.width} {camera.height} {' '.join(repr(float(p)) for p in parameters)}\n")
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for number, frame in enumerate(folder.frames, start=1):
        pose = rig.pose(frame.orbit_deg, frame.elevation_deg)
        values = [*quaternion(pose.rotation), *pose.translation_mm]
        lines += [f"{number} {' '.join(repr(float(v)) for v in values)} 1 {Path(frame.image).name}", ""]
    (out / "images.txt").write_text("\n".join(lines) + "\n")
    (out / "points3D.txt").write_text("# 3D point list (empty: COLMAP's point_triangulator fills it)\n")
    return out


def export_meshroom(folder: CaptureFolder, out: str | Path, rig: Rig | None = None) -> Path:
    """Meshroom's ``cameras.sfm`` for the capture (see the module docstring); returns its path."""
    rig = _rig(folder, rig)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    camera = rig.camera
    k1, k2, p1, p2, k3 = camera.distortion
    sensor_width_mm = camera.width / NOMINAL_PX_PER_MM
    intrinsic = {
        "intrinsicId": "1", "width": str(camera.width), "height": str(camera.height),
        "sensorWidth": repr(sensor_width_mm), "sensorHeight": repr(camera.height / NOMINAL_PX_PER_MM),
        "serialNumber": "phantom-scanner", "type": "brown", "initializationMode": "calibrated",
        "initialFocalLength": repr(camera.fx / NOMINAL_PX_PER_MM), "focalLength": repr(camera.fx / NOMINAL_PX_PER_MM),
        "pixelRatio": repr(camera.fy / camera.fx), "pixelRatioLocked": "true",
        "principalPoint": [repr(camera.cx - (camera.width - 1) / 2), repr(camera.cy - (camera.height - 1) / 2)],
        "distortionInitializationMode": "calibrated",
        "distortionParams": [repr(float(value)) for value in (k1, k2, k3, p1, p2)], "locked": "true"}
    views, poses = [], []
    for number, frame in enumerate(folder.frames, start=1):
        pose = rig.pose(frame.orbit_deg, frame.elevation_deg)
        views.append({"viewId": str(number), "poseId": str(number), "intrinsicId": "1",
                      "path": str((folder.path / frame.image).resolve()), "width": str(camera.width),
                      "height": str(camera.height), "metadata": {}})
        poses.append({"poseId": str(number), "pose": {"transform": {
            "rotation": [repr(float(v)) for v in pose.rotation.ravel(order="F")],
            "center": [repr(float(v)) for v in pose.centre_mm]}, "locked": "1"}})
    document = {"version": ["1", "2", "1"], "featuresFolders": [], "matchesFolders": [], "views": views,
                "intrinsics": [intrinsic], "poses": poses}
    out.write_text(json.dumps(document, indent=1) + "\n")
    return out


def import_mesh(path: str | Path, units: str = "mm") -> TriangleMesh:
    """A photogrammetry tool's mesh (OBJ, PLY, STL): read, its largest piece kept, its holes closed, outward."""
    closed, _, _ = clean_scan(read_scan(path, units))
    return closed
