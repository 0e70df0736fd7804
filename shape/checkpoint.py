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

from phantom import require_extra
from phantom.shape.errors import ShapeError
from phantom.shape.vae import Parameters, VAEConfig, flatten, init_parameters, unflatten_like

with require_extra("shape"):
    import jax

RUN_FORMAT = "phantom-shape-run"
RUN_VERSION = 1


def write_checkpoint(run: Path, params: Parameters, statistics: Parameters) -> Path:
    """``parameters.npz`` in ``run`` (written whole, then moved into place)."""
    arrays: dict[str, Any] = {f"params/{path}": value for path, value in flatten(params).items()}
    arrays.update({f"statistics/{path}": value for path, value in flatten(statistics).items()})
    temporary = run / "parameters.tmp.npz"
    np.savez(temporary, **arrays)
    temporary.replace(run / "parameters.npz")
    return run / "parameters.npz"


def write_config(run: Path, vae: VAEConfig, training: dict[str, Any], data: dict[str, Any], epochs_done: int,
                 seconds: float) -> None:
    """``config.json`` in ``run``."""
    config = {"format": RUN_FORMAT, "version": RUN_VERSION, "vae": vae.as_dict(),
              "training": training, "data": data, "epochs_done": epochs_done,
              "seconds": round(seconds, 1)}
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
        config = json.loads(config_path.read_text())
    except json.JSONDecodeError as error:
        raise ShapeError(f"{config_path}: not valid JSON ({error})") from None
    if config.get("format") != RUN_FORMAT or config.get("version") != RUN_VERSION:
        raise ShapeError(f"{config_path}: not a {RUN_FORMAT} version {RUN_VERSION} run")
    template_params, template_statistics = init_parameters(VAEConfig.from_dict(config["vae"]), jax.random.PRNGKey(0))
    with np.load(weights_path) as stored:
        params = unflatten_like(template_params, _prefixed(stored, "params/"), str(weights_path))
        statistics = unflatten_like(template_statistics, _prefixed(stored, "statistics/"), str(weights_path))
    return config, params, statistics


def _prefixed(stored: Any, prefix: str) -> dict[str, np.ndarray]:
    return {name[len(prefix):]: stored[name] for name in stored.files if name.startswith(prefix)}
