"""``phantom shape encode`` gives latent vectors of glands only: a mask of a few voxels is refused in one line that
says its volume and the volumes the run was trained on, while a gland of the population still encodes."""

import json

import numpy as np
import pytest

pytest.importorskip("jax")
nibabel = pytest.importorskip("nibabel")
pytest.importorskip("skimage")

from phantom.cli.main import main  # noqa: E402
from phantom.shape.dataset import load_shapes  # noqa: E402
from phantom.shape.synthetic import synthesize  # noqa: E402
from phantom.shape.training import TrainConfig, train  # noqa: E402
from phantom.shape.vae import VAEConfig  # noqa: E402

pytestmark = pytest.mark.slow
GRID = 16


def trained_run(folder):
    """Four synthetic cases and a run of one epoch on them: what is refused or encoded does not depend on how well
    the network learned."""
    synthesize(folder / "population", cases=4, seed=5, images=False)
    shapes = load_shapes(folder / "population", grid_size=GRID, workers=1)
    return train(shapes, folder / "run", VAEConfig(grid_size=GRID, channels=(8, 16)),
                 TrainConfig(epochs=1, batch_size=2, validation_fraction=0.25, seed=1), on_epoch=None)


def test_encode_refuses_a_speck_with_its_volume_and_the_runs_and_still_encodes_a_gland(tmp_path, capsys):
    run = trained_run(tmp_path)
    speck = np.zeros((30, 30, 20), np.uint8)
    speck[13:16, 13:16, 9:11] = 1   # 18 voxels: 0.0123 ml, far below any gland, yet on the run's grid
    path = tmp_path / "speck.nii.gz"
    nibabel.save(nibabel.Nifti1Image(speck, np.diag([0.7, 0.7, 1.4, 1.0])), str(path))
    assert main(["shape", "encode", str(run), str(path)]) == 2
    captured = capsys.readouterr()
    error = captured.err.strip()
    assert captured.out == "" and len(error.splitlines()) == 1 and error.startswith("phantom shape: error: ")
    trained_ml = np.load(run / "latents.npz")["volumes_ml"]
    assert f"{path}: the shape is 0.0123 ml, no gland's size (2-400 ml)" in error
    assert f"this run was trained on {trained_ml.min():.1f}-{trained_ml.max():.1f} ml" in error

    gland = tmp_path / "population" / "data" / "000001_mask.nii"
    assert main(["shape", "encode", str(run), str(gland), "--json"]) == 0
    latent = json.loads(capsys.readouterr().out)["latent"]
    assert len(latent) == json.loads((run / "config.json").read_text())["vae"]["latent_dim"]
    assert np.all(np.isfinite(latent))
