"""Coverage kernels: which triangle is nearest at each pixel centre, and its barycentrics.

Both take projected vertices: ``sx, sy`` (V,) screen coordinates in pixels (x right, y down,
pixel (i, j) centred at (j + 0.5, i + 0.5)), ``iw`` (V,) = 1 / w_clip (larger = nearer), and
``tris`` (T, 3) int64 with ``valid`` (T,) bool (triangles to draw). They return ``tri`` (H*W,)
int32 (-1 where uncovered) and the perspective-correct barycentrics ``b0, b1`` (H*W,) float32
of vertices 0 and 1 (``b2 = 1 - b0 - b1``).

A pixel centre is inside a triangle when all three screen-space barycentrics are >= 0 (both
windings: every face is kept). The nearest triangle has the largest interpolated 1/w; exact
ties go to the larger triangle index in both kernels.

* :func:`raster_numba`: binned into 16x16 tiles, tiles rasterised in parallel (numba
  ``prange``), each tile owning its part of the z-buffer (no races).
* :func:`raster_torch`: vectorised over triangles grouped by bounding-box size, resolved by
  ``scatter_reduce``; device-agnostic, and the reference the numba kernel is tested against.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

TILE = 16


@numba.njit(cache=True)
def _bbox(sx, sy, tris, valid, H, W):
    T = tris.shape[0]
    box = np.empty((T, 4), dtype=np.int64)  # j0, j1, i0, i1 inclusive; j1 < j0 when empty
    for t in range(T):
        box[t, 0], box[t, 1], box[t, 2], box[t, 3] = 0, -1, 0, -1
        if not valid[t]:
            continue
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        xmin = min(sx[a], min(sx[b], sx[c]))
        xmax = max(sx[a], max(sx[b], sx[c]))
        ymin = min(sy[a], min(sy[b], sy[c]))
        ymax = max(sy[a], max(sy[b], sy[c]))
        if not (xmax >= 0.0 and ymax >= 0.0 and xmin <= W and ymin <= H):
            continue
        j0 = max(0, int(math.ceil(xmin - 0.5)))
        j1 = min(W - 1, int(math.floor(xmax - 0.5)))
        i0 = max(0, int(math.ceil(ymin - 0.5)))
        i1 = min(H - 1, int(math.floor(ymax - 0.5)))
        if j1 < j0 or i1 < i0:
            continue
        area = (sx[b] - sx[a]) * (sy[c] - sy[a]) - (sy[b] - sy[a]) * (sx[c] - sx[a])
        if area == 0.0 or not math.isfinite(area):
            continue
        box[t, 0], box[t, 1], box[t, 2], box[t, 3] = j0, j1, i0, i1
    return box


@numba.njit(cache=True)
def _bin(box, ntx, nty):
    T = box.shape[0]
    counts = np.zeros(ntx * nty + 1, dtype=np.int64)
    for t in range(T):
        if box[t, 1] < box[t, 0]:
            continue
        for ty in range(box[t, 2] // TILE, box[t, 3] // TILE + 1):
            for tx in range(box[t, 0] // TILE, box[t, 1] // TILE + 1):
                counts[ty * ntx + tx + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    items = np.empty(start[-1], dtype=np.int64)
    for t in range(T):  # ascending t inside every bin
        if box[t, 1] < box[t, 0]:
            continue
        for ty in range(box[t, 2] // TILE, box[t, 3] // TILE + 1):
            for tx in range(box[t, 0] // TILE, box[t, 1] // TILE + 1):
                k = ty * ntx + tx
                items[fill[k]] = t
                fill[k] += 1
    return start, items


@numba.njit(parallel=True, cache=True)
def _raster_tiles(sx, sy, iw, tris, box, start, items, H, W, ntx, nty, out_tri, out_b0, out_b1):
    for k in numba.prange(ntx * nty):
        ty, tx = k // ntx, k % ntx
        ti0, tj0 = ty * TILE, tx * TILE
        ti1, tj1 = min(H - 1, ti0 + TILE - 1), min(W - 1, tj0 + TILE - 1)
        depth = np.full((TILE, TILE), -np.inf)
        for q in range(start[k], start[k + 1]):
            t = items[q]
            a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
            ax, ay, bx, by, cx, cy = sx[a], sy[a], sx[b], sy[b], sx[c], sy[c]
            inv_area = 1.0 / ((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
            wa, wb, wc = iw[a], iw[b], iw[c]
            for i in range(max(ti0, box[t, 2]), min(ti1, box[t, 3]) + 1):
                py = i + 0.5
                for j in range(max(tj0, box[t, 0]), min(tj1, box[t, 1]) + 1):
                    px = j + 0.5
                    la = ((bx - px) * (cy - py) - (by - py) * (cx - px)) * inv_area
                    if la < 0.0:
                        continue
                    lb = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) * inv_area
                    if lb < 0.0:
                        continue
                    lc = ((ax - px) * (by - py) - (ay - py) * (bx - px)) * inv_area
                    if lc < 0.0:
                        continue
                    d = la * wa + lb * wb + lc * wc
                    p = i * W + j
                    cur = depth[i - ti0, j - tj0]
                    if d > cur or (d == cur and t > out_tri[p]):
                        depth[i - ti0, j - tj0] = d
                        out_tri[p] = t
                        out_b0[p] = la * wa / d
                        out_b1[p] = lb * wb / d


def raster_numba(sx, sy, iw, tris, valid, H: int, W: int):
    """Numba tiled z-buffer. Inputs numpy (float64 / int64 / bool); see the module doc."""
    box = _bbox(sx, sy, tris, valid, H, W)
    ntx, nty = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
    start, items = _bin(box, ntx, nty)
    out_tri = np.full(H * W, -1, dtype=np.int32)
    out_b0 = np.zeros(H * W, dtype=np.float32)
    out_b1 = np.zeros(H * W, dtype=np.float32)
    _raster_tiles(sx, sy, iw, tris, box, start, items, H, W, ntx, nty, out_tri, out_b0, out_b1)
    return out_tri, out_b0, out_b1


def raster_torch(sx, sy, iw, tris, valid, H: int, W: int, chunk: int = 1 << 22):
    """Vectorised torch z-buffer (float64 tensors on any device); see the module doc.

    Triangles are grouped by the power of two that bounds their pixel bounding box, and each
    group is evaluated densely over that box in chunks of at most ``chunk`` candidates."""
    dev = sx.device
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    X = torch.stack([sx[a], sx[b], sx[c]], 1)
    Y = torch.stack([sy[a], sy[b], sy[c]], 1)
    IW = torch.stack([iw[a], iw[b], iw[c]], 1)
    area = (X[:, 1] - X[:, 0]) * (Y[:, 2] - Y[:, 0]) - (Y[:, 1] - Y[:, 0]) * (X[:, 2] - X[:, 0])
    j0 = torch.ceil(X.min(1).values - 0.5).clamp(min=0)
    j1 = torch.floor(X.max(1).values - 0.5).clamp(max=W - 1)
    i0 = torch.ceil(Y.min(1).values - 0.5).clamp(min=0)
    i1 = torch.floor(Y.max(1).values - 0.5).clamp(max=H - 1)
    ok = valid & (area != 0) & torch.isfinite(area) & (j1 >= j0) & (i1 >= i0)
    side = torch.maximum(j1 - j0 + 1, i1 - i0 + 1).clamp(min=1)
    level = torch.where(ok, torch.ceil(torch.log2(side)).long(), torch.full_like(a, -1))
    cand_pix, cand_tri, cand_d = [], [], []
    for lv in torch.unique(level).tolist():
        if lv < 0:
            continue
        k = 1 << lv
        ids = torch.nonzero(level == lv).squeeze(1)
        off = torch.arange(k, device=dev, dtype=torch.float64)
        per = max(1, chunk // (k * k))
        for s in range(0, ids.numel(), per):
            t = ids[s : s + per]
            ii = i0[t, None, None] + off[None, :, None]  # (n, k, 1)
            jj = j0[t, None, None] + off[None, None, :]  # (n, 1, k)
            py, px = ii + 0.5, jj + 0.5
            x, y = X[t][:, :, None, None], Y[t][:, :, None, None]
            inv = (1.0 / area[t])[:, None, None]
            la = ((x[:, 1] - px) * (y[:, 2] - py) - (y[:, 1] - py) * (x[:, 2] - px)) * inv
            lb = ((x[:, 2] - px) * (y[:, 0] - py) - (y[:, 2] - py) * (x[:, 0] - px)) * inv
            lc = ((x[:, 0] - px) * (y[:, 1] - py) - (y[:, 0] - py) * (x[:, 1] - px)) * inv
            inside = (la >= 0) & (lb >= 0) & (lc >= 0)
            inside &= (ii <= i1[t, None, None]) & (jj <= j1[t, None, None])
            n_i, r_i, c_i = torch.nonzero(inside, as_tuple=True)
            w = IW[t][n_i]
            d = la[n_i, r_i, c_i] * w[:, 0] + lb[n_i, r_i, c_i] * w[:, 1]
            d = d + lc[n_i, r_i, c_i] * w[:, 2]
            cand_pix.append((ii[n_i, r_i, 0] * W + jj[n_i, 0, c_i]).long())
            cand_tri.append(t[n_i])
            cand_d.append(d)
    out_tri = torch.full((H * W,), -1, dtype=torch.int64, device=dev)
    out_b0 = torch.zeros(H * W, dtype=torch.float32, device=dev)
    out_b1 = torch.zeros(H * W, dtype=torch.float32, device=dev)
    if not cand_pix:
        return out_tri.int(), out_b0, out_b1
    pix, tri, d = torch.cat(cand_pix), torch.cat(cand_tri), torch.cat(cand_d)
    best = torch.full((H * W,), -math.inf, dtype=torch.float64, device=dev)
    best = best.scatter_reduce(0, pix, d, "amax")
    keep = d == best[pix]
    pix, tri = pix[keep], tri[keep]
    out_tri = out_tri.scatter_reduce(0, pix, tri, "amax")
    sel = out_tri[pix] == tri
    pix, tri = pix[sel], tri[sel]
    # perspective-correct barycentrics of the winners
    px = (pix % W).double() + 0.5
    py = torch.div(pix, W, rounding_mode="floor").double() + 0.5
    x, y, w = X[tri], Y[tri], IW[tri]
    inv = 1.0 / area[tri]
    la = ((x[:, 1] - px) * (y[:, 2] - py) - (y[:, 1] - py) * (x[:, 2] - px)) * inv
    lb = ((x[:, 2] - px) * (y[:, 0] - py) - (y[:, 2] - py) * (x[:, 0] - px)) * inv
    lc = ((x[:, 0] - px) * (y[:, 1] - py) - (y[:, 0] - py) * (x[:, 1] - px)) * inv
    dd = la * w[:, 0] + lb * w[:, 1] + lc * w[:, 2]
    out_b0[pix] = (la * w[:, 0] / dd).float()
    out_b1[pix] = (lb * w[:, 1] / dd).float()
    return out_tri.int(), out_b0, out_b1


@numba.njit(inline="always")
def _normalize3(x, y, z, eps):
    n2 = x * x + y * y + z * z
    if not (n2 > eps):  # also catches NaN
        return 0.0, 0.0, 0.0, False
    inv = 1.0 / math.sqrt(n2)
    return x * inv, y * inv, z * inv, True


@numba.njit(parallel=True, cache=True)
def interpolate_numba(
    pix, tri, b0, b1, tris, v_pos, v_nrm, v_tng, v_uv, sx, sy, iw, eye, W,
    o_bary, o_pos, o_nrm, o_tng, o_uv, o_uvg, o_view, o_back,
):  # fmt: skip
    """Fused CPU version of :func:`pbrsr_core.render.raster.build_gbuffer` (same maths,
    float64 inside, float32 out). ``v_uv`` (S, V, 2); outputs preallocated."""
    P = pix.shape[0]
    S = v_uv.shape[0]
    for p in numba.prange(P):
        t = tri[p]
        ia, ib, ic = tris[t, 0], tris[t, 1], tris[t, 2]
        ba = np.float64(b0[p])
        bb = np.float64(b1[p])
        bc = 1.0 - ba - bb
        o_bary[p, 0], o_bary[p, 1], o_bary[p, 2] = ba, bb, bc
        pos = np.empty(3)
        for k in range(3):
            pos[k] = ba * v_pos[ia, k] + bb * v_pos[ib, k] + bc * v_pos[ic, k]
            o_pos[p, k] = pos[k]
        vx, vy, vz, _ = _normalize3(eye[0] - pos[0], eye[1] - pos[1], eye[2] - pos[2], 1e-40)
        o_view[p, 0], o_view[p, 1], o_view[p, 2] = vx, vy, vz
        e1x, e1y, e1z = (
            v_pos[ib, 0] - v_pos[ia, 0],
            v_pos[ib, 1] - v_pos[ia, 1],
            v_pos[ib, 2] - v_pos[ia, 2],
        )
        e2x, e2y, e2z = (
            v_pos[ic, 0] - v_pos[ia, 0],
            v_pos[ic, 1] - v_pos[ia, 1],
            v_pos[ic, 2] - v_pos[ia, 2],
        )
        gx, gy, gz, g_ok = _normalize3(
            e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x, 1e-40
        )
        back = (gx * (eye[0] - pos[0]) + gy * (eye[1] - pos[1]) + gz * (eye[2] - pos[2])) < 0.0
        o_back[p] = back
        nx, ny, nz, n_ok = _normalize3(
            ba * v_nrm[ia, 0] + bb * v_nrm[ib, 0] + bc * v_nrm[ic, 0],
            ba * v_nrm[ia, 1] + bb * v_nrm[ib, 1] + bc * v_nrm[ic, 1],
            ba * v_nrm[ia, 2] + bb * v_nrm[ib, 2] + bc * v_nrm[ic, 2],
            1e-20,
        )
        if not n_ok:
            if g_ok:
                nx, ny, nz = gx, gy, gz
            else:
                nx, ny, nz = vx, vy, vz
        tx = ba * v_tng[ia, 0] + bb * v_tng[ib, 0] + bc * v_tng[ic, 0]
        ty = ba * v_tng[ia, 1] + bb * v_tng[ib, 1] + bc * v_tng[ic, 1]
        tz = ba * v_tng[ia, 2] + bb * v_tng[ib, 2] + bc * v_tng[ic, 2]
        tw = ba * v_tng[ia, 3] + bb * v_tng[ib, 3] + bc * v_tng[ic, 3]
        d = nx * tx + ny * ty + nz * tz
        tx, ty, tz, t_ok = _normalize3(tx - nx * d, ty - ny * d, tz - nz * d, 1e-12)
        if not t_ok:
            if abs(nx) < 0.9:
                rx, ry = 1.0, 0.0
            else:
                rx, ry = 0.0, 1.0
            d = nx * rx + ny * ry
            tx, ty, tz, _ = _normalize3(rx - nx * d, ry - ny * d, -nz * d, 1e-40)
        sign = -1.0 if tw < 0.0 else 1.0
        f = -1.0 if back else 1.0
        o_nrm[p, 0], o_nrm[p, 1], o_nrm[p, 2] = nx * f, ny * f, nz * f
        o_tng[p, 0], o_tng[p, 1], o_tng[p, 2], o_tng[p, 3] = tx * f, ty * f, tz * f, sign * f
        # screen-space UV derivatives
        ax, ay, bx, by, cx, cy = sx[ia], sy[ia], sx[ib], sy[ib], sx[ic], sy[ic]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if not (abs(area) > 1e-30):
            area = 1e-30
        wa, wb, wc = iw[ia], iw[ib], iw[ic]
        wsum = ba / wa + bb / wb + bc / wc
        dxa, dxb, dxc = (by - cy) / area, (cy - ay) / area, (ay - by) / area
        dya, dyb, dyc = (cx - bx) / area, (ax - cx) / area, (bx - ax) / area
        for s in range(S):
            for k in range(2):
                u = ba * v_uv[s, ia, k] + bb * v_uv[s, ib, k] + bc * v_uv[s, ic, k]
                o_uv[s, p, k] = u
                da = (v_uv[s, ia, k] - u) * wa
                db = (v_uv[s, ib, k] - u) * wb
                dc = (v_uv[s, ic, k] - u) * wc
                gxv = (dxa * da + dxb * db + dxc * dc) * wsum
                gyv = (dya * da + dyb * db + dyc * dc) * wsum
                o_uvg[s, p, k] = gxv if math.isfinite(gxv) else 0.0
                o_uvg[s, p, 2 + k] = gyv if math.isfinite(gyv) else 0.0
