"""The scanner's own error on pictures a real rig takes: the gland hung by its tubes, glossy, in front of an uneven
cloth, with vignetting and noise, against the number of views and the picture size, with and without the tubes.

The pictures come from a renderer that is not the scanner's (tests/reference/hung_phantom.py: a ray caster of
analytic shapes through OpenCV's undistortion; a flat-topped ellipsoid of 26.28 ml, three tubes of 4.4 mm up
out of the pictures), at the virtual rig's true geometry (60 stops a turn at 0 and 30 deg), and also from the
scanner's own virtual camera in its real look (``render.REAL_LOOK``) of the model's gland at rest (26.43 ml).
Reconstructions are carved from every k-th stop (the fewer-view rows are subsets of the same pictures) with the
true rig, and their volume compared with the truth.

Run: ``.venv/bin/python bench/scan_realistic.py [--scales 0.25,0.5] [--views 12,30,60]`` (about 15 minutes on
two loaded cores); prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from phantom.hil.truth_shape import TruthShape  # noqa: E402
from phantom.model.mesh.surface import enclosed_volume_ml  # noqa: E402
from phantom.scan.camera import virtual_rig  # noqa: E402
from phantom.scan.capture import CaptureFolder, Plan  # noqa: E402
from phantom.scan.reconstruct import reconstruct  # noqa: E402
from phantom.scan.render import IDEAL_LOOK, REAL_LOOK  # noqa: E402
from phantom.scan.virtual import render_capture  # noqa: E402
from tests.reference.hung_phantom import HungPhantom, write_capture  # noqa: E402

STOPS = 60


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", default="0.25,0.5")
    parser.add_argument("--views", default="12,30,60")
    args = parser.parse_args()
    scales = [float(value) for value in args.scales.split(",")]
    views = [int(value) for value in args.views.split(",")]
    rest = TruthShape().surface([0.0, 0.0, 0.0])
    cases = [
        ("reference ray caster, hung by tubes", "oracle", HungPhantom()),
        ("reference ray caster, no tubes", "oracle", HungPhantom(tubes=False)),
        ("reference ray caster, ideal", "oracle", HungPhantom(tubes=False, gloss=False, cloth=False,
                                                              vignetting=False, noise=False)),
        ("virtual camera, real look", "virtual", REAL_LOOK),
        ("virtual camera, ideal look", "virtual", IDEAL_LOOK),
    ]
    print("| pictures | picture | views a turn | volume vs truth | tubes cut at (mm) | reconstruction (loaded) |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as scratch:
        for scale in scales:
            rig = virtual_rig(scale)
            size = f"{rig.camera.width}x{rig.camera.height}"
            for label, kind, scene in cases:
                folder = Path(scratch) / f"{kind}-{scale}-{len(label)}"
                if kind == "oracle":
                    assert isinstance(scene, HungPhantom)
                    write_capture(folder, rig.to_json(), scene, STOPS, [0.0, 30.0])
                    truth_ml = scene.gland_volume_ml()
                else:
                    render_capture(rest, rig, Plan(STOPS), folder, look=scene)  # type: ignore[arg-type]
                    truth_ml = enclosed_volume_ml(rest)
                capture = CaptureFolder.open(folder)
                for count in views:
                    step = max(1, STOPS // count)
                    frames = [frame for frame in capture.frames if round((frame.orbit_deg + 180.0) / 6.0) % step == 0]
                    started = time.perf_counter()
                    result = reconstruct(capture, frames=frames)
                    took_s = time.perf_counter() - started
                    cut = "-" if result.hanging is None else f"{result.hanging.cut_mm:.2f}"
                    print(f"| {label} | {size} | {STOPS // step} | {100 * (result.volume_ml / truth_ml - 1):+.2f} % "
                          f"| {cut} | {took_s:.1f} s |", flush=True)


if __name__ == "__main__":
    main()
