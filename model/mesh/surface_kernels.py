"""The closest-point kernels of :class:`phantom.model.mesh.surface.SurfaceIndex` (numba, cached under
``phantom.cache_dir("numba")``).

Imported only when closest points are first asked for, so the rest of the model never pays for numba here.
Arrays as :class:`~phantom.model.mesh.surface.SurfaceIndex` holds them: C-contiguous float64 positions (mm) and
int64 indices; the outputs are written in place.
"""

import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np

import phantom
from phantom.model.arrays import BoolArray, FloatArray, IntArray

os.environ.setdefault("NUMBA_CACHE_DIR", str(phantom.cache_dir("numba")))
import numba  # noqa: E402  (the cache location must be set first)

Kernel = TypeVar("Kernel", bound=Callable[..., Any])


def kernel(function: Kernel) -> Kernel:
    """Compile ``function`` with numba (cached on disk); the compiled kernel takes the same arguments."""
    return cast(Kernel, numba.njit(cache=True)(function))


@kernel
def closest_on_triangle(p: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray, out: FloatArray) -> float:
    """Closest point to ``p`` on triangle ``abc`` (written to ``out``) by its Voronoi region: vertex, edge or
    face (the classic barycentric case analysis); returns the squared distance."""
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ac0, ac1, ac2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    ap0, ap1, ap2 = p[0] - a[0], p[1] - a[1], p[2] - a[2]
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    if d1 <= 0.0 and d2 <= 0.0:
        v, w = 0.0, 0.0
    else:
        bp0, bp1, bp2 = p[0] - b[0], p[1] - b[1], p[2] - b[2]
        d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
        d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
        cp0, cp1, cp2 = p[0] - c[0], p[1] - c[1], p[2] - c[2]
        d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
        d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            v, w = 1.0, 0.0
        elif d6 >= 0.0 and d5 <= d6:
            v, w = 0.0, 1.0
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v, w = d1 / (d1 - d3), 0.0
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            v, w = 0.0, d2 / (d2 - d6)
        elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            v = 1.0 - w
        else:
            denominator = 1.0 / (va + vb + vc)
            v, w = vb * denominator, vc * denominator
    out[0] = a[0] + v * ab0 + w * ac0
    out[1] = a[1] + v * ab1 + w * ac1
    out[2] = a[2] + v * ab2 + w * ac2
    squared: float = (p[0] - out[0]) ** 2 + (p[1] - out[1]) ** 2 + (p[2] - out[2]) ** 2
    return squared


@kernel
def _record_if_closer(points: FloatArray, i: int, j: int, vertices: FloatArray, triangles: IntArray, best: float,
                      point_out: FloatArray, closest: FloatArray, triangle: IntArray) -> float:
    """Point i against triangle j: when it is closer than ``best`` (a squared distance), record the triangle and
    the closest point for the point; returns the best squared distance."""
    squared = closest_on_triangle(points[i], vertices[triangles[j, 0]], vertices[triangles[j, 1]],
                                  vertices[triangles[j, 2]], point_out)
    if squared >= best:
        return best
    triangle[i] = j
    closest[i, 0], closest[i, 1], closest[i, 2] = point_out[0], point_out[1], point_out[2]
    return squared


@kernel
def closest_on_candidates(points: FloatArray, pending: IntArray, candidates: IntArray, centroid_distance: FloatArray,
                          vertices: FloatArray, triangles: IntArray, radius: FloatArray, radius_max: float,
                          all_candidates: bool, distance: FloatArray, closest: FloatArray, triangle: IntArray,
                          done: BoolArray) -> None:
    """For each pending point, the closest point over its candidate triangles (nearest centroid first).

    Triangle j lies at least ``|p - centroid_j| - radius_j`` from p (``radius_j``: its farthest corner from its
    centroid), so it is skipped when that exceeds the best distance; once ``|p - centroid| - radius_max`` does,
    no later candidate can be closer and the answer is exact (``done``). Points whose candidates run out first
    stay not done, unless the candidates were every triangle.
    """
    point_out = np.empty(3)
    n_triangles = triangles.shape[0]
    for row in range(pending.shape[0]):
        i = pending[row]
        best = np.inf
        finished = all_candidates
        for k in range(candidates.shape[1]):
            j = candidates[row, k]
            if j >= n_triangles:
                finished = True
                break
            if best < np.inf:
                reach = np.sqrt(best)
                if centroid_distance[row, k] - radius_max > reach:
                    finished = True
                    break
                if centroid_distance[row, k] - radius[j] > reach:
                    continue
            best = _record_if_closer(points, i, j, vertices, triangles, best, point_out, closest, triangle)
        if finished:
            distance[i] = np.sqrt(best)
            done[row] = True


@kernel
def closest_by_neighbours(points: FloatArray, nearest: IntArray, nearest_distance: FloatArray,
                          neighbour_start: IntArray, neighbours: IntArray, centroids: FloatArray, radius: FloatArray,
                          radius_max: float, reach: float, vertices: FloatArray, triangles: IntArray,
                          distance: FloatArray, closest: FloatArray, triangle: IntArray, done: BoolArray) -> None:
    """Closest points for many queries on a small surface: each point checks the triangles whose centroids lie
    within ``reach`` of its nearest centroid (a precomputed list). Every triangle that could be closer than the
    best found has its centroid within ``best + radius_max`` of the point, hence within
    ``best + radius_max + |p - nearest centroid|`` of the nearest centroid: when that is at most ``reach`` the
    answer is exact (``done``); the caller answers the other points another way."""
    point_out = np.empty(3)
    for i in range(points.shape[0]):
        best = np.inf
        c = nearest[i]
        for entry in range(neighbour_start[c], neighbour_start[c + 1]):
            j = neighbours[entry]
            if best < np.inf:
                gap = np.sqrt((points[i, 0] - centroids[j, 0]) ** 2 + (points[i, 1] - centroids[j, 1]) ** 2
                              + (points[i, 2] - centroids[j, 2]) ** 2)
                if gap - radius[j] > np.sqrt(best):
                    continue
            best = _record_if_closer(points, i, j, vertices, triangles, best, point_out, closest, triangle)
        if np.sqrt(best) + radius_max + nearest_distance[i] <= reach:
            distance[i] = np.sqrt(best)
            done[i] = True
