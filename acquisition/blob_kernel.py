"""The compiled per-blob pass of :mod:`.blob_detection` (numba): weighted centroid and second
moments of every blob in one pass over its window's pixels (in numpy, a dozen passes over
padded windows cost 2/3 of the detection time). Cached on disk by numba; releases the GIL (cameras
can be detected on threads)."""

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
