"""The scanner's numba kernels (cached under ``phantom.cache_dir("numba")``): the virtual camera's (the rays of
the sensor's samples through the lens, the z-buffered triangle rasteriser, the ray cast of a plane target, the
shading and averaging of each pixel's samples), the silhouette's colour key, the carving's field and the carved
hull's surface seen by the views (what each covers, which bounds it).

Arrays are C-contiguous: float64 positions (mm), int64 triangles, float32 sample rays and outputs. The rasteriser
works in the ideal (undistorted) normalized image plane, where a triangle's edges are straight: every sample
carries the ideal normalized coordinates of its ray (:func:`sample_rays`), so straight edges in space come out
bent by the lens as they should.
"""

import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np

import phantom
from phantom.model.arrays import FloatArray, IntArray

os.environ.setdefault("NUMBA_CACHE_DIR", str(phantom.cache_dir("numba")))
import numba  # noqa: E402  (the cache location must be set first)

Kernel = TypeVar("Kernel", bound=Callable[..., Any])


def kernel(function: Kernel) -> Kernel:
    """Compile ``function`` with numba (cached on disk), releasing the interpreter's lock while it runs, so that
    threads can run kernels side by side."""
    return cast(Kernel, numba.njit(cache=True, nogil=True)(function))

#: The nearest depth (mm) a triangle may have and still be drawn.
NEAR_MM = 1.0


@kernel
def distort_point(x: float, y: float, distortion: FloatArray) -> tuple[float, float]:
    """Brown-Conrady distortion of one ideal normalized point (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = distortion[0], distortion[1], distortion[2], distortion[3], distortion[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


@kernel
def sample_rays(fx: float, fy: float, cx: float, cy: float, distortion: FloatArray, supersample: int,
                rays: np.ndarray) -> float:
    """The ideal normalized coordinates of each sample's ray, written to ``rays`` (height * s, width * s, 2):
    sample (j, i) sits at pixel coordinates ((i + 0.5) / s - 0.5, (j + 0.5) / s - 0.5). Newton's method on the
    distortion with its exact Jacobian, from the previous sample's answer; returns the largest residual."""
    rows, columns = rays.shape[0], rays.shape[1]
    worst = 0.0
    eps = 1e-7
    for j in range(rows):
        gx, gy = 0.0, 0.0
        for i in range(columns):
            tx = (((i + 0.5) / supersample - 0.5) - cx) / fx
            ty = (((j + 0.5) / supersample - 0.5) - cy) / fy
            if i == 0:
                gx, gy = tx, ty
            for _ in range(30):
                dx, dy = distort_point(gx, gy, distortion)
                rx, ry = dx - tx, dy - ty
                if abs(rx) < 1e-14 and abs(ry) < 1e-14:
                    break
                ax, ay = distort_point(gx + eps, gy, distortion)
                bx, by = distort_point(gx, gy + eps, distortion)
                a, c = (ax - dx) / eps, (ay - dy) / eps
                b, d = (bx - dx) / eps, (by - dy) / eps
                determinant = a * d - b * c
                gx -= (d * rx - b * ry) / determinant
                gy -= (a * ry - c * rx) / determinant
            dx, dy = distort_point(gx, gy, distortion)
            worst = max(worst, abs(dx - tx), abs(dy - ty))
            rays[j, i, 0] = gx
            rays[j, i, 1] = gy
    return worst


