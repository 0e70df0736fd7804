"""Three ways to answer "what volumes (and shape) do these chamber pressures give", from cheap to exact.

``rest``
    The rest compliance: ``c(p) = c_0 + W_0 p``, ``g(p) = g_0 + h_0 . p``, a 3x3 matrix product. The shape is
    ``x = X + sum_i p_i D_i`` with ``D_i`` the displacement per pascal of chamber ``i``.
``updated``
    The compliance updated along the way: the pressure ray ``t p``, ``t`` in [0, 1], is followed in
    ``steps`` increments with the midpoint rule, each taking the tangent displacement per pascal
    ``D = K_t(x, p)^-1 H(x)^T`` at the half-step configuration (one sparse factorisation per increment; the
    rest one is cached). ``K_t`` is the exact tangent of the co-rotational energy, including the stiffness of
    the follower pressure load ``-sum_i p_i d^2 V_i / dx^2``. Volumes are then measured exactly on the
    predicted nodes, so the geometric part of the nonlinearity is kept. For a small-strain (linear) material
    the displacement is exactly the rest compliance's, so this level is the full (linear) answer at no solve:
    one tensor product and a volume measure, milliseconds. The ``rest`` level is then exact in the
    displacements but not in the volumes, which are not linear in the displacements (at p ~ E, tens of %).
``full``
    The full solve (``model.equilibrium``) of the model's material law.
``table``
    The full solves on a grid over the operating box, solved once (cached on disk) and interpolated by cubic
    splines (:mod:`phantom.model.fidelity.response_table`): volumes, shape and the tangent compliance in a fraction of a
    millisecond, to the interpolation's error (checked against full solves when the table is built). For a
    hyperelastic scene a daemon must answer at its control rate; it is never chosen by the probe (its build
    costs a few minutes once), only named by a scene. A table whose volumes ship with the scene has no shapes:
    its outer surface's shapes come from the shapes the scene ships beside them (``[model] table_shapes``, a
    coarser grid), other shapes are full solves.

Only what is asked for is computed: :meth:`VolumeEstimator.volumes` never forms nodal positions at the rest
level, and nothing here builds meshes or stresses. ``counts`` records the work done (full solves, tangent
solves, shapes formed) so that tests can show it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from phantom import PhantomError
from phantom.model.arrays import FloatArray
from phantom.model.errors import PeakPressureError
from phantom.model.fem.model import Compliance, PhantomModel, State, warn_if_kpa
from phantom.model.fidelity.response_table import (
    Progress,
    ResponseTable,
    SurfaceShapes,
    response_table,
    shipped_table_shapes,
)
from phantom.model.mesh.geometry import MESH_SIZE_RANGE_MM
from phantom.model.scene import FIDELITY_LEVELS

#: The levels the probe compares (``table`` is only ever named: its first build is minutes of solves).
PROBED_LEVELS = ("rest", "updated", "full")
#: Where the pressure limit lies above a chamber's peak, the levels are probed at this fraction of the peak.
PROBE_BELOW_PEAK = 0.9
#: Full-level states kept as warm starts for later answers.
KEPT_STATES = 16

#: Chamber volumes (m^3), the gland volume (m^3) and the solver's state where the level has one.
Evaluation = tuple[FloatArray, float, State | None]


def _checked_pressures(pressures_pa: ArrayLike, n_chambers: int) -> FloatArray:
    pressures = np.asarray(pressures_pa, dtype=float).reshape(-1)
    if pressures.shape != (n_chambers,):
        raise PhantomError(f"give {n_chambers} chamber pressures, got {pressures.size}")
    if not np.all(np.isfinite(pressures)):
        raise PhantomError(f"chamber pressures must be finite numbers, got {pressures.tolist()} Pa")
    return pressures


class VolumeEstimator:
    """Chamber and gland volumes (m^3), and on request the shape, at given chamber pressures (Pa).

    Parameters
    ----------
    model : PhantomModel
    level : {"rest", "updated", "full", "table"} or None
        None: the scene's ``[model] fidelity`` if it names one, else the cheapest level whose volume error
        against the converged answer, probed with every chamber at ``pressure_max_pa``, is within the scene's
        ``accuracy_pct`` (default 1 %); cheapest = the least work counted on that probe (``probe_costs``: linear
        systems solved anew), never its clock time, so that the choice does not depend on the machine or its
        load. The error is the level's against the full solve on the model's mesh plus that solve's
        discretisation error, estimated on a finer mesh (a built-in mesh only; ``discretisation_error_pct``).
        The probe's errors (% of the volume), costs and times (s; shown, not used) are kept in
        ``probe_errors_pct``, ``probe_costs`` and ``probe_times_s``; when no level meets the accuracy,
        PhantomError says what mesh size would.
    accuracy_pct, pressure_max_pa : float, optional
        Override the scene's model settings (:class:`phantom.model.scene.ModelSettings`: %, and Pa).
    steps : int
        Increments of the ``updated`` level.
    progress : callable(done, total), optional
        Told how the ``table`` level's build goes (when it is not cached).

    The scene's settings are the model's (:attr:`PhantomModel.model_settings`).
    """

    def __init__(self, model: PhantomModel, level: str | None = None, accuracy_pct: float | None = None,
                 pressure_max_pa: float | None = None, steps: int = 1, progress: Progress | None = None):
        settings = model.model_settings
        self.model = model
        self.n_chambers = int(model.n_chambers)
        self.steps = int(steps)
        if self.steps < 1:
            raise PhantomError(f"steps must be at least 1, got {steps}")
        self.accuracy_pct = float(accuracy_pct if accuracy_pct is not None else settings.accuracy_pct)
        if not np.isfinite(self.accuracy_pct) or self.accuracy_pct <= 0:
            raise PhantomError(f"accuracy_pct must be a positive percentage, got {self.accuracy_pct}")
        self.pressure_max_pa = float(settings.pressure_max_pa if pressure_max_pa is None else pressure_max_pa)
        self.counts = {"full_solves": 0, "tangent_solves": 0, "shapes": 0}
        self.probe_errors_pct: dict[str, float] = {}
        self.probe_times_s: dict[str, float] = {}
        #: the probe's work per level, which ranks them: linear systems solved anew (tangent factorisations, Newton
        #: iterations; the rest level's 3x3 product and the one-time rest compliance count nothing)
        self.probe_costs: dict[str, int] = {}
        #: the probe's full solve against the converged answer; None when no probe ran or the mesh cannot be
        #: refined (:func:`discretisation_error`)
        self.discretisation: Discretisation | None = None
        self._rest_compliance: Compliance | None = None
        self._states: list[State] = []
        self.table: ResponseTable | None = None
        #: the outer surface's shapes shipped with a table of volumes only (``[model] table_shapes``), or None
        self.shapes: SurfaceShapes | None = None
        level = level if level is not None else settings.fidelity
        if level is None:
            level = self._cheapest_level()
        if level not in FIDELITY_LEVELS:
            raise PhantomError(f"fidelity must be one of {', '.join(FIDELITY_LEVELS)}, got {level!r}")
        self.level = level
        if level == "table":
            points = settings.table_points
            self.table = response_table(model, self.pressure_max_pa, points, progress=progress)
            if self.table.check_errors_pct > self.accuracy_pct:
                raise PhantomError(
                    f"the response table misses the full solve by {self.table.check_errors_pct:.3g} % of a volume "
                    f"(accuracy_pct {self.accuracy_pct:g}): raise [model] table_points (now {points}), or use "
                    "fidelity full")
            if self.table.position_values is None:
                self.shapes = shipped_table_shapes(model, self.pressure_max_pa)

    # ----------------------------------------------------------------- public
    @property
    def discretisation_error_pct(self) -> float | None:
        """The probe's full solve against the converged answer, % of a volume (:attr:`discretisation`)."""
        return None if self.discretisation is None else self.discretisation.error_pct

    def volumes(self, pressures_pa: ArrayLike) -> tuple[FloatArray, float]:
        """Chamber volumes (m^3, one per chamber) and the gland volume (m^3) at ``pressures_pa`` (Pa: ones that look
        like kPa are warned of, :func:`~phantom.model.fem.model.warn_if_kpa`)."""
        warn_if_kpa(_checked_pressures(pressures_pa, self.n_chambers), self.model)
        chamber_volumes_m3, gland_volume_m3, _ = self.evaluate(pressures_pa)
        return chamber_volumes_m3, gland_volume_m3

    def shape(self, pressures_pa: ArrayLike, nodes: ArrayLike | None = None) -> FloatArray:
        """Nodal positions (m, shape (nodes, 3)) at ``pressures_pa``: of every node, or of ``nodes`` (indices)
        when given; computed only when called."""
        pressures = _checked_pressures(pressures_pa, self.n_chambers)
        warn_if_kpa(pressures, self.model)
        self.counts["shapes"] += 1
        if self.shapes is not None and nodes is not None:
            surface_m = self.shapes.positions_m(pressures, nodes)
            if surface_m is not None:
                return surface_m
        if self.level == "rest":
            positions_m = self._rest_positions(pressures)
        elif self.level == "updated":
            positions_m = self._updated_positions(pressures)
        elif self.table is not None and self.table.position_values is not None:
            positions_m = self.table.positions_m(pressures)
        else:
            # (a table shipped with its scene has volumes only: a shape its shipped shapes do not hold is solved,
            # from the nearest one solved)
            positions_m = self._full_state(pressures).positions_m
        return positions_m if nodes is None else positions_m[np.asarray(nodes)]

    def evaluate(self, pressures_pa: ArrayLike) -> Evaluation:
        """Volumes as :meth:`volumes`, plus the solver state where the level has one (else None): ``full``, and
        ``updated`` for a small-strain material, whose positions are exactly the linear solve's."""
        pressures = _checked_pressures(pressures_pa, self.n_chambers)
        warn_if_kpa(pressures, self.model)
        if self.level == "rest":
            compliance = self.rest_compliance
            return (np.asarray(self.model.rest_chamber_volumes_m3, dtype=float) + compliance.chamber_m3_per_pa
                    @ pressures, float(self.model.rest_gland_volume_m3 + compliance.gland_m3_per_pa @ pressures),
                    None)
        if self.table is not None:
            table_chambers_m3, table_gland_m3 = self.table.volumes(pressures)
            return table_chambers_m3, table_gland_m3, None
        if self.level == "updated":
            positions_m = self._updated_positions(pressures)
            chamber_volumes_m3, gland_volume_m3 = self.model.volumes(positions_m)
            state: State | None = None
            if self.model.formulation == "linear":
                state = State(positions_m, chamber_volumes_m3, gland_volume_m3, 0, 0.0, pressures, "linear")
            return np.asarray(chamber_volumes_m3, dtype=float), float(gland_volume_m3), state
        full = self._full_state(pressures)
        return np.asarray(full.chamber_volumes_m3, dtype=float), float(full.gland_volume_m3), full

    @property
    def rest_compliance(self) -> Compliance:
        """The model's rest compliance (computed once; the model caches it on disk)."""
        if self._rest_compliance is None:
            self._rest_compliance = self.model.compliance()
        return self._rest_compliance

    # ----------------------------------------------------------------- levels
    def _rest_positions(self, pressures_pa: FloatArray) -> FloatArray:
        displacement = np.asarray(self.rest_compliance.displacement_m_per_pa, dtype=float)
        positions_m: FloatArray = (np.asarray(self.model.nodes_m, dtype=float)
                                   + np.tensordot(pressures_pa, displacement, axes=1))
        return positions_m

    def _updated_positions(self, pressures_pa: FloatArray) -> FloatArray:
        """Midpoint-rule path along ``t pressures_pa``: x_{k+1} = x_k + D(x_k + D(x_k) dp/2) dp."""
        if self.model.formulation == "linear":
            # Small-strain material: the displacement is exactly linear in p, only the volume measure is not.
            return self._rest_positions(pressures_pa)
        positions_m = np.asarray(self.model.nodes_m, dtype=float).copy()
        increment_pa = pressures_pa / self.steps
        reached_pa = np.zeros(self.n_chambers)
        if not np.any(pressures_pa):
            return positions_m
        for step in range(self.steps):
            start_displacement = (self.rest_compliance.displacement_m_per_pa if step == 0
                                  else self._tangent_displacement(positions_m, reached_pa))
            half_positions_m = positions_m + 0.5 * np.tensordot(increment_pa, start_displacement, axes=1)
            half_displacement = self._tangent_displacement(half_positions_m, reached_pa + 0.5 * increment_pa)
            positions_m = positions_m + np.tensordot(increment_pa, half_displacement, axes=1)
            reached_pa = reached_pa + increment_pa
        return positions_m

    def _tangent_displacement(self, positions_m: FloatArray, pressures_pa: FloatArray) -> FloatArray:
        self.counts["tangent_solves"] += 1
        return self.model.tangent_displacement_m_per_pa(positions_m, pressures_pa)

    def _full_state(self, pressures_pa: FloatArray) -> State:
        self.counts["full_solves"] += 1
        if self.model.formulation == "linear":
            # A small-strain solve takes its load on the starting configuration: it must start at rest.
            return self.model.equilibrium(pressures_pa)
        # Start from the nearest state solved before (the inverse's iterates, the pressure limit its first
        # step often reaches), or return it when the pressures are the same.
        nearest = min(self._states, default=None,
                      key=lambda state: float(np.max(np.abs(state.pressures_pa - pressures_pa))))
        if nearest is not None and np.array_equal(pressures_pa, nearest.pressures_pa):
            return nearest
        if not np.any(pressures_pa):
            state = self.model.equilibrium(pressures_pa)  # the rest shape, no iteration
        else:
            state = self.model.equilibrium(pressures_pa,
                                           initial_positions_m=None if nearest is None else nearest.positions_m)
        self._states = [*self._states[-(KEPT_STATES - 1):], state]
        return state

    def _cheapest_level(self) -> str:
        """Probe each level with every chamber at the pressure limit and keep the cheapest (:attr:`probe_costs`,
        counted on the probe, not timed: the same scene gets the same level on any machine under any load) whose
        volume error against the converged answer is within the stated accuracy: its error against the full
        solve on this mesh plus that solve's own discretisation error (:func:`discretisation_error`; none where
        the mesh cannot be refined here). Raises PhantomError, saying what would meet it, when no level does."""
        probe_pa = np.full(self.n_chambers, self.pressure_max_pa)
        try:
            self._full_state(probe_pa)  # (kept: the full level's probe below takes it)
        except PeakPressureError as error:
            # the limit lies above a chamber's peak (a soft material): probe below the peak the path found
            probe_pa = probe_pa * PROBE_BELOW_PEAK * error.peak_pressure_kpa / error.pressure_kpa
        self.level = "rest"
        self.evaluate(probe_pa)  # the one-time rest compliance is not part of an answer's cost
        results = {}
        for level in ("full", "rest", "updated"):
            self.level = level
            tangent_solves = self.counts["tangent_solves"]
            started = time.perf_counter()
            chambers, gland, state = self.evaluate(probe_pa)
            self.probe_times_s[level] = time.perf_counter() - started
            self.probe_costs[level] = (self.counts["tangent_solves"] - tangent_solves if level == "updated"
                                       else 0 if level == "rest" else max(1, 0 if state is None else state.iterations))
            results[level] = np.append(chambers, gland)
        reference = results["full"]
        self.discretisation = discretisation = discretisation_error(self.model, probe_pa, reference)
        for level, volumes in results.items():
            self.probe_errors_pct[level] = (float(np.max(np.abs(volumes - reference) / np.abs(reference)) * 100)
                                            + (self.discretisation_error_pct or 0.0))
        meeting = [level for level in PROBED_LEVELS if self.probe_errors_pct[level] <= self.accuracy_pct]
        if not meeting and discretisation is not None:
            # (the full level's error is the discretisation's alone: it misses only where that was measured)
            size_mm = discretisation.mesh_size_for_mm(self.accuracy_pct)
            refine = (f"[geometry] mesh_size_mm = {size_mm:.2g} or less" if size_mm >= MESH_SIZE_RANGE_MM[0] else
                      f"no mesh size down to {MESH_SIZE_RANGE_MM[0]:g} mm is estimated to reach it")
            raise PhantomError(
                f"no level meets accuracy_pct {self.accuracy_pct:g}: the full solve on this mesh is an estimated "
                f"{discretisation.error_pct:.2g} % of a volume from the converged answer at "
                f"{self.pressure_max_pa / 1e3:g} kPa (a {discretisation.finer_mesh_size_mm:.3g} mm mesh moved it). "
                f"Refine the mesh ({refine}{'; or element_order = 2' if self.model.order == 1 else ''}), state the "
                f"accuracy this mesh has ([model] accuracy_pct = {1.05 * discretisation.error_pct:.2g}), or name a "
                "level ([model] fidelity)")
        # (a tie, e.g. a small-strain material's "updated" and "full" at one linear solve or none, goes to the
        # level listed first in PROBED_LEVELS)
        return min(meeting, key=lambda level: (self.probe_costs[level], PROBED_LEVELS.index(level)))


