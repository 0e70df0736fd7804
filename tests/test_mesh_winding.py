"""Triangle surfaces wound one way (phantom.model.mesh.winding): a closed surface with every other triangle turned
comes back as it was, open and multi-piece surfaces too, a consistent one is left as it is, and a surface that
cannot be wound one way (non-manifold, one-sided) is refused naming why."""

import numpy as np
import pytest

from phantom.model.mesh.surface import TriangleMesh, enclosed_volume_ml
from phantom.model.mesh.tetmesh import open_edge_count
from phantom.model.mesh.winding import WindingError, consistent_winding, outward_surface
from phantom.scan.synthetic import sphere


def mixed(triangles: np.ndarray, every: int = 2) -> np.ndarray:
    """Every ``every``-th triangle turned (its vertices listed the other way round)."""
    turned = triangles.copy()
    turned[::every] = turned[::every, ::-1]
    return turned


def ball_mesh() -> TriangleMesh:
    """A closed sphere of 2048 triangles, outward, away from the origin."""
    return sphere(20.0, np.array([3.0, -2.0, 40.0]), levels=4)


def test_a_closed_surface_with_every_other_triangle_turned_comes_back_as_it_was():
    ball = ball_mesh()
    true_ml = enclosed_volume_ml(ball)
    broken = TriangleMesh(ball.vertices_mm, mixed(ball.triangles))
    assert abs(enclosed_volume_ml(broken)) < 0.01 * true_ml  # the defect: most of the volume cancels
    for triangles in (mixed(ball.triangles), mixed(ball.triangles[:, ::-1]), mixed(ball.triangles, every=3)):
        repaired, rewound = outward_surface(TriangleMesh(ball.vertices_mm, triangles))
        assert enclosed_volume_ml(repaired) == pytest.approx(true_ml, rel=1e-12)
        np.testing.assert_array_equal(repaired.triangles, ball.triangles)
        assert 0 < rewound <= len(triangles) // 2


def test_a_consistent_surface_is_left_as_it_is():
    ball = ball_mesh()
    triangles, rewound = consistent_winding(ball.triangles)
    assert triangles is ball.triangles and rewound == 0
    surface, rewound = outward_surface(ball)
    assert surface.triangles is ball.triangles and rewound == 0
    # inward as a whole: turned as a whole, as before
    inward = ball.triangles[:, ::-1].copy()
    surface, rewound = outward_surface(TriangleMesh(ball.vertices_mm, inward))
    np.testing.assert_array_equal(surface.triangles, ball.triangles)
    assert rewound == 0


def test_an_open_surface_keeps_the_winding_of_most_of_its_triangles():
    ball = ball_mesh()
    upper = ball.triangles[ball.vertices_mm[ball.triangles].mean(axis=1)[:, 2] > 45.0]
    triangles = mixed(upper, every=5)
    wound, rewound = consistent_winding(triangles)
    np.testing.assert_array_equal(wound, upper)
    assert rewound == len(range(0, len(upper), 5))


def test_each_closed_piece_is_turned_outward_on_its_own():
    ball = ball_mesh()
    other = sphere(8.0, np.array([60.0, 0.0, 0.0]), levels=3)
    vertices = np.vstack([ball.vertices_mm, other.vertices_mm])
    both = np.vstack([ball.triangles, other.triangles + len(ball.vertices_mm)])
    repaired, _ = outward_surface(TriangleMesh(vertices, mixed(both)))
    np.testing.assert_array_equal(repaired.triangles, both)
    assert enclosed_volume_ml(repaired) == pytest.approx(enclosed_volume_ml(ball) + enclosed_volume_ml(other))


def moebius_strip(segments: int = 12) -> np.ndarray:
    """The triangles of a Moebius strip: a band of ``segments`` quads (vertices 2k on top, 2k + 1 below), its
    last quad joined to the first with a half twist (top to bottom)."""
    strip = []
    for k in range(segments):
        top, bottom = 2 * k, 2 * k + 1
        next_top, next_bottom = (2 * k + 2, 2 * k + 3) if k < segments - 1 else (1, 0)
        strip += [[top, bottom, next_top], [bottom, next_bottom, next_top]]
    return np.array(strip, np.int64)


def klein_bottle(n: int = 6, m: int = 6) -> np.ndarray:
    """The triangles of a closed one-sided surface: an n x m grid of quads whose columns close into a ring and
    whose last row joins the first mirrored (i to -i)."""
    def vertex(i: int, j: int) -> int:
        if j == m:
            i, j = -i, 0
        return (i % n) + n * j

    triangles = []
    for j in range(m):
        for i in range(n):
            a, b, c, d = vertex(i, j), vertex(i + 1, j), vertex(i + 1, j + 1), vertex(i, j + 1)
            triangles += [[a, b, c], [a, c, d]]
    return np.array(triangles, np.int64)


def test_a_surface_that_cannot_be_wound_one_way_is_refused_naming_why():
    ball = ball_mesh()
    # a fin: a third triangle on one edge makes that edge non-manifold
    a, b, _ = ball.triangles[0]
    fin = np.array([[a, b, len(ball.vertices_mm)]])
    with pytest.raises(WindingError, match=r"1 edges are shared by more than two triangles \(non-manifold\)"):
        consistent_winding(np.vstack([mixed(ball.triangles), fin]))
    # consistent apart from the fin: nothing to decide, left as it was (as before)
    finned = np.vstack([ball.triangles, fin])
    assert consistent_winding(finned)[0] is finned
    with pytest.raises(WindingError, match="one-sided"):
        consistent_winding(moebius_strip())
    bottle = klein_bottle()
    assert open_edge_count(bottle) == 0  # closed, and still no inside
    with pytest.raises(WindingError, match=r"one-sided \(like a Moebius strip or a Klein bottle: 72 triangles"):
        outward_surface(TriangleMesh(np.random.default_rng(0).normal(size=(36, 3)), bottle))


def test_an_icosphere_of_5120_triangles_half_turned_comes_back_as_it_was():
    # about 6 ms here (trimesh.repair.fix_winding, a networkx traversal, took 260 ms and refuses nothing)
    trimesh = pytest.importorskip("trimesh")
    icosphere = trimesh.creation.icosphere(subdivisions=4)
    vertices, triangles = np.asarray(icosphere.vertices, float), np.asarray(icosphere.faces, np.int64)
    repaired, rewound = outward_surface(TriangleMesh(vertices, mixed(triangles)))
    np.testing.assert_array_equal(repaired.triangles, triangles)
    assert rewound == len(triangles) // 2


def test_the_shape_inverse_reads_a_mixed_winding_target_at_its_volume(tmp_path):
    ball = ball_mesh()
    import meshio

    from phantom.model.shape_file import read_target_surface

    path = tmp_path / "mixed.ply"
    meshio.write_points_cells(path, ball.vertices_mm, [("triangle", mixed(ball.triangles))])
    target = read_target_surface(path)
    assert enclosed_volume_ml(target) == pytest.approx(enclosed_volume_ml(ball), rel=1e-9)
