"""The table files a scene ships, damaged or oversized: each is refused as a SceneError (exit status 2, which the
daemon's systemd unit does not restart on) naming the file and what to do, never a traceback, and only the arrays
a table uses are read (phantom.model.fidelity.table_files)."""

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from phantom.model import SceneError
from phantom.model.fidelity.table_files import Member, read_members
from phantom.model.scene import SCENES_DIR

PHANTOM = Path(sys.executable).parent / "phantom"
VOLUMES = SCENES_DIR / "prostate_converged.volumes.npz"
SHAPES = SCENES_DIR / "prostate_converged.shapes.npz"
#: The most memory (MiB) `phantom inverse` on builtin:converged may take with a table file of an unused 1 GiB
#: member: the command alone takes 110 MiB.
MAX_RSS_MIB = 300


def _arrays(path):
    with np.load(path) as stored:
        return dict(stored)


def _scene(tmp_path, volumes=None, shapes=None):
    """A copy of builtin:converged that ships these table files (the shipped ones where None)."""
    text = (SCENES_DIR / "prostate_converged.toml").read_text()
    lines = [line for line in text.splitlines() if not line.startswith(("table_volumes", "table_shapes"))]
    lines.append(f'table_volumes = "{volumes or VOLUMES}"')
    lines.append(f'table_shapes = "{shapes or SHAPES}"')
    path = tmp_path / "scene.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _inverse(scene, *wrapper):
    return subprocess.run([*wrapper, str(PHANTOM), "inverse", "--scene", str(scene), "--volume-ml", "30", "--json"],
                          capture_output=True, text=True, timeout=300)


def _with_member(path, source, name, header_shape, data=b"", compression=zipfile.ZIP_STORED):
    """``source``'s arrays and a member ``name`` whose .npy header declares ``header_shape`` (float64)."""
    np.savez(path, **{key: value for key, value in _arrays(source).items() if key != name})
    header = {"descr": "<f8", "fortran_order": False, "shape": header_shape}
    # (the fastest deflate: 512 MiB of zeros took 2.5 s at the default level, 0.9 s at 1)
    with zipfile.ZipFile(path, "a", compression, compresslevel=1) as archive, \
            archive.open(f"{name}.npy", "w") as stream:
        np.lib.format.write_array_header_1_0(stream, header)
        stream.write(data)
    return path


def _changed(path, source, **arrays):
    fields = {**_arrays(source), **arrays}
    np.savez(path, **{key: value for key, value in fields.items() if value is not None})
    return path


def _volumes_case(tmp_path, case):
    """A damaged volumes file and what its refusal says."""
    v = tmp_path / "v.npz"
    chamber = _arrays(VOLUMES)["chamber"]
    if case == "provenance a list":
        return _changed(v, VOLUMES, provenance=json.dumps([1, 2])), "provenance is not a JSON object"
    if case == "missing array":
        return _changed(v, VOLUMES, gland=None), "it has no array 'gland'"
    if case == "a 10^12 header":
        return _with_member(v, VOLUMES, "gland", (10**12,)), "its array 'gland' is float64 of shape (1000000000000,)"
    if case == "NaN":
        return _changed(v, VOLUMES, chamber=np.where(chamber > 0, np.nan, 0)), "'chamber' holds NaN"
    if case == "another grid":
        return _changed(v, VOLUMES, chamber=chamber[:5]), "its array 'chamber' is float64 of shape (5, 7, 7, 3)"
    import pickle

    v.write_bytes(pickle.dumps({"chamber": [1, 2, 3]}))
    return v, "is damaged (BadZipFile"


@pytest.mark.parametrize("case", ["provenance a list", "missing array", "a 10^12 header", "NaN", "another grid",
                                  "a pickle"])