#: How much finer (in ``mesh_size_mm``) the mesh that measures a mesh's discretisation error is.
REFINEMENT_RATIO = 1.4


def assumed_convergence_order(element_order: int) -> int:
    """The order ``q`` in ``error ~ h^q`` assumed for the volumes: the displacements' L2 rate, element order + 1.
    The prostate's 10-node volumes converged faster than that when measured (bench/README.md, "Convergence under
    mesh refinement"), so an estimate made with it errs high there."""
    return element_order + 1


@dataclass(frozen=True)
class Discretisation:
    """A full solve's estimated error against the converged answer (:func:`discretisation_error`)."""

    #: the largest over the chambers and the gland, % of each volume
    error_pct: float
    mesh_size_mm: float
    finer_mesh_size_mm: float
    #: how much smaller the finer mesh's effective element size (``nodes^(-1/3)``) is
    effective_ratio: float
    #: ``q`` of :func:`assumed_convergence_order`
    convergence_order: int

    def mesh_size_for_mm(self, error_pct: float) -> float:
        """The ``mesh_size_mm`` estimated to bring the error to ``error_pct``: the effective size scales as the
        nominal one to the power these two meshes showed (gmsh's curvature sizing keeps it from scaling 1:1)."""
        power = math.log(self.effective_ratio) / math.log(self.mesh_size_mm / self.finer_mesh_size_mm)
        return float(self.mesh_size_mm * (error_pct / self.error_pct) ** (1.0 / (self.convergence_order * power)))


