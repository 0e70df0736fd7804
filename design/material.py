"""The material a designed phantom inherits: the calibrated law and element order of a shipped (or given) scene.

A design is only as good as the material it is sized with: the built-in prostate's small-strain modulus (E 50
kPa, co-rotational) is what silicone's data sheet suggests, and the project's own calibration to the paper's
measured volumes shows it far too stiff (``builtin:converged``: Gent, E 10.86 kPa, J_m 5, on 10-node mixed
elements). A design therefore takes the calibrated law and element order of ``builtin:converged`` by default,
or of the scene given with ``--material-from``, sizes its chambers with it (:mod:`phantom.design.sizing`), and
writes it into its scene, saying which calibration it inherits: it is the cast silicone's only as far as the
cast is the calibrated one's, so the cast must be measured and the scene calibrated to it (``phantom
calibrate``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from phantom.design.errors import DesignError
from phantom.model.errors import SceneError
from phantom.model.scene import QUADRATIC_POISSON_RATIO, load_scene

#: The scene whose calibration a design inherits by default.
DEFAULT_MATERIAL_FROM = "builtin:converged"


@dataclass(frozen=True)
class InheritedMaterial:
    """The ``[material]`` table a design writes (``table``, the law's keys in the units a scene file takes), the
    element order it is meshed with, and where both come from (``source``: a scene name or path)."""

    source: str
    table: dict[str, Any]
    element_order: int

    @property
    def description(self) -> str:
        """The law in words, e.g. ``gent, E 10.86 kPa, nu 0.4996, J_m 5, 10-node elements``."""
        named = (("gent_jm", "J_m"), ("yeoh_c20_over_c10", "C20/C10"), ("yeoh_c30_over_c10", "C30/C10"))
        extra = "".join(f", {name} {self.table[key]:g}" for key, name in named if key in self.table)
        return (f"{self.table['model']}, E {self.table['youngs_modulus_kpa']:g} kPa, nu "
                f"{self.table['poisson_ratio']:g}{extra}, {4 if self.element_order == 1 else 10}-node elements")

    @property
    def caveat(self) -> str:
        """What the scene and the report say of it."""
        return (f"the material is {self.source}'s calibration ({self.description}), inherited, not measured: "
                "measure the cast phantom's volumes at a few pressures and calibrate this scene to them (phantom "
                "calibrate --scene SCENE --measurements FILE)")


def inherited_material(source: str | Path = DEFAULT_MATERIAL_FROM, element_order: int | None = None
                       ) -> InheritedMaterial:
    """The material of the scene ``source`` and its element order (``element_order`` overrides it: a 4-node mesh
    takes a 4-node ratio of 0.45 where the scene's 10-node one is nearly incompressible). DesignError for a scene
    that cannot be read or whose law cannot be meshed at the order asked."""
    try:
        scene = load_scene(source)
    except SceneError as error:
        raise DesignError(f"--material-from {source}: {error}") from None
    scene_order = scene.geometry.element_order if scene.geometry is not None else 1
    order = scene_order if element_order is None else element_order
    material = scene.material
    poisson_ratio = material.poisson_ratio
    law = material.model
    if order == 1 and scene_order == 2:
        # 4-node elements lock when nearly incompressible: the 4-node ratio, the same modulus
        poisson_ratio = min(poisson_ratio, 0.45)
    elif order == 2 and law in ("linear", "corotational"):
        # 10-node elements take a hyperelastic law, nearly incompressible like silicone; the same small-strain E
        law, poisson_ratio = "neo_hookean", QUADRATIC_POISSON_RATIO
    table: dict[str, Any] = {"model": law, "youngs_modulus_kpa": round(material.youngs_modulus_pa / 1e3, 6),
                             "poisson_ratio": poisson_ratio}
    for key in ("gent_jm", "yeoh_c20_over_c10", "yeoh_c30_over_c10"):
        value = getattr(material, key)
        if value is not None:
            table[key] = value
    return InheritedMaterial(str(source), table, order)
