"""The same hyperelastic problem solved with FElupe: the independent reference of the tests and the bench.

FElupe (a test extra, imported only when these functions run) supplies the solid: its linear tetrahedra
(``RegionTetra``), its compressible Neo-Hookean law (``NeoHookeCompressible``: ``W = mu/2 (tr C - 3) - mu ln J
+ lambda/2 (ln J)^2``, the model's law) and its assembly of forces and tangent. FElupe has no pressure boundary
for tetrahedra, so the chamber pressure is written here from its definition, independently of the model's
code: the follower load ``p dV/dx`` and its stiffness ``p d2V/dx2`` of the volume ``V = sum_t x_a . (x_b x
x_c) / 6`` enclosed by each chamber wall. Newton iterations with load steps and scipy's direct solver; the held
dofs are the model's (3-2-1, a mesh without a fixed group), so both solve the same discrete problem.
"""

import numpy as np


def _volume_load_and_stiffness(positions_m, triangles, n_dofs):
    """``dV/dx`` (3n,) and ``d2V/dx2`` (sparse) of the volume enclosed by oriented triangles."""
    import scipy.sparse as sp

    a, b, c = (positions_m[triangles[:, k]] for k in range(3))
    gradient = np.zeros((len(positions_m), 3))
    for corner, (second, third) in enumerate(((b, c), (c, a), (a, b))):
        np.add.at(gradient, triangles[:, corner], np.cross(second, third) / 6.0)
    rows, columns, values = [], [], []
    # d2V / dx_a dx_b = -[x_c]x / 6 for each cyclic order (a, b, c), and its transpose for (b, a).
    for first, second, third in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        x = positions_m[triangles[:, third]]
        skew = np.zeros((len(triangles), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2] = -x[:, 2], x[:, 1]
        skew[:, 1, 0], skew[:, 1, 2] = x[:, 2], -x[:, 0]
        skew[:, 2, 0], skew[:, 2, 1] = -x[:, 1], x[:, 0]
        block = -skew / 6.0
        for i in range(3):
            for j in range(3):
                for row_node, column_node, value in ((first, second, block[:, i, j]), (second, first, block[:, i, j])):
                    rows.append(3 * triangles[:, row_node] + (i if row_node == first else j))
                    columns.append(3 * triangles[:, column_node] + (j if row_node == first else i))
                    values.append(value)
    hessian = sp.coo_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(columns))),
                            shape=(n_dofs, n_dofs)).tocsr()
    return gradient.ravel(), hessian


def felupe_solid(model, umat=None):
    """FElupe's solid on the model's 4-node mesh: ``(solid, field)``; its law ``umat``, by default FElupe's
    Neo-Hookean of the model's material."""
    import felupe as fem

    mesh = fem.Mesh(model.nodes_m.copy(), model.tets.copy(), "tetra")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(mesh), dim=3)])
    material = model.material
    if umat is None:
        umat = fem.NeoHookeCompressible(mu=material.lame_mu_pa, lmbda=material.lame_lambda_pa)
    return fem.SolidBody(umat, field), field


def felupe_compressible_yeoh(material):
    """The model's 4-node Yeoh law, ``W = C10 (I1 - 3) + C20 (I1 - 3)^2 + C30 (I1 - 3)^3 - mu ln J + lambda/2
    (ln J)^2`` (``I1 = tr C``, not FElupe's isochoric one), as a FElupe material whose stress and elasticity
    tensortrax differentiates automatically from this energy alone."""
    import felupe.constitution.tensortrax as mat
    import tensortrax.math as tm

    def energy(C, C10, C20, C30, mu, lmbda):
        shifted = tm.trace(C) - 3
        log_j = tm.log(tm.linalg.det(C)) / 2
        return C10 * shifted + C20 * shifted**2 + C30 * shifted**3 - mu * log_j + lmbda / 2 * log_j**2

    c10 = material.lame_mu_pa / 2
    return mat.Hyperelastic(energy, C10=c10, C20=material.yeoh_c20_over_c10 * c10,
                            C30=material.yeoh_c30_over_c10 * c10, mu=material.lame_mu_pa, lmbda=material.lame_lambda_pa)


def felupe_forces(model, positions_m) -> np.ndarray:
    """FElupe's internal nodal forces (N, (n, 3)) of the model's mesh at ``positions_m``."""
    solid, field = felupe_solid(model)
    field[0].values[:] = positions_m - model.nodes_m
    return np.asarray(solid.assemble.vector(field).todense()).reshape(-1, 3)


