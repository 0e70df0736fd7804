"""The quasi-static finite-element model of the phantom: equilibrium, volumes, compliance (SI units throughout).

:class:`PhantomModel` is a scene's :class:`~phantom.model.fem.body.SolidBody` (mesh, material, fixation) with the
answers people ask of it: the equilibrium at given chamber pressures (:meth:`PhantomModel.equilibrium`, Newton
on the :class:`~phantom.model.fem.problem.EquilibriumProblem` from a nearby state, else path following from
rest), volumes, deformed shapes, and the compliance (volume per pressure) at rest or at a state.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

import phantom
from phantom.model.arrays import FloatArray, IntArray
from phantom.model.errors import MeshError, PressureUnitWarning, SolveError
from phantom.model.fem import heap
from phantom.model.fem.body import Factor, SolidBody
from phantom.model.fem.linsolve import Factorization, indefinite_method
from phantom.model.fem.newton import RELATIVE_TOLERANCE, newton
from phantom.model.fem.pathfollow import follow_path
from phantom.model.fem.problem import EquilibriumProblem
from phantom.model.mesh.geometry import ProstateGeometry
from phantom.model.mesh.prostate import builtin_prostate
from phantom.model.mesh.tetmesh import Surfaces, TetMesh, prepare_surfaces, read_mesh
from phantom.model.scene import HYPERELASTIC_MODELS, MATERIAL_MODELS, Material, ModelSettings, Scene

if TYPE_CHECKING:
    import scipy.sparse

#: The formulations a solve may use: the material laws.
FORMULATIONS = MATERIAL_MODELS
#: A chamber pressure smaller in magnitude than this fraction of the Young's modulus is zero. Newton's tolerance is
#: relative to the load, and at a load of 1e-3 Pa (the simulated plant reads 2e-9 Pa after a vent) rounding in the
#: node positions alone exceeds it; the 10-node converged model (E 10.86 kPa) solves 0.1 Pa and fails at 0.01 Pa.
#: 1e-5 E is 0.11 Pa there and 0.5 Pa on the built-in 50 kPa scene, under the board's 1 Pa step (the wire
#: protocol's pressures are whole pascals); a fraction of E, not pascals, so that the same p/E gives the same
#: shape at any modulus.
PRESSURE_RESOLUTION_OF_MODULUS = 1e-5
#: Chamber pressures (Pa) all above 0 and under this are kPa given as Pa, most likely: the phantom's sensors
#: resolve one ADC count, 54.25 Pa (docs/physics.md, "Sensor"), so a state its board holds has a chamber at a count
#: or more, or every one vented (about 0); its box is 0 to a few kPa, which as Pa is all under it. ``[1, 2, 0.5]``
#: answered all but the rest shape in silence (:func:`warn_if_kpa`) ...
KPA_AS_PA_BELOW_PA = 50.0
#: ... when they are under this fraction of the Young's modulus too: a load that deforms the body by about 0.1 % at
#: most, all but the rest shape (the box's kPa as Pa on the phantom's silicone, 6-50 kPa, is 2e-5 to 5e-4 of it). A
#: model of a softer material (a test's 1 Pa sphere) is deformed by a few Pa, which are then no mistake.
KPA_AS_PA_OF_MODULUS = 1e-3


def warn_if_kpa(pressures_pa: FloatArray, model: PhantomModel) -> None:
    """Warn (:class:`PressureUnitWarning`, at the caller's line) when every chamber pressure (Pa) is above 0 and under
    :data:`KPA_AS_PA_BELOW_PA` and :data:`KPA_AS_PA_OF_MODULUS` of the ``model``'s modulus, and the function
    calling this was called from outside the package: the package's own calls pass measured pressures (a vented
    chamber reads a few Pa) and solvers' iterates, which are Pa. A warning, not a refusal: a load of a few Pa on
    purpose (a small-strain check) is the model's to answer."""
    if not (pressures_pa.size and np.all(pressures_pa > 0) and np.all(pressures_pa < KPA_AS_PA_BELOW_PA)):
        return
    # frames: 0 this function, 1 the model's entry point, then its caller, past a decorator's wrapper
    # (equilibrium's heap.solving is a context manager's)
    frame, depth = sys._getframe(2), 2
    while frame.f_back is not None and frame.f_globals.get("__name__") == "contextlib":
        frame, depth = frame.f_back, depth + 1
    caller = str(frame.f_globals.get("__name__", ""))
    if caller == "phantom" or caller.startswith("phantom.") \
            or np.any(pressures_pa >= KPA_AS_PA_OF_MODULUS * model.material.youngs_modulus_pa):
        return
    shown, times_1000 = (", ".join(f"{p:g}" for p in pressures) for pressures in (pressures_pa, 1e3 * pressures_pa))
    warnings.warn(f"the chamber pressures {shown} Pa are all under {KPA_AS_PA_BELOW_PA:g} Pa, below one count of the "
                  f"phantom's sensors (54 Pa), and answer all but the rest shape: did you pass kPa? this takes Pa (x "
                  f"1000: {times_1000} Pa)", PressureUnitWarning, stacklevel=depth + 1)


