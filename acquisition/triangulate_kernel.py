"""The compiled triangulation kernel (numba), imported by :mod:`.triangulate` on first use.

One serial pass over a range of chunks of points, releasing the GIL (the caller runs one range
per thread): undistortion (OpenCV's fixed-point iteration), closed-form DLT normal equations
reweighted by focal / depth, per-view reprojection errors, for points whose views disagree a
refit without the worst view (4+ views) else the two-view pair consensus, refit and growth, and
the RMS residual in the distorted image. Every function has one explicit signature, so that
each is compiled once (about 10 CPU-s in all, when the module is first imported) and then
loaded from numba's disk cache; kept in its own module so that importing
:mod:`mocaptk.acquisition` does not import numba.
"""

from __future__ import annotations

import numpy as np

from .compiled import compiled

# Fixed-point undistortion iterations, as cv2.undistortPoints with (COUNT, 6, 0):
# < 1e-4 px error over a whole Cara image.
UNDISTORT_ITERATIONS = 6
# Points per chunk (each chunk allocates its scratch arrays once).
CHUNK = 512

# One signature per function (numba would otherwise also compile the helpers for the literal
# values their arguments start from, e.g. n = 0: each specialization a compile of its own).
_F1, _F2, _F3 = "float64[::1]", "float64[:, ::1]", "float64[:, :, ::1]"
_I1, _B1, _B2 = "int64[::1]", "boolean[::1]", "boolean[:, ::1]"


# Helpers: compiled once each, then inlined into the kernel by LLVM (not by numba, whose inlining
# re-types every call site: 2-3x the compile time). They allocate nothing, so they are compiled
# without numba's reference counting: with it, their array arguments cost runtime calls (atomic
# increfs and decrefs) that LLVM cannot remove after inlining (the kernel ran 1.5x slower).
_HELPER = {"error_model": "numpy", "forceinline": True, "_nrt": False}


def _signature(result: str, *arguments: str) -> str:
    return f"{result}({', '.join(arguments)})"


@compiled(_signature("void", _F3, "int64", "float64", "float64", _F1), **_HELPER)
def _normal_terms(poses, c, u, v, terms):
    """The 9 terms ``terms (9,)`` that the view of camera ``c`` with ray ``u, v`` adds (times
    its squared row weight) to the DLT normal equations: ``a aᵀ + b bᵀ`` (upper triangle
    00 01 02 11 12 22) and ``a a₄ + b b₄`` (3), with the rows ``a = u P3 - P1`` and
    ``b = v P3 - P2`` (``P1..P3`` the rows of ``[R | t]``)."""
    a0 = u * poses[c, 2, 0] - poses[c, 0, 0]
    a1 = u * poses[c, 2, 1] - poses[c, 0, 1]
    a2 = u * poses[c, 2, 2] - poses[c, 0, 2]
    a3 = u * poses[c, 2, 3] - poses[c, 0, 3]
    b0 = v * poses[c, 2, 0] - poses[c, 1, 0]
    b1 = v * poses[c, 2, 1] - poses[c, 1, 1]
    b2 = v * poses[c, 2, 2] - poses[c, 1, 2]
    b3 = v * poses[c, 2, 3] - poses[c, 1, 3]
    terms[0] = a0 * a0 + b0 * b0
    terms[1] = a0 * a1 + b0 * b1
    terms[2] = a0 * a2 + b0 * b2
    terms[3] = a1 * a1 + b1 * b1
    terms[4] = a1 * a2 + b1 * b2
    terms[5] = a2 * a2 + b2 * b2
    terms[6] = a0 * a3 + b0 * b3
    terms[7] = a1 * a3 + b1 * b3
    terms[8] = a2 * a3 + b2 * b3


@compiled(_signature("void", "int64", _I1, _F1, _F2, _F1), **_HELPER)
def _solve_weighted(count, views, weight, terms, x):
    """Solve the DLT normal equations of the views ``views[:count]`` (rows of ``terms``, see
    :func:`_normal_terms`) with row weights ``weight[:count]`` in closed form (adjugate) into
    ``x (3,)``; NaN where the matrix is (nearly) singular."""
    m00 = m01 = m02 = m11 = m12 = m22 = r0 = r1 = r2 = 0.0
    for k in range(count):
        t = terms[views[k]]
        w2 = weight[k] * weight[k]
        m00 += w2 * t[0]
        m01 += w2 * t[1]
        m02 += w2 * t[2]
        m11 += w2 * t[3]
        m12 += w2 * t[4]
        m22 += w2 * t[5]
        r0 -= w2 * t[6]
        r1 -= w2 * t[7]
        r2 -= w2 * t[8]
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    scale = m00 + m11 + m22
    if not abs(det) > 1e-12 * scale * scale * scale:
        x[0] = x[1] = x[2] = np.nan
        return
    x[0] = (c00 * r0 + c01 * r1 + c02 * r2) / det
    x[1] = (c01 * r0 + c11 * r1 + c12 * r2) / det
    x[2] = (c02 * r0 + c12 * r1 + c22 * r2) / det


