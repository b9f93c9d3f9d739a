"""The compiled proposal pass of :mod:`.correspondence` (numba): every frame's epipolar blob
pairs, their two-view points and their support in the other cameras, in one pass (as numpy
over padded (frames, blobs, blobs) arrays it was 3/4 of the reconstruction time). Cached on disk."""

from __future__ import annotations

import numpy as np

from .compiled import compiled


@compiled(error_model="numpy", inline="always")
def _solve3(m, out):  # pragma: no cover (compiled)
    """``out (3,)`` = the solution of ``m[:, :3] x = -m[:, 3]`` (Cramer's rule)."""
    a, b, c = m[0, 0], m[0, 1], m[0, 2]
    d, e, f = m[1, 0], m[1, 1], m[1, 2]
    g, h, k = m[2, 0], m[2, 1], m[2, 2]
    co0, co1, co2 = e * k - f * h, f * g - d * k, d * h - e * g
    det = a * co0 + b * co1 + c * co2
    r0, r1, r2 = -m[0, 3], -m[1, 3], -m[2, 3]
    out[0] = (r0 * co0 + r1 * (c * h - b * k) + r2 * (b * f - c * e)) / det
    out[1] = (r0 * co1 + r1 * (a * k - c * g) + r2 * (c * d - a * f)) / det
    out[2] = (r0 * co2 + r1 * (b * g - a * h) + r2 * (a * e - b * d)) / det


@compiled(error_model="numpy", nogil=True)
def proposals_kernel(norm, by_y, order, essentials, projections, focal, tolerance, out_frame, out_keys,
                     out_error, out_point):  # pragma: no cover (compiled)
    """Write the proposals of ``norm (C, F, B, 2)`` normalized blobs (NaN padding): for every
    camera pair ``i < j`` the blob pairs within ``tolerance`` px of each other's epipolar line
    (``essentials (C, C, 3, 3)``), triangulated (two-view linear, ``projections (C, 3, 4)``),
    with the nearest blob within ``tolerance`` px of the reprojection in every other camera.
    ``out_keys (N, C)`` blob per camera (-1 none), ``out_error`` mean reprojection error px,
    ``out_point (N, 3)`` mm, ``out_frame``. Returns the number of proposals (only the first
    ``len(out_frame)`` are written). ``by_y (C, F, B, 2)``: the blobs in px sorted by y (NaN
    last), ``order (C, F, B)`` their indices (the nearest blob is searched in a band of rows)."""
    n_cams, n_frames, width = norm.shape[0], norm.shape[1], norm.shape[2]
    capacity = len(out_frame)
    n = 0
    a_mat = np.empty((4, 4))
    normal = np.empty((3, 4))
    point = np.empty(3)
    keys = np.empty(n_cams, np.int64)
    near = np.empty(width, np.int64)
    for f in range(n_frames):
        for i in range(n_cams):
            for j in range(i + 1, n_cams):
                e = essentials[i, j]
                for a in range(width):
                    xa, ya = norm[i, f, a, 0], norm[i, f, a, 1]
                    if not np.isfinite(xa):
                        continue
                    l0 = e[0, 0] * xa + e[0, 1] * ya + e[0, 2]
                    l1 = e[1, 0] * xa + e[1, 1] * ya + e[1, 2]
                    l2 = e[2, 0] * xa + e[2, 1] * ya + e[2, 2]
                    scale = focal[j] / np.sqrt(l0 * l0 + l1 * l1)
                    # the blobs of camera j near the epipolar line of blob a, in order: a
                    # branch-free pass over all blobs (SIMD), then the few candidates
                    m = 0
                    for b in range(width):
                        near[m] = b
                        m += abs(l0 * norm[j, f, b, 0] + l1 * norm[j, f, b, 1] + l2) * scale \
                            < tolerance  # NaN: no
                    for candidate in range(m):
                        b = near[candidate]
                        xb, yb = norm[j, f, b, 0], norm[j, f, b, 1]
                        # two-view linear point: 4 equations, 3 unknowns, normal equations
                        for q in range(4):
                            a_mat[0, q] = xa * projections[i, 2, q] - projections[i, 0, q]
                            a_mat[1, q] = ya * projections[i, 2, q] - projections[i, 1, q]
                            a_mat[2, q] = xb * projections[j, 2, q] - projections[j, 0, q]
                            a_mat[3, q] = yb * projections[j, 2, q] - projections[j, 1, q]
                        for p in range(3):
                            for q in range(4):
                                total = 0.0
                                for r in range(4):
                                    total += a_mat[r, p] * a_mat[r, q]
                                normal[p, q] = total  # column 3: the right-hand side (negated)
                        _solve3(normal, point)
                        error = 0.0
                        views = 0
                        for k in range(n_cams):
                            keys[k] = -1
                            depth = projections[k, 2, 3]
                            px = projections[k, 0, 3]
                            py = projections[k, 1, 3]
                            for q in range(3):
                                depth += projections[k, 2, q] * point[q]
                                px += projections[k, 0, q] * point[q]
                                py += projections[k, 1, q] * point[q]
                            px, py = px / depth * focal[k], py / depth * focal[k]
                            if k == i or k == j:
                                own = a if k == i else b
                                keys[k] = own
                                views += 1
                                if depth > 0:
                                    error += np.hypot(px - norm[k, f, own, 0] * focal[k],
                                                      py - norm[k, f, own, 1] * focal[k])
                                else:
                                    error = np.inf
                            elif depth > 0:
                                best, gap = -1, tolerance * tolerance
                                rows = by_y[k, f, :, 1]
                                c = np.searchsorted(rows, py - tolerance)
                                while c < width and rows[c] < py + tolerance:  # NaN (last): stop
                                    dx, dy = px - by_y[k, f, c, 0], py - rows[c]
                                    if dx * dx + dy * dy < gap:
                                        best, gap = c, dx * dx + dy * dy
                                    c += 1
                                if best >= 0:
                                    keys[k] = order[k, f, best]
                                    views += 1
                                    error += np.sqrt(gap)
                        if n < capacity:
                            out_frame[n] = f
                            out_keys[n] = keys
                            out_error[n] = error / views
                            out_point[n] = point
                        n += 1
    return n


@compiled("int64(int64[:, :], int64[:], boolean[:, :], int64[:])", error_model="numpy")
def first_come(keys, rows, used, out):  # pragma: no cover (compiled)
    """Take the hypotheses ``rows`` in their order, each while none of its blobs ``keys[row]``
    (-1: camera unused) is marked in ``used (C, B)``; mark the blobs of each taken one. Writes
    the taken rows to ``out[:n]`` (in order) and returns ``n``."""
    n = 0
    for row in rows:
        free = True
        for c in range(keys.shape[1]):
            if keys[row, c] >= 0 and used[c, keys[row, c]]:
                free = False
                break
        if free:
            for c in range(keys.shape[1]):
                if keys[row, c] >= 0:
                    used[c, keys[row, c]] = True
            out[n] = row
            n += 1
    return n
