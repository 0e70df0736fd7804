"""Triangle surfaces (phantom.model.mesh.surface) on closed forms: an octahedron's area and volume, and a rigid
motion recovered by alignment from a lumpy ellipsoid whose three axes differ (so that only one rotation fits)."""

import numpy as np
import pytest

from phantom import PhantomError
from phantom.model.mesh.surface import (
    AlignmentError,
    Frame,
    SurfaceIndex,
    TriangleMesh,
    align,
    enclosed_volume_ml,
    rotation_angle_deg,
    rotation_from_vector,
    subdivide,
    triangle_areas_mm2,
    vertex_areas_mm2,
)

OCTAHEDRON = TriangleMesh(np.vstack([np.eye(3), -np.eye(3)]) * 10.0,
                          np.array([[0, 1, 2], [1, 3, 2], [3, 4, 2], [4, 0, 2],
                                    [1, 0, 5], [3, 1, 5], [4, 3, 5], [0, 4, 5]]))


def lumpy_ellipsoid(semi_axes_mm, levels: int = 3) -> TriangleMesh:
    """The octahedron subdivided and pushed onto an ellipsoid, with a bump on +x so that no turn maps it onto
    itself."""
    vertices, triangles = OCTAHEDRON.vertices_mm, OCTAHEDRON.triangles
    for _ in range(levels):
        vertices, triangles = subdivide(vertices, triangles)
    unit = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    bump = 1.0 + 0.15 * np.exp(-8.0 * np.sum((unit - [0.6, 0.8, 0.0]) ** 2, axis=1))
    return TriangleMesh(unit * np.asarray(semi_axes_mm) * bump[:, None], triangles)


def test_an_octahedron_has_its_area_and_volume():
    # |x| + |y| + |z| <= a: volume 4/3 a^3; eight equilateral faces of side a sqrt(2)
    assert enclosed_volume_ml(OCTAHEDRON) == pytest.approx(4 / 3 * 10.0**3 * 1e-3)
    np.testing.assert_allclose(triangle_areas_mm2(OCTAHEDRON.vertices_mm, OCTAHEDRON.triangles),
                               np.sqrt(3) / 4 * 2 * 10.0**2)
    assert vertex_areas_mm2(OCTAHEDRON.vertices_mm, OCTAHEDRON.triangles).sum() == pytest.approx(
        8 * np.sqrt(3) / 2 * 10.0**2)
    inward = TriangleMesh(OCTAHEDRON.vertices_mm, OCTAHEDRON.triangles[:, ::-1])
    assert enclosed_volume_ml(inward) == pytest.approx(-4 / 3)


def test_closest_points_on_a_face_an_edge_and_a_corner():
    index = SurfaceIndex(OCTAHEDRON.vertices_mm, OCTAHEDRON.triangles)
    points = np.array([[10.0, 10.0, 10.0], [20.0, 20.0, 0.0], [30.0, 0.0, 0.0]])
    distance, closest, _ = index.closest(points)
    np.testing.assert_allclose(closest, [[10 / 3, 10 / 3, 10 / 3], [5.0, 5.0, 0.0], [10.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(distance, [20 / np.sqrt(3), 15 * np.sqrt(2), 20.0])


def test_alignment_recovers_a_rigid_motion():
    target = lumpy_ellipsoid((30.0, 20.0, 12.0))
    rotation = rotation_from_vector(np.array([0.4, -1.1, 2.0]))
    translation_mm = np.array([40.0, -15.0, 7.0])
    moving = TriangleMesh(target.vertices_mm @ rotation.T + translation_mm, target.triangles)
    alignment = align(Frame.of(moving), moving.vertices_mm, target, Frame.of(target),
                      SurfaceIndex(target.vertices_mm, target.triangles), np.random.default_rng(0))
    # x_target = R^T (x_moving - t): the inverse of the motion that made the moving surface
    assert rotation_angle_deg(alignment.rotation @ rotation) < 1e-4
    np.testing.assert_allclose(alignment.translation_mm, -rotation.T @ translation_mm, atol=1e-4)
    assert alignment.rms_mm < 1e-6 and not alignment.ambiguous
    np.testing.assert_allclose(alignment.apply(moving.vertices_mm), target.vertices_mm, atol=1e-4)


def test_surfaces_no_motion_brings_together_are_refused():
    target = lumpy_ellipsoid((30.0, 20.0, 12.0), levels=2)
    needle = lumpy_ellipsoid((60.0, 4.0, 4.0), levels=2)
    with pytest.raises(AlignmentError) as raised:
        align(Frame.of(needle), needle.vertices_mm, target, Frame.of(target),
              SurfaceIndex(target.vertices_mm, target.triangles), np.random.default_rng(0))
    error = raised.value
    assert isinstance(error, PhantomError) and "\n" not in str(error)
    assert error.rms_mm > 0.1 * error.size_mm and error.size_mm == pytest.approx(Frame.of(target).rms_radius_mm)