@compiled(_signature("float64", _F3, "float64", "int64", "float64", "float64", _F1), **_HELPER)
def _error_px(poses, focal, c, u, v, x):
    """Reprojection error in px (normalized coordinates times ``focal``) of ``x (3,)`` in
    camera ``c`` against the ray ``u, v``; ``inf`` behind the camera or where ``x`` is NaN."""
    if not (np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])):
        return np.inf
    z = poses[c, 2, 0] * x[0] + poses[c, 2, 1] * x[1] + poses[c, 2, 2] * x[2] + poses[c, 2, 3]
    if not z > 0:
        return np.inf
    du = (poses[c, 0, 0] * x[0] + poses[c, 0, 1] * x[1] + poses[c, 0, 2] * x[2]
          + poses[c, 0, 3]) / z - u
    dv = (poses[c, 1, 0] * x[0] + poses[c, 1, 1] * x[1] + poses[c, 1, 2] * x[2]
          + poses[c, 1, 3]) / z - v
    return focal * np.sqrt(du * du + dv * dv)


@compiled(_signature("void", _F3, _F1, "int64", _I1, _F1, _F1, _F1, _F1), **_HELPER)
def _errors_px(poses, focal, n, cam, u, v, x, error):
    """Reprojection errors ``error[:n]`` in px of the views ``cam[:n]`` (see
    :func:`_error_px`)."""
    for j in range(n):
        error[j] = _error_px(poses, focal[cam[j]], cam[j], u[j], v[j], x)


@compiled(_signature("void", _F1, "int64", _I1, _B1, "int64", _F3, _F2, _I1, _F1, _F1), **_HELPER)
def _solve(focal, n, cam, use, refine_iterations, poses, terms, views, weight, x):
    """Weighted inhomogeneous DLT over the views ``use[:n]`` into ``x (3,)`` mm; NaN with
    fewer than 2 views or a degenerate system.

    Rows are weighted by ``focal / depth`` (depth from the previous solution), so after the
    first step the algebraic residual is the reprojection error in px. ``views, weight``:
    scratch.
    """
    count = 0
    for j in range(n):
        if use[j]:
            views[count], weight[count] = j, focal[cam[j]]
            count += 1
    for step in range(refine_iterations + 1):
        _solve_weighted(count, views, weight, terms, x)
        if count < 2:
            x[0] = x[1] = x[2] = np.nan
        if step < refine_iterations:
            for k in range(count):
                c = cam[views[k]]
                depth = poses[c, 2, 0] * x[0] + poses[c, 2, 1] * x[1] + poses[c, 2, 2] * x[2] \
                    + poses[c, 2, 3]
                weight[k] = focal[c] / depth if depth > 0 else 0.0  # NaN: 0


@compiled(_signature("void", _F3, _F1, "int64", "float64", "int64", "int64", _I1, _F1, _F1, _B1,
                     _F1, _I1, _F1, _F2, _F1), **_HELPER)
