"""Bad arguments to ``phantom scan synthetic``, ``scan import``, ``scan reconstruct``, ``compare-scan`` and
``design`` are refused in one line, in the command line's terms, before the model is solved: ``--noise-mm nan``
wrote a scan of NaN vertices, ``--noise-mm 1e6`` one 64,000 times too large, ``--levels 12`` ran for minutes,
``--out s.txt``, ``--seed -1`` and ``--holes 100000`` were tracebacks after the solve, ``--rerun-save FOLDER`` a
traceback after the whole comparison, ``design`` of a NaN mesh a traceback, ``scan import --units cm`` of a mesh
in mm a 32-litre scan, and ``--voxel-mm 1000`` was called too fine."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from phantom.cli.main import main
from phantom.model.fem.model import PhantomModel
from phantom.model.mesh.surface import subdivide
from phantom.scan.reconstruct import write_mesh
from phantom.scan.synthetic import make_scan, sphere


@pytest.fixture
def no_solve(monkeypatch):
    """Fail the test (not the command: pytest's Failed is not an Exception) if the model is built."""
    def built(*args, **kwargs):
        pytest.fail("the model was built before the arguments were checked")
    monkeypatch.setattr(PhantomModel, "from_scene", built)


def refused(capsys, argv):
    """The command's exit status is 2 and its error one line (a numba notice may come first): that line."""
    assert main(argv) == 2
    error = capsys.readouterr().err.strip()
    assert "Traceback" not in error, error
    return error.splitlines()[-1]


def phantom_sized_mesh(path, scale=1.0):
    """A closed sphere of the phantom's size (its RMS radius, 18.8 mm) times ``scale``, written to ``path``."""
    return write_mesh(sphere(18.8 * scale, np.zeros(3), levels=3), path)


@pytest.mark.parametrize("noise", ["nan", "inf", "-inf", "-0.1", "5.5", "1e6"])
def test_synthetic_refuses_a_noise_that_is_not_a_finite_few_mm(tmp_path, capsys, no_solve, noise):
    out = tmp_path / "s.ply"
    line = refused(capsys, ["scan", "synthetic", "--out", str(out), "--levels", "1", f"--noise-mm={noise}"])
    assert f"--noise-mm {float(noise):g}" in line and "from 0 to 5 mm" in line, line
    assert not out.exists()


@pytest.mark.parametrize("levels", ["7", "12"])
def test_synthetic_refuses_more_levels_than_memory_allows(tmp_path, capsys, no_solve, levels):
    line = refused(capsys, ["scan", "synthetic", "--out", str(tmp_path / "s.ply"), "--levels", levels])
    assert f"--levels {levels}" in line and "0 to 6" in line and "vertices" in line and "memory" in line, line


@pytest.mark.parametrize("option", ["--levels", "--holes"])
def test_synthetic_still_says_a_negative_count_is_negative(tmp_path, capsys, no_solve, option):
    line = refused(capsys, ["scan", "synthetic", "--out", str(tmp_path / "s.ply"), option, "-1"])
    assert f"{option} -1" in line and "not negative" in line, line


@pytest.mark.parametrize("name", ["s9.txt", "s9", "s9.vtk"])
def test_synthetic_refuses_an_out_it_cannot_write_naming_the_formats(tmp_path, capsys, no_solve, name):
    line = refused(capsys, ["scan", "synthetic", "--out", str(tmp_path / name)])
    assert f"--out {tmp_path / name}" in line and ".ply, .stl or .obj" in line, line


def test_synthetic_refuses_a_folder_as_out(tmp_path, capsys, no_solve):
    folder = tmp_path / "scan.ply"
    folder.mkdir()
    assert "is a folder" in refused(capsys, ["scan", "synthetic", "--out", str(folder)])


def test_synthetic_refuses_a_negative_seed(tmp_path, capsys, no_solve):
    line = refused(capsys, ["scan", "synthetic", "--out", str(tmp_path / "s.ply"), "--seed", "-1"])
    assert "--seed -1" in line and "0 or more" in line, line


@pytest.mark.parametrize("holes", ["51", "100000"])
def test_synthetic_refuses_more_holes_than_a_scan_has(tmp_path, capsys, no_solve, holes):
    line = refused(capsys, ["scan", "synthetic", "--out", str(tmp_path / "s.ply"), "--holes", holes])
    assert f"--holes {holes}" in line and "0 to 50" in line, line


@pytest.mark.parametrize("factor", ["nan", "inf", "0", "-1"])
def test_synthetic_refuses_a_modulus_factor_that_is_not_a_finite_positive_number(tmp_path, capsys, no_solve,
                                                                                  factor):
    line = refused(capsys, ["scan", "synthetic", "--out", str(tmp_path / "s.ply"), "--modulus-factor", factor])
    assert "--modulus-factor" in line, line


def test_the_holes_of_a_synthetic_scan_are_cut_as_before():
    """make_scan's holes, now cut one at a time (a level-6 surface's triangles against 50 centres at once were
    GBs), are the same holes."""
    surface = sphere(18.8, np.zeros(3), levels=3)
    scan = make_scan(surface, np.random.default_rng(3), levels=1, holes=5)
    vertices = scan.mesh.vertices_mm
    rng = np.random.default_rng(3)
    fine_vertices, fine_triangles = subdivide(surface.vertices_mm, surface.triangles)
    rng.normal(size=(len(fine_vertices), 1))
    centres = fine_vertices[rng.choice(len(fine_vertices), 5, replace=False)]
    centroid = fine_vertices[fine_triangles].mean(axis=1)
    near = np.linalg.norm(centroid[:, None, :] - centres[None], axis=2).min(axis=1) < 2.5
    assert len(scan.mesh.triangles) == np.count_nonzero(~near)
    assert np.isfinite(vertices).all()


@pytest.mark.parametrize("kind", ["folder", "suffix", "parent is a file"])
def test_compare_scan_refuses_a_recording_path_it_cannot_write_before_comparing(tmp_path, capsys, no_solve, kind):
    scan = phantom_sized_mesh(tmp_path / "good.ply")
    blocker = tmp_path / "blocker"
    blocker.write_text("a file")
    folder = tmp_path / "adir"
    folder.mkdir()
    path = {"folder": folder, "suffix": tmp_path / "run.txt", "parent is a file": blocker / "run.rrd"}[kind]
    line = refused(capsys, ["compare-scan", str(scan), "--scene", "builtin:calibrated", "--pressures-kpa",
                            "1,2,0.5", "--out", str(tmp_path / "cmpout"), "--rerun-save", str(path)])
    assert f"--rerun-save {path}" in line and ".rrd" in line, line
    assert not (tmp_path / "cmpout").exists()


def test_design_refuses_a_mesh_with_non_finite_vertices_naming_the_file(tmp_path, capsys):
    mesh = sphere(18.8, np.zeros(3), levels=2)
    vertices = mesh.vertices_mm.copy()
    vertices[4] = np.nan
    path = tmp_path / "nan.ply"
    meshio.write_points_cells(path, vertices, [("triangle", mesh.triangles.astype(np.int32))])
    line = refused(capsys, ["design", str(path), "--out", str(tmp_path / "des"), "--growth-kpa", "none"])
    assert str(path) in line and "non-finite coordinates" in line, line
    assert not (tmp_path / "des").exists()


def test_scan_import_refuses_a_mesh_read_in_the_wrong_unit_naming_the_right_one(tmp_path, capsys):
    path = phantom_sized_mesh(tmp_path / "meshed.ply")
    out = tmp_path / "scan.ply"
    line = refused(capsys, ["scan", "import", str(path), "--out", str(out), "--units", "cm"])
    assert "10 times the model's size" in line and "it looks like the file is in mm: pass --units mm" in line, line
    assert not out.exists()
    metres = phantom_sized_mesh(tmp_path / "metres.ply", 1e-3)
    assert "pass --units m" in refused(capsys, ["scan", "import", str(metres), "--out", str(out)])
    assert main(["scan", "import", str(path), "--out", str(out)]) == 0
    assert out.exists()


@pytest.mark.parametrize(("voxel", "words"), [
    ("1000", "loses the phantom's shape"), ("5.5", "loses the phantom's shape"), ("inf", "loses the phantom's shape"),
    ("0.01", "less than a pixel"), ("0", "less than a pixel"), ("nan", "not a finite number")])
def test_reconstruct_says_which_way_a_voxel_is_out_of_range_before_reading_the_capture(tmp_path, capsys, voxel,
                                                                                      words):
    """The carving's own check (scan.reconstruct.check_voxel_mm), before the capture is read: it called every
    voxel out of range too fine ("a finer grid resolves less than a pixel", for 1000 mm)."""
    line = refused(capsys, ["scan", "reconstruct", str(tmp_path / "no-capture"), "--out", str(tmp_path / "o.ply"),
                            "--voxel-mm", voxel])
    assert f"got {float(voxel)!r} mm" in line and words in line and "from 0.05 to 5 mm" in line, line
    assert "--voxel-mm" in line, line
