"""Large regions: the gap-aware correlation across row blocks equals np.corrcoef on the common
frames, and heatmaps of large regions are block means in cluster order (bounded image)."""

from __future__ import annotations

import numpy as np

from mocaptk.clustering.correlation import _BLOCK, consolidated_correlation
from mocaptk.clustering.figures import _ordered_cells


def test_gappy_correlation_across_blocks_equals_corrcoef():
    rng = np.random.default_rng(3)
    n = _BLOCK + 90  # two row blocks: pairs inside each and across them
    signals = rng.normal(size=(60, 8, 3)).cumsum(axis=0)
    pos = signals[:, rng.integers(8, size=n)] + rng.normal(scale=0.3, size=(60, n, 3))
    pos[rng.random((60, n)) < 0.01] = np.nan
    matrix = consolidated_correlation(pos).matrix
    np.testing.assert_array_equal(matrix, matrix.T)
    for i, j in [(0, 1), (3, _BLOCK - 1), (5, _BLOCK + 7), (_BLOCK + 2, _BLOCK + 80), (n - 1, 0)]:
        both = np.isfinite(pos[:, i, 0]) & np.isfinite(pos[:, j, 0])
        want = sum(np.corrcoef(pos[both, i, a], pos[both, j, a])[0, 1] for a in range(3))
        assert abs(matrix[i, j] - want) < 1e-9, (i, j)


def test_large_heatmap_is_block_means_in_cluster_order():
    rng = np.random.default_rng(0)
    matrix = rng.normal(size=(10, 10))
    order = rng.permutation(10)
    edges = [0, 2, 5, 7, 10]  # 10 markers on 4 cells
    ordered = matrix[np.ix_(order, order)]
    want = [[ordered[a:b, c:d].mean() for c, d in zip(edges, edges[1:])]
            for a, b in zip(edges, edges[1:])]
    np.testing.assert_allclose(_ordered_cells(matrix, order, 4), want)
    np.testing.assert_array_equal(_ordered_cells(matrix, order, 10), ordered)


def test_large_heatmap_cells_are_sums_in_row_order_across_chunks():
    """The block sums add a cell's rows one after the other, also across 1,024-row chunks:
    the bits of np.add.at's sums (the heatmap PNGs stay byte-identical)."""
    rng = np.random.default_rng(1)
    n, cells = 2600, 512
    matrix = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-3, 3, size=(n, 1))
    order = rng.permutation(n)
    starts = (np.arange(cells) * n) // cells
    sums = np.zeros((cells, cells))
    np.add.at(sums, np.searchsorted(starts, np.arange(n), side="right") - 1,
              np.add.reduceat(matrix[np.ix_(order, order)], starts, axis=1))
    sizes = np.diff(np.append(starts, n)).astype(float)
    np.testing.assert_array_equal(_ordered_cells(matrix, order, cells),
                                  sums / sizes[:, None] / sizes[None, :])
