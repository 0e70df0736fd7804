"""The exact radial solution of a thick hollow sphere of compressible Neo-Hookean material under cavity pressure.

Spherical symmetry: a material point at radius R (inner a, outer b) moves to r(R); the stretches are
``lr = dr/dR`` (radial) and ``lt = r / R`` (twice, hoop), ``J = lr lt^2``, and with
``W = mu/2 (lr^2 + 2 lt^2 - 3) - mu ln J + lambda/2 (ln J)^2`` the nominal (first Piola-Kirchhoff) stresses are

    P_r = dW/dlr = mu lr + (lambda ln J - mu) / lr,     P_t = (1/2) dW/dlt = mu lt + (lambda ln J - mu) / lt.

Equilibrium in the reference configuration is ``dP_r/dR = 2 (P_t - P_r) / R``, with the pressure p on the
deformed cavity, ``P_r(a) = -p lt(a)^2`` (force per deformed area times the area ratio), and a free outer
surface, ``P_r(b) = 0``. For a given cavity radius r(a) (volume control: the pressure-volume curve is single
valued in the volume, also past a limit point) the pressure is the root of ``P_r(b; p) = 0``; each trial
integrates the two first-order equations for (r, P_r) from a to b (scipy's DOP853, relative tolerance 1e-12),
recovering lr from P_r and lt by Newton's method on the monotonic ``P_r(lr)``. That is the "fine 1-D solve":
its error is far below any 3-D mesh's.
"""

import numpy as np


def _radial_stretch(nominal_stress, hoop, mu, lam, guess):
    """lr with ``P_r(lr, lt) = nominal_stress`` (Newton; P_r increases with lr where the law is stable)."""
    stretch = guess
    for _ in range(60):
        log_j = np.log(stretch * hoop * hoop)
        value = mu * stretch + (lam * log_j - mu) / stretch - nominal_stress
        slope = mu + (lam + mu - lam * log_j) / stretch**2
        change = value / slope
        stretch = max(stretch - change, 0.5 * stretch)
        if abs(change) <= 1e-15 * stretch:
            break
    return stretch


def _outer_stress(inner_radius_m, outer_radius_m, cavity_radius_m, pressure_pa, mu, lam):
    """Integrate from the cavity outward; returns (P_r at b, r(b))."""
    from scipy.integrate import solve_ivp

    hoop_inner = cavity_radius_m / inner_radius_m
    guess = [hoop_inner]

    def derivatives(radius, state):
        r, nominal = state
        hoop = r / radius
        radial = _radial_stretch(nominal, hoop, mu, lam, guess[0])
        guess[0] = radial
        log_j = np.log(radial * hoop * hoop)
        hoop_stress = mu * hoop + (lam * log_j - mu) / hoop
        return [radial, 2.0 * (hoop_stress - nominal) / radius]

    solution = solve_ivp(derivatives, (inner_radius_m, outer_radius_m),
                         [cavity_radius_m, -pressure_pa * hoop_inner**2], method="DOP853", rtol=1e-12,
                         atol=1e-14 * max(1.0, pressure_pa))
    return solution.y[1, -1], solution.y[0, -1]


def pressure_at_cavity_radius(inner_radius_m, outer_radius_m, cavity_radius_m, youngs_modulus_pa, poisson_ratio):
    """The cavity pressure (Pa) and deformed outer radius (m) at which the cavity has radius ``cavity_radius_m``."""
    from scipy.optimize import brentq

    mu = youngs_modulus_pa / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus_pa * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))

    def outer(pressure_pa):
        return _outer_stress(inner_radius_m, outer_radius_m, cavity_radius_m, pressure_pa, mu, lam)[0]

    # P_r(b) falls as p rises (the cavity's pull is fixed by its radius): bracket the root on both sides.
    high = mu
    while outer(high) > 0 or outer(-high) < 0:
        high *= 2.0
    pressure_pa = brentq(outer, -high, high, xtol=1e-14 * mu, rtol=1e-14, maxiter=200)
    return pressure_pa, _outer_stress(inner_radius_m, outer_radius_m, cavity_radius_m, pressure_pa, mu, lam)[1]


