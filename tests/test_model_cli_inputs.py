"""Bad inputs to the offline model commands (``phantom forward``, ``mesh``, ``scene check``) and to the scene
reader every command shares: each refused in one line that names what was wrong, before any solve."""

import numpy as np
import pytest

from phantom.cli.main import main
from phantom.model import SceneError, load_scene
from phantom.model.scene import BUILTIN_SCENES, SCENES_DIR, scene_from_dict

BUILTIN_PHANTOM = {"mesh": "builtin:prostate", "units": "mm", "chambers": ["chamber0", "chamber1", "chamber2"],
                   "fixed": "fixed"}


def one_line_error(capsys):
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1, error
    return error


@pytest.fixture
def no_solve(monkeypatch):
    """Fail a test whose command builds a model: a refusal comes before any."""
    from phantom.model.fem.model import PhantomModel

    def refuse(*args, **kwargs):
        raise AssertionError("the command built a model before refusing its input")

    monkeypatch.setattr(PhantomModel, "from_scene", refuse)


# 1. --out's format, checked up front against what the writers accept


def test_forward_out_of_an_unknown_format_is_refused_before_the_solve_naming_the_users_path(tmp_path, capsys,
                                                                                          no_solve):
    """``--out x.xyz`` solved, then said ``Could not deduce file format from path '/tmp/.x.g7e2o6w_.xyz'.; use .msh
    or .vtu``: a temporary file's name, and not the surface formats that work."""
    from phantom.cli.model import SURFACE_FORMATS, VOLUME_FORMATS

    out = tmp_path / "x.xyz"
    assert main(["forward", "--scene", "builtin", "--pressures-kpa", "1,1,1", "--out", str(out)]) == 2
    error = one_line_error(capsys)
    assert f"--out {out}" in error and "'.xyz'" in error
    assert all(suffix in error for suffix in VOLUME_FORMATS + SURFACE_FORMATS)
    assert "/." not in error and not out.exists()


def test_mesh_out_of_an_unknown_format_is_refused_naming_the_users_path(tmp_path, capsys):
    out = tmp_path / "x.xyz"
    assert main(["mesh", "--scene", "builtin", "--out", str(out)]) == 2
    error = one_line_error(capsys)
    assert f"--out {out}" in error and ".msh" in error and ".vtu" in error and "/." not in error


@pytest.mark.parametrize("order", [1, 2])
def test_every_format_forward_out_names_is_written_with_the_tetrahedra(tmp_path, order):
    """The formats the refusal names are those the writer really writes, for 4- and 10-node meshes."""
    import meshio

    from phantom.cli.model import VOLUME_FORMATS
    from phantom.model.mesh.tetmesh import TetMesh, write_mesh

    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]) * 1e-3
    if order == 1:
        mesh = TetMesh(corners, np.array([[0, 1, 2, 3]]), {"chamber0": np.array([[0, 2, 1]])})
    else:
        middles = [(corners[a] + corners[b]) / 2 for a, b in ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))]
        mesh = TetMesh(np.vstack([corners, middles]), np.arange(10)[None], {"chamber0": np.array([[0, 2, 1, 6, 5, 4]])})
    for suffix in VOLUME_FORMATS:
        path = tmp_path / f"m{suffix}"
        write_mesh(mesh, path, 1e-3, {"volume_ratio": np.ones(1)})
        assert path.stat().st_size > 0
        if suffix not in (".msh",):
            assert len(meshio.read(path).points) == mesh.n_nodes, suffix


# 2. --out's folder: made as documented, only for a file that is written


def test_forward_out_in_a_missing_folder_refused_for_its_format_makes_no_folder(tmp_path, capsys, no_solve):
    """A refused --out left the folder it named made (the folders were made before the writer failed)."""
    out = tmp_path / "new" / "deeper" / "x.xyz"
    assert main(["forward", "--scene", "builtin", "--pressures-kpa", "1,1,1", "--out", str(out)]) == 2
    one_line_error(capsys)
    assert not (tmp_path / "new").exists()


def test_forward_out_under_a_file_is_refused_before_the_solve(tmp_path, capsys, no_solve):
    (tmp_path / "file").write_text("x")
    out = tmp_path / "file" / "x.stl"
    assert main(["forward", "--scene", "builtin", "--pressures-kpa", "1,1,1", "--out", str(out)]) == 2
    assert f"--out {out}" in one_line_error(capsys)


@pytest.mark.slow
def test_forward_out_in_a_missing_folder_says_it_made_it(tmp_path, capsys):
    out = tmp_path / "new" / "x.stl"
    assert main(["forward", "--scene", "builtin", "--pressures-kpa", "0.5,0.5,0.5", "--out", str(out)]) == 0
    assert out.stat().st_size > 0
    assert f"made the folder {tmp_path / 'new'}" in capsys.readouterr().out


