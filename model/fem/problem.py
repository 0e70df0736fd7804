"""The equilibrium problem at given chamber pressures: what Newton and path following solve.

Equilibrium minimises the total energy

    Pi(x) = E_elastic(x) + 1/2 sum_fixed k_i |x_i - X_i|^2 - sum_c p_c V_c(x) - f_b . x

over node positions x (m): co-rotational (or small-strain linear, or hyperelastic) elasticity on 4-node
tetrahedra, or hyperelastic (or small-strain) elasticity on 10-node ones in the mixed formulation, penalty springs
on the fixation, a constant pressure p_c (Pa) in each closed chamber, whose load ``p_c dV_c/dx`` follows the
walls (the linear formulation takes it, dead, on the starting configuration instead), and a body force ``b``
(N/m^3, gravity: density times g) whose consistent nodal load ``f_b = b integral N_a dV`` is dead (it acts on
the rest volume, which a body force per unit mass does). A load factor scales the pressures and the body force
together.
An :class:`EquilibriumProblem` gives, at any x, the out-of-balance force (the energy's gradient), the energy and
the smallest det F in one element pass (:meth:`EquilibriumProblem.evaluate`), the tangent (its data, its product
with a vector, or a factorisation), and the worst element: the callables a Newton iteration needs, as FElupe's
``newtonraphson`` takes them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from phantom.model.arrays import FloatArray
from phantom.model.fem.body import (
    EXACT_TANGENT,
    NO_TANGENT,
    POSITIVE_TANGENT,
    Constraints,
    Factor,
    SolidBody,
    load_from_gradients_n,
)
from phantom.model.scene import HYPERELASTIC_MODELS

#: Diagonal shifts (relative to each diagonal entry) tried in turn on a hyperelastic Hessian that is not positive
#: definite in Newton's minimisation (:meth:`EquilibriumProblem.tangent`); measured on 10-node elements at
#: (1, 1, 1) kPa, 1e-4 to 1e-2 sufficed.
DAMPING_SHIFTS = (1e-4, 1e-3, 1e-2, 1e-1, 1.0)


@dataclass(frozen=True)
class Evaluation:
    """The problem at one configuration: ``residual_n`` (3n,) the out-of-balance force (N, zero at held dofs),
    ``energy_j`` the total energy (J; +inf outside a hyperelastic law's domain), ``smallest_det`` the smallest
    det F (inf for the linear formulation), and ``tangent_data`` the exact tangent's CSR data from the same
    element pass when it was asked for (else None)."""

    residual_n: FloatArray
    energy_j: float
    smallest_det: float
    tangent_data: FloatArray | None = None

    @property
    def admissible(self) -> bool:
        """No element at det F <= 0 and a finite energy: a state a solve may accept."""
        return bool(self.smallest_det > 0 and np.isfinite(self.energy_j))


@dataclass(frozen=True)
class EquilibriumProblem:
    """Equilibrium of ``body`` under chamber pressures (see the module docstring).

    Attributes
    ----------
    body : SolidBody
    pressures_pa : (n_chambers,) float array
        Gauge pressures (Pa), chamber order.
    formulation : str
        "linear", "corotational", "neo_hookean" or "gent".
    start_m : (n, 3) float array
        The configuration the solve starts from; the linear formulation takes its (dead) pressure load there.
    constraints : Constraints
        The held dofs (none with a fixed patch).
    body_force_n_per_m3 : (3,) float array
        The body force per unit rest volume (N/m^3): density (or, in water, its excess over water's) times the
        gravitational acceleration; zeros for none.
    """

    body: SolidBody
    pressures_pa: FloatArray
    formulation: str
    start_m: FloatArray
    constraints: Constraints
    body_force_n_per_m3: FloatArray = dataclasses.field(default_factory=lambda: np.zeros(3))

    @property
    def nonlinear(self) -> bool:
        """The tangent depends on the configuration (every formulation but "linear")."""
        return self.formulation != "linear"

    def at_load_factor(self, load_factor: float) -> EquilibriumProblem:
        """The same problem with the pressures and the body force scaled by ``load_factor``."""
        return dataclasses.replace(self, pressures_pa=load_factor * self.pressures_pa,
                                   body_force_n_per_m3=load_factor * self.body_force_n_per_m3)

    @property
    def mixed(self) -> bool:
        """A 10-node hyperelastic body: its element pressures can be Newton's independent unknowns."""
        return self.body.quadratic is not None and self.formulation in HYPERELASTIC_MODELS

    @property
    def loaded(self) -> bool:
        """Some pressure or body force acts (else the rest shape is the equilibrium)."""
        return bool(np.any(self.pressures_pa) or np.any(self.body_force_n_per_m3))

    # --- the load --------------------------------------------------------------------------------------------

    def body_force_load_n(self) -> FloatArray:
        """The body force's consistent nodal load ``b integral N_a dV`` (3n,) N (dead: the rest volume's)."""
        load: FloatArray = np.outer(self.body.node_volumes_m3, self.body_force_n_per_m3).ravel()
        return load

    def load_n(self, positions_m: FloatArray) -> FloatArray:
        """The load per unit load factor at ``positions_m`` (3n,) N: the pressures' ``sum_c p_c dV_c/dx`` (the
        walls' own configuration; a follower load) and the body force's, zero at held dofs."""
        load = load_from_gradients_n(self.pressures_pa, self.body.chamber_volume_gradients(positions_m))
        load += self.body_force_load_n()
        load[self.constraints.dofs] = 0.0
        return load

    def load_scale_n(self) -> float:
        """The size (N) of the load at the start (free dofs), which tolerances are relative to; at least
        1e-12 E L^2, so that a zero load still has a scale."""
        load = self.load_n(self.start_m)
        free = load[self.constraints.free_mask]
        floor = 1e-12 * self.body.material.youngs_modulus_pa * self.body.length_scale_m**2
        return max(float(np.sqrt(np.einsum("i,i->", free, free))), floor)

    def _load_and_energy(self, positions_m: FloatArray) -> tuple[FloatArray, float]:
        """Load (3n,) and its potential (J): ``sum p dV/dx + f_b`` and ``-sum p V - f_b . x`` (follower pressure),
        or the dead load ``sum p dV/dx(start) + f_b`` and ``-load . x`` (linear)."""
        gravity = self.body_force_load_n()
        if self.formulation == "linear":
            load = load_from_gradients_n(self.pressures_pa, self.body.chamber_volume_gradients(self.start_m)) + gravity
            return load, -float(np.einsum("i,i->", load, positions_m.ravel()))
        load = load_from_gradients_n(self.pressures_pa, self.body.chamber_volume_gradients(positions_m)) + gravity
        return load, -float(self.pressures_pa @ self.body.chamber_volumes_m3(positions_m)
                            + np.einsum("i,i->", gravity, positions_m.ravel()))

    # --- residual, energy, tangent ---------------------------------------------------------------------------

    def evaluate(self, positions_m: FloatArray, with_tangent: bool = False,
                 element_pressures_pa: FloatArray | None = None) -> Evaluation:
        """Out-of-balance force, total energy and smallest det F at ``positions_m`` (n, 3); with
        ``with_tangent``, also the exact tangent's CSR data from the same element pass. ``element_pressures_pa``:
        a 10-node body's pressure field as an independent unknown (None: eliminated, ``K (Jbar - 1)``)."""
        elastic = self.body.elastic(positions_m, self.formulation, EXACT_TANGENT if with_tangent else NO_TANGENT,
                                    self.constraints, self.pressures_pa if with_tangent else None,
                                    element_pressures_pa)
        load, load_energy = self._load_and_energy(positions_m)
        residual = elastic.forces_n - load
        residual[self.constraints.dofs] = 0.0
        return Evaluation(residual, elastic.energy_j + load_energy, elastic.smallest_det,
                          elastic.tangent_data if with_tangent else None)

    def eliminated_residual_n(self, positions_m: FloatArray, carried_residual_n: FloatArray,
                              volume_ratios: FloatArray, element_pressures_pa: FloatArray) -> FloatArray:
        """A 10-node body's residual (3n,) at eliminated pressures, ``K (Jbar - 1)``, from its residual at carried
        ones ``element_pressures_pa`` at the same positions (volume ratios ``Jbar``): they differ by the pressures'
        change times the elements' volume gradients, one pass over the elements' volumes instead of an evaluation
        (the law at every quadrature point, the load)."""
        change_pa = self.body.eliminated_pressures_pa(volume_ratios) - element_pressures_pa
        residual = carried_residual_n + self.body.element_pressure_forces_n(positions_m, change_pa)
        residual[self.constraints.dofs] = 0.0
        return residual

    def tangent_data(self, positions_m: FloatArray, element_pressures_pa: FloatArray | None = None) -> FloatArray:
        """The exact tangent's CSR data (N/m) at ``positions_m``, with the follower-pressure stiffness (and a
        10-node body's carried element pressures in its ``p d2v`` term, if given)."""
        return self.body.tangent_data(positions_m, self.formulation, self.pressures_pa, self.constraints,
                                      element_pressures_pa)

    def multiply(self, tangent_data: FloatArray) -> Callable[[FloatArray], FloatArray]:
        """``v -> K v`` for the tangent with CSR data ``tangent_data`` (from :meth:`tangent_data`)."""
        def product(vector: FloatArray) -> FloatArray:
            return self.body.multiply(tangent_data, vector)
        return product

    def tangent(self, positions_m: FloatArray, exact: bool = True, damped: bool = False,
                element_pressures_pa: FloatArray | None = None, tangent_data: FloatArray | None = None) -> Factor:
        """The factorised tangent at ``positions_m``: the exact Hessian, or (``exact`` False) a positive definite
        stand-in that still gives a descent direction: ``R K R^T`` (co-rotational) or the small-strain stiffness
        (hyperelastic). An exactly singular Hessian (at a limit point) gives the stand-in.

        The exact Hessian goes to CHOLMOD first (where it is the solver) and to SuperLU when it is not positive
        definite (past a limit point, which the path's tangent direction needs as it is). With ``damped``
        (Newton's minimisation at fixed pressures, and a path's volume-controlled steps), a hyperelastic Hessian
        that is not positive definite (off equilibrium: an iterate far from its answer) is shifted instead,
        ``K + tau |diag K|`` with the first ``tau`` of DAMPING_SHIFTS that CHOLMOD factorises: a
        Levenberg-Marquardt step, a descent direction, at a CHOLMOD factorisation's cost (SuperLU's costs 5-8
        times more on 10-node elements; the small-strain stiffness as the stand-in makes Newton crawl there). See
        bench/README.md, "The 10-node solve's speed". ``tangent_data``: the exact tangent's data where an
        evaluation at the same state made it already (:meth:`evaluate` with ``with_tangent``; no element pass
        then)."""
        if not exact and self.formulation in HYPERELASTIC_MODELS:
            return self.body.rest_factorization(self.constraints)
        matrix = EXACT_TANGENT if exact else POSITIVE_TANGENT
        data = tangent_data if exact and tangent_data is not None else self.body.elastic(
            positions_m, self.formulation, matrix, self.constraints, self.pressures_pa,
            element_pressures_pa).tangent_data
        if exact and damped and self.formulation in HYPERELASTIC_MODELS and self.body.detects_indefinite:
            damped_factor = self._damped_factorization(data)
            if damped_factor is not None:
                return damped_factor
        try:
            return self.body.factorize(data, positive_definite=not exact)
        except (RuntimeError, ArithmeticError):
            if not exact:
                raise
            return self.tangent(positions_m, exact=False)

    def _damped_factorization(self, tangent_data: FloatArray) -> Factor | None:
        """CHOLMOD's factor of ``K + tau |diag K|`` for the first ``tau`` in (0, *DAMPING_SHIFTS) that is positive
        definite; None if none is."""
        diagonal = self.body.pattern.diagonal
        magnitudes = np.abs(tangent_data[diagonal])
        for shift in (0.0, *DAMPING_SHIFTS):
            shifted = tangent_data
            if shift:
                shifted = tangent_data.copy()
                shifted[diagonal] += shift * magnitudes
            try:
                return self.body.factorize(shifted, positive_definite=True)
            except ArithmeticError:
                continue
        return None

    def rest_factorization(self) -> Factor:
        """The factorised small-strain stiffness under the problem's constraints (kept by the body)."""
        return self.body.rest_factorization(self.constraints)

    @property
    def preconditioned(self) -> bool:
        """The rest stiffness is factorised for these constraints (those of the rest shape), so conjugate
        gradients preconditioned with it can stand in for a factorisation of the tangent."""
        return self.constraints.key == self.body.rest_constraints.key

    # --- admissibility and conditioning ----------------------------------------------------------------------

    def worst_element(self, positions_m: FloatArray) -> int:
        """The element with the smallest det F if any is flat or inverted at ``positions_m``, else -1."""
        return self.body.worst_element(positions_m)

    def rounding_floor_n(self, positions_m: FloatArray) -> float:
        """The residual (N) that rounding ``positions_m`` to double precision alone leaves."""
        return self.body.rounding_floor_n(positions_m)
