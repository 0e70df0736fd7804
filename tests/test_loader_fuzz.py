"""Every loader of a file a user names, fed random and mutated files (hypothesis): each answers, or refuses with
one line (a PhantomError: exit status 2 from the command line), never a traceback, and never takes more than
MAX_MIB of memory (traced by tracemalloc, which sees NumPy's allocations) for a file of a few kilobytes.

The loaders: a scene (TOML), a rig calibration and a capture folder's capture.json (JSON), a NIfTI mask, the
table files a scene ships (.npz), a shape run's config.json and checkpoint."""

import copy
import json
import math
import tracemalloc
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from phantom import PhantomError
from phantom.model.scene import SCENES_DIR, builtin_scene_path, load_scene

#: The most memory (MiB) a loader may take for one of these files (each is under 100 KB).
MAX_MIB = 64
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                       HealthCheck.too_slow])

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10**12, 10**12) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12)


def answered_or_refused(load):
    """Run ``load``: a PhantomError of one line is a clean refusal; any other exception fails the test; the
    memory it took is bounded either way."""
    tracemalloc.start()
    try:
        load()
    except PhantomError as refusal:
        assert "\n" not in str(refusal), str(refusal)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < MAX_MIB * 2**20, f"took {peak / 2**20:.0f} MiB"


def leaf_paths(document, prefix=()):
    """The paths to every value of a nested dict/list document."""
    children = document.items() if isinstance(document, dict) else enumerate(document)
    paths = []
    for key, value in children:
        paths.append((*prefix, key))
        if isinstance(value, dict | list) and value:
            paths += leaf_paths(value, (*prefix, key))
    return paths


def mutated(data, document, values=json_values):
    """``document`` with one of its values (drawn) replaced by a drawn value, or a drawn key added or removed."""
    document = copy.deepcopy(document)
    path = data.draw(st.sampled_from(leaf_paths(document)))
    *parents, last = path
    parent = document
    for key in parents:
        parent = parent[key]
    action = data.draw(st.sampled_from(["replace", "remove", "add"]))
    if action == "replace" or not isinstance(parent, dict):
        parent[last] = data.draw(values)
    elif action == "remove":
        del parent[last]
    else:
        parent[data.draw(st.text(max_size=12))] = data.draw(values)
    return document


def mutated_bytes(data, original):
    """``original`` with a few bytes overwritten, or cut short."""
    content = bytearray(original)
    if data.draw(st.booleans()):
        return bytes(content[:data.draw(st.integers(0, len(content)))])
    for _ in range(data.draw(st.integers(1, 8))):
        content[data.draw(st.integers(0, len(content) - 1))] = data.draw(st.integers(0, 255))
    return bytes(content)


# --- scenes ---------------------------------------------------------------------------------------------------

toml_values = st.recursive(
    st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=3),
    max_leaves=8)


@FUZZ
@given(data=st.data())
def test_a_mutated_scene_is_read_or_refused(data):
    from phantom.model.scene import read_scene_toml, scene_from_dict

    source = builtin_scene_path("builtin:converged")
    document = mutated(data, read_scene_toml(source), toml_values)
    answered_or_refused(lambda: scene_from_dict(document, source))


