"""The chambers sized to a growth target: the paper's phantom grows from 26.3 to 45 ml within 3 kPa.

The chambers' size is one number, the scale of the template's semi-axes (:func:`place_chambers`'s ``chamber_scale``;
each chamber then shrinks where a wall would be under the minimum, so above some scale a chamber stays as large as its
walls allow). The search finds that scale from the model's growth at the target pressure, on cheap solves: a coarse
mesh of the same design (one element through the thinnest wall, the inherited material's element order:
:mod:`phantom.design.material`) and one solve each with the inherited calibrated law at the target pressure (a small-
strain solve would miss a soft silicone's large-strain growth several-fold). It starts from the largest scale: when
even the largest chambers the walls allow fall short, those are the design and the shortfall is said; a scale whose
walls give way before the target pressure (no equilibrium) counts as growing without bound. Else it steps by the power
law of growth in scale through its last two solves (a secant in log-log: growth goes about as the cube of the scale,
faster in thin walls), kept within the bracket the solves so far give (bisecting when a step would leave it), until
the coarse growth is within GROWTH_TOLERANCE of the target's: three or four solves. The designed mesh confirms the
answer (the pipeline solves it at the target pressure with the scene's own material law), and the report gives both
figures.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from phantom.design.chambers import CHAMBER_SCALE_RANGE, ChamberDesign, place_chambers
from phantom.design.errors import DesignError
from phantom.design.material import InheritedMaterial
from phantom.design.surface import Surface
from phantom.model.arrays import FloatArray
from phantom.model.mesh.geometry import MESH_SIZE_RANGE_MM

#: The paper's targets: the average gland's volume (ml) and the growth its phantom reaches (to 45 ml) within 3 kPa.
PAPER_VOLUME_ML = 26.3
PAPER_GROWN_VOLUME_ML = 45.0
PAPER_PRESSURE_KPA = 3.0
#: The phantom's pressure limit (kPa): a target pressure above it cannot be applied.
PRESSURE_LIMIT_KPA = 3.0
#: A grown volume above this multiple of the gland's is not a phantom's (silicone walls stretched past tearing).
LARGEST_GROWTH_RATIO = 4.0
#: Steps of the search after the largest chambers' solve.
SEARCH_STEPS = 5
#: The search stops when the coarse growth is this close to the target's (fraction of the growth wanted).
GROWTH_TOLERANCE = 0.05
#: The coarse mesh's element size: this multiple of the design's, at least COARSE_SIZE_MM.
COARSE_FACTOR = 1.6
COARSE_SIZE_MM = 4.0


@dataclass(frozen=True)
class GrowthTarget:
    """The grown gland's volume (ml) to reach, every chamber at ``pressure_kpa``."""

    volume_ml: float
    pressure_kpa: float


def growth_target(gland_volume_ml: float, volume_ml: float | None = None,
                  pressure_kpa: float = PAPER_PRESSURE_KPA) -> GrowthTarget:
    """``--growth-target-ml`` and ``--growth-target-kpa`` checked; the volume defaults to the paper's growth (45 ml
    from 26.3) scaled to a gland of ``gland_volume_ml``."""
    if not 0.0 < pressure_kpa <= PRESSURE_LIMIT_KPA:
        raise DesignError(f"--growth-target-kpa {pressure_kpa:g} is out of range: use above 0 and up to "
                          f"{PRESSURE_LIMIT_KPA:g} kPa (the phantom's limit)")
    if volume_ml is None:
        volume_ml = PAPER_GROWN_VOLUME_ML / PAPER_VOLUME_ML * gland_volume_ml
    if not volume_ml > gland_volume_ml:
        raise DesignError(f"--growth-target-ml {volume_ml:g} is not above the gland's {gland_volume_ml:g} ml: it is "
                          f"the grown gland's volume (the paper's: 45 ml from 26.3)")
    if volume_ml > LARGEST_GROWTH_RATIO * gland_volume_ml:
        raise DesignError(f"--growth-target-ml {volume_ml:g} is more than {LARGEST_GROWTH_RATIO:g} times the gland's "
                          f"{gland_volume_ml:g} ml: no silicone phantom grows so much; give a grown volume up to "
                          f"{LARGEST_GROWTH_RATIO * gland_volume_ml:g} ml")
    return GrowthTarget(float(volume_ml), float(pressure_kpa))


def target_reached(gland_volume_ml: float, target: GrowthTarget, reached_ml: float | None) -> bool | None:
    """Whether the designed gland grows to the target, to within the search's tolerance of the growth wanted (None:
    not solved)."""
    if reached_ml is None:
        return None
    return reached_ml - gland_volume_ml >= (1.0 - GROWTH_TOLERANCE) * (target.volume_ml - gland_volume_ml)


@dataclass
class Sizing:
    """What the search found: the chambers' scale of the template, whether the coarse model reached the target,
    whether the scale is the walls' limit (the largest tried), and each step's (scale, coarse grown volume ml)."""

    target: GrowthTarget
    scale: float
    reached: bool
    coarse_size_mm: float
    steps: list[tuple[float, float]] = field(default_factory=list)

    @property
    def coarse_volume_ml(self) -> float:
        return dict(self.steps)[self.scale]

    @property
    def at_walls_limit(self) -> bool:
        return self.scale == CHAMBER_SCALE_RANGE[1]


