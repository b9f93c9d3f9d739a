"""The compiled passes of :mod:`.blob_detection` (numba): the components of the thresholded box
and, per blob, weighted centroid and second moments in one pass over its window's pixels (in
numpy, a dozen passes over padded windows cost 2/3 of the detection time; windows grouped by
size, 8x the kernel). Cached on disk by numba; they release the GIL (images are detected on
threads)."""

from __future__ import annotations

import numpy as np

from .compiled import compiled


@compiled(error_model="numpy", nogil=True)
def blob_moments(image, labels, x0, y0, ids, cx, cy, half, radius, background,
                 mx, my, sxx, syy, sxy):  # pragma: no cover (compiled)
    """Fill ``mx, my`` (px: the centroid of ``image - background`` over the disc of ``radius``
    px around ``(cx, cy)``, pixels of blob ``ids[b]`` or of no blob) and ``sxx, syy, sxy``
    (px^2: second moments of the blob's own pixels) for every blob ``b``. ``labels`` are the
    components of the box whose pixel (0, 0) is image pixel ``(x0, y0)`` (outside it: none).
    A window pixel outside the image reads the nearest edge pixel."""
    height, width = image.shape
    box_h, box_w = labels.shape
    for b in range(len(ids)):
        total = sx = sy = 0.0
        n = ox = oy = oxx = oyy = oxy = 0.0
        r2 = radius[b] * radius[b]
        for dy in range(-half[b], half[b] + 1):
            y = min(max(cy[b] + dy, 0), height - 1)
            ry = y - cy[b]
            for dx in range(-half[b], half[b] + 1):
                x = min(max(cx[b] + dx, 0), width - 1)
                rx = x - cx[b]
                ly, lx = y - y0, x - x0
                owner = labels[ly, lx] if 0 <= ly < box_h and 0 <= lx < box_w else 0
                if owner == ids[b]:
                    n += 1.0
                    ox += rx
                    oy += ry
                    oxx += rx * rx
                    oyy += ry * ry
                    oxy += rx * ry
                elif owner != 0:
                    continue
                if rx * rx + ry * ry <= r2:
                    value = image[y, x] - background
                    if value > 0:
                        total += value
                        sx += value * rx
                        sy += value * ry
        mx[b] = cx[b] + sx / total
        my[b] = cy[b] + sy / total
        ox, oy = ox / n, oy / n
        sxx[b] = oxx / n - ox * ox
        syy[b] = oyy / n - oy * oy
        sxy[b] = oxy / n - ox * oy


@compiled(error_model="numpy", nogil=True)
def label_components(mask, labels, capacity):  # pragma: no cover (compiled)
    """8-connected components of the nonzero pixels of ``mask (H, W)``, as OpenCV's
    ``connectedComponentsWithStats`` gives them (labels 1.. in the raster order of each
    component's first pixel; ``labels (H, W)`` painted, 0 elsewhere) but from the rows' runs of
    bright pixels: one pass over the box finds the runs, and the union-find and stats then cost
    per run, not per pixel. Returns the
    label count (with the background) and ``stats (count, 5)``: left, top, width, height, area
    px. ``capacity``: at least the number of nonzero pixels."""
    height, width = mask.shape
    row_of = np.empty(capacity, np.int64)
    start = np.empty(capacity, np.int64)
    stop = np.empty(capacity, np.int64)
    parent = np.empty(capacity, np.int64)
    labels[:, :] = 0
    runs = 0
    previous, previous_end = 0, 0  # the previous row's runs
    for y in range(height):
        first = runs
        other = previous  # the previous row's runs ending left of this run are passed once
        x = 0
        while x < width:
            if mask[y, x] == 0:
                x += 1
                continue
            begin = x
            while x < width and mask[y, x] != 0:
                x += 1
            row_of[runs], start[runs], stop[runs], parent[runs] = y, begin, x, runs
            # join the previous row's runs that touch this one (8-connected: corners too)
            while other < previous_end and stop[other] < begin:
                other += 1
            for touching in range(other, previous_end):
                if start[touching] > x:
                    break
                a, b = runs, touching
                while parent[a] != a:
                    a = parent[a]
                while parent[b] != b:
                    b = parent[b]
                if a != b:  # the lower run index is the root: the component's first run
                    parent[max(a, b)] = min(a, b)
            runs += 1
        previous, previous_end = first, runs
    # OpenCV numbers components in the order of each one's first 2x2 block (it scans two rows
    # at a time), so the order here is that of the lowest (row pair, column pair) of each
    key = np.full(runs, np.iinfo(np.int64).max, np.int64)
    for run in range(runs):
        root = run
        while parent[root] != root:
            root = parent[root]
        parent[run] = root
        key[root] = min(key[root], (row_of[run] // 2) * (width + 2) + start[run] // 2)
    roots = np.nonzero(key != np.iinfo(np.int64).max)[0]
    order = roots[np.argsort(key[roots], kind="mergesort")]
    count = len(order) + 1
    label = np.zeros(runs, np.int64)
    label[order] = np.arange(1, count)
    stats = np.zeros((count, 5), np.int32)
    stats[:, 0], stats[:, 1] = width, height
    right = np.zeros(count, np.int64)
    bottom = np.zeros(count, np.int64)
    for run in range(runs):
        own = label[parent[run]]
        stats[own, 0] = min(stats[own, 0], start[run])
        stats[own, 1] = min(stats[own, 1], row_of[run])
        right[own] = max(right[own], stop[run])
        bottom[own] = max(bottom[own], row_of[run] + 1)
        stats[own, 4] += stop[run] - start[run]
        for x in range(start[run], stop[run]):
            labels[row_of[run], x] = own
    for own in range(1, count):
        stats[own, 2] = right[own] - stats[own, 0]
        stats[own, 3] = bottom[own] - stats[own, 1]
    return count, stats[:count]
