"""Baseline layouts of a given size: random, farthest-point and k-means on trajectories.

Every function returns sorted marker indices ``(count,) intp`` so layouts compare like for like.
"""

from __future__ import annotations

import numpy as np

from mocaptk.errors import OptionError


def _check_count(n_markers: int, count: int) -> None:
    if not 1 <= count <= n_markers:
        raise OptionError(f"layout size must be between 1 and {n_markers} markers, got {count}")


def random_layout(n_markers: int, count: int, *, seed: int) -> np.ndarray:
    """``count`` distinct markers drawn uniformly at random out of ``n_markers``."""
    _check_count(n_markers, count)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n_markers, size=count, replace=False)).astype(np.intp)


def farthest_point_layout(neutral: np.ndarray, count: int) -> np.ndarray:
    """Farthest-point sampling of the neutral pose.

    Parameters
    ----------
    neutral : (markers, 3) float, mm
        Markers with NaN coordinates are never chosen.
    count : int

    Returns
    -------
    (count,) intp, sorted
        Starts at the marker farthest from the centroid (deterministic), then repeatedly adds
        the marker farthest from all chosen ones.
    """
    pts = np.asarray(neutral, dtype=np.float64)
    valid = np.isfinite(pts).all(axis=1)
    _check_count(int(valid.sum()), count)
    centroid = pts[valid].mean(axis=0)
    far = np.where(valid, np.linalg.norm(np.where(valid[:, None], pts, 0.0) - centroid, axis=1), -1.0)
    chosen = [int(np.argmax(far))]
    nearest = np.where(valid, np.linalg.norm(np.where(valid[:, None], pts, 0.0) - pts[chosen[0]],
                                             axis=1), -1.0)
    for _ in range(count - 1):
        nxt = int(np.argmax(nearest))
        chosen.append(nxt)
        dist = np.linalg.norm(np.where(valid[:, None], pts, 0.0) - pts[nxt], axis=1)
        nearest = np.where(valid, np.minimum(nearest, dist), -1.0)
    return np.sort(np.array(chosen, dtype=np.intp))


#: Values per tile of the k-means features (512 KiB of float64): the transposed copy and its gap
#: fill while the tile is in cache (one whole copy, then a pass: ~2x the time at 200 markers).
FEATURE_TILE_VALUES = 2 ** 16


def kmeans_layout(displacements: np.ndarray, count: int, *, seed: int, iterations: int = 50) -> np.ndarray:
    """K-means on marker trajectories; per cluster the marker nearest its centre.

    Parameters
    ----------
    displacements : (frames, markers, 3) float, mm
        Displacement of each marker from its neutral position; NaN gaps count as 0 (at rest).
    count : int
        Number of clusters = layout size.
    seed : int
        Seeds the k-means++ initialisation.
    iterations : int
        Lloyd iterations (stops earlier when assignments settle).

    Returns
    -------
    (count,) intp, sorted
    """
    disp = np.asarray(displacements, dtype=np.float64)
    n_markers = disp.shape[1]
    _check_count(n_markers, count)
    feats = np.empty((n_markers,) + disp.shape[:1] + disp.shape[2:])
    step = max(1, FEATURE_TILE_VALUES // max(1, disp[:1].size))
    for lo in range(0, disp.shape[0], step):  # markers-major, gaps 0, tile by tile
        tile = feats[:, lo:lo + step]
        tile[...] = disp[lo:lo + step].transpose(1, 0, 2)
        np.nan_to_num(tile, nan=0.0, copy=False)
    feats = feats.reshape(n_markers, -1)
    # the iterations run on coordinates with the same dot products: (markers, markers) for a long
    # session, one pass over its frames instead of one per centre
    coords = _gram_coordinates(feats) if feats.shape[1] > n_markers else feats
    rng = np.random.default_rng(seed)

    def sq_dist_to(points: np.ndarray, centres: np.ndarray, norms: np.ndarray | None = None) -> np.ndarray:
        norms = np.einsum("ij,ij->i", points, points) if norms is None else norms
        # 2 x (points . centres), not (2 x points) . centres: no (markers, d) temporary (exact: x2)
        d = norms[:, None] - 2.0 * (points @ centres.T) + np.einsum("ij,ij->i", centres, centres)[None]
        return np.maximum(d, 0.0)

    coord_norms = np.einsum("ij,ij->i", coords, coords)  # once, not once per k-means++ pick

    def sq_dist(centres: np.ndarray) -> np.ndarray:
        return sq_dist_to(coords, centres, coord_norms)

    # k-means++ initialisation
    first = int(rng.integers(n_markers))
    centres = [coords[first]]
    closest = sq_dist(np.array(centres))[:, 0]
    made_of = [np.arange(n_markers) == first]  # the markers each centre is the mean of
    for _ in range(count - 1):
        total = closest.sum()
        pick = int(rng.choice(n_markers, p=closest / total)) if total > 0 else int(rng.integers(n_markers))
        centres.append(coords[pick])
        made_of.append(np.arange(n_markers) == pick)
        closest = np.minimum(closest, sq_dist(coords[pick][None])[:, 0])
    centres_arr = np.array(centres)
    assign = np.full(n_markers, -1)
    for _ in range(iterations):
        new_assign = np.argmin(sq_dist(centres_arr), axis=1)
        if np.array_equal(new_assign, assign):
            break
        assign = new_assign
        for k in range(count):
            members = assign == k
            if members.any():
                centres_arr[k] = coords[members].mean(axis=0)
                made_of[k] = members
    # the member nearest each centre in the trajectories themselves, by direct differences: the
    # expanded |x|^2 - 2 x.c + |c|^2 of long trajectories is mostly cancellation, and a BLAS
    # kernel's rounding then broke a two-member cluster's exact tie (CPU-dependent layouts)
    means = np.array([feats[m].mean(axis=0) for m in made_of])
    energy = np.einsum("ij,ij->i", feats, feats)
    chosen: list[int] = []
    for k in range(count):
        members = np.flatnonzero(assign == k)
        if members.size:
            chosen.append(_nearest_member(feats[members] - means[k], members, energy[members]))
    if len(chosen) < count:  # empty clusters: the markers worst represented by the chosen ones
        remaining = np.setdiff1d(np.arange(n_markers), chosen)
        worst = sq_dist_to(feats[remaining], means).min(axis=1)
        extra = remaining[np.argsort(-worst, kind="stable")[: count - len(chosen)]]
        chosen.extend(int(i) for i in extra)
    return np.sort(np.array(chosen, dtype=np.intp))


def _nearest_member(offsets: np.ndarray, members: np.ndarray, energy: np.ndarray) -> int:
    """The member nearest its cluster's mean, ``offsets`` (m, d) from it; members within 1e-9
    (relative) of the nearest tie (two members are always equidistant from their mean), won by
    the one that moves most (``energy``, summed squared displacement), then the lowest index."""
    dist = np.einsum("ij,ij->i", offsets, offsets)
    tied = np.flatnonzero(dist <= dist.min() * (1.0 + 1e-9))
    return int(members[tied[np.argmax(energy[tied])]])


def _gram_coordinates(feats: np.ndarray) -> np.ndarray:
    """(n, n) coordinates ``V sqrt(L)`` of the Gram matrix of ``feats`` (n, d): the same pairwise
    dot products (to rounding) in n columns."""
    values, vectors = np.linalg.eigh(feats @ feats.T)
    return vectors * np.sqrt(np.clip(values, 0.0, None))
