"""The finite-element model of the phantom and its inverse problem (SI units inside: m, Pa, m^3, N).

Public API (see model/README.md)::

    from phantom.model import load_scene, PhantomModel, MeshError, SolveError
    scene = load_scene("builtin")
    model = PhantomModel.from_scene(scene)
    state = model.equilibrium([1e3, 1e3, 1e3])
    compliance = model.compliance()

Names are imported lazily so that ``phantom --help`` does not load numpy, scipy or numba.
"""

import importlib
from typing import Any

_EXPORTS = {
    "load_scene": "phantom.model.scene",
    "Scene": "phantom.model.scene",
    "Material": "phantom.model.scene",
    "PhantomModel": "phantom.model.fem.model",
    "State": "phantom.model.fem.model",
    "Compliance": "phantom.model.fem.model",
    "MeshError": "phantom.model.errors",
    "SolveError": "phantom.model.errors",
    "PeakPressureError": "phantom.model.errors",
    "PressureUnitWarning": "phantom.model.errors",
    "SceneError": "phantom.model.errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'phantom.model' has no attribute {name!r}")