def _triangulate_point(poses, focal, min_views, threshold, refine_iterations,
                       n, cam, u, v, use, error, views, weight, terms, x):
    """Robust solve of one point seen by the ``n`` cameras ``cam[:n]`` (ascending) with rays
    ``u, v`` into ``x (3,)``; ``use[:n]`` ends as its inlier views.
    ``error, views, weight, terms``: scratch. (Arrays of length >= n; only the first n are
    used.)"""
    for j in range(n):
        _normal_terms(poses, cam[j], u[j], v[j], terms[j])
    # 1) all views; a point whose views all agree is done
    for j in range(n):
        use[j] = True
    _solve(focal, n, cam, use, refine_iterations, poses, terms, views, weight, x)
    _errors_px(poses, focal, n, cam, u, v, x, error)
    n_inliers = 0
    for j in range(n):
        use[j] = error[j] <= threshold
        n_inliers += use[j]
    if n >= 2 and n_inliers < n:
        # 2) a single outlier first: drop the worst view, refit on the others; done when
        # they all agree (the pair search below would find the same views)
        best_count = 0
        if n >= 4:
            worst = 0
            for j in range(1, n):
                if error[j] > error[worst]:
                    worst = j
            for j in range(n):
                use[j] = j != worst
            _solve(focal, n, cam, use, refine_iterations, poses, terms, views, weight, x)
            _errors_px(poses, focal, n, cam, u, v, x, error)
            best_count = n - 1
            for j in range(n):
                if j != worst and not error[j] <= threshold:
                    best_count = 0
        if best_count == 0:
            # 3) else consensus over the two-view hypotheses of every camera pair seeing the
            # point: each pair is solved from its two views only; a pair that can no longer
            # beat the best count (even with all its remaining views agreeing) stops being
            # checked
            best_count, best_cost, best_mask = 0, np.inf, 0
            for i in range(n):
                for j in range(i + 1, n):
                    views[0], views[1] = i, j
                    weight[0], weight[1] = focal[cam[i]], focal[cam[j]]
                    _solve_weighted(2, views, weight, terms, x)
                    count, cost, mask = 0, 0.0, 0
                    for m in range(n):
                        if count + n - m < best_count:
                            break
                        e = _error_px(poses, focal[cam[m]], cam[m], u[m], v[m], x)
                        if e <= threshold:
                            count += 1
                            cost += e
                            mask |= 1 << m
                    if count > best_count or (count == best_count and cost < best_cost):
                        best_count, best_cost, best_mask = count, cost, mask
            for j in range(n):
                use[j] = (best_mask >> j) & 1 == 1
            _solve(focal, n, cam, use, refine_iterations, poses, terms, views, weight, x)
            _errors_px(poses, focal, n, cam, u, v, x, error)
        # views that agree with the refit consensus point join it (one more pass)
        grown = 0
        for j in range(n):
            grown += error[j] <= threshold
        if grown > best_count:
            for j in range(n):
                use[j] = error[j] <= threshold
            _solve(focal, n, cam, use, refine_iterations, poses, terms, views, weight, x)
    n_inliers = 0
    for j in range(n):
        n_inliers += use[j]
    if n_inliers < min_views:
        x[0] = x[1] = x[2] = np.nan
    if not (np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])):
        for j in range(n):
            use[j] = False