def felupe_solve(model, pressures_pa, load_steps: int = 4, tolerance: float = 1e-10,
                 max_iterations: int = 30) -> np.ndarray:
    """Node positions (m, (n, 3)) at equilibrium under the chamber pressures (Pa), solved with FElupe's solid.

    Only for meshes without a fixed group (the model's 3-2-1 held dofs are held here too).
    """
    import scipy.sparse.linalg as spla

    if model.fixed_triangles is not None:
        raise ValueError("felupe_solve compares free meshes (no fixed group): the model's held dofs are used")
    solid, field = felupe_solid(model)
    n_dofs = model.nodes_m.size
    free = np.ones(n_dofs, bool)
    free[model.held_dofs] = False
    pressures = np.asarray(pressures_pa, float)
    for load_factor in np.linspace(0.0, 1.0, load_steps + 1)[1:]:
        for _ in range(max_iterations):
            positions_m = model.nodes_m + field[0].values
            forces = np.asarray(solid.assemble.vector(field).todense()).ravel()
            stiffness = solid.assemble.matrix(field).tocsr()
            load = np.zeros(n_dofs)
            for pressure_pa, triangles in zip(pressures, model.chamber_triangles, strict=True):
                gradient, hessian = _volume_load_and_stiffness(positions_m, triangles, n_dofs)
                load += load_factor * pressure_pa * gradient
                stiffness = stiffness - load_factor * pressure_pa * hessian
            residual = forces - load
            if np.linalg.norm(residual[free]) <= tolerance * max(np.linalg.norm(load[free]), 1e-300):
                break
            step = np.zeros(n_dofs)
            step[free] = spla.spsolve(stiffness[free][:, free].tocsc(), -residual[free])
            field[0].values += step.reshape(-1, 3)
        else:
            raise RuntimeError(f"FElupe reference: Newton did not converge at load factor {load_factor:g}")
    return model.nodes_m + field[0].values


def _tetra10_mesh(model):
    """The model's 10-node mesh as FElupe's: ``(mesh, nodes, renumbered)``, the nodes (m) in FElupe's order (its
    dual mesh takes the first points as the corners, so the corners are numbered first) and ``renumbered``, each
    model node's index in it."""
    import felupe as fem

    nodes_m, tets = model.nodes_m, model.tets
    corners = np.unique(tets[:, :4])
    order = np.concatenate([corners, np.setdiff1d(np.arange(len(nodes_m)), corners)])
    renumbered = np.empty(len(nodes_m), np.int64)
    renumbered[order] = np.arange(len(nodes_m))
    nodes = nodes_m[order]
    return fem.Mesh(nodes.copy(), renumbered[tets], "tetra10"), nodes, renumbered


def _mixed_solid(model):
    """FElupe's P2/P1 mixed Neo-Hookean solid on the model's 10-node mesh: ``(solid, field, nodes, renumbered)``
    (see :func:`_tetra10_mesh`)."""
    import felupe as fem

    mesh, nodes, renumbered = _tetra10_mesh(model)
    field = fem.FieldsMixed(fem.RegionQuadraticTetra(mesh), n=3)
    material = model.material
    solid = fem.SolidBody(fem.ThreeFieldVariation(fem.NeoHooke(mu=material.lame_mu_pa, bulk=material.bulk_modulus_pa)),
                          field)
    return solid, field, nodes, renumbered


def _mixed_newton(solid, field, held, external, tolerance, max_iterations, what):
    """Newton on FElupe's whole mixed system with the dofs ``held`` (mask over all fields) fixed and the dead
    nodal load ``external`` (over all fields; zero beyond the displacement's); returns the last residual."""
    import scipy.sparse.linalg as spla

    sizes = [f.values.size for f in field.fields]
    for _ in range(max_iterations):
        residual = np.asarray(solid.assemble.vector(field).todense()).ravel() - external
        scale = max(np.linalg.norm(residual[held]), np.linalg.norm(external))
        if np.linalg.norm(residual[~held]) <= tolerance * scale:
            return residual
        tangent = solid.assemble.matrix(field).tocsr()[~held][:, ~held]
        step = np.zeros(len(held))
        step[~held] = spla.spsolve(tangent.tocsc(), -residual[~held])
        field += np.split(step, np.cumsum(sizes)[:-1])
    raise RuntimeError(f"FElupe mixed: Newton did not converge {what}")


