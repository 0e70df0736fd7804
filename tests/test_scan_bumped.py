"""A capture whose pictures do not line up is refused, not carved: one picture taken after the camera or the
turntable was bumped (shifted a few pixels against the others) cuts the visual hull, and every volume read from
it, short (phantom.scan.carve.view_agreement, phantom.scan.reconstruct). Also phantom scan reconstruct's --out
over an existing mesh, and a capture whose picture is missing (one line of error, nothing of OpenCV's).

The captures are the virtual camera's at 320x240 (16 pictures at 0 and 30 deg) of a dented sphere, ideal and as
a real rig sees it (hung by its tubes, which leave the pictures' top edge); a bumped picture is the same picture
moved by a few pixels, as a knocked camera moves it (8 px here is 32 px at 1280x960, 16 at the verify scan's
640x480)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from phantom.scan.camera import VIRTUAL_CENTRE_MM, virtual_rig
from phantom.scan.capture import CaptureFolder, Plan
from phantom.scan.synthetic import sphere

cv2 = pytest.importorskip("cv2")
pytest.importorskip("skimage")

from phantom.cli.main import main  # noqa: E402
from phantom.scan.carve import CarveError  # noqa: E402
from phantom.scan.reconstruct import reconstruct  # noqa: E402
from phantom.scan.render import LOOKS  # noqa: E402
from phantom.scan.virtual import render_capture  # noqa: E402

RIG = virtual_rig(0.25)
PLAN = Plan(8)
VOXEL_MM = 0.6
#: Not round every way (a dent on one side), so that no picture is any other's moved.
SHAPE = sphere(14.0, VIRTUAL_CENTRE_MM, levels=4, dent_mm=4.0)


@pytest.fixture(scope="module", params=["ideal", "real"])
def steady(request, tmp_path_factory):
    """A capture taken with nothing bumped: ideal, or hung by its tubes as a real rig sees it (a second to render,
    once for the module: tests/conftest.py keeps its tests on one worker). The tests copy it, never change it."""
    return render_capture(SHAPE, RIG, PLAN, tmp_path_factory.mktemp(request.param) / "capture",
                          look=LOOKS[request.param])


def bumped(folder: CaptureFolder, moves: dict[int, tuple[float, float]], out) -> CaptureFolder:
    """A copy of ``folder`` with each picture of ``moves`` (its number: the shift, px, x right and y down) moved,
    the picture's edge repeated into what is uncovered, as the backdrop runs on past it."""
    shutil.copytree(folder.path, out)
    for number, (right_px, down_px) in moves.items():
        path = out / folder.frames[number].image
        picture = cv2.imread(str(path))
        move = np.float32([[1, 0, right_px], [0, 1, down_px]])
        cv2.imwrite(str(path), cv2.warpAffine(picture, move, picture.shape[1::-1], borderMode=cv2.BORDER_REPLICATE))
    return CaptureFolder.open(out)


def test_a_steady_capture_is_carved_with_every_picture_in_line(steady):
    result = reconstruct(steady, voxel_mm=VOXEL_MM)
    # measured 0.00 % for both (the hung one 1.3 % if its tubes' tops, past the hull's, were counted)
    assert 0.0 <= result.worst_uncovered_pct < 0.1, result.worst_uncovered_pct


@pytest.mark.parametrize("number, shift_px", [(3, (8.0, 0.0)), (11, (0.0, -8.0)), (6, (-6.0, 6.0))])
def test_one_bumped_picture_is_refused_by_name(steady, tmp_path, number, shift_px):
    folder = bumped(steady, {number: shift_px}, tmp_path / "bumped")
    with pytest.raises(CarveError) as refused:
        reconstruct(folder, voxel_mm=VOXEL_MM)
    message = str(refused.value)
    name = folder.frames[number].image
    assert message.startswith(f"{name} (frame {number}) is out of line with the other 15 pictures"), message
    assert message.endswith("take the capture again") and "\n" not in message
    # no other picture is named
    assert not any(frame.image in message for frame in folder.frames if frame.image != name)


def test_two_moved_pictures_are_refused_as_a_capture_that_does_not_line_up(steady, tmp_path):
    """Leaving out one picture mends nothing: the three pictures least covered are named, none as the one."""
    folder = bumped(steady, {3: (8.0, 0.0), 9: (0.0, 8.0)}, tmp_path / "bumped")
    with pytest.raises(CarveError) as refused:
        reconstruct(folder, voxel_mm=VOXEL_MM)
    message = str(refused.value)
    assert message.startswith("the pictures do not line up: the hull carved from all 16 leaves up to "), message
    assert sum(frame.image in message for frame in folder.frames) == 3 and "out of line" not in message
    assert message.endswith("take the capture again (or calibrate the rig again)") and "\n" not in message


def test_the_command_line_refuses_a_bumped_capture_in_one_line_and_writes_nothing(steady, tmp_path, capsys):
    folder = bumped(steady, {5: (8.0, 0.0)}, tmp_path / "bumped")
    out = tmp_path / "scan.ply"
    assert main(["scan", "reconstruct", str(folder.path), "--out", str(out), "--voxel-mm", str(VOXEL_MM),
                 "--json"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("phantom scan: error: images/0005.png (frame 5) is out of line") and err.count("\n") == 1
    assert not out.exists()


def test_reconstruct_refuses_to_write_over_a_mesh_unless_told_to_replace_it(steady, tmp_path, capsys):
    out = tmp_path / "scan.ply"
    out.write_text("an earlier scan\n")
    args = ["scan", "reconstruct", str(steady.path), "--out", str(out), "--voxel-mm", str(VOXEL_MM), "--json"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err == (f"phantom scan: error: --out {out} exists already: give another --out, or --replace to write "
                   f"over it\n")
    assert out.read_text() == "an earlier scan\n"
    assert main([*args, "--replace"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["mesh"] == str(out) and out.read_bytes().startswith(b"ply")


def test_a_missing_picture_is_one_line_of_error_and_nothing_of_opencvs(steady, tmp_path, capfd):
    shutil.copytree(steady.path, tmp_path / "capture")
    missing = tmp_path / "capture" / steady.frames[2].image
    missing.unlink()
    capfd.readouterr()
    assert main(["scan", "reconstruct", str(tmp_path / "capture"), "--out", str(tmp_path / "scan.ply")]) == 2
    captured = capfd.readouterr()  # OpenCV writes to the process's stderr itself: read at the descriptor
    assert captured.err == (f"phantom scan: error: the picture {missing} that capture.json names is missing: copy "
                            f"the capture folder whole, or take the capture again\n"), captured.err
