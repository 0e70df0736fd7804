"""The paper's 3D convolutional variational autoencoder of voxelised shapes, in JAX.

Encoder: one 3x3x3 convolution of stride 2 per level (channels ``(16, 32, 64)`` by default: 32^3 -> 16^3 -> 8^3
-> 4^3), each followed by batch normalisation and LeakyReLU; a dense layer gives the mean and log-variance of a
64-dimensional latent vector. Decoder, the mirror image: a dense layer (LeakyReLU) to the coarsest grid, then
per level a 3x3x3 convolution to eight times the channels and a depth-to-space step that doubles the grid (a
sub-pixel convolution: the same family of maps as a stride-2 transposed convolution), batch norm and LeakyReLU
on all but the last, which gives one logit per voxel. The dense layers have no batch norm: over a batch of ten
shapes their statistics are too noisy, and a decoder that learned them decodes badly with the running ones.
Loss: binary cross-entropy of the voxels plus ``kld_weight`` (0.01) times the Kullback-Leibler divergence from
the unit normal.

Why these layers and not a library's ``Conv3d``/``ConvTranspose3d``: on the CPU, XLA runs a convolution whose
input is dilated (the input gradient of a strided convolution, and every transposed convolution) 10-100 times
slower than a plain one (measured in ``bench/shape_vae.py``); a strided convolution written as strided slices
and one matrix product, and upsampling by depth-to-space, use none. Arrays are channels-last, ``(N, D, H, W, C)``,
the layout XLA's CPU convolutions are fastest in.

The parameters and the batch-norm statistics are nested dicts of arrays (:func:`flatten` names them
``encoder/0/weight`` ... for a checkpoint). Everything here is a pure function, so ``jax.jit`` and
``jax.grad`` apply directly.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.shape.errors import ShapeError

with require_extra("shape"):
    import jax
    import jax.numpy as jnp
    from jax import lax

Parameters = dict[str, Any]
"""Nested dicts (and lists) of arrays: the trained weights, or the batch-norm running statistics."""

_CHANNELS_LAST = ("NDHWC", "DHWIO", "NDHWC")


#: The largest settings a run's config may have (a 256^3 grid, 4096 latents, 1024 channels in eight levels, a
#: 9^3 kernel): beyond them the network would not fit a machine, and the file is not a run of ours.
VAE_LIMITS = {"grid_size": 256, "latent_dim": 4096, "channels": 1024, "levels": 8, "kernel_size": 9}


@dataclass(frozen=True)
class VAEConfig:
    """The network's architecture (the paper's defaults; every field may be changed).

    Attributes
    ----------
    grid_size : int
        Voxels along each side of the input grid; divisible by ``2 ** len(channels)``.
    latent_dim : int
        Size of the latent vector.
    channels : tuple of int
        Feature channels of the encoder's levels (each halves the grid); the decoder mirrors them.
    kernel_size : int
        Side of the cubic convolution kernels (odd).
    negative_slope : float
        LeakyReLU's slope for negative inputs.
    batch_norm_momentum : float
        Weight of the old running statistics in each batch-norm update (0.9: PyTorch's momentum 0.1).
    batch_norm_epsilon : float
        Added to the variance before normalising.
    """

    grid_size: int = 32
    latent_dim: int = 64
    channels: tuple[int, ...] = (16, 32, 64)
    kernel_size: int = 3
    negative_slope: float = 0.01
    batch_norm_momentum: float = 0.9
    batch_norm_epsilon: float = 1e-5

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        levels = len(self.channels)
        if levels < 1 or min(self.channels) < 1:
            raise ShapeError(f"channels must be one or more positive counts, got {list(self.channels)}")
        if self.grid_size < 2**levels or self.grid_size % 2**levels:
            raise ShapeError(f"grid_size {self.grid_size} must be a multiple of 2^{levels} = {2**levels} "
                             f"(one halving per level of channels {list(self.channels)})")
        if self.latent_dim < 1:
            raise ShapeError(f"latent_dim must be at least 1, got {self.latent_dim}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ShapeError(f"kernel_size must be odd and positive, got {self.kernel_size}")
        if not 0.0 <= self.batch_norm_momentum < 1.0:
            raise ShapeError(f"batch_norm_momentum must be in [0, 1), got {self.batch_norm_momentum}")

    @property
    def coarsest_side(self) -> int:
        """Voxels along a side of the coarsest grid (after the encoder's last level)."""
        return int(self.grid_size // 2 ** len(self.channels))

    def as_dict(self) -> dict[str, Any]:
        """The config as JSON-ready values."""
        values = dataclasses.asdict(self)
        values["channels"] = list(self.channels)
        return values

    @classmethod
    def from_dict(cls, values: Any) -> VAEConfig:
        """The config written by :meth:`as_dict`, checked before any network is built: unknown keys, a value of
        the wrong type and sizes beyond :data:`VAE_LIMITS` are ShapeErrors (``latent_dim`` 1e9 took 7.9 GB and
        ended in a JAX abort)."""
        if not isinstance(values, dict):
            raise ShapeError(f"the VAE settings must be a JSON object, got {values!r:.80}")
        names = {field.name for field in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ShapeError(f"unknown VAE settings {unknown}: known are {sorted(names)}")
        channels = values.get("channels", list(cls.channels))
        if not isinstance(channels, list) or not channels:
            raise ShapeError(f"channels must be a list of whole numbers, got {channels!r:.80}")
        for name, value in [*((key, values[key]) for key in values if key != "channels"),
                            *(("channels", count) for count in channels)]:
            whole = name == "channels" or isinstance(getattr(cls, name), int)
            kind = (int,) if whole else (int, float)
            if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value):
                raise ShapeError(f"{name} must be {'a whole number' if whole else 'a finite number'}, got "
                                 f"{value!r:.80}")
            if name in VAE_LIMITS and not value <= VAE_LIMITS[name]:
                raise ShapeError(f"{name} = {value} is more than the {VAE_LIMITS[name]} a shape network has: not a "
                                 f"run of ours")
        if len(channels) > VAE_LIMITS["levels"]:
            raise ShapeError(f"channels has {len(channels)} levels, more than {VAE_LIMITS['levels']}")
        return cls(**{**values, "channels": tuple(channels)})


def _normal(key: jax.Array, shape: tuple[int, ...], fan_in: int, gain: float) -> jax.Array:
    return jax.random.normal(key, shape, jnp.float32) * (gain / math.sqrt(fan_in))


def _norm_parameters(size: int) -> tuple[Parameters, Parameters]:
    scale_offset = {"scale": jnp.ones(size, jnp.float32), "offset": jnp.zeros(size, jnp.float32)}
    running = {"mean": jnp.zeros(size, jnp.float32), "variance": jnp.ones(size, jnp.float32)}
    return scale_offset, running


def init_parameters(config: VAEConfig, key: jax.Array) -> tuple[Parameters, Parameters]:
    """Initial weights (He-normal for the LeakyReLU layers) and batch-norm statistics for ``config``."""
    k = config.kernel_size
    levels = len(config.channels)
    keys = iter(jax.random.split(key, 2 * levels + 4))
    leaky_gain = math.sqrt(2.0 / (1.0 + config.negative_slope**2))
    params: Parameters = {"encoder": [], "decoder": []}
    statistics: Parameters = {"encoder": [], "decoder": []}
    inputs = (1, *config.channels[:-1])
    for c_in, c_out in zip(inputs, config.channels, strict=True):
        norm, running = _norm_parameters(c_out)
        weight = _normal(next(keys), (k, k, k, c_in, c_out), k**3 * c_in, leaky_gain)
        params["encoder"].append({"weight": weight, "bias": jnp.zeros(c_out, jnp.float32), **norm})
        statistics["encoder"].append(running)
    flat = config.channels[-1] * config.coarsest_side**3
    params["latent"] = {"weight": _normal(next(keys), (flat, 2 * config.latent_dim), flat, 1.0),
                        "bias": jnp.zeros(2 * config.latent_dim, jnp.float32)}
    params["expand"] = {"weight": _normal(next(keys), (config.latent_dim, flat), config.latent_dim, leaky_gain),
                        "bias": jnp.zeros(flat, jnp.float32)}
    outputs = (*config.channels[::-1][1:], 1)
    for level, (c_in, c_out) in enumerate(zip(config.channels[::-1], outputs, strict=True)):
        last = level == levels - 1
        weight = _normal(next(keys), (k, k, k, c_in, 8 * c_out), k**3 * c_in, 1.0 if last else leaky_gain)
        layer = {"weight": weight, "bias": jnp.zeros(8 * c_out, jnp.float32)}
        if not last:
            norm, running = _norm_parameters(c_out)
            layer.update(norm)
            statistics["decoder"].append(running)
        params["decoder"].append(layer)
    return params, statistics


def strided_convolution(x: jax.Array, weight: jax.Array) -> jax.Array:
    """A stride-2 convolution with 'same' padding, ``(N, D, H, W, C) -> (N, D/2, H/2, W/2, C')``.

    Written as strided slices and one matrix product so that its gradient needs no input-dilated convolution.
    """
    k = weight.shape[0]
    pad = (k - 1) // 2
    n, d, h, w, c = x.shape
    padded = jnp.pad(x, ((0, 0), (pad, k - 1 - pad), (pad, k - 1 - pad), (pad, k - 1 - pad), (0, 0)))
    out = (d // 2, h // 2, w // 2)
    patches = [padded[:, i:i + 2 * out[0] - 1:2, j:j + 2 * out[1] - 1:2, m:m + 2 * out[2] - 1:2, :]
               for i in range(k) for j in range(k) for m in range(k)]
    return jnp.concatenate(patches, axis=-1) @ weight.reshape(k**3 * c, -1)


def subpixel_convolution(x: jax.Array, weight: jax.Array, bias: jax.Array) -> jax.Array:
    """A 'same' convolution to ``8 C'`` channels, then depth-to-space: ``(N, D, H, W, C) -> (N, 2D, 2H, 2W, C')``."""
    y = lax.conv_general_dilated(x, weight, (1, 1, 1), "SAME", dimension_numbers=_CHANNELS_LAST) + bias
    n, d, h, w, c8 = y.shape
    c = c8 // 8
    y = y.reshape(n, d, h, w, 2, 2, 2, c).transpose(0, 1, 4, 2, 5, 3, 6, 7)
    return y.reshape(n, 2 * d, 2 * h, 2 * w, c)


def batch_norm(x: jax.Array, layer: Parameters, running: Parameters, config: VAEConfig,
                training: bool) -> tuple[jax.Array, Parameters]:
    """Normalise over every axis but the last (channels); in training, update the running statistics."""
    if training:
        axes = tuple(range(x.ndim - 1))
        mean = x.mean(axes)
        variance = x.var(axes)
        count = x.size // x.shape[-1]
        unbiased = variance * count / max(count - 1, 1)
        m = config.batch_norm_momentum
        running = {"mean": m * running["mean"] + (1 - m) * mean,
                   "variance": m * running["variance"] + (1 - m) * unbiased}
    else:
        mean, variance = running["mean"], running["variance"]
    normalised = (x - mean) * lax.rsqrt(variance + config.batch_norm_epsilon)
    return normalised * layer["scale"] + layer["offset"], running


def encode(params: Parameters, statistics: Parameters, config: VAEConfig, occupancy: jax.Array,
           training: bool = False) -> tuple[jax.Array, jax.Array, Parameters]:
    """Latent means and log-variances ``(N, latent_dim)`` of occupancy grids ``(N, G, G, G)`` in [0, 1].

    Returns the updated encoder statistics too (unchanged unless ``training``).
    """
    x = occupancy[..., None]
    new_statistics = []
    for layer, running in zip(params["encoder"], statistics["encoder"], strict=True):
        x = strided_convolution(x, layer["weight"]) + layer["bias"]
        x, running = batch_norm(x, layer, running, config, training)
        x = jax.nn.leaky_relu(x, config.negative_slope)
        new_statistics.append(running)
    h = x.reshape(x.shape[0], -1) @ params["latent"]["weight"] + params["latent"]["bias"]
    return h[:, :config.latent_dim], h[:, config.latent_dim:], {**statistics, "encoder": new_statistics}


def decode_logits(params: Parameters, statistics: Parameters, config: VAEConfig, latent: jax.Array,
                  training: bool = False) -> tuple[jax.Array, Parameters]:
    """Voxel logits ``(N, G, G, G)`` of latent vectors ``(N, latent_dim)``, and the updated decoder statistics."""
    y = jax.nn.leaky_relu(latent @ params["expand"]["weight"] + params["expand"]["bias"], config.negative_slope)
    side = config.coarsest_side
    y = y.reshape(-1, side, side, side, config.channels[-1])
    new_statistics = []
    for level, layer in enumerate(params["decoder"]):
        y = subpixel_convolution(y, layer["weight"], layer["bias"])
        if level < len(statistics["decoder"]):
            y, running = batch_norm(y, layer, statistics["decoder"][level], config, training)
            y = jax.nn.leaky_relu(y, config.negative_slope)
            new_statistics.append(running)
    return y[..., 0], {**statistics, "decoder": new_statistics}


def loss_terms(params: Parameters, statistics: Parameters, config: VAEConfig, occupancy: jax.Array,
               key: jax.Array, kld_weight: float) -> tuple[jax.Array, tuple[jax.Array, jax.Array, Parameters]]:
    """The training loss of one batch: (BCE + kld_weight KLD, (BCE, KLD, updated statistics)).

    BCE is summed over a grid's voxels and KLD over the latent dimensions, both averaged over the batch (the
    per-shape negative evidence lower bound when ``kld_weight`` is 1).
    """
    mean, log_variance, statistics = encode(params, statistics, config, occupancy, training=True)
    noise = jax.random.normal(key, mean.shape, mean.dtype)
    latent = mean + jnp.exp(0.5 * log_variance) * noise
    logits, statistics = decode_logits(params, statistics, config, latent, training=True)
    # BCE with logits: max(l, 0) - l x + log(1 + exp(-|l|)), stable for large |l|.
    bce_voxels = jnp.maximum(logits, 0) - logits * occupancy + jnp.log1p(jnp.exp(-jnp.abs(logits)))
    bce = bce_voxels.sum(axis=(1, 2, 3)).mean()
    kld = (-0.5 * jnp.sum(1.0 + log_variance - mean**2 - jnp.exp(log_variance), axis=1)).mean()
    return bce + kld_weight * kld, (bce, kld, statistics)


def tree_leaves(tree: Parameters | list[Any], prefix: str = "") -> dict[str, Any]:
    """The leaves of a nested dict/list tree keyed by their path (``encoder/0/weight``), as they are (arrays, or
    the shapes ``jax.eval_shape`` gives)."""
    items: dict[str, Any] = {}
    children: Any = enumerate(tree) if isinstance(tree, list) else tree.items()
    for name, value in children:
        path = f"{prefix}{name}"
        if isinstance(value, dict | list):
            items.update(tree_leaves(value, path + "/"))
        else:
            items[path] = value
    return items


def flatten(tree: Parameters | list[Any], prefix: str = "") -> dict[str, np.ndarray]:
    """Arrays of a nested dict/list tree keyed by their path (``encoder/0/weight``), as NumPy arrays."""
    return {path: np.asarray(value) for path, value in tree_leaves(tree, prefix).items()}


def unflatten_like(template: Parameters, arrays: dict[str, np.ndarray], what: str) -> Parameters:
    """``template``'s tree with its arrays replaced by ``arrays[path]``; shapes must match."""
    expected = tree_leaves(template)
    missing = sorted(set(expected) - set(arrays))
    if missing:
        raise ShapeError(f"{what} lacks {len(missing)} arrays of this network ({missing[0]} ...): "
                         f"it was written for another architecture")
    for path, value in expected.items():
        if arrays[path].shape != value.shape:
            raise ShapeError(f"{what}: {path} has shape {arrays[path].shape}, the network's config needs "
                             f"{value.shape}")

    def rebuild(tree: Any, prefix: str) -> Any:
        if isinstance(tree, list):
            return [rebuild(value, f"{prefix}{index}/") for index, value in enumerate(tree)]
        if isinstance(tree, dict):
            return {name: rebuild(value, f"{prefix}{name}/") for name, value in tree.items()}
        return jnp.asarray(arrays[prefix[:-1]])

    rebuilt: Parameters = rebuild(template, "")
    return rebuilt
