"""Compiled CPU kernels of the soft rasterizer (numba). Internal: use ``pipeline.render``.

All geometry is in pixels, float64 inside. Faces are packed: ``faces (F, 3)`` index ``uv (N, 2)``, and
``face_batch (F,)`` says which image of the batch each face belongs to.

Forward: faces are binned into square tiles by their cut-off-expanded bounding boxes; each tile (in parallel)
loops over its pixels and the faces of its bin, accumulating ``acc = -log(1 - S) = sum_f softplus(x_f)`` with
``x_f = -signed_d2 / sigma``, and stops early once ``acc`` exceeds the saturation level.
Backward: each face (in parallel) loops over the pixels of its bounding box whose upstream weight
``G = dL/dS * (1 - S)`` is non-zero and accumulates its three vertices' gradients; then one pass scatters them.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = dict(cache=True, nogil=True, fastmath=False)


# Per-face record ``fe (F, 22)``: for each edge k = 0, 1, 2 (from corner k to corner k+1) seven numbers
# (ax, ay, ex, ey, 1/|e|^2, nx, ny): start corner, edge vector, inverse squared length, unit inward normal; then
# ``fe[f, 21]`` = 1 for a face that is drawn, 0 for a culled one.
_EDGE = 7
_NFE = 22


@nb.njit(inline="always", **_JIT)
def _line(px, py, fe, f, k):
    """Signed distance from p to the line of edge k (positive on the triangle's side)."""
    o = k * _EDGE
    return (px - fe[f, o]) * fe[f, o + 5] + (py - fe[f, o + 1]) * fe[f, o + 6]


@nb.njit(inline="always", **_JIT)
def _closest_on_edge(px, py, fe, f, k):
    """Squared distance from p to edge segment k and the clamped parameter t of its closest point."""
    o = k * _EDGE
    ax = fe[f, o]
    ay = fe[f, o + 1]
    ex = fe[f, o + 2]
    ey = fe[f, o + 3]
    t = ((px - ax) * ex + (py - ay) * ey) * fe[f, o + 4]
    if t < 0.0:
        t = 0.0
    elif t > 1.0:
        t = 1.0
    dx = px - (ax + t * ex)
    dy = py - (ay + t * ey)
    return dx * dx + dy * dy, t


@nb.njit(inline="always", **_JIT)
def _pair(px, py, fe, f, cutoff):
    """Signed geometry of pixel centre p against face f.

    Returns (counted, inside, d2, k, t): whether the face counts at p (inside, or nearer than the cut-off),
    whether p is strictly inside, the squared distance to the boundary, the nearest edge k and the parameter t
    in [0, 1] of the closest point a_k + t e_k. Inside, the nearest boundary point is the foot of the
    perpendicular to the nearest edge line; outside, it lies on an edge whose line p is beyond.
    """
    l0 = _line(px, py, fe, f, 0)
    l1 = _line(px, py, fe, f, 1)
    l2 = _line(px, py, fe, f, 2)
    if l0 <= -cutoff or l1 <= -cutoff or l2 <= -cutoff:
        return False, False, 0.0, 0, 0.0
    if l0 > 0.0 and l1 > 0.0 and l2 > 0.0:
        k = 0
        lk = l0
        if l1 < lk:
            k = 1
            lk = l1
        if l2 < lk:
            k = 2
            lk = l2
        _, t = _closest_on_edge(px, py, fe, f, k)
        return True, True, lk * lk, k, t
    best = 1e300
    bk = 0
    bt = 0.0
    for k in range(3):
        lk = l0 if k == 0 else (l1 if k == 1 else l2)
        if lk <= 0.0:
            d2, t = _closest_on_edge(px, py, fe, f, k)
            if d2 < best:
                best = d2
                bk = k
                bt = t
    if best >= cutoff * cutoff:
        return False, False, 0.0, 0, 0.0
    return True, False, best, bk, bt


@nb.njit(inline="always", **_JIT)
def _row_span(fe, f, py, j0, j1, cutoff):
    """Columns [lo, hi] of row ``py`` where all three edge lines are less than ``cutoff`` outside, clipped to
    [j0, j1] (a superset of the pixels where face f counts; empty when lo > hi)."""
    lo = float(j0)
    hi = float(j1)
    for k in range(3):
        o = k * _EDGE
        nx = fe[f, o + 5]
        rest = (py - fe[f, o + 1]) * fe[f, o + 6] - fe[f, o] * nx + cutoff  # l_k + cutoff = nx * u + rest
        if nx > 1e-12:
            lo = max(lo, -rest / nx - 1e-6)
        elif nx < -1e-12:
            hi = min(hi, -rest / nx + 1e-6)
        elif rest <= 0.0:
            return 1, 0
    return int(math.ceil(lo)), int(math.floor(hi))


@nb.njit(parallel=True, **_JIT)
def face_setup(uv, z, faces, H, W, cutoff, near, min_area, cull_back):
    """Per-face edge records ``fe (F, 22)`` and the clipped cut-off-expanded pixel bounding boxes
    ``bbox (F, 4)`` (i0, i1, j0, j1); culled faces (behind the near plane, degenerate, off-screen, with
    ``cull_back`` turned away: clockwise on the screen) get an empty box (i0 > i1) and a zero record. Faces in
    parallel (a CAD polish batch has about 450 000 of them)."""
    F = faces.shape[0]
    fe = np.empty((F, _NFE))
    bbox = np.empty((F, 4), np.int64)
    for f in nb.prange(F):
        fe[f, :] = 0.0
        bbox[f, 0] = 1
        bbox[f, 1] = 0
        bbox[f, 2] = 1
        bbox[f, 3] = 0
        c0 = faces[f, 0]
        c1 = faces[f, 1]
        c2 = faces[f, 2]
        if z[c0] < near or z[c1] < near or z[c2] < near:
            continue
        xs = (uv[c0, 0], uv[c1, 0], uv[c2, 0])
        ys = (uv[c0, 1], uv[c1, 1], uv[c2, 1])
        area2 = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (ys[1] - ys[0]) * (xs[2] - xs[0])
        if not abs(area2) * 0.5 > min_area or (cull_back and area2 > 0.0):
            continue
        umin = min(xs[0], min(xs[1], xs[2])) - cutoff
        umax = max(xs[0], max(xs[1], xs[2])) + cutoff
        vmin = min(ys[0], min(ys[1], ys[2])) - cutoff
        vmax = max(ys[0], max(ys[1], ys[2])) + cutoff
        if umax < 0.0 or vmax < 0.0 or umin > W - 1.0 or vmin > H - 1.0:
            continue
        bbox[f, 0] = max(0, int(math.ceil(vmin)))
        bbox[f, 1] = min(H - 1, int(math.floor(vmax)))
        bbox[f, 2] = max(0, int(math.ceil(umin)))
        bbox[f, 3] = min(W - 1, int(math.floor(umax)))
        orient = 1.0 if area2 > 0.0 else -1.0
        for k in range(3):
            ax = xs[k]
            ay = ys[k]
            ex = xs[(k + 1) % 3] - ax
            ey = ys[(k + 1) % 3] - ay
            length2 = ex * ex + ey * ey
            inv_len = 1.0 / math.sqrt(length2)
            o = k * _EDGE
            fe[f, o] = ax
            fe[f, o + 1] = ay
            fe[f, o + 2] = ex
            fe[f, o + 3] = ey
            fe[f, o + 4] = 1.0 / length2
            fe[f, o + 5] = -ey * inv_len * orient
            fe[f, o + 6] = ex * inv_len * orient
        fe[f, 21] = 1.0
    return fe, bbox


@nb.njit(inline="always", **_JIT)
def _count_bins(bbox, face_batch, f0, f1, nty, ntx, tile, counts):
    for f in range(f0, f1):
        if bbox[f, 0] > bbox[f, 1] or bbox[f, 2] > bbox[f, 3]:
            continue
        base = face_batch[f] * nty
        for ty in range(bbox[f, 0] // tile, bbox[f, 1] // tile + 1):
            for tx in range(bbox[f, 2] // tile, bbox[f, 3] // tile + 1):
                counts[(base + ty) * ntx + tx + 1] += 1


@nb.njit(inline="always", **_JIT)
def _fill_bins(bbox, face_batch, f0, f1, nty, ntx, tile, fill, ids):
    for f in range(f0, f1):
        if bbox[f, 0] > bbox[f, 1] or bbox[f, 2] > bbox[f, 3]:
            continue
        base = face_batch[f] * nty
        for ty in range(bbox[f, 0] // tile, bbox[f, 1] // tile + 1):
            for tx in range(bbox[f, 2] // tile, bbox[f, 3] // tile + 1):
                k = (base + ty) * ntx + tx
                ids[fill[k]] = f
                fill[k] += 1


@nb.njit(parallel=True, **_JIT)
def bin_faces(bbox, face_batch, B, H, W, tile):
    """CSR lists of the faces whose bounding box touches each tile: ``offsets (n_bins + 1,)``, ``ids`` (each bin's
    faces in face order). Bin index = (b * n_tiles_y + ty) * n_tiles_x + tx. When the faces come grouped by image
    (``face_batch`` non-decreasing, as packed batches are), the images are binned in parallel (their bins are
    disjoint); otherwise serially."""
    nty = (H + tile - 1) // tile
    ntx = (W + tile - 1) // tile
    n_bins = B * nty * ntx
    counts = np.zeros(n_bins + 1, np.int64)
    F = bbox.shape[0]
    grouped = True
    for f in range(1, F):
        if face_batch[f] < face_batch[f - 1]:
            grouped = False
            break
    starts = np.searchsorted(face_batch, np.arange(B + 1)) if grouped else np.zeros(1, np.int64)
    if grouped:
        for b in nb.prange(B):
            _count_bins(bbox, face_batch, starts[b], starts[b + 1], nty, ntx, tile, counts)
    else:
        _count_bins(bbox, face_batch, 0, F, nty, ntx, tile, counts)
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    ids = np.empty(offsets[-1], np.int64)
    if grouped:
        for b in nb.prange(B):
            _fill_bins(bbox, face_batch, starts[b], starts[b + 1], nty, ntx, tile, fill, ids)
    else:
        _fill_bins(bbox, face_batch, 0, F, nty, ntx, tile, fill, ids)
    return offsets, ids


@nb.njit(**_JIT)
def _interleaved_work(offsets, T):
    """Non-empty bin indices, dealt round-robin to the threads: prange hands each thread one contiguous block,
    and the work of a mesh sits in a few neighbouring tiles."""
    n_bins = offsets.shape[0] - 1
    nonempty = np.empty(n_bins, np.int64)
    m = 0
    for k in range(n_bins):
        if offsets[k + 1] > offsets[k]:
            nonempty[m] = k
            m += 1
    work = np.empty(m, np.int64)
    w = 0
    for t in range(T):
        for q in range(t, m, T):
            work[w] = nonempty[q]
            w += 1
    return work


@nb.njit(parallel=True, **_JIT)
def soft_forward(fe, bbox, offsets, ids, B, H, W, tile, inv_sigma, cutoff, saturation, n_threads, silhouette,
                 one_minus, hard, want_hard, hard_value):
    """Fill ``silhouette (B, H, W)`` with S and ``one_minus (B, H, W)`` with 1 - S (0 where saturated or where no
    face counts); with ``want_hard``, also ``hard (B, H, W)`` with 1 where the pixel centre is strictly inside a
    face (as ``hard_forward`` does, for the same faces). With ``hard_value`` (which needs ``want_hard``),
    ``silhouette`` gets the hard value (0 or 1) instead of S, and ``one_minus`` is still S's (the straight-through
    silhouette: the hard value, the soft gradient).

    The arrays come in uninitialised: every pixel of ``silhouette`` and ``hard`` is written, ``one_minus`` only in
    the tiles that some face touches (the only pixels ``soft_backward`` reads: a face's box lies in its tiles).
    Tiles run in parallel; inside a tile each face of the bin visits only the pixels of its row spans, multiplying
    ``1 - S`` by ``1 - p_f = 1 / (1 + exp(x_f))``, ``x_f = -sd2_f / sigma``; pixels already past saturation
    (``1 - S < exp(-saturation)``) are skipped (for S; for the hard value only once a face is found to contain
    them)."""
    nty = (H + tile - 1) // tile
    ntx = (W + tile - 1) // tile
    floor = math.exp(-saturation)
    work = _interleaved_work(offsets, n_threads)
    for w in nb.prange(work.shape[0]):
        k = work[w]
        start = offsets[k]
        end = offsets[k + 1]
        b = k // (nty * ntx)
        ti = (k // ntx) % nty * tile
        tj = k % ntx * tile
        om = np.ones((tile, tile))  # 1 - S = prod_f (1 - p_f), p_f = sigmoid(x_f)
        hd = np.zeros((tile, tile), np.bool_)  # strictly inside some face
        for n in range(start, end):
            f = ids[n]
            for i in range(max(bbox[f, 0], ti), min(bbox[f, 1], ti + tile - 1) + 1):
                py = float(i)
                lo, hi = _row_span(fe, f, py, max(bbox[f, 2], tj), min(bbox[f, 3], tj + tile - 1), cutoff)
                for j in range(lo, hi + 1):
                    saturated = om[i - ti, j - tj] < floor
                    if saturated and (not want_hard or hd[i - ti, j - tj]):
                        continue
                    counted, inside, d2, _, _ = _pair(float(j), py, fe, f, cutoff)
                    if inside:
                        hd[i - ti, j - tj] = True
                    if counted and not saturated:
                        x = d2 * inv_sigma if inside else -d2 * inv_sigma
                        om[i - ti, j - tj] /= 1.0 + math.exp(min(x, 700.0))
        for i in range(ti, min(H, ti + tile)):
            for j in range(tj, min(W, tj + tile)):
                q = om[i - ti, j - tj]
                if q < floor:
                    silhouette[b, i, j] = 1.0
                    one_minus[b, i, j] = 0.0
                else:
                    silhouette[b, i, j] = 1.0 - q
                    one_minus[b, i, j] = q if q < 1.0 else 0.0
                if want_hard:
                    hard[b, i, j] = hd[i - ti, j - tj]
                    if hard_value:
                        silhouette[b, i, j] = 1.0 if hd[i - ti, j - tj] else 0.0
    for k in nb.prange(offsets.shape[0] - 1):  # the tiles no face touches: S = 0
        if offsets[k + 1] > offsets[k]:
            continue
        b = k // (nty * ntx)
        ti = (k // ntx) % nty * tile
        tj = k % ntx * tile
        for i in range(ti, min(H, ti + tile)):
            for j in range(tj, min(W, tj + tile)):
                silhouette[b, i, j] = 0.0
                if want_hard:
                    hard[b, i, j] = False


@nb.njit(parallel=True, **_JIT)
def soft_backward(fe, bbox, face_batch, grad_s, one_minus, inv_sigma, cutoff):
    """Gradient of the loss w.r.t. each face's corners ``(F, 3, 2)`` from ``grad_s = dL/dS`` (B, H, W).

    dS/dx_f = (1 - S) p_f; x_f = -sd2_f / sigma; for the nearest edge (a, b) with closest point c = a + t (b - a):
    d(d2)/da = -2 (p - c)(1 - t), d(d2)/db = -2 (p - c) t. Saturated pixels (one_minus = 0) are skipped."""
    F = fe.shape[0]
    out = np.zeros((F, 3, 2))
    for f in nb.prange(F):
        i0, i1, j0, j1 = bbox[f, 0], bbox[f, 1], bbox[f, 2], bbox[f, 3]
        if i0 > i1 or j0 > j1:
            continue
        b = face_batch[f]
        g = np.zeros((3, 2))
        for i in range(i0, i1 + 1):
            py = float(i)
            lo, hi = _row_span(fe, f, py, j0, j1, cutoff)
            for j in range(lo, hi + 1):
                w = grad_s[b, i, j] * one_minus[b, i, j]
                if w == 0.0:
                    continue
                px = float(j)
                counted, inside, d2, k, t = _pair(px, py, fe, f, cutoff)
                if not counted:
                    continue
                x = d2 * inv_sigma if inside else -d2 * inv_sigma
                prob = 1.0 / (1.0 + math.exp(-x)) if x >= 0.0 else math.exp(x) / (1.0 + math.exp(x))
                g_d2 = w * prob * inv_sigma  # dL/d(d2) outside; the sign flips inside (sd2 = -d2)
                if not inside:
                    g_d2 = -g_d2
                o = k * _EDGE
                rx = px - (fe[f, o] + t * fe[f, o + 2])
                ry = py - (fe[f, o + 1] + t * fe[f, o + 3])
                k1 = (k + 1) % 3
                g[k, 0] -= 2.0 * rx * (1.0 - t) * g_d2
                g[k, 1] -= 2.0 * ry * (1.0 - t) * g_d2
                g[k1, 0] -= 2.0 * rx * t * g_d2
                g[k1, 1] -= 2.0 * ry * t * g_d2
        out[f] = g
    return out


@nb.njit(**_JIT)
def scatter_face_grads(face_grad, faces, n_verts):
    """Sum per-face corner gradients ``(F, 3, 2)`` into per-vertex gradients ``(N, 2)``."""
    out = np.zeros((n_verts, 2))
    for f in range(faces.shape[0]):
        for c in range(3):
            v = faces[f, c]
            out[v, 0] += face_grad[f, c, 0]
            out[v, 1] += face_grad[f, c, 1]
    return out


@nb.njit(parallel=True, **_JIT)
def hard_forward(fe, bbox, offsets, ids, B, H, W, tile, n_threads, out):
    """Set the ``False``-filled ``out (B, H, W)`` bool to ``True`` where a pixel centre is strictly inside any drawn
    face. A tile stops reading its bin once all its pixels are set (inside a large silhouette most tiles fill
    after a few of their faces)."""
    nty = (H + tile - 1) // tile
    ntx = (W + tile - 1) // tile
    work = _interleaved_work(offsets, n_threads)
    for w in nb.prange(work.shape[0]):
        k = work[w]
        b = k // (nty * ntx)
        ti = (k // ntx) % nty * tile
        tj = k % ntx * tile
        unset = (min(H, ti + tile) - ti) * (min(W, tj + tile) - tj)  # pixels of the tile not yet set
        for n in range(offsets[k], offsets[k + 1]):
            if unset == 0:
                break
            f = ids[n]
            for i in range(max(bbox[f, 0], ti), min(bbox[f, 1], ti + tile - 1) + 1):
                lo, hi = _row_span(fe, f, float(i), max(bbox[f, 2], tj), min(bbox[f, 3], tj + tile - 1), 0.0)
                for j in range(lo, hi + 1):  # strictly inside: all three edge lines > 0 (``_pair``'s test)
                    if not out[b, i, j]:
                        px = float(j)
                        py = float(i)
                        if _line(px, py, fe, f, 0) > 0.0 and _line(px, py, fe, f, 1) > 0.0 \
                                and _line(px, py, fe, f, 2) > 0.0:
                            out[b, i, j] = True
                            unset -= 1