@kernel
def rasterize(vertices: FloatArray, triangles: IntArray, fx: float, fy: float, cx: float, cy: float,
              distortion: FloatArray, supersample: int, rays: np.ndarray, depth: np.ndarray, face: np.ndarray,
              weights: np.ndarray) -> int:
    """Draw triangles (vertices in the camera's frame, mm) into the z-buffer ``depth`` (rows, columns; +inf where
    nothing is drawn), with the nearest triangle's index in ``face`` (-1: none) and the perspective-correct
    barycentric weights of its vertices 1 and 2 in ``weights`` (rows, columns, 2). A sample is inside when its
    ray's ideal normalized point is inside the triangle's pinhole projection, edges included (no cracks between
    neighbours). Returns the number of triangles drawn."""
    rows, columns = depth.shape[0], depth.shape[1]
    drawn = 0
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        za, zb, zc = vertices[a, 2], vertices[b, 2], vertices[c, 2]
        if za < NEAR_MM or zb < NEAR_MM or zc < NEAR_MM:
            continue
        xa, ya = vertices[a, 0] / za, vertices[a, 1] / za
        xb, yb = vertices[b, 0] / zb, vertices[b, 1] / zb
        xc, yc = vertices[c, 0] / zc, vertices[c, 1] / zc
        area = (xb - xa) * (yc - ya) - (xc - xa) * (yb - ya)
        if area == 0.0:
            continue
        # the bounding box in samples of the distorted corners, widened for the edges' bend
        low_i, low_j, high_i, high_j = 1e30, 1e30, -1e30, -1e30
        for x, y in ((xa, ya), (xb, yb), (xc, yc)):
            dx, dy = distort_point(x, y, distortion)
            si = (fx * dx + cx + 0.5) * supersample - 0.5
            sj = (fy * dy + cy + 0.5) * supersample - 0.5
            low_i, high_i = min(low_i, si), max(high_i, si)
            low_j, high_j = min(low_j, sj), max(high_j, sj)
        margin = 2.0 + 0.02 * max(high_i - low_i, high_j - low_j)
        i0, i1 = max(int(np.floor(low_i - margin)), 0), min(int(np.ceil(high_i + margin)), columns - 1)
        j0, j1 = max(int(np.floor(low_j - margin)), 0), min(int(np.ceil(high_j + margin)), rows - 1)
        if i0 > i1 or j0 > j1:
            continue
        drawn += 1
        inverse_area = 1.0 / area
        for j in range(j0, j1 + 1):
            for i in range(i0, i1 + 1):
                px, py = rays[j, i, 0], rays[j, i, 1]
                w0 = ((xb - px) * (yc - py) - (xc - px) * (yb - py)) * inverse_area
                w1 = ((xc - px) * (ya - py) - (xa - px) * (yc - py)) * inverse_area
                w2 = 1.0 - w0 - w1
                if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                    continue
                inverse_depth = w0 / za + w1 / zb + w2 / zc
                z = 1.0 / inverse_depth
                if z < depth[j, i]:
                    depth[j, i] = z
                    face[j, i] = t
                    weights[j, i, 0] = w1 / zb * z
                    weights[j, i, 1] = w2 / zc * z
    return drawn


@kernel
def cast_plane(rays: np.ndarray, origin: FloatArray, axis_u: FloatArray, axis_v: FloatArray, texture: np.ndarray,
               pixels_per_mm: float, depth: np.ndarray, value: np.ndarray) -> int:
    """Cast each sample's ray onto a textured rectangle in the camera's frame: its corner ``origin`` (mm) and
    unit edge directions ``axis_u``, ``axis_v``; ``texture`` (rows, columns) covers it at ``pixels_per_mm``,
    its row 0 along axis_u at v = 0. Where the ray meets the rectangle in front of what ``depth`` holds, the
    texture's bilinear value goes to ``value`` and the depth to ``depth``. Returns the samples it covered."""
    normal0 = axis_u[1] * axis_v[2] - axis_u[2] * axis_v[1]
    normal1 = axis_u[2] * axis_v[0] - axis_u[0] * axis_v[2]
    normal2 = axis_u[0] * axis_v[1] - axis_u[1] * axis_v[0]
    offset = normal0 * origin[0] + normal1 * origin[1] + normal2 * origin[2]
    height, width = texture.shape[0], texture.shape[1]
    covered = 0
    for j in range(rays.shape[0]):
        for i in range(rays.shape[1]):
            rx, ry = rays[j, i, 0], rays[j, i, 1]
            along = normal0 * rx + normal1 * ry + normal2
            if along == 0.0:
                continue
            t = offset / along
            if t < NEAR_MM or t >= depth[j, i]:
                continue
            hx, hy, hz = rx * t - origin[0], ry * t - origin[1], t - origin[2]
            u = (hx * axis_u[0] + hy * axis_u[1] + hz * axis_u[2]) * pixels_per_mm - 0.5
            v = (hx * axis_v[0] + hy * axis_v[1] + hz * axis_v[2]) * pixels_per_mm - 0.5
            if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):  # NaN too: it would index anywhere
                continue
            u = min(max(u, 0.0), width - 1.0)
            v = min(max(v, 0.0), height - 1.0)
            iu, iv = min(int(u), width - 2), min(int(v), height - 2)
            fu, fv = u - iu, v - iv
            value[j, i] = ((1 - fu) * (1 - fv) * texture[iv, iu] + fu * (1 - fv) * texture[iv, iu + 1]
                           + (1 - fu) * fv * texture[iv + 1, iu] + fu * fv * texture[iv + 1, iu + 1])
            depth[j, i] = t
            covered += 1
    return covered


