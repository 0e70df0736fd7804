"""The commands that read a mesh, a scan, a rig file or a capture folder check its size before a library reads it
whole (issue 23, defect 9): a 2 GB sparse file was read by ``phantom scan import``, ``render``, ``reconstruct``
and ``export`` (2.2 GB of memory, then a MemoryError traceback or a misleading message) and /dev/zero would never
end. Each now gets a one-line error and exit status 2, at once, without reading the file."""

from __future__ import annotations

import json
import resource
import time

import pytest

from phantom.cli.main import main
from phantom.scan.capture import CAPTURE_FILE, CAPTURE_FORMAT

HUGE_BYTES = 2 * 2**30


def sparse(path, size=HUGE_BYTES):
    with open(path, "wb") as handle:
        handle.truncate(size)                               # zeros, sparse: no disk used
    return path


def capture_folder(folder, picture_bytes=1000):
    """A capture folder of one picture of ``picture_bytes`` (sparse)."""
    (folder / "images").mkdir(parents=True)
    sparse(folder / "images" / "0000.png", picture_bytes)
    (folder / CAPTURE_FILE).write_text(json.dumps({
        "format": CAPTURE_FORMAT, "frames": [{"index": 0, "image": "images/0000.png", "orbit_deg": 0.0,
                                              "elevation_deg": 0.0}]}))
    return folder


def scene_with_mesh(folder, mesh, name):
    scene = folder / name
    scene.write_text(f'[phantom]\nmesh = "{mesh}"\nunits = "mm"\nchambers = ["chamber0"]\nfixed = "fixed"\n\n'
                     '[material]\nmodel = "corotational"\nyoungs_modulus_kpa = 50.0\npoisson_ratio = 0.45\n')
    return scene


def cases(tmp):
    """(command line, words of the error) for every reading command, each given a 2 GB file or /dev/zero."""
    huge_capture = tmp / "huge_capture"
    huge_capture.mkdir()
    sparse(huge_capture / CAPTURE_FILE)
    return {
        "mesh: the scene's mesh": (["mesh", "--scene", str(scene_with_mesh(tmp, sparse(tmp / "huge.msh"), "a.toml")),
                                    "--out", str(tmp / "out.msh")], "2048 MiB, more than the 256 MiB"),
        "forward: the scene's mesh": (["forward", "--scene", str(scene_with_mesh(tmp, "/dev/zero", "b.toml")),
                                       "--pressures-kpa", "1"], "/dev/zero is not a regular file"),
        "compare-scan: the scan": (["compare-scan", str(sparse(tmp / "huge.stl")), "--scene", "builtin",
                                    "--pressures-kpa", "1,1,1"], "decimate it first"),
        "scan import": (["scan", "import", str(sparse(tmp / "huge.ply")), "--out", str(tmp / "o.ply")],
                        "more than the 256 MiB"),
        "scan render: the mesh": (["scan", "render", str(tmp / "huge.stl"), "--out", str(tmp / "r")],
                                  "more than the 256 MiB"),
        "scan render: the rig": (["scan", "render", str(tmp / "huge.stl"), "--rig", "/dev/zero", "--out",
                                  str(tmp / "r")], "the rig file /dev/zero is not a regular file"),
        "scan reconstruct: capture.json": (["scan", "reconstruct", str(huge_capture), "--out", str(tmp / "o.ply")],
                                           "the capture file"),
        "scan reconstruct: a picture": (["scan", "reconstruct", str(capture_folder(tmp / "cap", HUGE_BYTES)),
                                         "--out", str(tmp / "o.ply")], "the picture"),
        "scan export: the rig": (["scan", "export", str(capture_folder(tmp / "small")), "--colmap", str(tmp / "c"),
                                  "--rig", str(sparse(tmp / "rig.json"))], "more than the 16 MiB"),
        "scan calibrate: capture.json": (["scan", "calibrate", str(huge_capture), "--out", str(tmp / "rig.json")],
                                         "the capture file"),
    }


CASES = [
    "mesh: the scene's mesh", "forward: the scene's mesh", "compare-scan: the scan", "scan import",
    "scan render: the mesh", "scan render: the rig", "scan reconstruct: capture.json", "scan reconstruct: a picture",
    "scan export: the rig", "scan calibrate: capture.json"]


@pytest.mark.parametrize("case", CASES)
def test_a_huge_or_endless_input_file_is_refused_in_one_line_before_it_is_read(tmp_path, capsys, case):
    argv, words = cases(tmp_path)[case]
    before_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    started = time.monotonic()
    assert main(argv) == 2
    assert time.monotonic() - started < 5.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - before_mb < 100   # before: 2.2 GB
    error = capsys.readouterr().err.strip()
    assert "Traceback" not in error and words in error.splitlines()[-1], error    # (a numba notice may come first)
