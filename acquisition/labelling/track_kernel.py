"""The compiled per-frame kernels of the labeller (numba; cached on disk, compiled once per install).

:func:`gauss_newton` is the pose + expression fit of :func:`.pose.fit_frame`; :func:`track` runs
:mod:`.tracker`'s tracked frames one after another without returning to Python — fit, release,
and assignment where no two points compete for a label — and hands a frame back only when it
needs a start-over (fewer than 3 carried points) or a real matching (Hungarian, in scipy).
:func:`finish_frame` stores a frame's labels. Why: the Python loop's cost was call overhead on
arrays of 40-140 points, not arithmetic (about 0.6 ms a frame).
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: :func:`track` return codes: all frames done; frame needs a start-over; frame needs a matching.
DONE, START_OVER, MATCH = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def _rodrigues(rx, ry, rz):  # pragma: no cover - compiled
    """The rotation matrix of a rotation vector (rad): ``cos I + sin [k]x + (1 - cos) k k^T``."""
    out = np.eye(3)
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-12:
        return out
    k = np.array([rx / angle, ry / angle, rz / angle])
    s, c = math.sin(angle), math.cos(angle)
    for i in range(3):
        for j in range(3):
            out[i, j] = (c if i == j else 0.0) + (1.0 - c) * k[i] * k[j]
    out[0, 1] -= s * k[2]
    out[0, 2] += s * k[1]
    out[1, 0] += s * k[2]
    out[1, 2] -= s * k[0]
    out[2, 0] -= s * k[1]
    out[2, 1] += s * k[0]
    return out


@numba.njit(cache=True, nogil=True)
def _solve_spd(a, b):  # pragma: no cover - compiled
    """``x`` with ``a x = b``, ``a`` symmetric positive definite (Cholesky). Why not
    ``np.linalg.solve``: its LAPACK binding was half of the kernel's ~20 CPU-s first compile."""
    n = len(b)
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = a[i, j]
            for k in range(j):
                acc -= low[i, k] * low[j, k]
            low[i, j] = math.sqrt(max(acc, 1e-300)) if i == j else acc / low[j, j]
    x = np.empty(n)
    for i in range(n):  # forward: L y = b
        acc = b[i]
        for k in range(i):
            acc -= low[i, k] * x[k]
        x[i] = acc / low[i, i]
    for i in range(n - 1, -1, -1):  # back: L^T x = y
        acc = x[i]
        for k in range(i + 1, n):
            acc -= low[k, i] * x[k]
        x[i] = acc / low[i, i]
    return x


@numba.njit(cache=True, nogil=True)
def gauss_newton(mean, basis_t, gram, mode_std, sigma, offset, idx, points, rot, trans, k,
                 rounds):  # pragma: no cover - compiled
    """``(rot, trans, coeffs)``: see :func:`.pose.fit_frame` (``k`` expression modes used;
    ``basis_t (M, 3, K)``, ``gram (M, K, K)``: :func:`model_arrays`). The normal equations are
    accumulated block by block, skipping the pose rows' zeros (about half the work of the dense
    outer products)."""
    n, p = len(idx), 6 + k
    coeffs = np.zeros(basis_t.shape[2])
    row = np.empty(6)
    for _ in range(rounds):
        lhs = np.zeros((p, p))
        rhs = np.zeros(p)
        for i in range(n):
            m = idx[i]
            d0, d1, d2 = points[i, 0] - trans[0], points[i, 1] - trans[1], points[i, 2] - trans[2]
            h0 = d0 * rot[0, 0] + d1 * rot[1, 0] + d2 * rot[2, 0]  # R^T (p - t)
            h1 = d0 * rot[0, 1] + d1 * rot[1, 1] + d2 * rot[2, 1]
            h2 = d0 * rot[0, 2] + d1 * rot[1, 2] + d2 * rot[2, 2]
            w = 1.0 / (sigma[m] * sigma[m])
            for c in range(3):
                # d(head)/d(rotation vector) of the update R <- R exp([w]): -[q]x
                if c == 0:
                    row[0], row[1], row[2], resid = 0.0, h2, -h1, h0
                elif c == 1:
                    row[0], row[1], row[2], resid = -h2, 0.0, h0, h1
                else:
                    row[0], row[1], row[2], resid = h1, -h0, 0.0, h2
                row[3], row[4], row[5] = 0.0, 0.0, 0.0
                row[3 + c] = 1.0
                resid -= mean[m, c] + offset[m, c]
                for a in range(6):  # the pose block
                    wa = w * row[a]
                    if wa == 0.0:
                        continue
                    rhs[a] += wa * resid
                    for b in range(a, 6):
                        lhs[a, b] += wa * row[b]
                    for j in range(k):  # pose x expression
                        lhs[a, 6 + j] += wa * basis_t[m, c, j]
                for j in range(k):
                    rhs[6 + j] += w * basis_t[m, c, j] * resid
            for a in range(k):  # expression x expression: the marker's mode Gram matrix
                for b in range(a, k):
                    lhs[6 + a, 6 + b] += w * gram[m, a, b]
        for a in range(p):
            for b in range(a):
                lhs[a, b] = lhs[b, a]
        for a in range(6):
            lhs[a, a] += 1e-6  # keeps the pose defined with fewer than 3 points
        for j in range(k):
            s = max(mode_std[j], 1e-6)
            lhs[6 + j, 6 + j] += 1.0 / (s * s)
        x = _solve_spd(lhs, rhs)
        coeffs[:k] = x[6:]
        step = _rodrigues(x[0], x[1], x[2])
        new_trans, new_rot = np.empty(3), np.empty((3, 3))
        for i in range(3):  # trans + R x[3:6]; R step (3 x 3 loops: no BLAS binding to compile)
            new_trans[i] = trans[i] + rot[i, 0] * x[3] + rot[i, 1] * x[4] + rot[i, 2] * x[5]
            for j in range(3):
                new_rot[i, j] = rot[i, 0] * step[0, j] + rot[i, 1] * step[1, j] + rot[i, 2] * step[2, j]
        trans, rot = new_trans, new_rot
    return rot, trans, coeffs