@kernel
def shade_pixels(face: np.ndarray, weights: np.ndarray, triangles: IntArray, normals: FloatArray, lamp: FloatArray,
                 ambient: float, lamp_power: float, albedo: FloatArray, material: IntArray, gloss: FloatArray,
                 shininess: float, rays: np.ndarray, backdrop: FloatArray, backdrop_level: np.ndarray, supersample: int,
                 out: np.ndarray) -> None:
    """Each pixel of ``out`` (height, width, 3) the mean of its samples: where drawn, Lambert's law with the normals
    (camera frame, per vertex) interpolated, in the colour ``albedo[material[t]]`` of the triangle's material,
    plus a white Blinn-Phong highlight of the lamp (``gloss`` per material, ``shininess`` its exponent; the view
    along the sample's ray ``rays``); elsewhere the backdrop's colour times its level at the pixel."""
    s = supersample
    share = 1.0 / (s * s)
    for row in range(out.shape[0]):
        for column in range(out.shape[1]):
            r, g, b = 0.0, 0.0, 0.0
            for j in range(row * s, row * s + s):
                for i in range(column * s, column * s + s):
                    t = face[j, i]
                    if t < 0:
                        level = backdrop_level[row, column]
                        r += level * backdrop[0]
                        g += level * backdrop[1]
                        b += level * backdrop[2]
                        continue
                    w1, w2 = weights[j, i, 0], weights[j, i, 1]
                    w0 = 1.0 - w1 - w2
                    a, bb, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
                    nx = w0 * normals[a, 0] + w1 * normals[bb, 0] + w2 * normals[c, 0]
                    ny = w0 * normals[a, 1] + w1 * normals[bb, 1] + w2 * normals[c, 1]
                    nz = w0 * normals[a, 2] + w1 * normals[bb, 2] + w2 * normals[c, 2]
                    length = max(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
                    nx, ny, nz = nx / length, ny / length, nz / length
                    cosine = nx * lamp[0] + ny * lamp[1] + nz * lamp[2]
                    light = ambient + lamp_power * max(cosine, 0.0)
                    m = material[t]
                    highlight = 0.0
                    if gloss[m] > 0.0:
                        # the halfway vector between the lamp and the eye (the eye looks along the ray)
                        dx, dy = rays[j, i, 0], rays[j, i, 1]
                        norm = np.sqrt(dx * dx + dy * dy + 1.0)
                        hx, hy, hz = lamp[0] - dx / norm, lamp[1] - dy / norm, lamp[2] - 1.0 / norm
                        hnorm = max(np.sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
                        facing = (nx * hx + ny * hy + nz * hz) / hnorm
                        if facing > 0.0:
                            highlight = gloss[m] * facing ** shininess
                    r += light * albedo[m, 0] + highlight
                    g += light * albedo[m, 1] + highlight
                    b += light * albedo[m, 2] + highlight
            out[row, column, 0] = r * share
            out[row, column, 1] = g * share
            out[row, column, 2] = b * share


@kernel
def plane_pixels(depth: np.ndarray, value: np.ndarray, light: float, backdrop: FloatArray, supersample: int,
                 out: np.ndarray) -> None:
    """Each pixel of ``out`` the mean of its samples: the grey print (``value`` times ``light``) where the plane
    was hit (finite depth), the backdrop's colour elsewhere."""
    s = supersample
    share = 1.0 / (s * s)
    for row in range(out.shape[0]):
        for column in range(out.shape[1]):
            r, g, b = 0.0, 0.0, 0.0
            for j in range(row * s, row * s + s):
                for i in range(column * s, column * s + s):
                    if np.isfinite(depth[j, i]):
                        grey = light * value[j, i]
                        r += grey
                        g += grey
                        b += grey
                    else:
                        r += backdrop[0]
                        g += backdrop[1]
                        b += backdrop[2]
            out[row, column, 0] = r * share
            out[row, column, 1] = g * share
            out[row, column, 2] = b * share


@kernel
def key_alpha(image: np.ndarray, table: np.ndarray, key: FloatArray, out: np.ndarray) -> None:
    """``out = clip(1 - key . linear(image), 0, 1)`` per pixel: the phantom's share of each pixel of an 8-bit sRGB
    picture, ``table`` the 256 codes in linear light."""
    for row in range(image.shape[0]):
        for column in range(image.shape[1]):
            k = (key[0] * table[image[row, column, 0]] + key[1] * table[image[row, column, 1]]
                 + key[2] * table[image[row, column, 2]])
            out[row, column] = min(max(1.0 - k, 0.0), 1.0)


@kernel
def crop_position(x: float, y: float, z: float, fx: float, fy: float, cx: float, cy: float, distortion: FloatArray,
                  max_radius2: float, x0: int, y0: int, width: int, height: int) -> tuple[float, float]:
    """Where a point in a camera's frame (mm, z >= NEAR_MM) falls in the crop ``x0, y0, width, height`` of its
    picture (px from the crop's corner); (-1, -1) outside the crop, or for a ray further from the optical axis than
    ``max_radius2`` (ideal normalized, squared), which the lens model would fold back into the picture."""
    xn, yn = x / z, y / z
    if xn * xn + yn * yn > max_radius2:
        return -1.0, -1.0
    dx, dy = distort_point(xn, yn, distortion)
    u = fx * dx + cx - x0
    w = fy * dy + cy - y0
    if not (0.0 <= u <= width - 1.0 and 0.0 <= w <= height - 1.0):  # NaN too: it would index anywhere
        return -1.0, -1.0
    return u, w


@kernel
def crop_value(values: np.ndarray, offset: int, width: int, height: int, u: float, w: float) -> float:
    """The bilinear interpolation at ``(u, w)`` (px, within the crop) of a crop's values, stored row by row from
    ``offset`` of ``values``."""
    iu, iw = min(int(u), width - 2), min(int(w), height - 2)
    fu, fw = u - iu, w - iw
    base = offset + iw * width + iu
    value: float = ((1.0 - fu) * (1.0 - fw) * values[base] + fu * (1.0 - fw) * values[base + 1]
                    + (1.0 - fu) * fw * values[base + width] + fu * fw * values[base + width + 1])
    return value


@kernel
def hull_distance(points: FloatArray, rotations: FloatArray, translations: FloatArray, fx: float, fy: float,
                  cx: float, cy: float, distortion: FloatArray, max_radius2: float, distances: np.ndarray,
                  offsets: IntArray, crops: IntArray, truncation_px: float, stop_mm: float, out: np.ndarray) -> int:
    """F at each point (see the module docstring), written to ``out``; a point stops at the first view that puts
    it more than ``stop_mm`` outside. Returns the projections made. ``distances`` holds every view's signed
    distance crop one after the other (view v's from ``offsets[v]``, ``crops[v] = x0, y0, width, height``);
    a ray further from the optical axis than ``max_radius2`` (ideal normalized, squared) is outside the picture."""
    focal = 0.5 * (fx + fy)
    projections = 0
    for n in range(points.shape[0]):
        px, py, pz = points[n, 0], points[n, 1], points[n, 2]
        worst = -1e30
        for v in range(rotations.shape[0]):
            projections += 1
            x = rotations[v, 0, 0] * px + rotations[v, 0, 1] * py + rotations[v, 0, 2] * pz + translations[v, 0]
            y = rotations[v, 1, 0] * px + rotations[v, 1, 1] * py + rotations[v, 1, 2] * pz + translations[v, 1]
            z = rotations[v, 2, 0] * px + rotations[v, 2, 1] * py + rotations[v, 2, 2] * pz + translations[v, 2]
            if z < NEAR_MM:
                worst = 1e30
                break
            u, w = crop_position(x, y, z, fx, fy, cx, cy, distortion, max_radius2, crops[v, 0], crops[v, 1],
                                 crops[v, 2], crops[v, 3])
            if u < 0.0:
                d = truncation_px
            else:
                d = crop_value(distances, offsets[v], crops[v, 2], crops[v, 3], u, w)
            d_mm = d * z / focal
            if d_mm > worst:
                worst = d_mm
            if worst > stop_mm:
                break
        out[n] = worst
    return projections


@kernel
def hull_in_views(points: FloatArray, rotations: FloatArray, translations: FloatArray, fx: float, fy: float,
                  cx: float, cy: float, distortion: FloatArray, max_radius2: float, distances: np.ndarray,
                  offsets: IntArray, crops: IntArray, truncation_px: float, covered: np.ndarray,
                  bounding: np.ndarray) -> None:
    """Points on the carved hull's surface (world, mm) seen by the views :func:`hull_distance` carved with: each
    view's pixel nearest each point's projection set to 1 in ``covered`` (uint8, laid out as ``distances``: the
    views' crops one after the other), and each point's ``bounding`` view, the one whose silhouette's edge is
    nearest it (the largest signed distance, mm; -1 where no view sees it)."""
    focal = 0.5 * (fx + fy)
    nearest = np.full(points.shape[0], -1e30)
    bounding[:] = -1
    # view by view: neighbouring points fall on neighbouring pixels of one crop (a quarter less time than point by
    # point: 107 ms against 142 for 87k points in 60 views)
    for v in range(rotations.shape[0]):
        x0, y0, width, height = crops[v, 0], crops[v, 1], crops[v, 2], crops[v, 3]
        for n in range(points.shape[0]):
            px, py, pz = points[n, 0], points[n, 1], points[n, 2]
            x = rotations[v, 0, 0] * px + rotations[v, 0, 1] * py + rotations[v, 0, 2] * pz + translations[v, 0]
            y = rotations[v, 1, 0] * px + rotations[v, 1, 1] * py + rotations[v, 1, 2] * pz + translations[v, 1]
            z = rotations[v, 2, 0] * px + rotations[v, 2, 1] * py + rotations[v, 2, 2] * pz + translations[v, 2]
            if z < NEAR_MM:
                continue
            u, w = crop_position(x, y, z, fx, fy, cx, cy, distortion, max_radius2, x0, y0, width, height)
            if u < 0.0:
                d = truncation_px
            else:
                covered[offsets[v] + int(w + 0.5) * width + int(u + 0.5)] = 1
                d = crop_value(distances, offsets[v], width, height, u, w)
            d_mm = d * z / focal
            if d_mm > nearest[n]:
                nearest[n] = d_mm
                bounding[n] = v