#: Newton iterations from a predicted start (:meth:`PhantomModel.equilibrium`'s ``predicted_positions_m``) before
#: it is given up for the last equilibrium: a calibration trace's quadratic prediction converges in 5-6.
PREDICTED_NEWTON_ITERATIONS = 10


@dataclass
class State:
    """A solved equilibrium.

    positions_m : (n, 3) node positions; chamber_volumes_m3 : (n_chambers,); gland_volume_m3 : volume enclosed
    by the outer boundary; iterations : Newton iterations over all load steps; solve_time_s : wall time;
    pressures_pa : (n_chambers,) the gauge pressures solved for; formulation : "corotational", "linear",
    "neo_hookean", "gent" or "yeoh"; load_steps : the accepted load (or volume) steps; load_positions_m : (n, 3)
    or None, for the linear formulation the configuration its (dead) pressure load was taken on when that was not
    the rest shape (None: rest); body_force_n_per_m3 : (3,) the body force (gravity) it was solved under (N/m^3).
    """

    positions_m: FloatArray
    chamber_volumes_m3: FloatArray
    gland_volume_m3: float
    iterations: int
    solve_time_s: float
    pressures_pa: FloatArray
    formulation: str = "corotational"
    load_steps: int = 1
    load_positions_m: FloatArray | None = None
    body_force_n_per_m3: FloatArray = dataclasses.field(default_factory=lambda: np.zeros(3))


@dataclass
class Compliance:
    """Volume (and displacement) per unit pressure at one state.

    chamber_m3_per_pa : (n_chambers, n_chambers) symmetric, W_ij = dV_i / dp_j = H_i K^-1 H_j^T;
    gland_m3_per_pa : (n_chambers,) d(gland volume) / dp_j; displacement_m_per_pa : (n_chambers, n_nodes, 3)
    the node displacement per pascal in each chamber (so a shape is ``x + sum_j dp_j displacement[j]``).
    """

    chamber_m3_per_pa: FloatArray
    gland_m3_per_pa: FloatArray
    displacement_m_per_pa: FloatArray