def size_chambers(surface: Surface, samples_mm: FloatArray, kinds: tuple[int, ...], min_wall_mm: float,
                  target: GrowthTarget, size_mm: float, fixation_radius_mm: float,
                  progress: Callable[[str], None], material: InheritedMaterial) -> tuple[ChamberDesign, Sizing]:
    """The chambers ``kinds`` at the least scale whose coarse growth with ``material`` reaches ``target``, else at
    the largest the walls allow (see the module docstring)."""
    coarse_mm = min(max(COARSE_FACTOR * size_mm, COARSE_SIZE_MM), MESH_SIZE_RANGE_MM[1])
    rest_ml = surface.volume_ml()
    steps: list[tuple[float, float]] = []
    designs: dict[float, ChamberDesign] = {}
    most = SEARCH_STEPS + 1

    def grown_ml(scale: float) -> float:
        designs[scale] = place_chambers(surface, min_wall_mm, scale, samples_mm, kinds)
        # the coarse mesh's growth on the designed surface's volume: its own rest volume is the coarse surface's
        volume = rest_ml + coarse_growth_ml(surface, designs[scale], target.pressure_kpa, coarse_mm,
                                            fixation_radius_mm, samples_mm, material)
        steps.append((scale, volume))
        progress(f"design: sizing {len(steps)}/{most}: chambers at {scale:.3f} of the template grow the gland to "
                 f"{volume:.2f} ml at {target.pressure_kpa:g} kPa (coarse {coarse_mm:g} mm mesh, "
                 f"{material.table['model']}; target {target.volume_ml:.2f} ml)")
        return volume

    wanted_ml = target.volume_ml - rest_ml
    smallest, top = CHAMBER_SCALE_RANGE
    largest = grown_ml(top) - rest_ml
    if largest < wanted_ml * (1.0 - GROWTH_TOLERANCE):
        return designs[top], Sizing(target, top, False, coarse_mm, steps)
    # the bracket in the scale asked for: no chambers grow nothing; from the largest chamber's own scale at the
    # walls' limit up, every chamber is as large as its walls allow
    low, high = (0.0, 0.0), (max(designs[top].scales), largest)
    last = high
    exponent = 3.0  # a thin-walled cavity's growth goes about as its volume
    scale = high[0] * (wanted_ml / largest) ** (1.0 / exponent)
    for _ in range(SEARCH_STEPS):
        scale = max(scale, smallest)
        growth = grown_ml(scale) - rest_ml
        close = abs(growth - wanted_ml) <= GROWTH_TOLERANCE * wanted_ml
        if close or (scale == smallest and growth >= wanted_ml):
            return designs[scale], Sizing(target, scale, growth >= wanted_ml * (1.0 - GROWTH_TOLERANCE), coarse_mm,
                                          steps)
        if growth >= wanted_ml:
            high = (scale, growth)
        else:
            low = (scale, growth)
        # the next scale from the power law through the last two solves (a secant in log-log), kept in the bracket
        if 0.0 < last[1] < math.inf and 0.0 < growth < math.inf and last[0] != scale:
            exponent = float(np.clip(math.log(last[1] / growth) / math.log(last[0] / scale), 1.0, 8.0))
        last = (scale, growth)
        scale = scale * (wanted_ml / max(growth, 1e-6 * wanted_ml)) ** (1.0 / exponent)
        if not low[0] < scale < high[0]:
            scale = 0.5 * (low[0] + high[0])
    if high[0] not in designs:  # the walls' limit was the nearest above
        return designs[top], Sizing(target, top, True, coarse_mm, steps)
    return designs[high[0]], Sizing(target, high[0], True, coarse_mm, steps)


def coarse_growth_ml(surface: Surface, chambers: ChamberDesign, pressure_kpa: float, size_mm: float,
                     fixation_radius_mm: float, samples_mm: FloatArray, material: InheritedMaterial) -> float:
    """The gland's growth (ml) at ``pressure_kpa`` in every chamber: the design meshed at ``size_mm`` with
    ``material``'s element order, one element through the thinnest wall, solved with its law; infinite where the
    walls give way before that pressure (no equilibrium: a limit point)."""
    from phantom.design.meshing import mesh_design, write_scene
    from phantom.model.errors import SolveError
    from phantom.model.fem.model import PhantomModel
    from phantom.model.mesh.tetmesh import write_mesh
    from phantom.model.scene import load_scene

    mesh = mesh_design(surface, chambers.chambers, size_mm, material.element_order, fixation_radius_mm, samples_mm,
                       elements_per_wall=1)
    with tempfile.TemporaryDirectory(prefix="phantom-sizing-") as folder:
        mesh_path = Path(folder) / "coarse.msh"
        write_mesh(mesh, mesh_path)
        write_scene(mesh_path, Path(folder) / "scene.toml", material, chambers.chambers)
        model = PhantomModel.from_scene(load_scene(Path(folder) / "scene.toml"))
        # a small-strain law's one linear solve is what its Newton iterations would converge to at these strains
        small_strain = material.table["model"] in ("linear", "corotational")
        try:
            state = model.equilibrium([pressure_kpa * 1e3] * model.n_chambers,
                                      formulation="linear" if small_strain else None)
        except SolveError:
            return math.inf
    return float(state.gland_volume_m3 - model.rest_gland_volume_m3) * 1e6
