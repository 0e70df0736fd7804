"""Writers that report a failed or short write (issue 23, defect 8): on a full disk `phantom mesh --out` and
`forward --out x.msh` exited 0 with "wrote" and a truncated file (gmsh does not report a failed write). The disk
is filled here by a file-size limit (RLIMIT_FSIZE) on the command: its writes past the limit fail as on a full
disk."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from phantom import PhantomError, written_atomically
from phantom.model.errors import MeshError
from phantom.model.mesh.tetmesh import read_mesh, write_mesh

PHANTOM = Path(sys.executable).with_name("phantom")


def limited_to(size_bytes: int) -> list[str]:
    """The command prefix that runs a command with RLIMIT_FSIZE at ``size_bytes`` (util-linux's prlimit: a
    ``preexec_fn`` would fork this process, which may hold JAX's threads from another test)."""
    return ["prlimit", f"--fsize={size_bytes}"]


@pytest.mark.parametrize("suffix", [".msh", ".vtu"])
def test_a_mesh_written_to_a_full_disk_is_an_error_and_leaves_no_file(tmp_path, suffix):
    out = tmp_path / f"mesh{suffix}"
    result = subprocess.run([*limited_to(20_000), str(PHANTOM), "mesh", "--scene", "builtin:calibrated", "--out",
                             str(out)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stdout + result.stderr
    assert "cannot write" in result.stderr and "wrote" not in result.stdout
    assert list(tmp_path.iterdir()) == []                       # no truncated file, no temporary left


def test_a_mesh_overwritten_on_a_full_disk_keeps_its_old_content(tmp_path):
    out = tmp_path / "mesh.msh"
    first = subprocess.run([str(PHANTOM), "mesh", "--scene", "builtin:calibrated", "--out", str(out)],
                           capture_output=True, text=True, timeout=120)
    assert first.returncode == 0 and "wrote" in first.stdout
    whole = out.read_bytes()
    again = subprocess.run([*limited_to(20_000), str(PHANTOM), "mesh", "--scene", "builtin:calibrated", "--out",
                            str(out)], capture_output=True, text=True, timeout=120)
    assert again.returncode == 2
    assert out.read_bytes() == whole
    assert oct(out.stat().st_mode & 0o777) == oct(0o666 & ~current_umask())


def current_umask() -> int:
    umask = os.umask(0o022)
    os.umask(umask)
    return umask


def test_a_mesh_with_a_coordinate_that_is_not_finite_is_not_written(tmp_path):
    good = tmp_path / "good.msh"
    subprocess.run([str(PHANTOM), "mesh", "--scene", "builtin:calibrated", "--out", str(good)], check=True,
                   capture_output=True, timeout=120)
    mesh = read_mesh(good, 1e-3)
    nodes_m = mesh.nodes_m.copy()
    nodes_m[7, 1] = np.nan
    broken = dataclasses.replace(mesh, nodes_m=nodes_m)
    with pytest.raises(MeshError, match="node 7 has a coordinate that is not finite"):
        write_mesh(broken, tmp_path / "broken.msh")
    assert not (tmp_path / "broken.msh").exists()


@pytest.mark.parametrize("suffix", [".msh", ".stl"])
def test_a_deformed_mesh_written_to_a_full_disk_is_an_error_and_leaves_no_file(tmp_path, suffix):
    out = tmp_path / f"deformed{suffix}"
    result = subprocess.run([*limited_to(20_000), str(PHANTOM), "forward", "--scene", "builtin:calibrated",
                             "--pressures-kpa", "1,1,1", "--out", str(out)], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 2, result.stdout + result.stderr
    assert "cannot write" in result.stderr and "wrote" not in result.stdout
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("folder", "says"), [("/proc", "No such file or directory"),
                                              ("/sys", "Permission denied"),
                                              ("missing", "No such file or directory")])
def test_a_file_in_a_folder_that_cannot_be_written_is_one_line(tmp_path, folder, says):
    """The temporary file beside the path was made outside the error's ``try``: a FileNotFoundError or
    PermissionError traceback after the work (``forward --out /proc/x.vtu``, ``corrections export --out
    /sys/m.csv``)."""
    path = (tmp_path / folder if folder == "missing" else Path(folder)) / "x.csv"
    with pytest.raises(PhantomError) as caught, written_atomically(path) as temporary:
        temporary.write_text("never written\n")
    assert str(caught.value) == f"cannot write {path}: {says} in {path.parent}: give a folder you can write"


def test_a_command_writing_into_a_folder_that_cannot_be_written_says_so_in_one_line():
    result = subprocess.run([str(PHANTOM), "mesh", "--scene", "builtin:calibrated", "--out", "/proc/x.msh"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr == ("phantom mesh: error: cannot write /proc/x.msh: No such file or directory in /proc: "
                             "give a folder you can write\n")