# 3. a built-in scene's name, misspelt


@pytest.mark.parametrize("command", [["inverse", "--scene", "builtin:nope", "--volume-ml", "32"],
                                     ["forward", "--scene", "builtin:nope", "--pressures-kpa", "1,1,1"],
                                     ["scene", "check", "builtin:nope"]])
def test_an_unknown_builtin_scene_is_named_as_such_with_the_builtin_names(capsys, command):
    """``builtin:nope`` said ``the scene file /tmp/.../builtin:nope does not exist``."""
    assert main(command) == 2
    error = one_line_error(capsys)
    assert "builtin:nope is not a built-in scene" in error and "does not exist" not in error
    assert all(name in error for name in BUILTIN_SCENES)


def test_a_timeline_scene_naming_an_unknown_builtin_model_says_so(tmp_path):
    from phantom.host.scenes import read_timeline_scene

    path = tmp_path / "timeline.toml"
    path.write_text('model = "builtin:nope"\n[[steps]]\nat_s = 0\nvolume_ml = 30\n')
    with pytest.raises(SceneError, match=r"builtin:nope is not a built-in scene.*builtin:converged"):
        read_timeline_scene(path)


# 4. what a scene names that cannot be right


def scene(phantom=None, material=None, model=None, path=None):
    raw = {"phantom": {**BUILTIN_PHANTOM, **(phantom or {})}, "material": material or {}}
    if model is not None:
        raw["model"] = model
    return scene_from_dict(raw, path)


def test_a_builtin_scene_naming_a_chamber_group_it_lacks_is_refused():
    with pytest.raises(SceneError, match=r"\[phantom\] chambers names 'nope'.*chamber0, chamber1, chamber2"):
        scene({"chambers": ["chamber0", "nope"]})


def test_a_builtin_scene_naming_a_fixed_group_it_lacks_is_refused():
    with pytest.raises(SceneError, match=r"\[phantom\] fixed = 'nothing'.*'fixed'"):
        scene({"fixed": "nothing"})


def test_scene_check_warns_of_a_mesh_file_that_does_not_exist(tmp_path, capsys):
    """The reader leaves a mesh file to the commands that mesh; scene check said valid and nothing else. A warning,
    not a refusal: tests/test_scene.py checks a scene whose mesh is not written (exit 0)."""
    path = tmp_path / "s.toml"
    path.write_text('[phantom]\nmesh = "missing.msh"\nchambers = ["a"]\n[material]\n')
    assert main(["scene", "check", str(path)]) == 0
    assert f"[phantom] mesh names {tmp_path / 'missing.msh'}, which is not a file" in one_line_error(capsys)


@pytest.mark.parametrize("key", ["table_volumes", "table_shapes"])
def test_scene_check_refuses_a_table_file_that_is_not_an_npz(tmp_path, capsys, key):
    """The model refuses it when it reads it; scene check said valid."""
    (tmp_path / "t.ply").write_text("ply\nformat ascii 1.0\nend_header\n")
    path = tmp_path / "s.toml"
    path.write_text(f'[phantom]\nmesh = "builtin:prostate"\nchambers = ["chamber0"]\n[material]\n'
                    f'[model]\n{key} = "t.ply"\n')
    assert main(["scene", "check", str(path)]) == 2
    assert f"[model] {key} names {tmp_path / 't.ply'}, which is not a .npz" in one_line_error(capsys)


def test_scene_check_of_a_shipped_scene_with_its_tables_is_valid(capsys):
    assert main(["scene", "check", "builtin:converged"]) == 0
    assert "valid" in capsys.readouterr().out


@pytest.mark.parametrize("modulus", [1e300, 1e6, 0.01])
def test_a_youngs_modulus_far_outside_any_elastomer_is_refused(modulus):
    """1e300 kPa passed, and forward answered zero growth in silence."""
    with pytest.raises(SceneError, match=r"\[material\] youngs_modulus_kpa .*0\.1 kPa .*100 MPa"):
        scene(material={"youngs_modulus_kpa": modulus})


def test_scene_check_refuses_a_chamber_group_the_builtin_mesh_lacks(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text('[phantom]\nmesh = "builtin:prostate"\nchambers = ["chamber0", "nope"]\n[material]\n')
    assert main(["scene", "check", str(path)]) == 2
    assert "chambers names 'nope'" in one_line_error(capsys)


def test_the_shipped_scenes_still_load():
    for name in BUILTIN_SCENES:
        load_scene(name)
    for path in SCENES_DIR.glob("*.toml"):
        load_scene(path)
