"""The scanner on pictures a real rig takes, made by a renderer that is not the scanner's own
(tests/reference/hung_phantom.py: a ray caster of analytic shapes through OpenCV's undistortion): the gland hung
by three tubes of 4.4 mm that leave the picture's top edge, glossy silicone, an uneven cloth, vignetting and
noise. The gland's volume is a closed form; the reconstruction must report the gland's, the tubes taken off
(phantom.scan.silhouette, phantom.scan.hanging)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("cv2")
pytest.importorskip("skimage")

from phantom.scan.camera import virtual_rig  # noqa: E402
from phantom.scan.capture import CaptureFolder  # noqa: E402
from phantom.scan.hanging import find_base  # noqa: E402
from phantom.scan.reconstruct import reconstruct  # noqa: E402
from phantom.scan.silhouette import alpha_matte  # noqa: E402
from tests.reference.hung_phantom import HungPhantom, HungPhantomCamera, write_capture  # noqa: E402

#: The rig: the virtual one's geometry at 640x480, 30 stops a turn at 0 and 30 deg (60 pictures).
SCALE, VIEWS, ELEVATIONS = 0.5, 30, [0.0, 30.0]


@pytest.fixture(scope="module")
def rig_json():
    return virtual_rig(SCALE).to_json()


@pytest.fixture(scope="module")
def hung_capture(tmp_path_factory, rig_json):
    scene = HungPhantom()
    return write_capture(tmp_path_factory.mktemp("hung"), rig_json, scene, VIEWS, ELEVATIONS), scene


@pytest.mark.slow  # renders 60 pictures and carves them: tens of seconds
def test_a_phantom_hung_by_its_tubes_scans_as_its_gland(hung_capture, tmp_path):
    folder, scene = hung_capture
    out = tmp_path / "scan.ply"
    # through the command line, as a user on a real rig's pictures
    done = subprocess.run([sys.executable, "-m", "phantom", "scan", "reconstruct", str(folder), "--out", str(out),
                           "--json"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    truth_ml = scene.gland_volume_ml()
    assert summary["volume_ml"] == pytest.approx(truth_ml, rel=0.005), (summary["volume_ml"], truth_ml)
    assert summary["silhouettes_touching_edge"] == 0  # the gland is whole in view; the tubes do not count
    hanging = summary["hanging"]
    # the tubes were found and taken off at the gland's base (its flat top), within a voxel and a half
    top_mm = scene.centre_mm[2] + scene.top_mm
    assert hanging is not None and hanging["cut_mm"] == pytest.approx(top_mm, abs=0.5)
    assert hanging["column_area_mm2"] == pytest.approx(3 * np.pi * scene.tube_radius_mm ** 2, rel=0.3)


@pytest.mark.slow
def test_the_same_gland_without_tubes_scans_within_three_tenths_of_a_percent(tmp_path, rig_json):
    scene = HungPhantom(tubes=False)
    folder = write_capture(tmp_path / "free", rig_json, scene, VIEWS, ELEVATIONS)
    result = reconstruct(CaptureFolder.open(folder))
    assert result.hanging is None and result.touching_edge == 0
    assert result.volume_ml == pytest.approx(scene.gland_volume_ml(), rel=0.003)


def test_the_key_reads_an_uneven_cloth_as_backdrop_and_tubes_as_opaque(rig_json):
    camera = HungPhantomCamera(rig_json, HungPhantom(), supersample=1)
    picture = camera.picture(0.0, 30.0)
    alpha = alpha_matte(picture)
    inside = np.zeros(alpha.shape, bool)
    x0, y0, x1, y1 = camera._box_px(*camera.rig.pose(0.0, 30.0))
    inside[:, x0:x1] = True
    # the cloth (brightness from about 0.6 to 1.4 of its mean, folds, darker corners): no pixel of it near the
    # key's half (a global key read its dark folds as 0.4 phantom)
    assert np.max(alpha[~inside]) < 0.45 and np.percentile(alpha[~inside], 99) < 0.2
    # the tubes above the gland (the top rows, inside the box): opaque where they are, so they carve nothing
    top = alpha[:20, x0:x1]
    assert np.count_nonzero(top > 0.5) >= 3 * 2 * camera.scene.tube_radius_mm * 700 / 230 * 20 * 0.5


def test_the_base_is_where_the_hull_widens_under_a_steady_column():
    h = 0.3
    heights = np.arange(-20.0, 60.0, h)
    gland = np.where(heights <= 18.0, 990.0 * (1 - np.clip((heights + 1) / 20, -1, 1) ** 2), 0.0)
    column = np.where(heights > 18.0, 50.0, 0.0) * (heights < 58.0)
    base, area = find_base(heights, gland + column)
    assert area == pytest.approx(50.0)
    assert base == pytest.approx(18.0, abs=h)
    # nothing hangs (the top of the gland is its widest is not a column): no base
    assert find_base(heights, gland) is None


def test_the_virtual_rigs_real_look_hangs_the_gland_by_tubes_out_of_the_picture():
    from phantom.scan.render import REAL_LOOK, Renderer, hung_scene, to_8bit
    from phantom.scan.silhouette import silhouette
    from phantom.scan.synthetic import sphere

    # a gland with a flat base at its top, as the model's (clamped at z = 20 mm)
    ball = sphere(15.0, np.array([0.0, 0.0, 0.0]), levels=4)
    vertices = ball.vertices_mm.copy()
    vertices[:, 2] = np.minimum(vertices[:, 2], 12.0)
    gland = type(ball)(vertices, ball.triangles)
    scene, normals, material = hung_scene(gland)
    assert set(np.unique(material)) == {0, 1, 2}
    tube_vertices = np.unique(scene.triangles[material == 1])
    # the tubes start inside the base and run up past any picture
    assert scene.vertices_mm[tube_vertices, 2].min() == pytest.approx(11.0)
    assert scene.vertices_mm[tube_vertices, 2].max() > 100.0
    rig = virtual_rig(0.25)
    picture = to_8bit(Renderer(rig.camera, look=REAL_LOOK).render_mesh(scene, rig.pose(0.0, 30.0), normals, material),
                      np.random.default_rng(0), REAL_LOOK)
    found = silhouette(picture)
    assert found.touches_top and found.touches_edge
    alpha = alpha_matte(picture)
    assert np.max(alpha[:, :20]) < 0.45 and np.max(alpha[-20:]) < 0.45  # the cloth's sides and bottom: backdrop
