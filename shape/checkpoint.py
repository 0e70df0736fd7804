"""The run folder's files: the checkpoint (``parameters.npz``) and ``config.json``, written and read back.

See :mod:`phantom.shape.training` for the whole folder. The weights are stored as ``params/<path>`` and the
batch-norm running statistics as ``statistics/<path>``, paths as :func:`phantom.shape.vae.flatten` names them;
reading rebuilds the network of the run's config and fills it, refusing arrays of another architecture.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from phantom import read_text, require_extra
from phantom.model.fidelity.table_files import Member, read_members
from phantom.shape.errors import ShapeError
from phantom.shape.vae import Parameters, VAEConfig, flatten, init_parameters, tree_leaves, unflatten_like

with require_extra("shape"):
    import jax

RUN_FORMAT = "phantom-shape-run"
RUN_VERSION = 1
#: The largest config.json read (bytes): a run's is under 10 KB, its held-out case names included.
MAX_CONFIG_BYTES = 2**20
#: The largest checkpoint read (bytes): the default network's is 3 MB.
MAX_CHECKPOINT_BYTES = 2**30


def write_checkpoint(run: Path, params: Parameters, statistics: Parameters) -> Path:
    """``parameters.npz`` in ``run`` (written whole, then moved into place)."""
    arrays: dict[str, Any] = {f"params/{path}": value for path, value in flatten(params).items()}
    arrays.update({f"statistics/{path}": value for path, value in flatten(statistics).items()})
    temporary = run / "parameters.tmp.npz"
    np.savez(temporary, **arrays)
    temporary.replace(run / "parameters.npz")
    return run / "parameters.npz"


def write_config(run: Path, vae: VAEConfig, training: dict[str, Any], data: dict[str, Any], epochs_done: int,
                 seconds: float, device: str) -> None:
    """``config.json`` in ``run``; ``device`` is what trained it ("cpu", "gpu (NVIDIA H200)")."""
    config = {"format": RUN_FORMAT, "version": RUN_VERSION, "vae": vae.as_dict(),
              "training": training, "data": data, "epochs_done": epochs_done,
              "seconds": round(seconds, 1), "device": device}
    (run / "config.json").write_text(json.dumps(config, indent=1))


def read_run(run: str | Path) -> tuple[dict[str, Any], Parameters, Parameters]:
    """A run folder's config, weights and batch-norm statistics; ShapeError when it is not a finished run."""
    run = Path(run)
    if not run.is_dir():
        raise ShapeError(f"{run}: no such run folder (train one with: phantom shape train DATA --out {run})")
    config_path, weights_path = run / "config.json", run / "parameters.npz"
    if not config_path.is_file() or not weights_path.is_file():
        missing = "config.json" if not config_path.is_file() else "parameters.npz"
        raise ShapeError(f"{run}: not a trained run (no {missing}): train one with phantom shape train")
    try:
        config = json.loads(read_text(config_path, MAX_CONFIG_BYTES, "the run's config", ShapeError))
    except (json.JSONDecodeError, RecursionError) as error:
        raise ShapeError(f"{config_path}: not valid JSON ({error})") from None
    if not isinstance(config, dict) or config.get("format") != RUN_FORMAT or config.get("version") != RUN_VERSION:
        raise ShapeError(f"{config_path}: not a {RUN_FORMAT} version {RUN_VERSION} run")
    if "vae" not in config:
        raise ShapeError(f"{config_path}: the run's config has no vae settings: not a finished run (train it again)")
    try:
        vae = VAEConfig.from_dict(config["vae"])
    except ShapeError as error:
        raise ShapeError(f"{config_path}: {error}") from None
    data = config.get("data")
    voxel_mm = data.get("voxel_mm") if isinstance(data, dict) else None
    labels = data.get("labels", []) if isinstance(data, dict) else None
    if (not isinstance(data, dict) or isinstance(voxel_mm, bool) or not isinstance(voxel_mm, int | float)
            or not 0 < voxel_mm < 100 or data.get("grid_size") != vae.grid_size
            or not isinstance(labels, list) or not all(isinstance(label, int) for label in labels)):
        raise ShapeError(f"{config_path}: the run's data settings must hold voxel_mm (mm, positive), grid_size "
                         f"({vae.grid_size}, the network's) and labels (whole numbers), got {data!r:.120}: not a run "
                         f"of ours (train it again)")
    # the network's shapes without building it: the weights are checked against them before anything is allocated
    template_params, template_statistics = jax.eval_shape(lambda key: init_parameters(vae, key),
                                                          jax.random.PRNGKey(0))
    members = {f"{prefix}/{path}": Member(tuple(leaf.shape))
               for prefix, template in (("params", template_params), ("statistics", template_statistics))
               for path, leaf in tree_leaves(template).items()}
    remedy = "it was written for another network, or damaged: train the run again (phantom shape train)"
    stored = read_members(weights_path, members, f"the checkpoint {weights_path}", remedy, ShapeError,
                          MAX_CHECKPOINT_BYTES)
    params = unflatten_like(template_params, _prefixed(stored, "params/"), str(weights_path))
    statistics = unflatten_like(template_statistics, _prefixed(stored, "statistics/"), str(weights_path))
    return config, params, statistics


def _prefixed(stored: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {name[len(prefix):]: value for name, value in stored.items() if name.startswith(prefix)}
