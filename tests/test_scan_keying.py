"""The silhouettes keyed as the capture takes its pictures (phantom.scan.keying): the reconstruction from them is
the folder's to the last digit, and a capture that did not complete, a picture changed since, a picture whose
keying failed or another capture's pictures leave nothing that a later reconstruction reads."""

import numpy as np
import pytest

from phantom.scan.camera import VIRTUAL_CENTRE_MM, virtual_rig
from phantom.scan.capture import CaptureError, CaptureFolder, Plan, capture
from phantom.scan.keying import KeyedPictures
from phantom.scan.synthetic import sphere

cv2 = pytest.importorskip("cv2")
pytest.importorskip("skimage")

from phantom.scan.reconstruct import reconstruct  # noqa: E402
from phantom.scan.render import Renderer, to_8bit  # noqa: E402
from phantom.scan.silhouette import SilhouetteError  # noqa: E402

RIG = virtual_rig(0.25)  # 320x240 pictures
PLAN = Plan(8, settle_s=0.0)  # 16 pictures
VOXEL_MM = 0.6


class Orbit:
    """Where it is told to be (a real orbit is tested through the daemon and simavr)."""

    def __init__(self, fault_at=None):
        self.at, self.moves, self.fault_at = (0.0, 0.0), 0, fault_at

    def move_to(self, orbit_deg, elevation_deg):
        if self.fault_at is not None and self.moves == self.fault_at:
            raise CaptureError("the orbit stalled")
        self.moves += 1
        self.at = (orbit_deg, elevation_deg)
        return self.at

    def position_deg(self):
        return self.at

    def release(self):
        pass


class SphereCamera:
    """A sphere rendered from where the orbit is, as the virtual camera renders the phantom (``take``: developed
    in the capture's pictures thread); ``blank_at``: that picture is the backdrop alone."""

    def __init__(self, orbit, blank_at=None):
        self.orbit, self.blank_at, self.taken = orbit, blank_at, 0
        self.renderer, self.rng = Renderer(RIG.camera), np.random.default_rng(5)
        self.mesh = sphere(14.0, VIRTUAL_CENTRE_MM, levels=4)

    def take(self):
        pose, blank = RIG.pose(*self.orbit.at), self.taken == self.blank_at
        self.taken += 1
        mesh = sphere(1e-3, VIRTUAL_CENTRE_MM + 1e4, levels=1) if blank else self.mesh
        return lambda: to_8bit(self.renderer.render_mesh(mesh, pose), self.rng)

    def describe(self):
        return {"kind": "virtual"}


class Phantom:
    def pressures_kpa(self):
        return [1.0, 1.0, 1.0]


def _capture(path, keyed, orbit=None, blank_at=None):
    orbit = orbit or Orbit()
    folder = CaptureFolder.create(path, {"kind": "virtual"}, PLAN.to_json(), rig=RIG)
    capture(orbit, SphereCamera(orbit, blank_at), Phantom(), PLAN, folder, keep=keyed.start(folder))
    return CaptureFolder.open(path)


def test_the_silhouettes_keyed_as_taken_reconstruct_the_folders_volume_to_the_last_digit(tmp_path):
    keyed = KeyedPictures()
    folder = _capture(tmp_path / "capture", keyed)
    taken = keyed.take(folder)
    assert sorted(taken) == [frame.image for frame in folder.frames] and len(taken) == 16
    assert all("key" in frame.stage_s and frame.stage_s["key"] >= 0 for frame in folder.frames)
    assert keyed.take(folder) == {}  # handed out once
    told = []
    ahead = reconstruct(folder, RIG, VOXEL_MM, progress=told.append, keyed=taken)
    assert "16 silhouettes in" in told[0] and "(16 keyed as they were taken)" in told[0]
    reference = reconstruct(folder, RIG, VOXEL_MM)  # phantom scan reconstruct's: every picture read back, keyed
    assert ahead.volume_ml == reference.volume_ml and ahead.volume_ml == pytest.approx(11.5, rel=0.05)
    np.testing.assert_array_equal(ahead.mesh.vertices_mm, reference.mesh.vertices_mm)
    np.testing.assert_array_equal(ahead.mesh.triangles, reference.mesh.triangles)


def test_a_picture_changed_after_it_was_keyed_is_keyed_again(tmp_path):
    keyed = KeyedPictures()
    folder = _capture(tmp_path / "capture", keyed)
    first = folder.path / folder.frames[0].image
    picture = folder.image(folder.frames[0])
    picture[0, 0] = 255 - picture[0, 0]  # one pixel of the border: another picture, of the same size
    assert cv2.imwrite(str(first), picture[:, :, ::-1])
    taken = keyed.take(folder)
    assert folder.frames[0].image not in taken and len(taken) == 15


def test_an_aborted_capture_and_a_superseded_one_leave_no_silhouettes(tmp_path):
    keyed = KeyedPictures()
    with pytest.raises(CaptureError, match="aborted after 5 of 16 pictures: the orbit stalled"):
        _capture(tmp_path / "aborted", keyed, Orbit(fault_at=5))
    aborted = CaptureFolder.open(tmp_path / "aborted")
    assert aborted.status == "aborted" and len(aborted.frames) == 5 and keyed.take(aborted) == {}
    # a complete capture's silhouettes are dropped by the next capture's start, and by a drop
    first = _capture(tmp_path / "first", keyed)
    second = _capture(tmp_path / "second", keyed)
    assert keyed.take(first) == {}
    keyed.drop(second)
    assert keyed.take(second) == {}


def test_a_picture_whose_keying_failed_is_keyed_by_the_reconstruction_which_names_it(tmp_path):
    keyed = KeyedPictures()
    folder = _capture(tmp_path / "capture", keyed, blank_at=3)
    taken = keyed.take(folder)
    assert len(taken) == 15 and "images/0003.png" not in taken
    with pytest.raises(SilhouetteError, match="images/0003.png: .*is the phantom in view"):
        reconstruct(folder, RIG, VOXEL_MM, keyed=taken)
