"""The same small-strain problem assembled by scikit-fem: the independent reference of the tests and the bench.

scikit-fem is a test extra (``pip install -e .[test]``), imported only when these functions run.
"""

import numpy as np


def skfem_stiffness(model):
    """scikit-fem's P1 linear-elasticity stiffness (N/m) on the model's mesh and material, and its basis."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    mesh = skfem.MeshTet(model.nodes_m.T.copy(), model.tets.T.copy())
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP1()))
    material = model.material
    lame = lame_parameters(material.youngs_modulus_pa, material.poisson_ratio)
    return skfem.asm(linear_elasticity(*lame), basis), basis


def skfem_problem(model, pressures_pa):
    """Stiffness, pressure load and held dofs of the model's problem, assembled by scikit-fem.

    Each chamber wall carries the traction -p n (n the solid's outward normal, which on a cavity wall points
    into the cavity); the model's own constrained dofs are held. Returns (basis, stiffness, load_n, held_dofs)
    in scikit-fem's dof numbering.
    """
    import skfem
    from skfem.helpers import dot

    stiffness, basis = skfem_stiffness(model)
    mesh = basis.mesh
    facet_of = {tuple(sorted(facet)): index for index, facet in enumerate(mesh.facets.T.tolist())}
    load = np.zeros(basis.N)
    for pressure_pa, triangles in zip(pressures_pa, model.chamber_triangles, strict=True):
        facets = np.array([facet_of[tuple(sorted(triangle))] for triangle in triangles.tolist()])

        @skfem.LinearForm
        def traction(v, w, pressure_pa=pressure_pa):
            return -pressure_pa * dot(w.n, v)

        load += skfem.asm(traction, skfem.FacetBasis(mesh, basis.elem, facets=facets))
    # The model numbers dofs 3 * node + axis; scikit-fem's are basis.nodal_dofs[axis, node].
    held = basis.nodal_dofs.T.ravel()[model.held_dofs]
    return basis, stiffness, load, held


def skfem_displacement(model, pressures_pa) -> np.ndarray:
    """Small-strain displacement (m, (n, 3)) of the model's problem solved by scikit-fem."""
    import skfem

    basis, stiffness, load, held = skfem_problem(model, pressures_pa)
    solution = skfem.solve(*skfem.condense(stiffness, load, D=held))
    return solution[basis.nodal_dofs.T]