@compiled(_signature("void", _F2, "int64", "int64", _F1, _F1, _F1, _B1, _F1, _F1), **_HELPER)
def undistort(observations, start, size, camera, u, v, valid, x0, y0):
    """Normalized image coordinates ``u, v`` of the pixels ``observations[start:start +
    size]`` of one camera (``valid``: finite; else ``u = v = 0``). cv2.undistortPoints'
    fixed-point iteration for ``(k1, k2, p1, p2, k3)`` with a fixed iteration count (skew
    ignored, as OpenCV does). ``x0, y0``: scratch. Each iteration is a loop over the points
    (independent, SIMD-friendly) rather than a dependent chain per point.
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = camera[0], camera[1], camera[2], camera[3], \
        camera[4], camera[5], camera[6], camera[7], camera[8]
    ifx, ify = 1.0 / fx, 1.0 / fy
    for k in range(size):
        x0[k] = u[k] = (observations[start + k, 0] - cx) * ifx
        y0[k] = v[k] = (observations[start + k, 1] - cy) * ify
        valid[k] = False  # here: "folded" (the model's fold was crossed)
    for _ in range(UNDISTORT_ITERATIONS):
        for k in range(size):
            x, y = u[k], v[k]
            r2 = x * x + y * y
            icdist = 1.0 / (1.0 + ((k3 * r2 + k2) * r2 + k1) * r2)
            valid[k] |= icdist < 0
            u[k] = (x0[k] - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) * icdist
            v[k] = (y0[k] - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) * icdist
    for k in range(size):
        x, y = (x0[k], y0[k]) if valid[k] else (u[k], v[k])  # folded: OpenCV keeps x0, y0
        ok = np.isfinite(x) and np.isfinite(y)  # NaN detections stay NaN
        valid[k] = ok
        u[k] = x if ok else 0.0
        v[k] = y if ok else 0.0


@compiled(_signature("float64", _F3, "int64", "int64", _F2, _F3, _F1), **_HELPER)
def _squared_pixel_error(observations, c, p, cameras, poses, x):
    """Squared distance in px between the detection ``observations[c, p]`` and ``x (3,)``
    projected with full distortion (same model as ``Camera.pixels_from_normalized``)."""
    z = poses[c, 2, 0] * x[0] + poses[c, 2, 1] * x[1] + poses[c, 2, 2] * x[2] + poses[c, 2, 3]
    xn = (poses[c, 0, 0] * x[0] + poses[c, 0, 1] * x[1] + poses[c, 0, 2] * x[2]
          + poses[c, 0, 3]) / z
    yn = (poses[c, 1, 0] * x[0] + poses[c, 1, 1] * x[1] + poses[c, 1, 2] * x[2]
          + poses[c, 1, 3]) / z
    fx, fy, cx, cy, k1, k2, p1, p2, k3, skew = cameras[c, 0], cameras[c, 1], cameras[c, 2], \
        cameras[c, 3], cameras[c, 4], cameras[c, 5], cameras[c, 6], cameras[c, 7], \
        cameras[c, 8], cameras[c, 9]
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    du = fx * xd + skew * yd + cx - observations[c, p, 0]
    dv = fy * yd + cy - observations[c, p, 1]
    return du * du + dv * dv


@compiled(_signature("void", _F3, _F2, _F3, _F1, "int64", "float64", "int64", "int64", "int64",
                     _F2, _B2, _F1), error_model="numpy", nogil=True)
def triangulate_kernel(observations, cameras, poses, focal, min_views, threshold,
                       refine_iterations, first_chunk, last_chunk, points, inliers,
                       rms):  # pragma: no cover (compiled)
    """Fill ``points (P, 3)``, ``inliers (C, P)`` and ``rms (P,)`` from ``observations
    (C, P, 2)`` px (``cameras``: see ``triangulate._camera_table``; ``poses (C, 3, 4)``
    ``[R | t]`` mm; ``focal (C,)`` px) for the points of the chunks ``first_chunk`` to
    ``last_chunk - 1`` (:data:`CHUNK` points each); see :func:`.triangulate.triangulate_points`.
    Releases the GIL, so that threads can each run a range of chunks."""
    n_cams, n_points = observations.shape[0], observations.shape[1]
    for chunk in range(first_chunk, last_chunk):
        start = chunk * CHUNK
        size = min(n_points, start + CHUNK) - start
        rays_u = np.zeros((n_cams, CHUNK))
        rays_v = np.zeros((n_cams, CHUNK))
        seen = np.zeros((n_cams, CHUNK), dtype=np.bool_)
        # one camera's detections, gathered (index in the chunk, px), undistorted, scratch
        index = np.empty(CHUNK, dtype=np.int64)
        pixels = np.empty((CHUNK, 2))
        ray_u, ray_v, ray_ok = np.empty(CHUNK), np.empty(CHUNK), np.empty(CHUNK, np.bool_)
        x0, y0 = np.empty(CHUNK), np.empty(CHUNK)
        for c in range(n_cams):
            m = 0
            for k in range(size):  # branch-free gather of the detections (seen at random)
                px, py = observations[c, start + k, 0], observations[c, start + k, 1]
                index[m], pixels[m, 0], pixels[m, 1] = k, px, py
                m += np.isfinite(px) and np.isfinite(py)
            undistort(pixels, 0, m, cameras[c], ray_u, ray_v, ray_ok, x0, y0)
            for i in range(m):
                k = index[i]
                rays_u[c, k], rays_v[c, k], seen[c, k] = ray_u[i], ray_v[i], ray_ok[i]
        # one point's views, compacted: camera index, ray, inlier flag; scratch
        cam = np.empty(n_cams, dtype=np.int64)
        u = np.empty(n_cams)
        v = np.empty(n_cams)
        use = np.empty(n_cams, dtype=np.bool_)
        error = np.empty(n_cams)
        views = np.empty(n_cams, dtype=np.int64)
        weight = np.empty(n_cams)
        terms = np.empty((n_cams, 9))
        x = np.empty(3)
        for k in range(size):
            p = start + k
            n = 0
            for c in range(n_cams):  # branch-free
                inliers[c, p] = False
                cam[n], u[n], v[n] = c, rays_u[c, k], rays_v[c, k]
                n += seen[c, k]
            _triangulate_point(poses, focal, min_views, threshold, refine_iterations,
                               n, cam, u, v, use, error, views, weight, terms, x)
            points[p, 0], points[p, 1], points[p, 2] = x[0], x[1], x[2]
            count = 0
            squared = 0.0
            for j in range(n):
                if use[j]:
                    inliers[cam[j], p] = True
                    count += 1
                    squared += _squared_pixel_error(observations, cam[j], p, cameras, poses, x)
            rms[p] = np.sqrt(squared / count) if count else np.nan