@FUZZ
@given(data=st.data())
def test_a_damaged_scene_file_is_read_or_refused(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("scene") / "scene.toml"
    path.write_bytes(mutated_bytes(data, builtin_scene_path("builtin").read_bytes()))
    answered_or_refused(lambda: load_scene(path))


# --- rig and capture files ------------------------------------------------------------------------------------

@FUZZ
@given(data=st.data())
def test_a_mutated_rig_file_is_read_or_refused(tmp_path_factory, data):
    from phantom.scan.camera import Rig, virtual_rig

    path = tmp_path_factory.mktemp("rig") / "rig.json"
    text = json.dumps(mutated(data, virtual_rig(0.25).to_json()))
    path.write_text(text if data.draw(st.booleans()) else mutated_bytes(data, text.encode()).decode("latin-1"))
    answered_or_refused(lambda: Rig.load(path))


@FUZZ
@given(data=st.data())
def test_a_mutated_capture_file_is_read_or_refused(tmp_path_factory, data):
    from phantom.scan.capture import CaptureFolder

    frames = [{"index": k, "image": f"images/{k:04d}.png", "orbit_deg": 30.0 * k, "elevation_deg": 0.0,
               "pressures_kpa": [1.0, 2.0, 0.5], "time_utc": "", "time_s": 0.5 * k} for k in range(3)]
    document = {"format": "phantom-capture/1", "status": "complete", "reason": None, "camera": {}, "plan": {},
                "conditions": {}, "rig": None, "frames": frames}
    folder = tmp_path_factory.mktemp("capture")
    (folder / "capture.json").write_text(json.dumps(mutated(data, document)))

    def load():
        opened = CaptureFolder.open(folder)
        for frame in opened.frames:
            assert math.isfinite(frame.orbit_deg) and math.isfinite(frame.elevation_deg)

    answered_or_refused(load)


# --- NIfTI masks ----------------------------------------------------------------------------------------------

@FUZZ
@given(data=st.data())
def test_a_damaged_nifti_mask_is_read_or_refused(tmp_path_factory, data):
    nibabel = pytest.importorskip("nibabel")
    from phantom.shape.dataset import find_cases, read_label_mask

    values = np.zeros((12, 12, 12), np.uint8)
    values[3:9, 4:8, 2:10] = 1
    folder = tmp_path_factory.mktemp("nifti")
    nibabel.save(nibabel.Nifti1Image(values, np.diag([0.8, 0.8, 2.0, 1.0])), str(folder / "good.nii"))
    original = (folder / "good.nii").read_bytes()
    # the header (348 bytes) is where a damaged file hurts: shape, dtype, scaling, affine
    content = bytearray(original)
    for _ in range(data.draw(st.integers(1, 6))):
        content[data.draw(st.integers(0, 351))] = data.draw(st.integers(0, 255))
    path = folder / "case.nii"
    path.write_bytes(bytes(content) if data.draw(st.booleans()) else mutated_bytes(data, original))

    def load():
        mask = read_label_mask(find_cases(path)[0])
        assert mask.mask.dtype == bool and np.all(np.isfinite(mask.affine))

    # the good file first, untraced: the modules its reading imports on first use (tens of MiB, once per process,
    # whichever test of this worker comes first) are not what the damaged file costs
    read_label_mask(find_cases(folder / "good.nii")[0])

    answered_or_refused(load)


# --- table files ----------------------------------------------------------------------------------------------

def _read_table(path):
    from phantom.model.fidelity.table_files import read_members, read_provenance, table_members

    read_provenance(path, "the table", "write it again")
    return read_members(path, table_members(3, 7, False), "the table", "write it again")


@FUZZ
@given(data=st.data())
def test_a_damaged_table_file_is_read_or_refused(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("table") / "volumes.npz"
    path.write_bytes(mutated_bytes(data, (SCENES_DIR / "prostate_converged.volumes.npz").read_bytes()))
    answered_or_refused(lambda: _read_table(path))


@FUZZ
@given(data=st.data())
def test_a_table_file_of_mutated_arrays_is_read_or_refused(tmp_path_factory, data):
    with np.load(SCENES_DIR / "prostate_converged.volumes.npz") as stored:
        arrays = dict(stored)
    name = data.draw(st.sampled_from(sorted(arrays)))
    shape = tuple(data.draw(st.lists(st.integers(0, 9), max_size=4)))
    dtype = data.draw(st.sampled_from([np.float64, np.float32, np.int32, np.bool_, np.uint8]))
    with np.errstate(over="ignore", invalid="ignore"):  # NaN or 1e300 cast to an integer: what a damaged file holds
        arrays[name] = np.full(shape, data.draw(st.floats(allow_nan=True, allow_infinity=True))).astype(dtype)
    path = tmp_path_factory.mktemp("table") / "volumes.npz"
    with zipfile.ZipFile(path, "w") as archive:
        for key, value in arrays.items():
            with archive.open(f"{key}.npy", "w") as stream:
                np.lib.format.write_array(stream, np.asarray(value))
    answered_or_refused(lambda: _read_table(path))


# --- shape runs -----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    jax = pytest.importorskip("jax")
    from phantom.shape.checkpoint import write_checkpoint, write_config
    from phantom.shape.vae import VAEConfig, init_parameters

    run = tmp_path_factory.mktemp("run")
    network = VAEConfig(grid_size=8, latent_dim=4, channels=(4, 8))
    write_checkpoint(run, *init_parameters(network, jax.random.PRNGKey(0)))
    write_config(run, network, {}, {"voxel_mm": 2.0, "grid_size": 8, "labels": [1], "names": [], "held_out": []},
                 1, 1.0, "cpu")
    return run


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_mutated_run_config_is_read_or_refused(run_folder, tmp_path_factory, data):
    from phantom.shape.checkpoint import read_run

    run = tmp_path_factory.mktemp("run")
    (run / "parameters.npz").write_bytes((run_folder / "parameters.npz").read_bytes())
    document = mutated(data, json.loads((run_folder / "config.json").read_text()))
    (run / "config.json").write_text(json.dumps(document))
    answered_or_refused(lambda: read_run(run))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_damaged_checkpoint_is_read_or_refused(run_folder, tmp_path_factory, data):
    from phantom.shape.checkpoint import read_run

    run = tmp_path_factory.mktemp("run")
    (run / "config.json").write_text((run_folder / "config.json").read_text())
    (run / "parameters.npz").write_bytes(mutated_bytes(data, (run_folder / "parameters.npz").read_bytes()))
    answered_or_refused(lambda: read_run(run))
