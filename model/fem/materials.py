"""The hyperelastic laws: each one small function of the first invariant, called by the element kernels.

A law is the distortional energy density ``W(I)`` per unit rest volume (Pa) of a first invariant ``I``, given as
``shifted = I - 3`` (0 at rest), returning ``(W, dW/dI, d2W/dI2)``; ``W`` is +inf outside the law's domain (an
element there is inadmissible: a line search rejects the step). The element kernels
(:mod:`phantom.model.fem.kernels`) supply the kinematics and the volumetric part, one generic kernel per element
order:

- 4-node tetrahedra (:func:`~phantom.model.fem.kernels.hyperelastic_forces`): ``I = I1 = tr(F^T F)`` and the
  compressible ``- mu ln J + lambda/2 (ln J)^2``, so ``P = 2 W' F + (lambda ln J - mu) F^-T``; rest is
  stress-free when ``W'(0) = mu / 2``, which every law here has.
- 10-node tetrahedra in the mixed formulation (:func:`~phantom.model.fem.kernels.mixed_forces`):
  ``I = I1bar = J^(-2/3) I1`` and ``K/2 (Jbar - 1)^2``.

The laws (``mu`` the shear modulus of E and nu; every law has the same small-strain stiffness):

- ``neo_hookean``: ``W = mu/2 (I - 3)``; parameters ``[mu]``.
- ``gent``: ``W = -(mu Jm/2) ln(1 - (I - 3)/Jm)``, defined for ``I - 3 < Jm`` (the chains lock); parameters
  ``[mu, 1/Jm]``.
- ``yeoh``: ``W = C10 (I - 3) + C20 (I - 3)^2 + C30 (I - 3)^3`` with ``C10 = mu/2``; parameters
  ``[C10, C20, C30]``; the scene gives ``C20 / C10`` and ``C30 / C10`` (dimensionless, so that the solution at
  (p, E) stays the one at (p E0/E, E0), as for the other laws).

Adding a law: its function here, its number in :data:`LAWS`, its branch in :func:`law_energy` and its parameters
in :func:`law_parameters` (and its keys in the scene's ``[material]``, :mod:`phantom.model.scene`).
"""

import numpy as np

from phantom.model.arrays import FloatArray
from phantom.model.errors import SolveError
from phantom.model.fem.jit import inline_kernel
from phantom.model.scene import Material

#: Each law's number, which the element kernels take.
LAWS = {"neo_hookean": 0, "gent": 1, "yeoh": 2}
NEO_HOOKEAN, GENT, YEOH = LAWS["neo_hookean"], LAWS["gent"], LAWS["yeoh"]


@inline_kernel
def neo_hookean(shifted: float, parameters: FloatArray) -> tuple[float, float, float]:
    """``W = mu/2 (I - 3)``, parameters ``[mu]``."""
    half_mu = 0.5 * parameters[0]
    return half_mu * shifted, half_mu, 0.0


@inline_kernel
def gent(shifted: float, parameters: FloatArray) -> tuple[float, float, float]:
    """``W = -(mu Jm/2) ln(1 - (I - 3)/Jm)``, parameters ``[mu, 1/Jm]``; +inf at and past the lock."""
    mu, inverse_jm = parameters[0], parameters[1]
    stiffening = 1.0 - shifted * inverse_jm
    if not stiffening > 0.0:
        return np.inf, 0.0, 0.0
    reciprocal = 1.0 / stiffening  # one division for both derivatives: the force pass is this law's hot path
    first = 0.5 * mu * reciprocal
    return -0.5 * mu / inverse_jm * np.log(stiffening), first, first * inverse_jm * reciprocal


@inline_kernel
def yeoh(shifted: float, parameters: FloatArray) -> tuple[float, float, float]:
    """``W = C10 (I - 3) + C20 (I - 3)^2 + C30 (I - 3)^3``, parameters ``[C10, C20, C30]``."""
    c10, c20, c30 = parameters[0], parameters[1], parameters[2]
    return (shifted * (c10 + shifted * (c20 + shifted * c30)), c10 + shifted * (2.0 * c20 + 3.0 * shifted * c30),
            2.0 * c20 + 6.0 * shifted * c30)


@inline_kernel
def law_energy(law: int, shifted: float, parameters: FloatArray) -> tuple[float, float, float]:
    """``(W, dW/dI, d2W/dI2)`` of law number ``law`` (:data:`LAWS`) at ``shifted = I - 3``."""
    if law == GENT:
        return gent(shifted, parameters)
    if law == YEOH:
        return yeoh(shifted, parameters)
    return neo_hookean(shifted, parameters)


def law_parameters(formulation: str, material: Material) -> tuple[int, FloatArray]:
    """The law number and parameter array (Pa or dimensionless, see the module's list) that the kernels take
    for ``formulation`` (one of :data:`LAWS`) with ``material``'s moduli and coefficients; SolveError when the
    material lacks the law's coefficients."""
    mu = material.lame_mu_pa
    if formulation == "gent":
        if material.gent_jm is None:
            raise SolveError("the Gent formulation needs the material's gent_jm (scene [material] gent_jm)")
        return GENT, np.array([mu, 1.0 / material.gent_jm])
    if formulation == "yeoh":
        if material.yeoh_c20_over_c10 is None or material.yeoh_c30_over_c10 is None:
            raise SolveError("the Yeoh formulation needs the material's yeoh_c20_over_c10 and yeoh_c30_over_c10 "
                             "(scene [material] keys)")
        return YEOH, 0.5 * mu * np.array([1.0, material.yeoh_c20_over_c10, material.yeoh_c30_over_c10])
    if formulation != "neo_hookean":
        raise SolveError(f"{formulation!r} is not a hyperelastic law: use one of {', '.join(LAWS)}")
    return NEO_HOOKEAN, np.array([mu])