def model_arrays(basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(basis_t (M, 3, K), gram (M, K, K))`` for :func:`gauss_newton`: the modes per marker in
    one contiguous block (a fit touches a few markers' modes in any order: one block each instead of
    K scattered rows), and per marker the sum over x, y, z of its mode vectors' outer products."""
    return np.ascontiguousarray(basis.transpose(1, 2, 0)), _mode_gram(basis)


@numba.njit(cache=True, nogil=True)
def _mode_gram(basis):  # pragma: no cover - compiled
    """``(M, K, K)``: per marker, the sum over x, y, z of its mode vectors' outer products."""
    n_modes, n_markers = basis.shape[0], basis.shape[1]
    gram = np.zeros((n_markers, n_modes, n_modes))
    for m in range(n_markers):
        for a in range(n_modes):
            for b in range(n_modes):
                gram[m, a, b] = basis[a, m, 0] * basis[b, m, 0] + basis[a, m, 1] * basis[b, m, 1] \
                    + basis[a, m, 2] * basis[b, m, 2]
    return gram


@numba.njit(cache=True, nogil=True)
def _predict(mean, basis, coeffs, offset, pred):  # pragma: no cover - compiled
    """``pred (M, 3)`` = model shape for ``coeffs`` + ``offset``."""
    pred[:, :] = mean + offset
    for j in range(len(coeffs)):
        cj = coeffs[j]
        if cj != 0.0:
            pred += cj * basis[j]


@numba.njit(cache=True, nogil=True)
def _to_head(points, rot, trans, head):  # pragma: no cover - compiled
    for i in range(len(points)):
        for c in range(3):
            head[i, c] = ((points[i, 0] - trans[0]) * rot[0, c] + (points[i, 1] - trans[1]) * rot[1, c]
                          + (points[i, 2] - trans[2]) * rot[2, c])


@numba.njit(cache=True, nogil=True)
def _dist(a, b):  # pragma: no cover - compiled
    return math.sqrt((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2 + (a[2] - b[2]) ** 2)


@numba.njit(cache=True, nogil=True)
def finish_frame(f, n, cols, lab, head, pred, sigma, fragments, label, conf, resid, frag_label, offset,
                 offset_rate, last, seen, tracked):  # pragma: no cover - compiled
    """Store frame ``f``'s labels ``lab[:n]`` of columns ``cols[:n]`` and their confidence; when
    ``tracked``, also each labelled point's residual from the model without its marker's offset
    (head coordinates, ``resid (F, N, 3)``), move each seen marker's offset toward the capture, keep
    its head-coordinate position in ``last`` and the frame in ``seen``, and carry the fragments'
    labels."""
    for i in range(n):
        m = lab[i]
        if m >= 0:
            z2 = 0.0
            for c in range(3):
                r = head[i, c] - pred[m, c]
                z2 += r * r
                if tracked:
                    resid[f, cols[i], c] = r + offset[m, c]
                    last[m, c] = head[i, c]
                    offset[m, c] += offset_rate * r
            label[f, cols[i]] = m
            conf[f, cols[i]] = math.exp(-0.5 * z2 / (sigma[m] * sigma[m]))
            if tracked:
                seen[m] = f
        if tracked:
            frag_label[fragments[f, cols[i]]] = m


@numba.njit(cache=True, nogil=True)
def track(f, positions, fragments, frag_label, offset, last, seen, rot, trans, mean, basis, basis_t, gram,
          mode_std, sigma, gate, new_gate, rounds, offset_rate, label, conf, resid, released, cols, lab, carried,
          head, pred, new_pred):  # pragma: no cover - compiled
    """Label frames from ``f`` on while every frame has 3+ carried points and needs no matching.

    Returns ``(frame, code, n)``: :data:`DONE`; :data:`START_OVER` at ``frame`` (nothing done in
    it); :data:`MATCH` at ``frame``, where ``cols[:n]``, ``lab[:n]`` (carried labels, -1 to
    assign), ``carried[:n]``, ``head[:n]``, ``pred`` and ``new_pred`` hold the frame for the
    caller's matching. ``new_pred`` is where a new point is also looked for, besides ``pred``: for a
    marker seen in the previous frame (its fragment broke), where it was then (``last``, head
    coordinates): where the expression goes beyond the template, the model refitted without the
    marker can move its prediction away by more than the gate; for any other marker, the model
    without the marker's offset: the offset was learnt where it was last seen, and once the
    expression has changed it can hold the prediction off the marker for good (a 6 Hz capture's
    chin, 5-6 mm off after a jaw opening beyond the template, never labelled again).
    ``basis_t``, ``gram``: :func:`model_arrays`. ``rot``, ``trans`` (the pose), ``offset``,
    ``last``, ``seen``, ``frag_label`` and the outputs are updated in place.
    """
    n_frames, n_cols = fragments.shape
    n_markers = mean.shape[0]
    k = len(mode_std)
    taken = np.zeros(n_markers, dtype=np.bool_)
    hits = np.zeros(n_markers, dtype=np.int64)
    choice = np.empty(n_cols, dtype=np.int64)
    idx = np.empty(n_cols, dtype=np.int64)
    pts = np.empty((n_cols, 3))
    while f < n_frames:
        n = 0
        for c in range(n_cols):
            if fragments[f, c] >= 0:
                cols[n] = c
                n += 1
        if n == 0:
            f += 1
            continue
        n_car = 0
        for i in range(n):
            lab[i] = frag_label[fragments[f, cols[i]]]
            carried[i] = lab[i] >= 0
            n_car += carried[i]
        if n_car < 3:
            return f, START_OVER, n
        for attempt in range(2):  # a second fit when points were released
            a = 0
            for i in range(n):
                if carried[i]:
                    idx[a] = lab[i]
                    pts[a] = positions[f, cols[i]]
                    a += 1
            r, t, coeffs = gauss_newton(mean, basis_t, gram, mode_std, sigma, offset, idx[:a], pts[:a], rot, trans,
                                        k, rounds)
            rot[:, :] = r
            trans[:] = t
            _predict(mean, basis, coeffs, offset, pred)
            for m in range(n_markers):
                for c in range(3):
                    new_pred[m, c] = last[m, c] if seen[m] == f - 1 else pred[m, c] - offset[m, c]
            for i in range(n):
                pts[i] = positions[f, cols[i]]
            _to_head(pts[:n], rot, trans, head)
            if attempt:
                break
            dropped = False
            for i in range(n):
                if carried[i] and _dist(head[i], pred[lab[i]]) > gate[lab[i]]:
                    released[f, cols[i]] = True
                    lab[i] = -1
                    carried[i] = False
                    dropped = True
            if not dropped:
                break
        # the free labels within reach of each new point; a matching only where two compete
        taken[:] = False
        hits[:] = 0
        for i in range(n):
            if lab[i] >= 0:
                taken[lab[i]] = True
        compete = False
        for i in range(n):
            choice[i] = -1
            if carried[i]:
                continue
            near = 0
            for m in range(n_markers):
                if not taken[m] and min(_dist(head[i], pred[m]), _dist(head[i], new_pred[m])) <= new_gate[m]:
                    near += 1
                    hits[m] += 1
                    choice[i] = m
                    if near > 1 or hits[m] > 1:
                        compete = True
        if compete:
            return f, MATCH, n
        for i in range(n):
            if choice[i] >= 0:
                lab[i] = choice[i]
        finish_frame(f, n, cols, lab, head, pred, sigma, fragments, label, conf, resid, frag_label, offset,
                     offset_rate, last, seen, True)
        f += 1
    return f, DONE, 0