def felupe_mixed_sphere(model, cavity_stretches, inner_radius_m, tolerance=1e-10, max_iterations=30):
    """FElupe's mixed P2/P1 solution of the model's 10-node hollow sphere with its cavity wall held at the given
    stretches (each node of the wall moved radially, ``x = stretch X``; the outer surface free): a list of
    (cavity pressure Pa, node positions (n, 3) m in the model's node order) per stretch.

    FElupe's ``FieldsMixed`` on ``RegionQuadraticTetra`` is a continuous quadratic displacement with continuous
    linear pressure and dilatation fields (P2/P1, Hu-Washizu through ``ThreeFieldVariation``), a different
    discretisation of the same continuum than the model's (pressure and dilatation constant per element): the two
    agree only as both converge. Its law is ``NeoHooke(mu, bulk)``, ``W = mu/2 (J^(-2/3) tr C - 3) + U(J)``. The
    pressure is the wall's reaction: the sum of the radial reaction forces over the deformed wall's area (a
    uniform pressure on a sphere). Newton on the whole mixed system, the wall's displacement prescribed.
    """
    solid, field, nodes, renumbered = _mixed_solid(model)
    wall = np.abs(np.linalg.norm(nodes, axis=1) - inner_radius_m) < 1e-6 * inner_radius_m
    held = np.zeros(sum(f.values.size for f in field.fields), bool)
    held[: nodes.size] = np.repeat(wall, 3)
    answers = []
    for stretch in cavity_stretches:
        field[0].values[wall] = nodes[wall] * (stretch - 1.0)
        residual = _mixed_newton(solid, field, held, np.zeros(len(held)), tolerance, max_iterations,
                                 f"at cavity stretch {stretch:g}")
        positions = nodes + field[0].values
        forces = residual[: nodes.size].reshape(-1, 3)
        normals = positions[wall] / np.linalg.norm(positions[wall], axis=1)[:, None]
        pressure_pa = float(np.einsum("ij,ij->", forces[wall], normals)) / (4 * np.pi * (stretch * inner_radius_m) ** 2)
        answers.append((pressure_pa, positions[renumbered]))
    return answers


def felupe_mixed_dead_load(model, forces_n, load_steps=4, tolerance=1e-10, max_iterations=30):
    """FElupe's mixed P2/P1 solution of the model's 10-node mesh under the dead nodal load ``forces_n`` (N, (n, 3)
    in the model's node order), the nodes of the model's fixed faces held: node positions (m, (n, 3)), in the
    model's order. The load is ramped over ``load_steps`` equal steps, each solved by Newton (as
    :func:`felupe_mixed_sphere`)."""
    solid, field, nodes, renumbered = _mixed_solid(model)
    fixed = np.zeros(len(nodes), bool)
    fixed[renumbered[np.unique(model.fixed_faces)]] = True
    held = np.zeros(sum(f.values.size for f in field.fields), bool)
    held[: nodes.size] = np.repeat(fixed, 3)
    load = np.zeros(len(held))
    load[: nodes.size] = np.asarray(forces_n)[np.argsort(renumbered)].ravel()
    for load_factor in np.linspace(0.0, 1.0, load_steps + 1)[1:]:
        _mixed_newton(solid, field, held, load_factor * load, tolerance, max_iterations,
                      f"at load factor {load_factor:g}")
    return (nodes + field[0].values)[renumbered]


def felupe_yeoh(material):
    """FElupe's own Yeoh law (``felupe.constitution.tensortrax.models.hyperelastic.yeoh``, ``W = C10 (I1bar - 3)
    + C20 (I1bar - 3)^2 + C30 (I1bar - 3)^3``, derivatives by tensortrax's automatic differentiation) with the
    model material's coefficients: ``C10 = mu / 2`` and its C20 / C10, C30 / C10."""
    import felupe.constitution.tensortrax as mat

    c10 = material.lame_mu_pa / 2
    return mat.Hyperelastic(mat.models.hyperelastic.yeoh, C10=c10, C20=material.yeoh_c20_over_c10 * c10,
                            C30=material.yeoh_c30_over_c10 * c10)


def felupe_nearly_incompressible_equilibrium(model, umat, forces_n, start_m, tolerance=1e-10, max_iterations=30):
    """FElupe's equilibrium of the model's 10-node mesh under the dead nodal load ``forces_n`` (N, (n, 3), the
    model's node order), the model's held dofs held: ``(positions (n, 3) m in the model's order, the relative
    residual at start_m)``.

    The solid is FElupe's ``SolidBodyNearlyIncompressible``: the distortional energy of ``umat`` and ``K/2 (Jbar -
    1)^2`` on cell-wise constant pressure and volume ratio ``Jbar = v / V`` (the model's P2/P0 mixed formulation,
    written independently; FElupe's quadrature of ``v`` is its degree-2 rule, the model's the exact degree-3 one).
    Newton on FElupe's assembly starts from ``start_m`` (its Newton has no line search: from rest it does not
    reach large strains) and stops at ``tolerance`` of the load.
    """
    import felupe as fem

    mesh, nodes, renumbered = _tetra10_mesh(model)
    field = fem.FieldContainer([fem.Field(fem.RegionQuadraticTetra(mesh), dim=3)])
    solid = fem.SolidBodyNearlyIncompressible(umat, field, bulk=model.material.bulk_modulus_pa)
    held_dofs = np.asarray(model.held_dofs)
    held = np.zeros(nodes.size, bool)
    held[3 * renumbered[held_dofs // 3] + held_dofs % 3] = True
    load = np.asarray(forces_n)[np.argsort(renumbered)].ravel()
    field[0].values[:] = np.asarray(start_m)[np.argsort(renumbered)] - nodes
    start_residual = np.asarray(solid.assemble.vector(field).todense()).ravel() - load
    _mixed_newton(solid, field, held, load, tolerance, max_iterations, "from the start given")
    return (nodes + field[0].values)[renumbered], np.linalg.norm(start_residual[~held]) / np.linalg.norm(load)
