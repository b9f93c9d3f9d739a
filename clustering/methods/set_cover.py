"""Zell & McDonnell: the smallest well-placed landmark set that sees every blendshape move.

Per shape k (a blendshape delta, or a representative frame of a dense session), the relative
displacement ``r_nk = |d_nk| / max_n |d_nk|``; point n is a *candidate* for k when ``r_nk ≥ ε``.
Quality ``ω_nk = c_nk (2 − (1−α) r_nk − α l_n)`` prefers points that move much and are visible
(``l_n`` = worst-case visibility over neutral + all shapes, :func:`visibility`, on the blendshape
mesh or — for a dense session — on the marker surface mesh, seen from the front). The weighted
set cover

    minimize Σ_n f_n Σ_k ω_nk   subject to   Σ_n c_nk f_n ≥ 1 for every shape k,  f ∈ {0, 1}

is solved to proven optimality with HiGHS (branch and bound, gap 0). To reach a requested marker
count, covers are repeated with the chosen points and their neighbourhood excluded (adaptive
multi-cover); the last round picks exactly the missing number of points, maximizing the shapes
it covers (a max-coverage ILP). ``symmetric``: displacements folded onto one side, the cover
mirrored (an off-midline point costs two markers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from mocaptk.errors import OptionError

from .problem import LayoutProblem

ALPHA = 0.5


@dataclass(frozen=True)
class CoverSolution:
    """One ILP solve: chosen points, HiGHS model status name, objective, shapes covered."""

    chosen: np.ndarray
    status: str
    objective: float
    covered: np.ndarray  # (K,) bool


@dataclass(frozen=True)
class SetCoverResult:
    """The layout (sorted), the status of every cover round and how many rounds ran."""

    layout: np.ndarray
    status: list[str]
    covers: int


def relative_displacement(shapes: np.ndarray) -> np.ndarray:
    """(N, K) ``r_nk``: each point's displacement in shape k over the largest in that shape."""
    mag = np.linalg.norm(np.asarray(shapes, dtype=np.float64), axis=2).T  # (N, K)
    peak = mag.max(axis=0)
    return np.divide(mag, peak, out=np.zeros_like(mag), where=peak > 0)


def representative_shapes(displacements: np.ndarray, *, max_shapes: int = 64) -> np.ndarray:
    """(K, N, 3) diverse extreme frames of a session (farthest-point sampling in frame space)."""
    disp = np.nan_to_num(np.asarray(displacements, dtype=np.float64))
    flat = disp.reshape(disp.shape[0], -1)
    norms = np.linalg.norm(flat, axis=1)
    if disp.shape[0] <= max_shapes:
        return disp[norms > 0]
    squared = norms ** 2
    chosen = [int(np.argmax(norms))]
    # squared distances as |a|² + |b|² − 2a·b: one matrix-vector product per pick, no (F, 3N) temporary
    dist = np.maximum(squared + squared[chosen[0]] - 2.0 * (flat @ flat[chosen[0]]), 0.0)
    while len(chosen) < max_shapes and dist.max() > 0:
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.maximum(squared + squared[chosen[-1]] - 2.0 * (flat @ flat[chosen[-1]]), 0.0))
        dist[chosen[-1]] = 0.0  # exactly: rounding must not let a chosen frame be picked again
    return disp[np.sort(chosen)]


def problem_shapes(problem: LayoutProblem) -> np.ndarray:
    """(K, N, 3) mm: the shapes set cover covers — :func:`representative_shapes` of the problem's
    displacements (a blendshape model's deltas as they are, up to 64); cached in ``problem.cache``."""
    if "set_cover_shapes" not in problem.cache:
        problem.cache["set_cover_shapes"] = representative_shapes(problem.displacements)
    return problem.cache["set_cover_shapes"]