def test_a_damaged_volumes_file_is_exit_2_naming_it_and_how_to_make_it_again(tmp_path, case):
    """Tracebacks with exit 1 from inverse and the daemon (which systemd restarted in a loop); NaN was served."""
    path, message = _volumes_case(tmp_path, case)
    result = _inverse(_scene(tmp_path, volumes=path))
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert "write the file again for this model (phantom model table SCENE --out FILE)" in result.stderr


@pytest.mark.parametrize(("change", "message"), [
    ({"nodes": lambda a: -a}, "not distinct, sorted, non-negative indices"),
    ({"nodes": lambda a: a[::-1].copy()}, "not distinct, sorted, non-negative indices"),
    ({"coefficients": lambda a: a[..., :5].copy()}, "nodes, modes and rest positions do not agree"),
    ({"modes_m": lambda a: a[:, :, :2].copy()}, "its array 'modes_m' is float32 of shape (19, 1718, 2)"),
    ({"nodes": lambda a: a.astype(float)}, "its array 'nodes' is float64"),
])
def test_a_damaged_shapes_file_is_exit_2(tmp_path, change, message):
    fields = _arrays(SHAPES)
    (name, function), = change.items()
    path = _changed(tmp_path / "s.npz", SHAPES, **{name: function(fields[name])})
    result = _inverse(_scene(tmp_path, shapes=path))
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr


@pytest.mark.slow  # 4.3 s CPU deflating the 1 GiB member (larger than MAX_RSS_MIB, or it could not fail)
def test_an_unused_member_is_not_read(tmp_path):
    """An .npz with an unused, deflated 3 GB member took 3.1 GB: only the table's arrays are read (1 GiB here)."""
    path = tmp_path / "v.npz"
    np.savez(path, **_arrays(VOLUMES))
    chunk = bytes(2**24)
    with zipfile.ZipFile(path, "a", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("unused.npy", "w", force_zip64=True) as stream:
            np.lib.format.write_array_header_1_0(stream, {"descr": "|u1", "fortran_order": False,
                                                          "shape": (2**30,)})
            for _ in range(2**30 // len(chunk)):
                stream.write(chunk)
    assert path.stat().st_size < 2**23
    probe = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, capture_output=True); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    result = _inverse(_scene(tmp_path, volumes=path), sys.executable, "-c", probe)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout) / 1024 < MAX_RSS_MIB


def test_an_oversized_member_is_refused_from_the_zip_directory(tmp_path):
    path = _with_member(tmp_path / "v.npz", VOLUMES, "gland", (2**26,), bytes(2**29), zipfile.ZIP_DEFLATED)
    with pytest.raises(SceneError, match=r"its array 'gland' is 512 MiB, more than the 256 MiB of any table's"):
        read_members(path, {"gland": Member((None,))}, "the table", "write it again")


def test_a_header_larger_than_its_data_is_refused_before_reading(tmp_path):
    path = _with_member(tmp_path / "v.npz", VOLUMES, "gland", (10**12,), bytes(64))
    with pytest.raises(SceneError, match=r"its array 'gland' declares \(1000000000000,\) but holds"):
        read_members(path, {"gland": Member((None,))}, "the table", "write it again")


def test_the_daemon_exits_with_the_status_its_unit_does_not_restart_on(tmp_path):
    """A damaged table file was a traceback and exit 1, which systemd restarted in a loop."""
    unit = (Path(__file__).parents[1] / "host" / "systemd" / "phantomd.service").read_text()
    no_restart = next(line.split("=")[1].split() for line in unit.splitlines()
                      if line.startswith("RestartPreventExitStatus="))
    path, _ = _volumes_case(tmp_path, "provenance a list")
    result = subprocess.run([str(PHANTOM), "daemon", "--scene", str(_scene(tmp_path, volumes=path)), "--socket",
                             str(tmp_path / "api.sock"), "--port", str(tmp_path / "no-board")],
                            capture_output=True, text=True, timeout=300)
    assert str(result.returncode) in no_restart, result.stderr
    assert "provenance is not a JSON object" in result.stderr and "Traceback" not in result.stderr
