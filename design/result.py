"""What ``phantom design`` is asked (:class:`DesignOptions`) and what it made (:class:`Design`): the pipeline
(:mod:`phantom.design.pipeline`) fills them, the report (:mod:`phantom.design.report`) reads them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from phantom.design.cast import Cast
from phantom.design.latent import LatentDistance
from phantom.design.material import DEFAULT_MATERIAL_FROM, InheritedMaterial
from phantom.design.meshing import ELEMENTS_PER_WALL
from phantom.design.sizing import PAPER_VOLUME_ML, GrowthTarget, Sizing

#: The pressures (kPa, all three chambers alike) of the predicted growth curve.
GROWTH_PRESSURES_KPA = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


@dataclass(frozen=True)
class DesignOptions:
    """What ``phantom design`` is asked for (its options; see its --help)."""

    volume_ml: float = PAPER_VOLUME_ML
    min_wall_mm: float = 2.0
    #: None: sized to the growth target (see :mod:`phantom.design.sizing`); a number: the template's times it
    chamber_scale: float | None = None
    size_mm: float = 2.5
    #: None: the inherited material's (``material_from``'s: 10-node for builtin:converged)
    element_order: int | None = None
    fixation_radius_mm: float = 6.0
    stem_diameter_mm: float = 3.0
    labels: tuple[int, ...] | None = None
    smoothing_iterations: int | None = None
    growth_pressures_kpa: tuple[float, ...] = GROWTH_PRESSURES_KPA
    #: the grown gland's volume (None: the paper's 45 ml from 26.3, scaled to --volume-ml) at this pressure
    growth_target_ml: float | None = None
    growth_target_kpa: float = 3.0
    #: the template's chambers to design (indices into CHAMBER_KINDS)
    chambers: tuple[int, ...] = (0, 1, 2)
    #: a trained shape run (``phantom shape train``): the source's latent distance to its population's average
    shape_run: str | None = None
    #: the scene whose calibrated material law and element order the design inherits (phantom.design.material)
    material_from: str = DEFAULT_MATERIAL_FROM
    #: elements through the thinnest wall: 2 (the design), or 1 (a preview on the sizing's own coarse mesh)
    elements_per_wall: int = ELEMENTS_PER_WALL


@dataclass
class Design:
    """What was designed: the figures of the report, the stages' times (s) and the files written."""

    out: Path
    gland_volume_ml: float
    source_volume_ml: float
    smoothing_change_pct: float
    scale: float
    chamber_labels: list[str]
    chamber_volumes_ml: list[float]
    chamber_scales: list[float]
    walls_mm: dict[str, float]
    mesh_nodes: int
    mesh_tets: int
    rest_volume_ml: float
    surface_distance_mm: float
    cast: Cast
    growth_kpa: list[float]
    growth_volumes_ml: list[float]
    target: GrowthTarget
    #: the designed gland's volume at the target's pressure (ml): its volume plus the designed model's growth (None:
    #: not solved, the chambers' scale given and the growth curve without the target's pressure)
    target_reached_ml: float | None
    sizing: Sizing | None
    latent: LatentDistance | None
    notes: list[str]
    #: what a user must know: printed on stderr as well as in the report
    warnings: list[str] = field(default_factory=list)
    stage_times_s: dict[str, float] = field(default_factory=dict)
    #: the calibrated law and element order the design inherits (phantom.design.material)
    material: InheritedMaterial | None = None
    #: the mesh's element size (mm, --size-mm) and elements through the thinnest wall (2; 1 for a preview)
    mesh_size_mm: float = DesignOptions.size_mm
    elements_per_wall: int = ELEMENTS_PER_WALL

    @property
    def thinnest_wall(self) -> tuple[str, float]:
        name = min(self.walls_mm, key=lambda key: self.walls_mm[key])
        return name, self.walls_mm[name]
