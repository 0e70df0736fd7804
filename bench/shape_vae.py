"""The shape VAE: time per epoch at the paper's sizes on this machine, and a trained synthetic run's average
against the population's known mean shape.

    python bench/shape_vae.py [--run out/shape-run] [--steps 5]

1. Time per epoch at the paper's sizes: 589 cases, batch 10 (58 steps an epoch, the last part-batch dropped),
   a 32^3 grid, latent 64, on the CPU (jax.devices() is printed; no GPU was lent to this task: on a machine with
   one, `pip install 'jax[cuda12]'` runs the same code there). The peer, timed in the same run: the same network
   with XLA's own strided and transposed convolutions (``lax.conv_general_dilated`` with window strides,
   ``lax.conv_transpose``), the layers a library's Conv3d/ConvTranspose3d produce. The ratio is what the
   slice-and-matmul strided convolution and the depth-to-space upsampling buy on a CPU.
2. With ``--run`` (a run trained on ``phantom shape synthesize`` output): the decoded average against the
   population's known mean shape, the phantom's body (26.3 ml): volumes, IoU of the two on the run's grid, mean
   closest-point distance after ICP and latent distance.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax

from phantom.shape import vae as network
from phantom.shape.vae import VAEConfig

PAPER_CASES = 589
PAPER_BATCH = 10


def library_layers_loss(params, statistics, config, occupancy, key, kld_weight):
    """The same network and loss as phantom.shape.vae.loss_terms, with XLA's strided and transposed
    convolutions in place of the slice-and-matmul strided convolution and the depth-to-space upsampling."""
    numbers = ("NDHWC", "DHWIO", "NDHWC")
    x = occupancy[..., None]
    for layer, running in zip(params["encoder"], statistics["encoder"], strict=True):
        x = lax.conv_general_dilated(x, layer["weight"], (2, 2, 2), ((1, 1),) * 3, dimension_numbers=numbers)
        x, _ = network.batch_norm(x + layer["bias"], layer, running, config, True)
        x = jax.nn.leaky_relu(x, config.negative_slope)
    h = x.reshape(x.shape[0], -1) @ params["latent"]["weight"] + params["latent"]["bias"]
    mean, log_variance = h[:, :config.latent_dim], h[:, config.latent_dim:]
    latent = mean + jnp.exp(0.5 * log_variance) * jax.random.normal(key, mean.shape)
    y = jax.nn.leaky_relu(latent @ params["expand"]["weight"] + params["expand"]["bias"], config.negative_slope)
    side = config.coarsest_side
    y = y.reshape(-1, side, side, side, config.channels[-1])
    for level, layer in enumerate(params["decoder"]):
        # a transposed convolution of stride 2 to the layer's output channels (the first of its 8 groups)
        weight = layer["weight"][..., : layer["weight"].shape[-1] // 8]
        y = lax.conv_transpose(y, weight, (2, 2, 2), "SAME", dimension_numbers=numbers)
        y = y + layer["bias"][: weight.shape[-1]]
        if level < len(statistics["decoder"]):
            y, _ = network.batch_norm(y, layer, statistics["decoder"][level], config, True)
            y = jax.nn.leaky_relu(y, config.negative_slope)
    logits = y[..., 0]
    bce = (jnp.maximum(logits, 0) - logits * occupancy + jnp.log1p(jnp.exp(-jnp.abs(logits)))).sum(axis=(1, 2, 3))
    kld = -0.5 * jnp.sum(1.0 + log_variance - mean**2 - jnp.exp(log_variance), axis=1)
    return bce.mean() + kld_weight * kld.mean(), (bce.mean(), kld.mean(), statistics)


def seconds_per_step(loss, config: VAEConfig, steps: int) -> tuple[float, float]:
    """(compile seconds, mean seconds per optimiser step) of a batch of PAPER_BATCH random shapes."""
    params, statistics = network.init_parameters(config, jax.random.PRNGKey(0))
    optimiser = optax.adam(1e-3)
    state = optimiser.init(params)

    @jax.jit
    def step(params, statistics, state, batch, key):
        (value, (_, _, statistics)), grads = jax.value_and_grad(loss, has_aux=True)(params, statistics, config,
                                                                                    batch, key, 0.01)
        updates, state = optimiser.update(grads, state, params)
        return optax.apply_updates(params, updates), statistics, state, value

    batch = (np.random.default_rng(0).uniform(size=(PAPER_BATCH,) + (config.grid_size,) * 3) > 0.6).astype(
        np.float32)
    key = jax.random.PRNGKey(1)
    started = time.perf_counter()
    result = step(params, statistics, state, batch, key)
    jax.block_until_ready(result)
    compile_s = time.perf_counter() - started
    started = time.perf_counter()
    for _ in range(steps):
        result = step(*result[:3], batch, key)
    jax.block_until_ready(result)
    return compile_s, (time.perf_counter() - started) / steps


def epoch_table(steps: int) -> None:
    config = VAEConfig()
    steps_per_epoch = PAPER_CASES // PAPER_BATCH
    print(f"devices: {jax.devices()} (no GPU lent to this task)")
    print(f"paper's sizes: {PAPER_CASES} cases, batch {PAPER_BATCH} ({steps_per_epoch} steps an epoch), "
          f"{config.grid_size}^3 grid, latent {config.latent_dim}, channels {list(config.channels)}\n")
    print("| layers | compile (s) | s per step | s per epoch | 500 epochs (h) |")
    print("| --- | --- | --- | --- | --- |")
    rows = {}
    for name, loss, n in (("slices + matmul, depth-to-space (phantom.shape.vae)", network.loss_terms, steps),
                          ("XLA strided + transposed convolutions (peer)", library_layers_loss, max(1, steps // 3))):
        compile_s, step_s = seconds_per_step(loss, config, n)
        rows[name] = step_s
        print(f"| {name} | {compile_s:.1f} | {step_s:.3f} | {step_s * steps_per_epoch:.1f} | "
              f"{step_s * steps_per_epoch * 500 / 3600:.2f} |", flush=True)
    ours, peer = rows.values()
    print(f"\npeer / ours: {peer / ours:.1f}x per step")


def average_against_mean_shape(run: str) -> None:
    from phantom.model.mesh.shape import inside_body
    from phantom.model.mesh.surface import TriangleMesh
    from phantom.shape.analysis import ShapeModel
    from phantom.shape.compare import compare_shapes, phantom_mesh
    from phantom.shape.report import model_rest_surface
    from phantom.shape.training import intersection_over_union
    from phantom.shape.voxels import RAS_FROM_PHANTOM, sample_offsets_mm

    model = ShapeModel.load(run)
    average = model.average()
    rest = model_rest_surface()
    result = compare_shapes(model, phantom_mesh(rest), phantom_mesh(TriangleMesh(average.vertices_mm,
                                                                                   average.triangles)))
    # the mean shape on the run's grid, centred on its centroid (sampled 3^3 per voxel)
    axis = sample_offsets_mm(model.grid_size, model.voxel_mm, 3)
    points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3) * RAS_FROM_PHANTOM
    centroid = points[inside_body(points)].mean(axis=0)
    n = model.grid_size
    truth = inside_body(points + centroid).reshape(n, 3, n, 3, n, 3).mean(axis=(1, 3, 5))
    iou = intersection_over_union(average.probabilities[None], truth[None])[0]
    names, latents = model.case_latents()
    spread = np.median(np.linalg.norm(latents[:, None] - latents[None], axis=2)[np.triu_indices(len(names), 1)])
    print(f"\nrun {run}: {len(names)} cases; the decoded average against the known mean shape (the phantom's body)\n")
    print("| figure | value |")
    print("| --- | --- |")
    print(f"| volume of the average | {average.volume_ml:.2f} ml |")
    print(f"| volume of the mean shape (model mesh) | {result.volume_a_ml:.2f} ml (26.3 by construction) |")
    print(f"| IoU, average vs mean shape on the grid | {iou:.3f} |")
    print(f"| mean closest-point distance after ICP | {result.mean_distance_mm:.2f} mm |")
    print(f"| latent distance | {result.latent_distance:.2f} (median between cases {spread:.2f}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", help="a run trained on the synthetic population, for part 2")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per variant (default 5)")
    args = parser.parse_args()
    epoch_table(args.steps)
    if args.run:
        average_against_mean_shape(args.run)


if __name__ == "__main__":
    main()
