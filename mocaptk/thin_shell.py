"""Linear thin-shell operators on triangle meshes and the marker interpolation weights they give.

Sign convention: :func:`cotangent_laplacian` is *negative* semi-definite (libigl's convention:
off-diagonal ``+½(cot α + cot β)``, rows sum to 0), so the thin-shell operator
``A = −ks·L + kb·L·M⁻¹·L`` is symmetric positive semi-definite with the constant vector in its
null space. The mass matrix is normalised to mean 1 before it enters ``A``, which makes ``A``
independent of the mesh's unit (mm or m) so that ``ks``/``kb`` mean the same for any scale.

``interpolation_weights`` solves Le, Zhu & Deng (2013)'s ``W = Â⁻¹B̂``: every vertex minimizes the
thin-shell energy with the markers pinned, i.e. ``W_free = −A_ff⁻¹ A_fm`` and ``W_markers = I``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import MocaptkError

__all__ = ["cotangent_laplacian", "interpolation_weights", "mass_matrix", "thin_shell_operator"]


def _mesh_arrays(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    verts = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(faces, dtype=np.intp)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise MocaptkError(f"vertices must have shape (V, 3), got {verts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise MocaptkError(f"faces must have shape (T, 3), got {tris.shape}")
    if tris.size and (tris.min() < 0 or tris.max() >= len(verts)):
        raise MocaptkError("faces index vertices that do not exist")
    return verts, tris


def _corner_cotangents(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(T, 3) cotangent of the angle at each triangle corner (0 for degenerate triangles)."""
    cots = np.zeros(tris.shape, dtype=np.float64)
    for corner in range(3):
        apex = verts[tris[:, corner]]
        u = verts[tris[:, (corner + 1) % 3]] - apex
        v = verts[tris[:, (corner + 2) % 3]] - apex
        sin_area = np.linalg.norm(np.cross(u, v), axis=1)
        dot = np.einsum("ij,ij->i", u, v)
        scale = np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1)
        np.divide(dot, sin_area, out=cots[:, corner], where=sin_area > 1e-12 * scale)
    return cots


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Cotangent Laplacian ``L`` (V, V), negative semi-definite, rows summing to 0.

    ``L[i, j] = ½(cot α_ij + cot β_ij)`` for every edge ``ij`` (the angles opposite the edge),
    ``L[i, i] = −Σ_j L[i, j]``. Dimensionless (the same for mm and m). Degenerate triangles
    contribute nothing.
    """
    verts, tris = _mesh_arrays(vertices, faces)
    n = len(verts)
    cots = _corner_cotangents(verts, tris)
    # The cotangent at corner c weights the edge between the other two corners.
    rows = np.concatenate([tris[:, (c + 1) % 3] for c in range(3)])
    cols = np.concatenate([tris[:, (c + 2) % 3] for c in range(3)])
    vals = 0.5 * np.concatenate([cots[:, c] for c in range(3)])
    off = sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()
    off = off + off.T
    diag = sp.diags(np.asarray(off.sum(axis=1)).ravel())
    return (off - diag).tocsr()


def mass_matrix(vertices: np.ndarray, faces: np.ndarray, *,
                kind: str = "voronoi") -> sp.csr_matrix:
    """Diagonal lumped mass matrix (V, V) in mm² (the square of the vertices' unit).

    ``kind="voronoi"``: mixed Voronoi areas (Meyer et al. 2003; obtuse triangles split ½ / ¼ / ¼);
    ``kind="barycentric"``: a third of each incident triangle's area. Isolated vertices get the
    smallest positive area so the matrix stays invertible.
    """
    verts, tris = _mesh_arrays(vertices, faces)
    n = len(verts)
    e1 = verts[tris[:, 1]] - verts[tris[:, 0]]
    e2 = verts[tris[:, 2]] - verts[tris[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    if kind == "barycentric":
        per_corner = np.repeat(area[:, None] / 3.0, 3, axis=1)
    elif kind == "voronoi":
        cots = _corner_cotangents(verts, tris)
        sq = np.stack([np.sum((verts[tris[:, (c + 2) % 3]] - verts[tris[:, (c + 1) % 3]]) ** 2,
                              axis=1) for c in range(3)], axis=1)  # squared edge opposite corner c
        # Voronoi share of corner c: 1/8 Σ over its two edges of |e|² cot(opposite angle).
        per_corner = np.stack([(sq[:, (c + 1) % 3] * cots[:, (c + 1) % 3]
                                + sq[:, (c + 2) % 3] * cots[:, (c + 2) % 3]) / 8.0
                               for c in range(3)], axis=1)
        obtuse = cots < 0  # cot < 0 ⇔ angle > 90°
        any_obtuse = obtuse.any(axis=1)
        per_corner[any_obtuse] = np.where(obtuse[any_obtuse], 0.5, 0.25) * area[any_obtuse, None]
    else:
        raise MocaptkError(f"unknown mass matrix kind {kind!r} (voronoi, barycentric)")
    diag = np.bincount(tris.ravel(), weights=per_corner.ravel(), minlength=n)
    positive = diag[diag > 0]
    diag[diag <= 0] = positive.min() if positive.size else 1.0
    return sp.diags(diag).tocsr()


def thin_shell_operator(vertices: np.ndarray, faces: np.ndarray, *, ks: float = 1.0,
                        kb: float = 10.0) -> sp.csr_matrix:
    """Thin-shell energy matrix ``A = −ks·L + kb·L·M̃⁻¹·L`` (V, V), symmetric PSD.

    ``ks`` weighs stretching (membrane), ``kb`` bending; ``M̃`` is the Voronoi mass matrix divided
    by its mean so ``A`` is unit-free. ``A @ ones = 0`` (translations cost nothing).
    """
    if ks < 0 or kb < 0 or ks + kb <= 0:
        raise MocaptkError(f"ks and kb must be >= 0 and not both 0, got ks={ks}, kb={kb}")
    lap = cotangent_laplacian(vertices, faces)
    mass = mass_matrix(vertices, faces).diagonal()
    inv_mass = sp.diags(mass.mean() / mass)
    op = -ks * lap + kb * (lap @ inv_mass @ lap)
    return ((op + op.T) * 0.5).tocsr()


def interpolation_weights(operator: sp.spmatrix, marker_vertices: np.ndarray) -> np.ndarray:
    """Weights ``W`` (V, M): vertex ``i`` follows marker ``j`` by ``W[i, j]`` (``W = Â⁻¹B̂``).

    Rows of markers are the identity; the free rows are ``−A_ff⁻¹ A_fm`` (one sparse LU of the
    free-vertex block). Rows sum to 1 because ``A`` annihilates constants. Every connected
    component of the mesh needs at least one marker, else the system is singular.
    """
    op = sp.csr_matrix(operator)
    n = op.shape[0]
    markers = np.asarray(marker_vertices, dtype=np.intp).ravel()
    if markers.size == 0:
        raise MocaptkError("at least one marker vertex is needed")
    if markers.min() < 0 or markers.max() >= n:
        raise MocaptkError(f"marker vertex indices must be in 0..{n - 1}")
    if len(np.unique(markers)) != len(markers):
        raise MocaptkError("marker vertices must be distinct")
    free = np.setdiff1d(np.arange(n), markers)
    weights = np.zeros((n, len(markers)))
    weights[markers, np.arange(len(markers))] = 1.0
    if free.size:
        a_ff = op[free][:, free].tocsc()
        a_fm = op[free][:, markers].toarray()
        try:
            solve = spla.splu(a_ff)
        except RuntimeError as exc:  # exactly singular: a component without a marker
            raise MocaptkError("a mesh component has no marker; its weights are undefined") from exc
        weights[free] = -solve.solve(a_fm)
        if not np.all(np.isfinite(weights)):
            raise MocaptkError("a mesh component has no marker; its weights are undefined")
    return weights
