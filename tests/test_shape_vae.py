"""The VAE's layers against XLA's own convolution, its parameters' round trip through a checkpoint, and short
trainings: reproducible with a seed, the run folder readable (the loss curves' .rrd read back), bad runs refused."""

import json

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("optax")

from jax import lax  # noqa: E402

from phantom.shape.analysis import ShapeModel  # noqa: E402
from phantom.shape.dataset import ShapeSet  # noqa: E402
from phantom.shape.errors import ShapeError  # noqa: E402
from phantom.shape.training import TrainConfig, compute_device, intersection_over_union, split_cases, train  # noqa: E402
from phantom.shape.vae import (  # noqa: E402
    VAEConfig,
    decode_logits,
    encode,
    flatten,
    init_parameters,
    strided_convolution,
    subpixel_convolution,
    unflatten_like,
)

TINY = VAEConfig(grid_size=8, latent_dim=4, channels=(4, 8))


@pytest.mark.slow
def test_the_strided_convolution_is_xlas_stride_2_convolution():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 8, 8, 8, 3)).astype(np.float32)
    for k in (3, 5):
        weight = rng.normal(size=(k, k, k, 3, 5)).astype(np.float32)
        pad = (k - 1) // 2
        expected = lax.conv_general_dilated(x, weight, (2, 2, 2), ((pad, pad),) * 3,
                                            dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
        np.testing.assert_allclose(strided_convolution(x, weight), expected, rtol=1e-4, atol=1e-4)


def test_the_subpixel_convolution_puts_each_channel_group_at_its_offset():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(1, 3, 3, 3, 2)).astype(np.float32)
    weight = np.zeros((3, 3, 3, 2, 8 * 4), np.float32)
    mixing = rng.normal(size=(2, 8 * 4)).astype(np.float32)
    weight[1, 1, 1] = mixing  # the centre tap only: each output voxel sees its own input voxel
    bias = rng.normal(size=8 * 4).astype(np.float32)
    y = np.asarray(subpixel_convolution(x, weight, bias))
    assert y.shape == (1, 6, 6, 6, 4)
    for a in range(2):
        for b in range(2):
            for c in range(2):
                group = (a * 2 + b) * 2 + c
                expected = x[0] @ mixing[:, group * 4:(group + 1) * 4] + bias[group * 4:(group + 1) * 4]
                np.testing.assert_allclose(y[0, a::2, b::2, c::2], expected, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_encode_and_decode_shapes_and_a_checkpoints_round_trip():
    params, statistics = init_parameters(TINY, jax.random.PRNGKey(0))
    occupancy = np.random.default_rng(2).uniform(size=(3, 8, 8, 8)).astype(np.float32)
    mean, log_variance, _ = encode(params, statistics, TINY, occupancy)
    logits, _ = decode_logits(params, statistics, TINY, mean)
    assert mean.shape == log_variance.shape == (3, 4) and logits.shape == (3, 8, 8, 8)
    arrays = flatten(params)
    assert "encoder/0/weight" in arrays and arrays["encoder/0/weight"].shape == (3, 3, 3, 1, 4)
    restored = unflatten_like(init_parameters(TINY, jax.random.PRNGKey(9))[0], arrays, "test")
    for path, value in flatten(restored).items():
        np.testing.assert_array_equal(value, arrays[path])
    wider = init_parameters(VAEConfig(grid_size=8, latent_dim=4, channels=(4, 16)), jax.random.PRNGKey(0))[0]
    with pytest.raises(ShapeError, match="has shape"):
        unflatten_like(wider, arrays, "test")
    with pytest.raises(ShapeError, match="another architecture"):
        unflatten_like(init_parameters(VAEConfig(grid_size=8, channels=(4,)), jax.random.PRNGKey(0))[0] | {
            "extra": np.zeros(1)}, arrays, "test")


def test_bad_settings_are_refused():
    with pytest.raises(ShapeError, match="multiple of 2\\^3"):
        VAEConfig(grid_size=20)
    with pytest.raises(ShapeError, match="odd"):
        VAEConfig(kernel_size=4)
    with pytest.raises(ShapeError, match="unknown VAE settings"):
        VAEConfig.from_dict({"depth": 3})
    with pytest.raises(ShapeError, match="validation_fraction"):
        TrainConfig(validation_fraction=1.0)
    with pytest.raises(ShapeError, match="leave 1 to train on"):
        split_cases(3, 0.5, 0)


def _ellipsoids(count, seed):
    """Occupancy grids of random axis-aligned ellipsoids on an 8^3 grid."""
    rng = np.random.default_rng(seed)
    axis = np.arange(8) - 3.5
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    grids = [((x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2 < 1).astype(np.float32)
             for a, b, c in rng.uniform(1.5, 3.5, (count, 3))]
    return ShapeSet([f"e{i}" for i in range(count)], np.stack(grids), 2.0, np.ones(count), (1,))


@pytest.mark.slow
def test_a_seed_makes_training_reproducible_and_the_run_loads(tmp_path):
    shapes = _ellipsoids(6, 0)
    runs = [train(shapes, tmp_path / name, TINY, TrainConfig(epochs=3, batch_size=2, seed=seed,
                                                             validation_fraction=0.3, checkpoint_every=2),
                  on_epoch=None)
            for name, seed in (("a", 7), ("b", 7), ("c", 8))]
    stored = [dict(np.load(run / "parameters.npz")) for run in runs]
    for name in stored[0]:
        np.testing.assert_array_equal(stored[0][name], stored[1][name])
    assert any(not np.array_equal(stored[0][name], stored[2][name]) for name in stored[0])
    config = json.loads((runs[0] / "config.json").read_text())
    assert config["format"] == "phantom-shape-run" and config["epochs_done"] == 3
    assert config["device"] == compute_device() == jax.devices()[0].platform  # this machine has no GPU: "cpu"
    assert config["data"]["voxel_mm"] == 2.0 and len(config["data"]["held_out"]) == 2
    history = json.loads((runs[0] / "history.json").read_text())
    assert [entry["epoch"] for entry in history] == [1, 2, 3]
    assert all(0.0 <= entry["validation_iou"] <= 1.0 for entry in history)
    assert (runs[0] / "loss.png").stat().st_size > 1000
    model = ShapeModel.load(runs[0])
    names, latents = model.case_latents()
    assert names == shapes.names and latents.shape == (6, 4)
    np.testing.assert_allclose(model.encode_grids(shapes.occupancy), latents, rtol=1e-5, atol=1e-5)
    assert model.decode_grids(latents).shape == (6, 8, 8, 8)
    _the_loss_recording_reads_back(runs[0] / "loss.rrd", epochs=3)
    (runs[2] / "parameters.npz").unlink()
    with pytest.raises(ShapeError, match="no parameters.npz"):
        ShapeModel.load(runs[2])


def _the_loss_recording_reads_back(path, epochs):
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    rows = {}
    for chunk in RrdReader(str(path)).stream().collect().stream():
        batch = chunk.to_record_batch()
        entity = batch.schema.metadata.get(b"rerun:entity_path", b"").decode()
        rows[entity] = rows.get(entity, 0) + batch.num_rows
    assert rows.get("/loss/training") == epochs and rows.get("/held_out_iou") == epochs


def test_a_run_folder_that_is_not_a_run_is_refused(tmp_path):
    with pytest.raises(ShapeError, match="no such run folder"):
        ShapeModel.load(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ShapeError, match="not a trained run \\(no config.json\\)"):
        ShapeModel.load(tmp_path / "empty")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "config.json").write_text('{"format": "something else"}')
    np.savez(tmp_path / "other" / "parameters.npz", x=np.zeros(1))
    with pytest.raises(ShapeError, match="not a phantom-shape-run"):
        ShapeModel.load(tmp_path / "other")


def test_intersection_over_union():
    a = np.zeros((1, 4, 4, 4))
    b = np.zeros((1, 4, 4, 4))
    a[0, :2] = 1.0
    b[0, 1:3] = 0.9
    assert intersection_over_union(a, b)[0] == pytest.approx(1 / 3)


def _run_folder(path, network=TINY, **config_changes):
    """A run folder of ``network``'s initial weights, as training writes one, with ``config_changes`` made."""
    from phantom.shape.checkpoint import write_checkpoint, write_config

    path.mkdir()
    params, statistics = init_parameters(network, jax.random.PRNGKey(0))
    write_checkpoint(path, params, statistics)
    write_config(path, network, {}, {"voxel_mm": 2.0, "grid_size": network.grid_size, "labels": [1], "names": [],
                                     "held_out": []}, 1, 1.0, "cpu")
    config = json.loads((path / "config.json").read_text())
    for key, value in config_changes.items():
        if key.startswith("vae."):
            config["vae"][key[4:]] = value
        elif value is None:
            del config[key]
        else:
            config[key] = value
    (path / "config.json").write_text(json.dumps(config))
    return path


@pytest.mark.parametrize(("changes", "message"), [
    ({"vae": None}, "the run's config has no vae settings"),
    ({"vae": [1, 2]}, "the VAE settings must be a JSON object"),
    ({"vae.latent_dim": 10**9}, "latent_dim = 1000000000 is more than the 4096 a shape network has"),
    ({"vae.latent_dim": 4.5}, "latent_dim must be a whole number, got 4.5"),
    ({"vae.grid_size": "8"}, "grid_size must be a whole number, got '8'"),
    ({"vae.channels": [4, 10**6]}, "channels = 1000000 is more than the 1024"),
    ({"vae.channels": "4,8"}, "channels must be a list of whole numbers"),
    ({"vae.negative_slope": None}, "negative_slope must be a finite number, got None"),
    ({"vae.latent_dim": 5}, "its array 'params/expand/weight' is float32 of shape (4, 64), not 5 x 64"),
    ({"data": {"voxel_mm": float("nan"), "grid_size": 8}}, "the run's data settings must hold voxel_mm"),
    ({"data": {"voxel_mm": 2.0, "grid_size": 16}}, "grid_size (8, the network's)"),
])
def test_a_foreign_run_config_is_refused_before_any_network_is_built(tmp_path, changes, message):
    """A config.json without vae was a KeyError; latent_dim 1e9 took 7.9 GB, then a JAX abort."""
    run = _run_folder(tmp_path / "run", **changes)
    with pytest.raises(ShapeError, match=message.replace("(", r"\(").replace(")", r"\)")) as raised:
        ShapeModel.load(run)
    assert "\n" not in str(raised.value)


def test_a_checkpoint_that_is_a_pickle_or_holds_nan_is_refused(tmp_path):
    """A pickle as parameters.npz was a ValueError traceback."""
    import pickle

    run = _run_folder(tmp_path / "run")
    good = dict(np.load(run / "parameters.npz"))
    (run / "parameters.npz").write_bytes(pickle.dumps({"params/latent/weight": [1.0]}))
    with pytest.raises(ShapeError, match="is damaged .*train the run again"):
        ShapeModel.load(run)
    np.savez(run / "parameters.npz", **{**good, "params/latent/bias": np.full(8, np.nan, np.float32)})
    with pytest.raises(ShapeError, match="'params/latent/bias' holds NaN"):
        ShapeModel.load(run)
    np.savez(run / "parameters.npz", **good)
    assert ShapeModel.load(run).vae == TINY


def test_a_damaged_latents_file_is_refused(tmp_path):
    """latents.npz was read with np.load whole: a pickle was a ValueError traceback, a missing array a KeyError."""
    run = _run_folder(tmp_path / "run")
    model = ShapeModel.load(run)
    (run / "latents.npz").write_bytes(b"\x80\x04not an npz")
    with pytest.raises(ShapeError, match="is damaged .*train the run again"):
        model.case_latents()
    np.savez(run / "latents.npz", names=np.array(["a", "b"]))
    with pytest.raises(ShapeError, match="it has no array 'mean'"):
        model.case_latents()
    np.savez(run / "latents.npz", names=np.array(["a", "b"]), mean=np.zeros((3, 4)))
    with pytest.raises(ShapeError, match="name 2 cases for 3 latent vectors"):
        model.case_latents()
    np.savez(run / "latents.npz", names=np.array(["a", "b"]), mean=np.ones((2, 4)))
    assert model.case_latents()[0] == ["a", "b"]


@pytest.mark.slow
def test_time_left_leaves_out_the_compiling_first_epoch_and_a_short_run_is_warned_about(tmp_path, capsys):
    """The first epoch compiles the network (4:26 was predicted for a 55 s run); the time left is the mean of the
    epochs after it. A run whose held-out IoU is under the threshold gets a warning from train, average and
    compare, saying what it means."""
    from phantom.cli.shape import _warn_if_undertrained
    from phantom.shape.training import IOU_WARNING_BELOW, run_held_out_iou

    seen = []
    run = train(_ellipsoids(6, 0), tmp_path / "run", TINY, TrainConfig(epochs=3, batch_size=2,
                                                                         validation_fraction=0.3),
                on_epoch=lambda record, epochs, left: seen.append((record.seconds, left)))
    assert np.isnan(seen[0][1])
    assert seen[1][1] == pytest.approx(seen[1][0] * 1) and seen[2][1] == 0.0
    iou, epochs = run_held_out_iou(run)
    history = json.loads((run / "history.json").read_text())
    assert (iou, epochs) == (history[-1]["validation_iou"], 3)
    assert iou < IOU_WARNING_BELOW  # three epochs of a tiny network reconstruct little
    _warn_if_undertrained(run)
    warning = capsys.readouterr().err
    assert f"held-out reconstruction IoU is {iou:.2f} after 3 epochs, below {IOU_WARNING_BELOW:g}" in warning
    assert "train more epochs" in warning


def test_the_iou_warning_threshold():
    from phantom.shape.training import IOU_WARNING_BELOW, held_out_iou_warning, run_held_out_iou

    assert held_out_iou_warning(IOU_WARNING_BELOW, 100) is None
    assert held_out_iou_warning(None, 100) is None  # nothing held out: nothing measured, nothing claimed
    assert "0.51 after 6 epochs" in held_out_iou_warning(0.51, 6)
    assert run_held_out_iou("/nonexistent/run") == (None, 0)
