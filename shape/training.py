"""Training the VAE on a shape set, and the run folder it writes (a small, documented checkpoint format;
:mod:`phantom.shape.checkpoint` writes and reads its checkpoint and config).

A run folder holds::

    config.json      {"format": "phantom-shape-run", "version": 1, "vae": VAEConfig, "training": TrainConfig,
                      "data": {source, grid_size, voxel_mm, labels, names, held_out}, "epochs_done", "seconds",
                      "device"}
    parameters.npz   the weights as "params/<path>" and the batch-norm running statistics as
                     "statistics/<path>", paths like encoder/0/weight (see phantom.shape.vae.flatten)
    latents.npz      names, latent means and log-variances of every case, held_out flags, volumes_ml
    history.json     one entry per epoch: loss, bce, kld, validation_loss, validation_iou, seconds
    loss.png         the loss curves; loss.rrd the same as a Rerun recording, where rerun-sdk is installed

``voxel_mm`` (the set's one scale factor) and ``grid_size`` say how any new shape is put on the grid, so that
decoded volumes come back in ml. Training is reproducible: the seed fixes the initial weights, the held-out
split, the batch order and the sampling noise.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from phantom import require_extra
from phantom.shape import vae as network
from phantom.shape.analysis import ShapeModel
from phantom.shape.checkpoint import write_checkpoint, write_config
from phantom.shape.dataset import ShapeSet
from phantom.shape.errors import ShapeError
from phantom.shape.vae import Parameters, VAEConfig

with require_extra("shape"):
    import jax
    import optax


@dataclass(frozen=True)
class TrainConfig:
    """How the network is trained (the paper's batch size, epochs and KLD weight as defaults).

    Attributes
    ----------
    epochs : int
        Passes over the training cases.
    batch_size : int
        Cases per optimiser step (a last, smaller batch of an epoch is dropped; the order changes every epoch).
    learning_rate : float
        Adam's step size.
    kld_weight : float
        Weight of the KL divergence against the reconstruction's binary cross-entropy.
    seed : int
        Seed of the weights, the split, the batch order and the sampling noise.
    validation_fraction : float
        Share of the cases held out of training to measure reconstruction (0 trains on all).
    checkpoint_every : int
        Also write the checkpoint every this many epochs (0: only at the end).
    """

    epochs: int = 500
    batch_size: int = 10
    learning_rate: float = 1e-3
    kld_weight: float = 0.01
    seed: int = 0
    validation_fraction: float = 0.1
    checkpoint_every: int = 50

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1:
            raise ShapeError(f"epochs and batch_size must be at least 1, got {self.epochs} and {self.batch_size}")
        if not 0.0 <= self.validation_fraction < 1.0:
            raise ShapeError(f"validation_fraction must be in [0, 1), got {self.validation_fraction}")
        if self.learning_rate <= 0 or self.kld_weight < 0:
            raise ShapeError("learning_rate must be positive and kld_weight not negative")


@dataclass
class EpochRecord:
    """What one epoch did (losses per case: BCE summed over the voxels, KLD over the latent dimensions)."""

    epoch: int
    loss: float
    bce: float
    kld: float
    validation_loss: float | None
    validation_iou: float | None
    seconds: float


def split_cases(count: int, validation_fraction: float, seed: int) -> np.ndarray:
    """A boolean mask of the held-out cases: ``round(fraction * count)`` of them, drawn with ``seed``."""
    held = int(round(validation_fraction * count))
    if count - held < 2:
        raise ShapeError(f"{count} shapes leave {count - held} to train on: give at least 2 (more than "
                         f"{held} held out)")
    mask = np.zeros(count, bool)
    mask[np.random.default_rng([seed, 1]).permutation(count)[:held]] = True
    return mask


def intersection_over_union(a: np.ndarray, b: np.ndarray, level: float = 0.5) -> np.ndarray:
    """IoU of the shapes ``a >= level`` and ``b >= level``, per leading index of ``(N, G, G, G)`` arrays."""
    a, b = a >= level, b >= level
    axes = tuple(range(1, a.ndim))
    union = np.logical_or(a, b).sum(axis=axes)
    iou: np.ndarray = np.logical_and(a, b).sum(axis=axes) / np.maximum(union, 1)
    return iou


#: The held-out reconstruction IoU below which a run is warned about: the network does not yet reconstruct shapes
#: it was not trained on, so its average shape, clusters and latent distances describe the network more than the
#: population. The docs' 120 synthetic cases reached 0.923 after 100 epochs (shape/README.md).
IOU_WARNING_BELOW = 0.8


def held_out_iou_warning(iou: float | None, epochs: int) -> str | None:
    """The warning a run with held-out IoU ``iou`` after ``epochs`` epochs deserves, or None (IoU high enough,
    or no case held out to measure it)."""
    if iou is None or iou >= IOU_WARNING_BELOW:
        return None
    return (f"the held-out reconstruction IoU is {iou:.2f} after {epochs} epochs, below {IOU_WARNING_BELOW:g}: the "
            "network does not yet reconstruct shapes it was not trained on, so its average, clusters and distances "
            "are not the population's; train more epochs (shape/README.md: 120 cases reach 0.92 in 100 epochs)")


def run_held_out_iou(run: str | Path) -> tuple[float | None, int]:
    """The last held-out IoU a run folder's history.json holds, and its epochs (None, 0 without a history)."""
    path = Path(run) / "history.json"
    if not path.is_file():
        return None, 0
    history = json.loads(path.read_text())
    if not history:
        return None, 0
    last = history[-1]
    return last.get("validation_iou"), int(last.get("epoch", len(history)))


def compute_device() -> str:
    """What JAX trains on: "gpu (NVIDIA H200)" where jax[cuda12] found a GPU, else "cpu" (JAX's default device,
    the first of the fastest backend it has). Recorded in config.json and printed by ``phantom shape train``."""
    device = jax.devices()[0]
    return device.platform if device.platform == "cpu" else f"{device.platform} ({device.device_kind})"


def print_progress(record: EpochRecord, epochs: int, seconds_left: float) -> None:
    """The default progress line on stderr: epoch, losses, time per epoch and time left (NaN: not known yet, the
    first epoch compiles the network). One line per epoch, so a log file holds one line each."""
    held = "" if record.validation_iou is None else (
        f"  held-out loss {record.validation_loss:.1f}  IoU {record.validation_iou:.3f}")
    if math.isfinite(seconds_left):
        minutes, seconds = divmod(int(round(seconds_left)), 60)
        left = f"left {minutes}:{seconds:02d}"
    else:
        left = "left: known after epoch 2 (this one compiled the network)"
    print(f"epoch {record.epoch}/{epochs}  loss {record.loss:.1f} (BCE {record.bce:.1f}, KLD {record.kld:.1f})"
          f"{held}  {record.seconds:.1f} s  {left}", file=sys.stderr, flush=True)


class Trainer:
    """The jitted training and evaluation steps of one network; a pure-JAX loop around them."""

    def __init__(self, vae: VAEConfig, training: TrainConfig):
        self.vae, self.training = vae, training
        self.optimiser = optax.adam(training.learning_rate)

        def step(params: Parameters, statistics: Parameters, optimiser_state: Any, batch: Any,
                 key: Any) -> tuple[Any, ...]:
            grad_fn = jax.value_and_grad(network.loss_terms, has_aux=True)
            (loss, (bce, kld, statistics)), grads = grad_fn(params, statistics, vae, batch, key,
                                                             training.kld_weight)
            updates, optimiser_state = self.optimiser.update(grads, optimiser_state, params)
            return optax.apply_updates(params, updates), statistics, optimiser_state, loss, bce, kld

        def evaluate(params: Parameters, statistics: Parameters, batch: Any) -> tuple[Any, Any]:
            mean, log_variance, _ = network.encode(params, statistics, vae, batch)
            logits, _ = network.decode_logits(params, statistics, vae, mean)
            bce = optax.sigmoid_binary_cross_entropy(logits, batch).sum(axis=(1, 2, 3))
            kld = -0.5 * (1.0 + log_variance - mean**2 - jax.numpy.exp(log_variance)).sum(axis=1)
            return bce + training.kld_weight * kld, jax.nn.sigmoid(logits)

        self.step = jax.jit(step)
        self.evaluate = jax.jit(evaluate)

    def fit(self, occupancy: np.ndarray, held_out: np.ndarray, on_epoch: Callable[[EpochRecord], None],
            on_checkpoint: Callable[[Parameters, Parameters, int], None]) -> tuple[Parameters, Parameters]:
        """Train on ``occupancy[~held_out]``; report each epoch and checkpoint every ``checkpoint_every``."""
        training = self.training
        key = jax.random.PRNGKey(training.seed)
        key, init_key = jax.random.split(key)
        params, statistics = network.init_parameters(self.vae, init_key)
        optimiser_state = self.optimiser.init(params)
        # the cases go to the device once and each batch is gathered there: on a GPU a step takes about 2 ms,
        # less than copying its batch from the host and reading its losses back one step at a time
        train = jax.device_put(occupancy[~held_out])
        validation = occupancy[held_out]
        batch_size = min(training.batch_size, len(train))
        order_rng = np.random.default_rng([training.seed, 2])
        for epoch in range(1, training.epochs + 1):
            started = time.perf_counter()
            order = order_rng.permutation(len(train))
            steps = len(train) // batch_size
            step_losses = []
            for index in range(steps):
                batch = train[order[index * batch_size:(index + 1) * batch_size]]
                key, step_key = jax.random.split(key)
                params, statistics, optimiser_state, *losses = self.step(params, statistics, optimiser_state,
                                                                         batch, step_key)
                step_losses.append(losses)
            # read back once an epoch, summed on the host in step order as before
            totals = np.asarray(jax.device_get(step_losses), dtype=np.float64).sum(axis=0)
            validation_loss = validation_iou = None
            if len(validation):
                losses, probabilities = self.evaluate(params, statistics, validation)
                validation_loss = float(np.mean(losses))
                validation_iou = float(np.mean(intersection_over_union(np.asarray(probabilities), validation)))
            loss, bce, kld = totals / steps
            on_epoch(EpochRecord(epoch, loss, bce, kld, validation_loss, validation_iou,
                                 time.perf_counter() - started))
            if training.checkpoint_every and epoch % training.checkpoint_every == 0 and epoch < training.epochs:
                on_checkpoint(params, statistics, epoch)
        return params, statistics


def write_loss_curves(history: list[EpochRecord], path: Path) -> Path:
    """The loss curves (training loss, its BCE and weighted KLD, held-out loss; held-out IoU) as a PNG."""
    # matplotlib (0.5 s to import) only where a figure is drawn
    with require_extra("shape"):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

    epochs = [r.epoch for r in history]
    figure, (losses, iou) = plt.subplots(1, 2, figsize=(10, 4))
    losses.plot(epochs, [r.loss for r in history], label="training loss")
    losses.plot(epochs, [r.bce for r in history], label="training BCE", linestyle="--")
    if history[0].validation_loss is not None:
        losses.plot(epochs, [r.validation_loss for r in history], label="held-out loss")
        iou.plot(epochs, [r.validation_iou for r in history], color="C3")
    iou.set_title("held-out reconstruction IoU")
    iou.set_xlabel("epoch")
    iou.set_ylim(0, 1)
    losses.set_yscale("log")
    losses.set_xlabel("epoch")
    losses.set_ylabel("per shape (BCE summed over voxels)")
    losses.set_title("loss")
    losses.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def write_loss_recording(history: list[EpochRecord], path: Path) -> Path | None:
    """The loss curves as a Rerun recording (timeline ``epoch``); None where rerun-sdk is not installed."""
    # rerun-sdk is optional (the [record] extra) and slow to import
    try:
        import rerun as rr
    except ImportError:
        return None
    stream = rr.RecordingStream("phantom_shape_training")
    stream.save(str(path))
    for record in history:
        stream.set_time("epoch", sequence=record.epoch)
        stream.log("loss/training", rr.Scalars(record.loss))
        stream.log("loss/bce", rr.Scalars(record.bce))
        stream.log("loss/kld", rr.Scalars(record.kld))
        if record.validation_loss is not None and record.validation_iou is not None:
            stream.log("loss/held_out", rr.Scalars(record.validation_loss))
            stream.log("held_out_iou", rr.Scalars(record.validation_iou))
    stream.flush()
    stream.disconnect()
    return path


def train(shapes: ShapeSet, run: str | Path, vae: VAEConfig | None = None, training: TrainConfig | None = None,
          source: str = "", on_epoch: Callable[[EpochRecord, int, float], None] | None = print_progress) -> Path:
    """Train a VAE on ``shapes`` and write the run folder ``run`` (see the module docstring); returns it.

    ``on_epoch(record, epochs, seconds_left)`` is called after every epoch (default: a line on stderr);
    ``seconds_left`` excludes the first epoch's compiling, and is NaN after the first of several epochs.
    """
    vae = vae or VAEConfig(grid_size=shapes.grid_size)
    training = training or TrainConfig()
    if vae.grid_size != shapes.grid_size:
        raise ShapeError(f"the network's grid_size {vae.grid_size} differs from the shapes' {shapes.grid_size}")
    run = Path(run)
    run.mkdir(parents=True, exist_ok=True)
    held_out = split_cases(len(shapes.names), training.validation_fraction, training.seed)
    data = {"source": source, "grid_size": shapes.grid_size, "voxel_mm": shapes.voxel_mm,
            "labels": list(shapes.labels), "names": shapes.names,
            "held_out": [name for name, held in zip(shapes.names, held_out, strict=True) if held]}
    history: list[EpochRecord] = []
    started = time.perf_counter()

    def epoch_done(record: EpochRecord) -> None:
        history.append(record)
        if on_epoch is not None:
            # the first epoch compiles the network's steps (its time is mostly that): the time left is the mean
            # of the epochs after it, unknown until there is one (or nothing is left)
            after_first = [r.seconds for r in history[1:]]
            left = training.epochs - record.epoch
            seconds_left = (sum(after_first) / len(after_first) * left if after_first else
                            0.0 if left == 0 else math.nan)
            on_epoch(record, training.epochs, seconds_left)

    device = compute_device()

    def checkpoint(params: Parameters, statistics: Parameters, epoch: int) -> None:
        write_checkpoint(run, params, statistics)
        write_config(run, vae, dataclasses.asdict(training), data, epoch, time.perf_counter() - started, device)

    trainer = Trainer(vae, training)
    params, statistics = trainer.fit(shapes.occupancy, held_out, epoch_done, checkpoint)
    write_checkpoint(run, params, statistics)
    write_config(run, vae, dataclasses.asdict(training), data, training.epochs, time.perf_counter() - started,
                 device)
    (run / "history.json").write_text(json.dumps([dataclasses.asdict(r) for r in history], indent=0))
    model = ShapeModel.load(run)
    means, log_variances = model.encode_distributions(shapes.occupancy)
    np.savez(run / "latents.npz", names=np.array(shapes.names), mean=means, log_variance=log_variances,
             held_out=held_out, volumes_ml=shapes.volumes_ml)
    write_loss_curves(history, run / "loss.png")
    write_loss_recording(history, run / "loss.rrd")
    if not math.isfinite(history[-1].loss):
        raise ShapeError(f"training diverged (loss {history[-1].loss}): lower --learning-rate")
    return run
