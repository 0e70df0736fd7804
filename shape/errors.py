"""The shape analysis's user errors, and the one-line error for a missing optional extra."""

from __future__ import annotations

import importlib
from types import ModuleType

from phantom import PhantomError


class ShapeError(PhantomError):
    """Bad input to the shape analysis: a missing label, an empty mask, an open mesh, a run without a checkpoint."""


def require(module: str) -> ModuleType:
    """Import ``module`` (a dependency of the ``[shape]`` extra), or say in one line how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ShapeError(f"the shape analysis needs {module.split('.')[0]}: "
                         f"pip install 'active-prostate-phantom[shape]'") from None


#: What the ``[shape]`` extra installs, as modules.
EXTRA_MODULES = ("jax", "optax", "nibabel", "skimage")


def require_extra() -> None:
    """Raise ShapeError (naming the pip command) unless every module of the ``[shape]`` extra imports."""
    for module in EXTRA_MODULES:
        require(module)