def cavity_radius_at_pressure(inner_radius_m, outer_radius_m, pressure_pa, youngs_modulus_pa, poisson_ratio,
                              max_stretch=4.0):
    """The cavity radius (m) and outer radius (m) under ``pressure_pa`` on the rising branch of the
    pressure-volume curve: the smallest cavity radius in equilibrium with it, found by stepping the cavity
    stretch by 1 % until the outer surface's stress changes sign, then bracketing. ValueError when none up to
    ``max_stretch`` (the pressure is past the peak of the curve)."""
    from scipy.optimize import brentq

    mu = youngs_modulus_pa / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus_pa * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))

    def outer(radius_m):
        return _outer_stress(inner_radius_m, outer_radius_m, radius_m, pressure_pa, mu, lam)[0]

    low, low_value = inner_radius_m, outer(inner_radius_m)
    while low < max_stretch * inner_radius_m:
        high = low * 1.01
        high_value = outer(high)
        if np.sign(high_value) != np.sign(low_value):
            radius_m = brentq(outer, low, high, xtol=1e-15 * inner_radius_m, rtol=1e-15)
            return radius_m, _outer_stress(inner_radius_m, outer_radius_m, radius_m, pressure_pa, mu, lam)[1]
        low, low_value = high, high_value
    raise ValueError(f"no equilibrium under {pressure_pa:g} Pa up to a cavity stretch of {max_stretch:g}: past the "
                     f"peak of the pressure-volume curve")


def volume_changes_m3(inner_radius_m, outer_radius_m, pressure_pa, youngs_modulus_pa, poisson_ratio):
    """(cavity, outer) volume changes (m^3) of the exact solution under ``pressure_pa``."""
    cavity_m, outer_m = cavity_radius_at_pressure(inner_radius_m, outer_radius_m, pressure_pa, youngs_modulus_pa,
                                                  poisson_ratio)
    sphere = 4.0 / 3.0 * np.pi
    return sphere * (cavity_m**3 - inner_radius_m**3), sphere * (outer_m**3 - outer_radius_m**3)


def incompressible_neo_hookean_pressure_pa(inner_radius_m, outer_radius_m, cavity_stretch, shear_modulus_pa):
    """The cavity pressure (Pa) of an incompressible Neo-Hookean thick sphere whose cavity radius is stretched by
    ``cavity_stretch``, in closed form.

    Incompressibility gives the deformation outright: ``r^3 - R^3 = a^3 (l_a^3 - 1)`` for every R, so the hoop
    stretch ``l = r / R`` runs from ``l_a`` at the cavity to ``l_b`` at the outer surface. With the strain energy
    ``w(l) = mu/2 (2 l^2 + l^-4 - 3)`` of the hoop stretch, equilibrium integrates to
    ``p = integral_{l_b}^{l_a} w'(l) / (l^3 - 1) dl = integral 2 mu (l^-2 + l^-5) dl``, that is
    ``p = 2 mu (1/l_b - 1/l_a) + mu/2 (1/l_b^4 - 1/l_a^4)``.
    """
    a, b = inner_radius_m, outer_radius_m
    outer_stretch = np.cbrt(1.0 + a**3 * (cavity_stretch**3 - 1.0) / b**3)
    mu = shear_modulus_pa
    return (2.0 * mu * (1.0 / outer_stretch - 1.0 / cavity_stretch)
            + 0.5 * mu * (outer_stretch**-4 - cavity_stretch**-4))


def incompressible_neo_hookean_growth(inner_radius_m, outer_radius_m, pressure_pa, shear_modulus_pa):
    """The cavity's relative volume growth ``l_a^3 - 1`` under ``pressure_pa`` on the rising branch of the
    closed form (:func:`incompressible_neo_hookean_pressure_pa`); ValueError past its peak."""
    from scipy.optimize import brentq

    def gap(stretch):
        return incompressible_neo_hookean_pressure_pa(inner_radius_m, outer_radius_m, stretch,
                                                      shear_modulus_pa) - pressure_pa

    # the pressure rises from 0 at l_a = 1 to a peak and falls after it: bracket the first crossing
    high = 1.0
    while gap(high) < 0:
        if high > 10.0:
            raise ValueError(f"{pressure_pa:g} Pa is past the peak of the pressure-volume curve")
        high += 0.01
    stretch = brentq(gap, 1.0, high, xtol=1e-15, rtol=1e-15)
    return stretch**3 - 1.0