def visibility(vertices: np.ndarray, faces: np.ndarray, shapes: np.ndarray, *, directions: int = 24,
               resolution: float = 1.5, front: np.ndarray | None = None) -> np.ndarray:
    """(V,) worst-case fraction of view directions that see each vertex, over neutral + every shape.

    Ambient-occlusion-style: ``directions`` view directions spread over the hemisphere around
    ``front`` (3,) (default +Z); per direction an orthographic depth buffer at ``resolution`` mm
    of points sampled on the triangles (at most 2 pixels apart, so a sparse marker mesh occludes
    like a dense one); a vertex counts as seen when it faces the direction and no surface in its
    pixel neighbourhood is in front of it (1 mm tolerance plus what the local slope explains).
    A vertex in no triangle has no normal: only occlusion decides for it.
    ``vertices`` (V, 3) mm, ``faces`` (T, 3), ``shapes`` (K, V, 3) mm deltas.
    """
    verts = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(faces, dtype=np.intp)
    axis = np.array([0.0, 0.0, 1.0]) if front is None else np.asarray(front, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    side = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    golden = np.pi * (3.0 - np.sqrt(5.0))
    k = np.arange(directions)
    z = 1.0 - (k + 0.5) / directions  # hemisphere around the front, cos in (0, 1]
    ring = np.sqrt(1.0 - z * z)
    dirs = (np.outer(ring * np.cos(golden * k), side) + np.outer(ring * np.sin(golden * k), np.cross(axis, side))
            + np.outer(z, axis))
    samples = _triangle_samples(verts, tris, spacing=2.0 * resolution)
    has_normal = np.zeros(len(verts), dtype=bool)
    has_normal[tris.ravel()] = True
    # per direction: image axes u, v and the depth axis, as (3, 3·directions) columns
    helper = np.where(np.abs(dirs[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(dirs, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    frames = np.concatenate([u, np.cross(dirs, u), dirs]).T
    worst = np.ones(len(verts))
    for delta in [np.zeros_like(verts)] + [s for s in np.asarray(shapes, dtype=np.float64)]:
        pos = verts + delta
        normals = np.zeros_like(pos)
        tri_n = np.cross(pos[tris[:, 1]] - pos[tris[:, 0]], pos[tris[:, 2]] - pos[tris[:, 0]])
        for c in range(3):
            np.add.at(normals, tris[:, c], tri_n)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        facing = np.where(has_normal[:, None], normals @ dirs.T, 1.0).T  # (directions, V)
        surface = np.einsum("sc,tcx->tsx", samples, pos[tris]).reshape(-1, 3)
        coords = (np.concatenate([pos, surface]) @ frames).T  # (3·directions, V + S)
        pixels = np.floor(coords[: 2 * directions] / resolution).astype(np.int64)
        pixels -= pixels.min(axis=1, keepdims=True)
        seen = _seen_counts(pixels[:directions], pixels[directions:], coords[2 * directions:], facing,
                            resolution)
        worst = np.minimum(worst, seen / directions)
    return worst


def _triangle_samples(verts: np.ndarray, tris: np.ndarray, *, spacing: float) -> np.ndarray:
    """(S, 3) barycentric weights of a regular grid on a triangle (corners left out), fine enough
    that points on a typical triangle of the mesh (median edge) lie at most ``spacing`` mm apart."""
    if len(tris) == 0:
        return np.zeros((0, 3))
    edges = np.linalg.norm(verts[tris] - verts[np.roll(tris, 1, axis=1)], axis=2)
    steps = int(np.clip(np.ceil(np.median(edges) / spacing), 1, 16))
    grid = [(i, j, steps - i - j) for i in range(steps + 1) for j in range(steps + 1 - i)
            if max(i, j, steps - i - j) < steps]  # the corners are the vertices themselves
    return np.array(grid, dtype=np.float64).reshape(-1, 3) / steps


def _seen_counts(i: np.ndarray, j: np.ndarray, depth: np.ndarray, facing: np.ndarray,
                 resolution: float) -> np.ndarray:
    """(V,) in how many directions each vertex is seen.

    ``i``, ``j`` pixels and ``depth`` (directions, V + S) of the vertices followed by the surface
    samples; ``facing`` (directions, V) cosine of each vertex normal with the direction.
    """
    n_dir, n = facing.shape
    shape = (n_dir, int(i.max()) + 3, int(j.max()) + 3)
    buffer = np.full(shape, -np.inf)
    flat = (np.arange(n_dir)[:, None] * shape[1] + i + 1) * shape[2] + j + 1
    np.maximum.at(buffer.reshape(-1), flat.ravel(), depth.ravel())  # 1-D: far faster than 3-D
    nearest = buffer[:, 1:-1, 1:-1].copy()  # 3×3 neighbourhood maximum
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            nearest = np.maximum(nearest, buffer[:, 1 + di:shape[1] - 1 + di, 1 + dj:shape[2] - 1 + dj])
    front = nearest[np.arange(n_dir)[:, None], i[:, :n], j[:, :n]]
    # the pixel neighbourhood of a tilted surface holds its own nearer points: allow their depth
    slope = np.sqrt(np.maximum(1.0 - facing ** 2, 0.0)) / np.maximum(facing, 0.1)
    tolerance = 1.0 + 3.0 * resolution * slope
    return ((facing > 0.1) & (depth[:, :n] >= front - tolerance)).sum(axis=0).astype(np.float64)


def facing_direction(problem: LayoutProblem) -> np.ndarray:
    """(3,) unit direction the face of ``problem`` looks towards (the frontal camera view).

    The face frame's forward axis (:func:`~mocaptk.clustering.regions.face_frame`) turned into
    the sagittal plane, so a half-face capture is still seen from the front, not from its side.
    """
    from ..neutral import max_displacement
    from ..regions import face_frame
    from ..symmetry import estimate_sagittal_plane, is_half_capture, plane_frame

    moved = max_displacement(problem.positions, problem.neutral)
    labels = problem.labels or tuple(f"p{i}" for i in range(problem.n_points))
    plane = estimate_sagittal_plane(labels, problem.neutral, moved, half=is_half_capture(labels))
    return plane_frame(plane, face_frame(problem.neutral, moved))[2]


def problem_visibility(problem: LayoutProblem) -> np.ndarray:
    """(N,) :func:`visibility` of ``problem``'s points on its surface mesh (the marker surface mesh
    of a dense session), over neutral + :func:`problem_shapes`, seen from
    :func:`facing_direction`; cached in ``problem.cache``.

    Depth-buffer pixels: 1.5 mm, or a quarter of the point spacing on a sparser mesh (markers
    ~1 cm apart cannot resolve finer occluders; 4× fewer pixels per buffer).
    """
    if "set_cover_visibility" not in problem.cache:
        from mocaptk.surface_mesh import marker_spacing
        resolution = max(1.5, marker_spacing(problem.neutral) / 4.0)
        problem.cache["set_cover_visibility"] = visibility(
            problem.neutral, problem.surface_faces(), problem_shapes(problem), front=facing_direction(problem),
            resolution=resolution)
    return problem.cache["set_cover_visibility"]


def cover_costs(relative: np.ndarray, candidate: np.ndarray, vis: np.ndarray | None, *,
                alpha: float = ALPHA) -> np.ndarray:
    """(N,) ``Σ_k ω_nk``, the objective weight of each point."""
    l_n = np.ones(relative.shape[0]) if vis is None else np.asarray(vis, dtype=np.float64)
    omega = candidate * (2.0 - (1.0 - alpha) * relative - alpha * l_n[:, None])
    return omega.sum(axis=1)


def solve_cover(candidate: np.ndarray, costs: np.ndarray, *, allowed: np.ndarray | None = None,
                exactly: int | None = None, sizes: np.ndarray | None = None,
                time_limit: float = 60.0) -> CoverSolution:
    """Weighted set cover ILP with HiGHS (proven optimal unless the time limit stops it).

    ``candidate`` (N, K) bool. Without ``exactly``: cover every shape that some allowed point can
    cover, at minimal cost. With ``exactly``: choose points of total ``sizes`` = ``exactly``
    maximizing the number of shapes covered (ties: lower cost).
    """
    import highspy

    n, k = candidate.shape
    allowed = np.ones(n, dtype=bool) if allowed is None else allowed
    cols = np.flatnonzero(allowed & candidate.any(axis=1)) if exactly is None else np.flatnonzero(allowed)
    coverable = candidate[cols].any(axis=0)
    shapes = np.flatnonzero(coverable)
    sub = sp.csc_matrix(candidate[np.ix_(cols, shapes)].T.astype(np.float64))  # (K', n')
    size = np.ones(n) if sizes is None else np.asarray(sizes, dtype=np.float64)
    h = highspy.Highs()
    h.setOptionValue("output_flag", False)
    h.setOptionValue("mip_rel_gap", 0.0)
    h.setOptionValue("time_limit", float(time_limit))
    h.setOptionValue("threads", 1)
    lp = highspy.HighsLp()
    big = float(costs[cols].sum() + 1.0)
    if exactly is None:
        n_var = cols.size
        cost = costs[cols]
        a = sub
        row_lo, row_hi = np.ones(shapes.size), np.full(shapes.size, highspy.kHighsInf)
    else:  # max coverage: y_k ≤ Σ c_nk f_n, Σ size_n f_n = exactly, minimize −big·Σy + Σ cost f
        n_var = cols.size + shapes.size
        cost = np.concatenate([costs[cols], np.full(shapes.size, -big)])
        a = sp.vstack([sp.hstack([sub, -sp.identity(shapes.size)]),
                       sp.hstack([sp.csr_matrix(size[cols][None]), sp.csr_matrix((1, shapes.size))])]).tocsc()
        row_lo = np.concatenate([np.zeros(shapes.size), [exactly]])
        row_hi = np.concatenate([np.full(shapes.size, highspy.kHighsInf), [exactly]])
    lp.num_col_, lp.num_row_ = int(n_var), int(a.shape[0])
    lp.col_cost_ = np.asarray(cost, dtype=np.float64)
    lp.col_lower_ = np.zeros(n_var)
    lp.col_upper_ = np.ones(n_var)
    lp.row_lower_, lp.row_upper_ = row_lo, row_hi
    a = sp.csc_matrix(a)
    lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
    lp.a_matrix_.start_ = a.indptr.astype(np.int32)
    lp.a_matrix_.index_ = a.indices.astype(np.int32)
    lp.a_matrix_.value_ = a.data
    lp.integrality_ = [highspy.HighsVarType.kInteger] * n_var
    h.passModel(lp)
    h.run()
    status = h.modelStatusToString(h.getModelStatus())
    if h.getModelStatus() not in (highspy.HighsModelStatus.kOptimal, highspy.HighsModelStatus.kTimeLimit):
        raise OptionError(f"set cover ILP: HiGHS says {status}")
    values = np.asarray(h.getSolution().col_value)[: cols.size]
    chosen = cols[values > 0.5]
    covered = candidate[chosen].any(axis=0) if chosen.size else np.zeros(k, dtype=bool)
    return CoverSolution(np.sort(chosen), status, float(costs[chosen].sum()), covered)


def layout_statistics(shapes: np.ndarray, layout: np.ndarray, *, epsilons: tuple[float, ...] = (0.3, 0.7)
                      ) -> dict[str, dict[str, float]]:
    """Zell's layout statistics per ε: % of layout markers where no shape moves ≥ ε (relative),
    and the number of shapes no layout marker sees move ≥ ε."""
    rel = relative_displacement(shapes)[np.asarray(layout, dtype=np.intp)]
    out = {}
    for eps in epsilons:
        hit = rel >= eps
        out[f"{eps:g}"] = {"idle_markers_percent": 100.0 * float((~hit.any(axis=1)).mean()),
                           "unseen_shapes": int((~hit.any(axis=0)).sum())}
    return out


def set_cover_layout(problem: LayoutProblem, count: int | None = None, *, epsilon: float = 0.3,
                     symmetric: bool = False, visibility_weights: np.ndarray | None = None,
                     exclusion_mm: float | None = None, alpha: float = ALPHA) -> SetCoverResult:
    """Zell & McDonnell's layout: minimal cover, or adaptive multi-cover up to ``count`` points.

    ``problem.displacements`` are the shapes (blendshape deltas); for a dense session with more
    than 64 frames, :func:`representative_shapes` picks them. ``visibility_weights`` (N,) ``l_n``
    (default: :func:`problem_visibility`, on the problem's surface mesh — the blendshape mesh, or
    the marker surface mesh of a dense session — over neutral + the shapes). ``exclusion_mm``:
    neighbourhood excluded around chosen points in later rounds (default: the median
    nearest-neighbour spacing × 1.5).
    """
    if not 0 < epsilon <= 1:
        raise OptionError(f"epsilon must be in (0, 1], got {epsilon}")
    shapes = problem_shapes(problem)
    relative = relative_displacement(shapes)
    n = problem.n_points
    sizes = np.ones(n)
    allowed = np.zeros(n, dtype=bool)
    allowed[problem.candidate_points()] = True
    if symmetric and problem.mirror is None:
        raise OptionError("symmetric set cover needs the mirror partner of every point")
    vis = problem_visibility(problem) if visibility_weights is None else visibility_weights
    if symmetric:
        mirror = problem.mirror
        relative = np.maximum(relative, relative[mirror])  # fold: a point covers what its mirror does
        vis = np.minimum(vis, vis[mirror])  # and must be seen on both sides
        side = problem.neutral[:, 0] >= problem.neutral[mirror, 0]  # one side + midline
        allowed &= side
        sizes = np.where(mirror == np.arange(n), 1.0, 2.0)
    candidate = relative >= epsilon
    costs = cover_costs(relative, candidate, vis, alpha=alpha)
    if exclusion_mm is None:
        from scipy.spatial import cKDTree
        dist, _ = cKDTree(problem.neutral).query(problem.neutral, k=2)
        exclusion_mm = 1.5 * float(np.median(dist[:, 1]))
    chosen: list[int] = []
    statuses: list[str] = []
    free = allowed.copy()
    while True:
        have = float(sizes[chosen].sum()) if chosen else 0.0
        if count is not None and have >= count:
            break
        solution = solve_cover(candidate, costs, allowed=free)
        need = None if count is None else count - have
        if need is not None and float(sizes[solution.chosen].sum()) > need:
            solution = solve_cover(candidate, costs, allowed=free, exactly=int(need), sizes=sizes)
        statuses.append(solution.status)
        if solution.chosen.size == 0:  # nothing left to cover: fill with the most-moving points
            if need is not None:
                order = np.flatnonzero(free)[np.argsort(-relative[free].sum(axis=1), kind="stable")]
                for p in order:
                    if float(sizes[chosen].sum()) + sizes[p] <= count:
                        chosen.append(int(p))
            break
        chosen.extend(int(c) for c in solution.chosen)
        if count is None:
            break
        near = np.linalg.norm(problem.neutral[:, None] - problem.neutral[solution.chosen][None], axis=2) \
            if n * solution.chosen.size < 5e7 else None
        free[solution.chosen] = False
        if near is not None:
            free &= ~(near < exclusion_mm).any(axis=1)
        if not (free & candidate.any(axis=1)).any():
            free = allowed.copy()  # neighbourhoods exhausted: allow everything not yet chosen
            free[chosen] = False
            if not free.any():
                break
    layout = np.array(sorted(set(chosen)), dtype=np.intp)
    if symmetric:
        layout = np.unique(np.concatenate([layout, problem.mirror[layout]]))
    if count is not None and layout.size != count:
        raise OptionError(f"set cover reached {layout.size} markers, not {count}")
    return SetCoverResult(layout, statuses, len(statuses))