class PhantomModel:
    """The phantom's finite-element model (mesh, material, fixation); see the module docstring.

    Build with :meth:`from_scene`. Attributes: ``body`` (the :class:`SolidBody`: assembly, springs, held dofs),
    ``chamber_names``, ``n_chambers``, ``nodes_m`` (n, 3) rest positions, ``tets`` (m, 4 or 10), ``order`` (1 or
    2), ``outer_triangles`` (k, 3) outward, ``chamber_triangles`` (list, each oriented out of its cavity),
    ``fixed_triangles`` (3-node triangles, for drawing: a 6-node face is split in four at its mid-edge nodes),
    ``outer_faces``, ``chamber_faces``, ``fixed_faces`` (the same surfaces as the model's own 3- or 6-node faces,
    whose curved volumes the model measures),
    ``rest_chamber_volumes_m3``, ``rest_gland_volume_m3``, ``material``, ``formulation`` (the scene's),
    ``scene`` (the Scene it was built from, None for a bare mesh), and its :attr:`model_settings`, which the
    inverse and the volume estimator read; ``mesh_size_mm``, the built-in mesh's element size (None for a mesh
    read from a file, which cannot be refined here).
    """

    def __init__(self, mesh: TetMesh, surfaces: Surfaces, chamber_names: list[str], material: Material,
                 source: str = "mesh", linear_solver: str | None = None, scene: Scene | None = None,
                 mesh_size_mm: float | None = None):
        self.body = SolidBody(mesh, surfaces, chamber_names, material, source, linear_solver)
        self.scene = scene
        self.mesh_size_mm = mesh_size_mm
        self.mesh = mesh
        self.source = source
        self.linear_solver = linear_solver
        self.material = material
        self.formulation = material.model
        self.nodes_m = self.body.nodes_m
        self.tets = self.body.tets
        self.chamber_names = self.body.chamber_names
        self.n_chambers = self.body.n_chambers
        self.order = self.body.order
        self.chamber_faces = self.body.chamber_faces
        self.outer_faces = self.body.outer_faces
        self.fixed_faces = self.body.fixed_faces
        self.chamber_triangles = surfaces.chamber_triangles
        self.outer_triangles = surfaces.outer_triangles
        self.fixed_triangles = surfaces.fixed_triangles
        self.rest_chamber_volumes_m3 = self.body.rest_chamber_volumes_m3
        self.rest_gland_volume_m3 = self.body.rest_gland_volume_m3
        #: The body force of the scene's ``[load]`` hanging in air (N/m^3): what a solve applies unless told.
        self.body_force_n_per_m3 = np.array(scene.load.body_force_n_per_m3() if scene is not None else (0.0,) * 3)

    @classmethod
    def from_scene(cls, scene: Scene, mesh_size_mm: float | None = None) -> PhantomModel:
        """The model of a scene; the built-in mesh comes from the on-disk cache when it was made before."""
        if scene.mesh == "builtin:prostate":
            if scene.units != "mm":
                raise MeshError(f"the built-in mesh is in millimetres: set [phantom] units = \"mm\" (not "
                                f"{scene.units!r})")
            geometry = scene.geometry or ProstateGeometry()
            mesh_size_mm = geometry.mesh_size_mm if mesh_size_mm is None else float(mesh_size_mm)
            mesh, source = builtin_prostate(mesh_size_mm, scene.geometry), "builtin:prostate"
        else:
            if mesh_size_mm is not None:
                raise MeshError(f"mesh_size_mm applies to the built-in mesh only; {scene.mesh} is read as it is")
            mesh, source = read_mesh(scene.mesh, scene.length_scale_m), scene.mesh
        surfaces = prepare_surfaces(mesh, scene.chambers, scene.fixed, source)
        return cls(mesh, surfaces, scene.chambers, scene.material, source, scene=scene, mesh_size_mm=mesh_size_mm)

    @property
    def pressure_resolution_pa(self) -> float:
        """The smallest chamber pressure (Pa) a solve tells from zero (:data:`PRESSURE_RESOLUTION_OF_MODULUS`)."""
        return PRESSURE_RESOLUTION_OF_MODULUS * self.material.youngs_modulus_pa

    def with_material(self, youngs_modulus_pa: float | None = None, poisson_ratio: float | None = None,
                      model: str | None = None, gent_jm: float | None = None,
                      yeoh_c20_over_c10: float | None = None, yeoh_c30_over_c10: float | None = None) -> PhantomModel:
        """The same mesh, fixation and scene settings with another material (modulus in Pa; ``gent_jm`` for
        model "gent", the ``yeoh_*`` coefficients for "yeoh", each kept from the current material when not
        given)."""
        model = model or self.material.model
        if gent_jm is None and model == "gent":
            gent_jm = self.material.gent_jm
        yeoh = (self.material.yeoh_c20_over_c10 if yeoh_c20_over_c10 is None else float(yeoh_c20_over_c10),
                self.material.yeoh_c30_over_c10 if yeoh_c30_over_c10 is None else float(yeoh_c30_over_c10))
        material = Material(
            model,
            self.material.youngs_modulus_pa if youngs_modulus_pa is None else float(youngs_modulus_pa),
            self.material.poisson_ratio if poisson_ratio is None else float(poisson_ratio),
            None if model != "gent" or gent_jm is None else float(gent_jm),
            *(yeoh if model == "yeoh" else (None, None)),
        )
        scene = None if self.scene is None else dataclasses.replace(self.scene, material=material)
        return PhantomModel(self.mesh, self.body.surfaces, self.chamber_names, material, self.source,
                            self.linear_solver, scene, self.mesh_size_mm)

    @property
    def model_settings(self) -> ModelSettings:
        """How the scene wants the model to answer (its ``[model]`` table; the defaults without a scene)."""
        return self.scene.model_settings if self.scene is not None else ModelSettings()

    @property
    def held_dofs(self) -> IntArray:
        """Dofs (3 node + axis) held at rest to remove rigid motion when there is no fixed group (else empty)."""
        return self.body.rest_constraints.dofs

    def cache_key(self, extra: bytes = b"") -> str:
        """A hash of the model (mesh, groups, springs, material, solver version) and ``extra``, to name a file
        that stores one of its answers (:meth:`SolidBody.cache_key`)."""
        return self.body.cache_key(extra)

    # --- deformed shapes ---------------------------------------------------------------------------------

    def deformed_mesh(self, state: State) -> TetMesh:
        """The model's tetrahedral mesh at ``state`` (same node order, tetrahedra and surface groups as the
        rest mesh; positions in m), e.g. for ``mesh.write_mesh``."""
        return TetMesh(np.array(state.positions_m, float), self.tets, dict(self.mesh.surface_groups))

    def deformed_surface(self, pressures_pa: FloatArray | list[float], formulation: str | None = None,
                         initial_positions_m: FloatArray | None = None) -> tuple[FloatArray, IntArray]:
        """The outer surface deformed by gauge pressures (Pa, chamber order): ``(positions_mm, triangles)``,
        the surface's own nodes (k, 3) in millimetres and its triangles (t, 3) indexing them, normals outward.

        Solves like :meth:`equilibrium` (same arguments and errors). The surface's node order is fixed for a
        model (``np.unique`` of the outer triangles), so successive calls can be drawn as one changing mesh.
        """
        warn_if_kpa(self._check_pressures(pressures_pa), self)
        state = self.equilibrium(pressures_pa, formulation=formulation, initial_positions_m=initial_positions_m)
        surface_nodes, triangles = self.outer_surface()
        return state.positions_m[surface_nodes] * 1e3, triangles

    def outer_surface(self) -> tuple[IntArray, IntArray]:
        """The outer surface as a mesh of its own: ``(surface_nodes, triangles)``, the indices of the model's
        nodes on it (sorted) and the outer triangles renumbered into them. Drawing only these keeps a mesh small.
        """
        surface_nodes, triangles = np.unique(self.outer_triangles, return_inverse=True)
        return surface_nodes, triangles.reshape(-1, 3)

    # --- volumes -----------------------------------------------------------------------------------------

    def volumes(self, positions_m: FloatArray) -> tuple[FloatArray, float]:
        """Chamber volumes (m^3, chamber order) and the gland volume (m^3, inside the outer boundary)."""
        return self.body.volumes(positions_m)

    def volume_gradients(self, positions_m: FloatArray) -> FloatArray:
        """``H``: (n_chambers + 1, 3 n) gradients of each chamber's volume and of the gland's (m^2)."""
        return self.body.volume_gradients(positions_m)

    # --- matrices ----------------------------------------------------------------------------------------

    def rest_factorization(self) -> Factor:
        """The factorised small-strain stiffness (elastic + springs + held dofs), made once per model and kept
        on disk (:meth:`SolidBody.rest_factorization`)."""
        return self.body.rest_factorization()

    def stiffness_matrix(self, positions_m: FloatArray | None = None, formulation: str = "linear",
                         pressures_pa: FloatArray | list[float] | None = None) -> scipy.sparse.csr_matrix:
        """The assembled tangent (N/m, CSR; held dofs replaced by scaled identity rows) at ``positions_m``
        (default: rest).

        "linear": the small-strain stiffness; "corotational" and the hyperelastic laws: the exact Hessian of the total
        energy, with the follower-load stiffness of ``pressures_pa`` when given.
        """
        pressures = None if pressures_pa is None else self._check_pressures(pressures_pa)
        return self.body.csr(self.body.tangent_data(positions_m, formulation, pressures))

    # --- equilibrium -------------------------------------------------------------------------------------

    def _check_pressures(self, pressures_pa: FloatArray | list[float]) -> FloatArray:
        pressures = np.asarray(pressures_pa, dtype=float).ravel()
        if pressures.shape != (self.n_chambers,):
            raise SolveError(f"expected {self.n_chambers} chamber pressures ({', '.join(self.chamber_names)}), "
                             f"got {pressures.size}")
        if not np.all(np.isfinite(pressures)):
            raise SolveError(f"chamber pressures must be finite numbers, got {pressures.tolist()} Pa")
        return pressures

    def problem(self, pressures_pa: FloatArray | list[float], formulation: str | None = None,
                start_m: FloatArray | None = None,
                body_force_n_per_m3: FloatArray | list[float] | None = None) -> EquilibriumProblem:
        """The equilibrium problem at gauge pressures (Pa, chamber order) from ``start_m`` (default: rest), in
        ``formulation`` (None: the scene's), under ``body_force_n_per_m3`` (None: the scene's gravity in air). Its
        held dofs (without a fixed group) are chosen in the frame of the start (of the rest shape for "linear",
        whose stiffness is the rest shape's)."""
        pressures = self._check_pressures(pressures_pa)
        body_force = (self.body_force_n_per_m3 if body_force_n_per_m3 is None
                      else np.asarray(body_force_n_per_m3, dtype=float).reshape(-1))
        if body_force.shape != (3,) or not np.all(np.isfinite(body_force)):
            raise SolveError(f"the body force must be three finite numbers (N/m^3), got {body_force.tolist()}")
        formulation = formulation or self.formulation
        if formulation not in FORMULATIONS:
            raise SolveError(f"unknown formulation {formulation!r}: use one of {', '.join(FORMULATIONS)}")
        if formulation in HYPERELASTIC_MODELS:
            self.body.law(formulation)  # SolveError for a law whose coefficients the material lacks
        start = self.nodes_m.copy() if start_m is None else np.array(start_m, float)
        if start.shape != self.nodes_m.shape or not np.all(np.isfinite(start)):
            raise SolveError(f"initial_positions_m must be a finite array of shape {self.nodes_m.shape}")
        frame_m = self.nodes_m if formulation == "linear" else start
        return EquilibriumProblem(self.body, pressures, formulation, start, self.body.constraints_for(frame_m),
                                  body_force.copy())

    @heap.solving()
    def equilibrium(self, pressures_pa: FloatArray | list[float], formulation: str | None = None,
                    initial_positions_m: FloatArray | None = None, tolerance: float = RELATIVE_TOLERANCE,
                    body_force_n_per_m3: FloatArray | list[float] | None = None,
                    predicted_positions_m: FloatArray | None = None,
                    predicted_element_pressures_pa: FloatArray | None = None) -> State:
        """The equilibrium under gauge pressures (Pa, chamber order) and a body force (N/m^3; None: the scene's
        gravity hanging in air, :attr:`body_force_n_per_m3`).

        ``formulation`` None uses the scene's; "linear" is small-strain elasticity with the pressure load taken
        on the starting configuration (one linear solve); "corotational" follows the walls and is solved by
        Newton iterations with a line search on the total energy, cutting the load into steps when a full
        step fails. ``initial_positions_m`` starts from another configuration (default: rest); for a hyperelastic
        law Newton at the full load is tried from there first (it converges in a few iterations from a nearby
        equilibrium), path following from zero load when it does not converge. ``predicted_positions_m`` (with
        ``initial_positions_m``): where that Newton starts instead, e.g. a continuation's extrapolation of its last
        equilibria, with a 10-node body's element pressures ``predicted_element_pressures_pa`` (None: eliminated
        there); the problem's frame and the path following stay those of ``initial_positions_m``.
        Raises SolveError (naming the chamber and pressure) when it cannot converge or elements invert. A pressure
        under :attr:`pressure_resolution_pa` in magnitude is zero. Pressures that look like kPa (all above 0 and
        under :data:`KPA_AS_PA_BELOW_PA`) are warned of (:func:`warn_if_kpa`), and solved.
        """
        started = time.perf_counter()
        pressures = self._check_pressures(pressures_pa)
        warn_if_kpa(pressures, self)
        resolved = np.where(np.abs(pressures) < self.pressure_resolution_pa, 0.0, pressures)
        problem = self.problem(resolved, formulation, initial_positions_m, body_force_n_per_m3)
        positions_m, iterations, steps = problem.start_m, 0, 0
        if problem.loaded or initial_positions_m is not None:
            warm = None
            if initial_positions_m is not None and problem.formulation in HYPERELASTIC_MODELS and problem.loaded:
                # From a nearby equilibrium (an iteration's previous answer) Newton at the full load takes a few
                # iterations; path following would start again from zero load on the inflated shape. A prediction
                # that does not converge within PREDICTED_NEWTON_ITERATIONS (near a limit point) is given up.
                if predicted_positions_m is not None:
                    warm = newton(problem, predicted_positions_m, tolerance,
                                  element_pressures_pa=predicted_element_pressures_pa,
                                  max_iterations=PREDICTED_NEWTON_ITERATIONS)
                    iterations = warm.iterations
                if warm is None or not warm.converged:
                    warm = newton(problem, problem.start_m, tolerance)
                    iterations += warm.iterations
            if warm is not None and warm.converged:
                positions_m, steps = warm.positions_m, 1
            else:
                path = follow_path(problem, tolerance)
                positions_m, iterations, steps = path.positions_m, iterations + path.iterations, path.steps
        chamber_volumes_m3, gland_volume_m3 = self.volumes(positions_m)
        load_positions_m = (problem.start_m if problem.formulation == "linear" and initial_positions_m is not None
                            else None)
        return State(positions_m, chamber_volumes_m3, gland_volume_m3, iterations, time.perf_counter() - started,
                     problem.pressures_pa, problem.formulation, steps, load_positions_m,
                     problem.body_force_n_per_m3)

    def extrapolated_start(self, line_m: list[FloatArray], load_factors: list[float] | None = None,
                           load_factor: float = 0.0) -> tuple[FloatArray | None, FloatArray | None]:
        """A predicted start (for :meth:`equilibrium`'s ``predicted_positions_m`` and
        ``predicted_element_pressures_pa``) of the equilibrium at ``load_factor`` from the equilibria ``line_m``
        at ``load_factors`` (nearest first; default equally spaced before it: ``-1, -2, ...``): the Lagrange
        polynomial through them (a secant through two, a quadratic through three), exact on a path that is that
        polynomial, and a 10-node body's element pressures extrapolated alike (eliminated at each equilibrium:
        eliminated at the extrapolated positions, ``K (Jbar - 1)`` would carry K times the extrapolation's error in
        the volume ratios; None for a 4-node body). ``(None, None)`` where only one is given or the polynomial
        would invert an element: start from the nearest equilibrium."""
        loads = [-(i + 1.0) for i in range(len(line_m))] if load_factors is None else list(load_factors)
        weights = np.array([np.prod([(load_factor - t_j) / (t_i - t_j) for j, t_j in enumerate(loads) if j != i])
                            for i, t_i in enumerate(loads)])
        guess: FloatArray = np.tensordot(weights, np.stack([np.asarray(x, float) for x in line_m]), axes=1)
        if len(line_m) < 2 or not np.isfinite(guess).all() or self.body.worst_element(guess) >= 0:
            return None, None
        if self.order != 2:
            return guess, None
        carried = np.stack([self.body.eliminated_pressures_pa(self.body.element_volume_ratios(x)) for x in line_m])
        pressures: FloatArray = np.tensordot(weights, carried, axes=1)
        return guess, pressures

    # --- compliance ----------------------------------------------------------------------------------------

    def compliance(self, state: State | None = None) -> Compliance:
        """Compliance at rest (``W = H K^-1 H^T`` with the rest stiffness) or the tangent at ``state``.

        At a co-rotational state the derivative of the nonlinear solution with respect to each chamber's
        pressure is taken by central differences of re-solves started from the state (step 1 % of the largest
        pressure, at least 1e-4 E), which includes the rotation and follower-load terms the Newton tangent leaves
        out. Cached on disk (``phantom.cache_dir("compliance")``) by a hash of mesh, material, solver and state.

        At a linear (small-strain) state ``x = X + K^-1 H(x_L)^T p``, with the rest stiffness K and the load
        taken on the solve's starting shape ``x_L`` (rest unless ``state.load_positions_m``), so the displacement
        per pascal ``D = K^-1 H(x_L)^T`` does not depend on p and the tangent is exactly
        ``dV_i/dp_j = H_i(x) . D_j``: the rest displacement, with the volume gradients of the deformed state
        (the volume measure's own nonlinearity). Re-solving from the state would take the load on the deformed
        shape instead, which is another problem. One back-substitution (none from rest), so not cached.

        At a hyperelastic (Neo-Hookean, Gent) state the law's Hessian is exact, follower-load stiffness
        included, so the tangent is ``D = K_t(x, p)^-1 H(x)^T``, ``dV_i/dp_j = H_i(x) . D_j``: one factorisation,
        which agrees with the central differences to their truncation error (tested) at a fraction of the cost
        (six path-following re-solves). Not cached either.
        """
        if state is not None and state.formulation == "linear":
            return self._linear_state_compliance(state)
        if state is not None and state.formulation in HYPERELASTIC_MODELS:
            return self._hyperelastic_state_compliance(state)
        extra = b"rest"
        if state is not None:
            extra = (state.formulation.encode() + np.ascontiguousarray(state.pressures_pa).tobytes()
                     + np.ascontiguousarray(state.positions_m).tobytes())
        path = phantom.cache_dir("compliance") / f"{self.cache_key(extra)}.npz"
        if path.is_file():
            try:
                with np.load(path) as stored:
                    return Compliance(stored["chamber"], stored["gland"], stored["displacement"])
            except (OSError, ValueError, KeyError):
                path.unlink(missing_ok=True)
        result = self.rest_compliance() if state is None else self._state_compliance(state)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".npz")
        os.close(handle)
        np.savez(temporary, chamber=result.chamber_m3_per_pa, gland=result.gland_m3_per_pa,
                 displacement=result.displacement_m_per_pa)
        os.replace(temporary, path)
        return result

    def rest_compliance(self) -> Compliance:
        """The compliance at rest, computed (one back-substitution per chamber with the rest factor), not read
        from the disk cache as :meth:`compliance` does."""
        displacement = self._small_strain_displacement(self.nodes_m)
        return self._compliance_of(displacement, self.nodes_m)

    def tangent_displacement_m_per_pa(self, positions_m: FloatArray, pressures_pa: FloatArray,
                                      formulation: str | None = None) -> FloatArray:
        """Node displacement per pascal of each chamber (n_chambers, nodes, 3) at a configuration under pressures:
        ``D = K_t(x, p)^-1 H(x)^T``, with ``K_t`` the exact tangent of ``formulation`` (default the model's) if it
        is a hyperelastic law, otherwise the co-rotational one, including the follower pressure load's stiffness.
        Held dofs (rows of ``K_t`` that are a bare diagonal) get no displacement."""
        formulation = formulation or self.formulation
        formulation = formulation if formulation in HYPERELASTIC_MODELS else "corotational"
        stiffness = self.stiffness_matrix(positions_m, formulation, pressures_pa=pressures_pa).tocsr()
        magnitudes = abs(stiffness)
        held = np.asarray(magnitudes.sum(axis=1)).ravel() == magnitudes.diagonal()
        gradients = self.body.chamber_volume_gradients(positions_m)
        gradients[:, held] = 0.0
        try:
            factorization = Factorization(stiffness)
        except ArithmeticError:
            # Past a limit point the tangent is indefinite: LDL' still solves it, and the compliance's negative
            # eigenvalue then says where the state is.
            factorization = Factorization(stiffness, method=indefinite_method())
        displacement = factorization.solve(np.ascontiguousarray(gradients.T)).T
        displacement[:, held] = 0.0
        return displacement.reshape(len(pressures_pa), -1, 3)

    def _small_strain_displacement(self, load_positions_m: FloatArray) -> FloatArray:
        """``D = K^-1 H(x_L)^T`` (n_chambers, 3n), m/Pa: the small-strain displacement per pascal of each chamber
        with the load taken on ``load_positions_m`` (held dofs do not move)."""
        gradients = self.body.chamber_volume_gradients(load_positions_m)
        held = ~self.body.rest_constraints.free_mask
        gradients[:, held] = 0.0
        displacement = self.rest_factorization().solve(gradients.T).T
        displacement[:, held] = 0.0
        return displacement

    def _compliance_of(self, displacement: FloatArray, positions_m: FloatArray) -> Compliance:
        """Volume derivatives ``H(x) D^T`` at ``positions_m`` for a displacement per pascal ``D`` (n_chambers, 3n)."""
        gradients = self.volume_gradients(positions_m)
        return Compliance(gradients[:-1] @ displacement.T, gradients[-1] @ displacement.T,
                          displacement.reshape(self.n_chambers, -1, 3))

    def _linear_state_compliance(self, state: State) -> Compliance:
        if state.load_positions_m is None:
            displacement = self.compliance().displacement_m_per_pa.reshape(self.n_chambers, -1)
        else:
            displacement = self._small_strain_displacement(np.asarray(state.load_positions_m, float))
        return self._compliance_of(displacement, state.positions_m)

    def _hyperelastic_state_compliance(self, state: State) -> Compliance:
        displacement = self.tangent_displacement_m_per_pa(np.asarray(state.positions_m, float),
                                                          np.asarray(state.pressures_pa, float), state.formulation)
        return self._compliance_of(displacement.reshape(self.n_chambers, -1), state.positions_m)

    def _state_compliance(self, state: State) -> Compliance:
        step_pa = max(1e-2 * float(np.max(np.abs(state.pressures_pa))), 1e-4 * self.material.youngs_modulus_pa)
        chamber = np.empty((self.n_chambers, self.n_chambers))
        gland = np.empty(self.n_chambers)
        displacement = np.empty((self.n_chambers, *self.nodes_m.shape))
        for j in range(self.n_chambers):
            solutions = []
            for sign in (1.0, -1.0):
                pressures = state.pressures_pa.copy()
                pressures[j] += sign * step_pa
                problem = self.problem(pressures, state.formulation, state.positions_m, state.body_force_n_per_m3)
                solutions.append(follow_path(problem, 1e-11).positions_m)
            displacement[j] = (solutions[0] - solutions[1]) / (2 * step_pa)
            plus, minus = self.volumes(solutions[0]), self.volumes(solutions[1])
            chamber[:, j] = (plus[0] - minus[0]) / (2 * step_pa)
            gland[j] = (plus[1] - minus[1]) / (2 * step_pa)
        return Compliance(chamber, gland, displacement)