def discretisation_error(model: PhantomModel, pressures_pa: FloatArray,
                         volumes_m3: FloatArray) -> Discretisation | None:
    """The full solve's error against the converged answer at ``pressures_pa``, estimated from one finer mesh:
    a built-in model (:attr:`PhantomModel.mesh_size_mm`) is solved again at ``mesh_size_mm / REFINEMENT_RATIO``
    and the change extrapolated (Richardson, ``V(h) = V* + C h^q``, ``h`` the effective element size
    ``nodes^(-1/3)``, ``q`` from :func:`assumed_convergence_order`). ``volumes_m3``: this model's chamber volumes
    then the gland's at ``pressures_pa``. None for a mesh read from a file, or one at the finest size there is."""
    size_mm = model.mesh_size_mm
    if model.scene is None or size_mm is None or size_mm / REFINEMENT_RATIO < MESH_SIZE_RANGE_MM[0]:
        return None
    finer = PhantomModel.from_scene(model.scene, mesh_size_mm=size_mm / REFINEMENT_RATIO)
    ratio = (len(finer.nodes_m) / len(model.nodes_m)) ** (1.0 / 3.0)
    if ratio <= 1.0:
        return None
    state = finer.equilibrium(pressures_pa)
    finer_m3 = np.append(state.chamber_volumes_m3, state.gland_volume_m3)
    change = float(np.max(np.abs(volumes_m3 - finer_m3) / np.abs(finer_m3)))
    order = assumed_convergence_order(model.order)
    refined = ratio ** order
    return Discretisation(100.0 * change * refined / (refined - 1.0), size_mm, size_mm / REFINEMENT_RATIO, ratio,
                          order)
