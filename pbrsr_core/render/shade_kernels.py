"""Fused CPU shading: the per-pixel part of :func:`shade.shade` in one numba pass.

:func:`shade.shade_terms` (the reference, and the path on CUDA) is a chain of ~25 pointwise
torch ops plus three ``grid_sample`` lookups per pixel; on a CPU its time goes into memory
traffic of (P, 3) temporaries and autograd bookkeeping. Here the same arithmetic runs once per
pixel in registers: :func:`shade_fused` takes the per-pixel material values that
:func:`shade.material_inputs` produces and the G-buffer frame, and returns the (P, 4) RGB +
alpha. The forward also stores, per pixel, the 33 looked-up values and their derivatives
(:data:`NAUX`; buffers pooled between views); the backward kernel recomputes only the cheap
per-pixel frame from the inputs and returns the exact derivatives w.r.t. every per-pixel
input (autograd chains them back into the texel-side scatter of ``texture.gather``).
:class:`DecodeNormal` does material_inputs' normal-map decoding the same way.

Exactness: every clamp, guard and lookup is the reference's, including what its autograd
does at the edges: ``clamp`` passes the gradient on its closed interval, ``where`` only to
the taken branch, and ``grid_sample`` (bilinear, ``padding_mode="border"``,
``align_corners=True``) gives a zero gradient w.r.t. a coordinate clipped to, or lying
exactly on, the border, treats a tap past the last texel as zero, and its bilinear /
trilinear gradients are the one-sided slopes of the cell ``floor(coordinate)``. The kernels
compute in float64 whatever the input dtype (float32 inputs therefore match the float32
reference to rounding, ~1e-6 relative; float64 ones to ~1e-15) and write the input dtype;
the equirect mapping's arctangents are a double-precision rational approximation
(:func:`_atan`, within 1 ulp of libm's, several times cheaper).

Threads: the kernels run on ``min(torch.get_num_threads(), NUMBA_NUM_THREADS)`` numba
threads (numba's OpenMP layer shares the thread count with torch).
"""

from __future__ import annotations

import math
import threading
import weakref

import numba
import numpy as np
import torch

from ..jit import JitOptions

NDOTV_MIN = 1e-4  # = shade.NDOTV_MIN
NORMAL_MIN2 = 1e-12  # a mapped / tangent-space normal with |v|^2 <= this is degenerate
NORM_EPS2 = 1e-24  # safe_normalize's clamp of |v|^2
POLE_MIN2 = 1e-12  # envmaps.dir_to_uv: x^2 + z^2 below this is a pole
POLE_X = 1e-6
ACOS_LIM = 1.0 - 1e-6
INV_2PI = 1.0 / (2.0 * math.pi)
INV_PI = 1.0 / math.pi

_JIT: JitOptions = {"cache": True, "fastmath": False, "error_model": "numpy"}
_INL: JitOptions = {**_JIT, "inline": "always"}
_PAR: JitOptions = {**_JIT, "parallel": True}
_f64 = np.float64  # (numba's float() keeps a float32 a float32)


@numba.njit(**_INL)
def _clamp01(x):
    """(value, gradient mask) of clamp(x, 0, 1): torch passes the gradient on [0, 1]."""
    if x < 0.0:
        return 0.0, 0.0
    if x > 1.0:
        return 1.0, 0.0
    return x, 1.0


@numba.njit(**_INL)
def _clip(x, size):
    """grid_sample's border clip of a pixel coordinate to [0, size - 1]: (coordinate,
    gradient); the gradient is zero on and past the border (as in ATen)."""
    hi = size - 1.0
    if x <= 0.0:
        return 0.0, 0.0
    if x >= hi:
        return hi, 0.0
    return x, 1.0


_T3P8 = 2.41421356237309504880  # tan(3 pi / 8)
_MOREBITS = 6.123233995736765886130e-17  # pi / 2 - float(pi / 2)


@numba.njit(**_INL)
def _atan(x):
    """arctan to double precision (Cephes' range reduction and rational minimax fit, within
    ~1 ulp of libm; ~4x faster than the libm call here)."""
    sign = 1.0
    if x < 0.0:
        sign = -1.0
        x = -x
    flag = 0
    y = 0.0
    if x > _T3P8:
        y = math.pi / 2.0
        flag = 1
        x = -1.0 / x
    elif x > 0.66:
        y = math.pi / 4.0
        flag = 2
        x = (x - 1.0) / (x + 1.0)
    z = x * x
    pz = -8.750608600031904122785e-1 * z - 1.615753718733365076637e1
    pz = (pz * z - 7.500855792314704667340e1) * z - 1.228866684490136173410e2
    pz = pz * z - 6.485021904942025371773e1
    qz = (z + 2.485846490142306297962e1) * z + 1.650270098316988542046e2
    qz = ((qz * z + 4.328810604912902668951e2) * z + 4.853903996359136964868e2) * z
    qz = qz + 1.945506571482613964425e2
    z = x * (z * pz / qz) + x
    if flag == 2:
        z += 0.5 * _MOREBITS
    elif flag == 1:
        z += _MOREBITS
    return sign * (y + z)


@numba.njit(**_INL)
def _atan2(y, x):
    """math.atan2 (signed zeros included) from :func:`_atan`."""
    if x > 0.0:
        return _atan(y / x)
    if x < 0.0:
        return _atan(y / x) + math.copysign(math.pi, y)
    if y != 0.0:
        return math.copysign(math.pi / 2.0, y)
    return math.copysign(math.pi if math.copysign(1.0, x) < 0.0 else 0.0, y)


@numba.njit(**_INL)
def _acos(y):
    """math.acos for |y| < 1: atan2(sqrt((1 - y)(1 + y)), y)."""
    return _atan2(math.sqrt((1.0 - y) * (1.0 + y)), y)


@numba.njit(**_INL)
def _dir_uv(x, y, z):
    """envmaps.dir_to_uv of one direction: (u, v, du/dx, du/dz, dv/dy)."""
    pole = x * x + z * z < POLE_MIN2
    xe = POLE_X if pole else x
    den = xe * xe + z * z
    u = 0.5 + _atan2(xe, -z) * INV_2PI
    du_dx = 0.0 if pole else -z / den * INV_2PI
    du_dz = xe / den * INV_2PI
    yc, gy = y, 1.0
    if y < -ACOS_LIM:
        yc, gy = -ACOS_LIM, 0.0
    elif y > ACOS_LIM:
        yc, gy = ACOS_LIM, 0.0
    v = _acos(yc) * INV_PI
    dv_dy = -gy * INV_PI / math.sqrt(1.0 - yc * yc)
    return u, v, du_dx, du_dz, dv_dy


@numba.njit(**_INL)
def _bilerp(img, k, ix, iy, c):
    """Bilinear tap of channel c of img[k] (K, H, W, C) at pixel coordinates (ix, iy) already
    clipped to the image: (value, d/dix, d/diy); taps past the last texel are zero."""
    h, w = img.shape[1], img.shape[2]
    x0 = int(math.floor(ix))
    y0 = int(math.floor(iy))
    fx = ix - x0
    fy = iy - y0
    x1 = x0 + 1
    y1 = y0 + 1
    a = _f64(img[k, y0, x0, c])
    b = _f64(img[k, y0, x1, c]) if x1 < w else 0.0
    d = _f64(img[k, y1, x0, c]) if y1 < h else 0.0
    e = _f64(img[k, y1, x1, c]) if (x1 < w and y1 < h) else 0.0
    val = (1.0 - fx) * (1.0 - fy) * a + fx * (1.0 - fy) * b + (1.0 - fx) * fy * d + fx * fy * e
    dx = (1.0 - fy) * (b - a) + fy * (e - d)
    dy = (1.0 - fx) * (d - a) + fx * (e - b)
    return val, dx, dy


@numba.njit(**_INL)
def _env_coords(u, v, h, wp):
    """Equirect UV -> clipped pixel coordinates of a wrap-padded (h, wp) map and the
    derivatives d(ix)/du, d(iy)/dv (EnvLight._grid_xy + grid_sample, align_corners)."""
    ix, gx = _clip(u * (wp - 2) + 0.5, wp)
    iy, gy = _clip(v * h - 0.5, h)
    return ix, iy, gx * (wp - 2), gy * h


@numba.njit(**_JIT)
def _material(p, base, rough, metal, ao, alpha):
    """Clamped material values of pixel p and their clamp masks (as in shade_terms)."""
    k0, mk0 = _clamp01(_f64(base[p, 0]))
    k1, mk1 = _clamp01(_f64(base[p, 1]))
    k2, mk2 = _clamp01(_f64(base[p, 2]))
    rg, mr = _clamp01(_f64(rough[p, 0]))
    mt, mm = _clamp01(_f64(metal[p, 0]))
    oc, mo = _clamp01(_f64(ao[p, 0]))
    al, ma = _clamp01(_f64(alpha[p, 0]))
    return k0, k1, k2, mk0, mk1, mk2, rg, mr, mt, mm, oc, mo, al, ma


@numba.njit(**_JIT)
def _frame(p, nts, nrm, tng, view):
    """Shading normal n (perturb_normal), N.V (raw, clamped, mask) and the reflection r of
    pixel p, with the TBN and norms the backward needs."""
    tx, ty, tz = _f64(nts[p, 0]), _f64(nts[p, 1]), _f64(nts[p, 2])
    gnx, gny, gnz = _f64(nrm[p, 0]), _f64(nrm[p, 1]), _f64(nrm[p, 2])
    t0, t1, t2, tw = _f64(tng[p, 0]), _f64(tng[p, 1]), _f64(tng[p, 2]), _f64(tng[p, 3])
    b0 = tw * (gny * t2 - gnz * t1)
    b1 = tw * (gnz * t0 - gnx * t2)
    b2 = tw * (gnx * t1 - gny * t0)
    v0 = t0 * tx + b0 * ty + gnx * tz
    v1 = t1 * tx + b1 * ty + gny * tz
    v2 = t2 * tx + b2 * ty + gnz * tz
    n2 = v0 * v0 + v1 * v1 + v2 * v2
    mapped = n2 > NORMAL_MIN2
    if mapped:
        sn = math.sqrt(max(n2, NORM_EPS2))
        n0, n1, nz = v0 / sn, v1 / sn, v2 / sn
    else:
        sn = 1.0
        n0, n1, nz = gnx, gny, gnz
    w0, w1, w2 = _f64(view[p, 0]), _f64(view[p, 1]), _f64(view[p, 2])
    ndr = n0 * w0 + n1 * w1 + nz * w2
    ndv, mndv = ndr, 1.0
    if ndr < NDOTV_MIN:
        ndv, mndv = NDOTV_MIN, 0.0
    elif ndr > 1.0:
        ndv, mndv = 1.0, 0.0
    q0 = 2.0 * ndr * n0 - w0
    q1 = 2.0 * ndr * n1 - w1
    q2 = 2.0 * ndr * nz - w2
    s2 = q0 * q0 + q1 * q1 + q2 * q2
    rs = math.sqrt(max(s2, NORM_EPS2))
    return (
        (t0, t1, t2, b0, b1, b2, gnx, gny, gnz, mapped, sn),
        (n0, n1, nz, w0, w1, w2, ndr, ndv, mndv),
        (s2, rs, q0 / rs, q1 / rs, q2 / rs),
    )


NAUX = 33  # values per pixel the forward stores for the backward (see _lookups)


@numba.njit(**_JIT)
def _lookups(n0, n1, nz, r0, r1, r2, rg, ndv, diff, spec, lut, aux, p):
    """The three table lookups of a pixel (diffuse(n), specular(r, rough), LUT(ndv, rough))
    and their derivatives, written to aux[p, :NAUX]: Ld (3), dLd/dn (3 x 3, channel-major),
    Ls (3), dLs/dr (3 x 3), dLs/drough (3), A, B, dA/drough, dA/dndv, dB/drough, dB/dndv."""
    ud, vd, dud_x, dud_z, dvd_y = _dir_uv(n0, n1, nz)
    dix, diy, ddu, ddv = _env_coords(ud, vd, diff.shape[1], diff.shape[2])
    for c in range(3):
        val, dx, dy = _bilerp(diff, 0, dix, diy, c)
        aux[p, c] = val
        aux[p, 3 + 3 * c] = dx * ddu * dud_x
        aux[p, 4 + 3 * c] = dy * ddv * dvd_y
        aux[p, 5 + 3 * c] = dx * ddu * dud_z
    us, vs, dus_x, dus_z, dvs_y = _dir_uv(r0, r1, r2)
    six, siy, sdu, sdv = _env_coords(us, vs, spec.shape[1], spec.shape[2])
    nk = spec.shape[0]
    siz, gz = _clip(rg * (nk - 1), nk)
    z0 = int(math.floor(siz))
    fz = siz - z0
    for c in range(3):
        a, ax, ay = _bilerp(spec, z0, six, siy, c)
        bv, bx, by = 0.0, 0.0, 0.0
        if z0 + 1 < nk:
            bv, bx, by = _bilerp(spec, z0 + 1, six, siy, c)
        lsx = ((1.0 - fz) * ax + fz * bx) * sdu
        lsy = ((1.0 - fz) * ay + fz * by) * sdv
        aux[p, 12 + c] = (1.0 - fz) * a + fz * bv
        aux[p, 15 + 3 * c] = lsx * dus_x
        aux[p, 16 + 3 * c] = lsy * dvs_y
        aux[p, 17 + 3 * c] = lsx * dus_z
        aux[p, 24 + c] = (bv - a) * gz * (nk - 1)
    ns = lut.shape[1]
    lix, lgx = _clip(rg * (ns - 1), ns)
    liy, lgy = _clip(ndv * (ns - 1), ns)
    la, lax, lay = _bilerp(lut, 0, lix, liy, 0)
    lb, lbx, lby = _bilerp(lut, 0, lix, liy, 1)
    aux[p, 27] = la
    aux[p, 28] = lb
    aux[p, 29] = lax * lgx * (ns - 1)
    aux[p, 30] = lay * lgy * (ns - 1)
    aux[p, 31] = lbx * lgx * (ns - 1)
    aux[p, 32] = lby * lgy * (ns - 1)


@numba.njit(**_JIT)
def _combine(m, e0, e1, e2, x, p):
    """rgb = ao (kd (1 - metal) Ld + Ls (F0 A + B)) + max(emissive, 0) from the material
    tuple m and the lookups x[p]; also returns the terms the backward reuses."""
    k0, k1, k2, mk0, mk1, mk2, rg, mr, mt, mm, oc, mo, al, ma = m
    km = 1.0 - mt
    f00 = 0.04 * km + mt * k0
    f01 = 0.04 * km + mt * k1
    f02 = 0.04 * km + mt * k2
    la, lb = _f64(x[p, 27]), _f64(x[p, 28])
    d0, d1, d2 = k0 * km * x[p, 0], k1 * km * x[p, 1], k2 * km * x[p, 2]
    sa0, sa1, sa2 = f00 * la + lb, f01 * la + lb, f02 * la + lb
    s0, s1, s2 = x[p, 12] * sa0, x[p, 13] * sa1, x[p, 14] * sa2
    out = (
        oc * (d0 + s0) + max(e0, 0.0),
        oc * (d1 + s1) + max(e1, 0.0),
        oc * (d2 + s2) + max(e2, 0.0),
    )
    return out, (km, f00, f01, f02, d0 + s0, d1 + s1, d2 + s2, sa0, sa1, sa2, la, lb)


@numba.njit(**_PAR)
def _shade_fwd(base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, diff, spec, lut, out, aux):
    """out (P, 4) = shaded RGB + alpha. aux (P, NAUX) receives the lookups and their
    derivatives for the backward; with fewer rows (no backward wanted) it is a scratch row
    per thread (at least NUMBA_NUM_THREADS rows)."""
    store = aux.shape[0] == base.shape[0]
    for p in numba.prange(base.shape[0]):
        m = _material(p, base, rough, metal, ao, alpha)
        _, nv, rf = _frame(p, nts, nrm, tng, view)
        row = np.int64(p) if store else np.int64(numba.get_thread_id())
        _lookups(nv[0], nv[1], nv[2], rf[2], rf[3], rf[4], m[6], nv[7], diff, spec, lut, aux, row)
        rgb, _ = _combine(m, _f64(emis[p, 0]), _f64(emis[p, 1]), _f64(emis[p, 2]), aux, row)
        out[p, 0] = rgb[0]
        out[p, 1] = rgb[1]
        out[p, 2] = rgb[2]
        out[p, 3] = m[12]


@numba.njit(**_PAR)
def _shade_bwd(g, base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, aux, grads):
    """Derivatives of sum(g * out) w.r.t. the seven inputs, written into ``grads``, from the
    inputs and the forward's aux rows (the lookups are not repeated)."""
    g_base, g_rough, g_metal, g_ao, g_emis, g_nts, g_alpha = grads
    for p in numba.prange(base.shape[0]):
        m = _material(p, base, rough, metal, ao, alpha)
        k0, k1, k2, mk0, mk1, mk2, rg, mr, mt, mm, oc, mo, al, ma = m
        tbn, nv, rf = _frame(p, nts, nrm, tng, view)
        t0, t1, t2, b0, b1, b2, gnx, gny, gnz, mapped, sn = tbn
        n0, n1, nz, w0, w1, w2, ndr, ndv, mndv = nv
        s2, rs, r0, r1, r2 = rf
        e0, e1, e2 = _f64(emis[p, 0]), _f64(emis[p, 1]), _f64(emis[p, 2])
        _, cb = _combine(m, e0, e1, e2, aux, p)
        km, f00, f01, f02, ds0, ds1, ds2, sa0, sa1, sa2, la, lb = cb
        x = aux[p]
        ld0, ld1, ld2, ls0, ls1, ls2 = x[0], x[1], x[2], x[12], x[13], x[14]
        o0, o1, o2, oa = _f64(g[p, 0]), _f64(g[p, 1]), _f64(g[p, 2]), _f64(g[p, 3])
        g_alpha[p, 0] = oa * ma
        g_emis[p, 0] = o0 if e0 >= 0.0 else 0.0
        g_emis[p, 1] = o1 if e1 >= 0.0 else 0.0
        g_emis[p, 2] = o2 if e2 >= 0.0 else 0.0
        g_ao[p, 0] = (o0 * ds0 + o1 * ds1 + o2 * ds2) * mo
        q0, q1, q2 = oc * o0, oc * o1, oc * o2  # d/d(diffuse_c) = d/d(specular_c)
        g_base[p, 0] = q0 * (km * ld0 + ls0 * la * mt) * mk0
        g_base[p, 1] = q1 * (km * ld1 + ls1 * la * mt) * mk1
        g_base[p, 2] = q2 * (km * ld2 + ls2 * la * mt) * mk2
        g_base[p, 3] = 0.0
        gm = q0 * (-k0 * ld0 + ls0 * la * (k0 - 0.04))
        gm += q1 * (-k1 * ld1 + ls1 * la * (k1 - 0.04))
        gm += q2 * (-k2 * ld2 + ls2 * la * (k2 - 0.04))
        g_metal[p, 0] = gm * mm
        # gradients of the looked-up values
        gld0, gld1, gld2 = q0 * k0 * km, q1 * k1 * km, q2 * k2 * km
        gls0, gls1, gls2 = q0 * sa0, q1 * sa1, q2 * sa2
        gla = q0 * ls0 * f00 + q1 * ls1 * f01 + q2 * ls2 * f02
        glb = q0 * ls0 + q1 * ls1 + q2 * ls2
        # roughness: the specular level coordinate and the LUT column
        gr = gls0 * x[24] + gls1 * x[25] + gls2 * x[26] + gla * x[29] + glb * x[31]
        g_rough[p, 0] = gr * mr
        # N.V through the LUT row
        gndr = (gla * x[30] + glb * x[32]) * mndv
        # reflection direction through the specular lookup, then its normalisation
        gr0 = gls0 * x[15] + gls1 * x[18] + gls2 * x[21]
        gr1 = gls0 * x[16] + gls1 * x[19] + gls2 * x[22]
        gr2 = gls0 * x[17] + gls1 * x[20] + gls2 * x[23]
        if s2 >= NORM_EPS2:
            rd = r0 * gr0 + r1 * gr1 + r2 * gr2
            gq0, gq1, gq2 = (gr0 - r0 * rd) / rs, (gr1 - r1 * rd) / rs, (gr2 - r2 * rd) / rs
        else:
            gq0, gq1, gq2 = gr0 / rs, gr1 / rs, gr2 / rs
        gndr += 2.0 * (gq0 * n0 + gq1 * n1 + gq2 * nz)
        # shading normal: diffuse lookup, reflection, N.V
        gn0 = gld0 * x[3] + gld1 * x[6] + gld2 * x[9] + 2.0 * ndr * gq0 + gndr * w0
        gn1 = gld0 * x[4] + gld1 * x[7] + gld2 * x[10] + 2.0 * ndr * gq1 + gndr * w1
        gn2 = gld0 * x[5] + gld1 * x[8] + gld2 * x[11] + 2.0 * ndr * gq2 + gndr * w2
        if mapped:
            nd = n0 * gn0 + n1 * gn1 + nz * gn2
            gv0, gv1, gv2 = (gn0 - n0 * nd) / sn, (gn1 - n1 * nd) / sn, (gn2 - nz * nd) / sn
            g_nts[p, 0] = gv0 * t0 + gv1 * t1 + gv2 * t2
            g_nts[p, 1] = gv0 * b0 + gv1 * b1 + gv2 * b2
            g_nts[p, 2] = gv0 * gnx + gv1 * gny + gv2 * gnz
        else:
            g_nts[p, 0] = 0.0
            g_nts[p, 1] = 0.0
            g_nts[p, 2] = 0.0


# (name, channels) of the per-pixel material inputs, in the kernels' argument order
INPUTS = (
    ("base", 4),
    ("rough", 1),
    ("metal", 1),
    ("ao", 1),
    ("emissive", 3),
    ("normal_ts", 3),
    ("alpha", 1),
)


def _set_threads() -> None:
    limit = numba.config.NUMBA_NUM_THREADS  # type: ignore[attr-defined]  # set at run time
    numba.set_num_threads(max(1, min(torch.get_num_threads(), limit)))


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


@numba.njit(**_INL)
def _encoded_normal(t, p, sx):
    """(v0, v1, v2, |v|^2) of v = (2 t[p] - 1) * (sx, sx, 1): the tangent-space normal an
    encoded normal-map sample stands for, before normalising."""
    v0 = (2.0 * _f64(t[p, 0]) - 1.0) * sx
    v1 = (2.0 * _f64(t[p, 1]) - 1.0) * sx
    v2 = 2.0 * _f64(t[p, 2]) - 1.0
    return v0, v1, v2, v0 * v0 + v1 * v1 + v2 * v2


@numba.njit(**_PAR)
def _decode_fwd(t, sx, out):
    for p in numba.prange(t.shape[0]):
        v0, v1, v2, n2 = _encoded_normal(t, p, sx)
        if n2 > NORMAL_MIN2:
            sn = math.sqrt(max(n2, NORM_EPS2))
            out[p, 0], out[p, 1], out[p, 2] = v0 / sn, v1 / sn, v2 / sn
        else:
            out[p, 0], out[p, 1], out[p, 2] = 0.0, 0.0, 1.0


@numba.njit(**_PAR)
def _decode_bwd(t, sx, g, gt):
    for p in numba.prange(t.shape[0]):
        v0, v1, v2, n2 = _encoded_normal(t, p, sx)
        if n2 > NORMAL_MIN2:
            sn = math.sqrt(max(n2, NORM_EPS2))
            n0, n1, nz = v0 / sn, v1 / sn, v2 / sn
            g0, g1, g2 = _f64(g[p, 0]), _f64(g[p, 1]), _f64(g[p, 2])
            d = n0 * g0 + n1 * g1 + nz * g2
            gt[p, 0] = 2.0 * sx * (g0 - n0 * d) / sn
            gt[p, 1] = 2.0 * sx * (g1 - n1 * d) / sn
            gt[p, 2] = 2.0 * (g2 - nz * d) / sn
        else:
            gt[p, 0], gt[p, 1], gt[p, 2] = 0.0, 0.0, 0.0


class DecodeNormal(torch.autograd.Function):
    """Tangent-space normal from an encoded normal-map sample, as shade.material_inputs
    does it: v = (2 t - 1) * (scale, scale, 1), n = v / |v|, or (0, 0, 1) when |v|^2 <=
    1e-12 (no gradient there). t (P, 3) CPU float32/float64 -> (P, 3)."""

    @staticmethod
    def forward(ctx, t, scale: float):
        t = t.detach().contiguous()
        out = torch.empty_like(t)
        _set_threads()
        _decode_fwd(t.numpy(), float(scale), out.numpy())
        ctx.save_for_backward(t)
        ctx.scale = float(scale)
        return out

    @staticmethod
    def backward(ctx, g):
        (t,) = ctx.saved_tensors
        gt = torch.empty_like(t)
        _set_threads()
        _decode_bwd(t.numpy(), ctx.scale, _np(g.to(t.dtype)), gt.numpy())
        return gt, None


class _AuxPool:
    """Reuses the (P, NAUX) lookup buffers between shading calls: a fresh 80 MB buffer costs
    ~60 ms of page faults per 1024^2 view, a reused one nothing. A buffer comes back to the
    pool only when the last tensor viewing it is freed (after the backward, with the graph),
    so a live buffer is never handed out twice; at most ``keep`` free buffers are kept."""

    def __init__(self, keep: int = 2):
        self.keep = keep
        self.free: list[np.ndarray] = []
        self.lock = threading.Lock()

    def get(self, rows: int, dtype: torch.dtype) -> torch.Tensor:
        np_dtype = np.float64 if dtype == torch.float64 else np.float32
        slab = None
        with self.lock:
            for i, s in enumerate(self.free):
                if s.dtype == np_dtype and rows <= s.shape[0] <= 2 * rows + 4096:
                    slab = self.free.pop(i)
                    break
        if slab is None:
            slab = np.empty((rows, NAUX), np_dtype)
        view = slab[:rows]
        weakref.finalize(view, self._put, slab)  # torch.from_numpy keeps `view` alive
        return torch.from_numpy(view)

    def _put(self, slab: np.ndarray) -> None:
        with self.lock:
            self.free.append(slab)
            del self.free[: -self.keep]

    def clear(self) -> None:
        with self.lock:
            self.free.clear()


AUX_POOL = _AuxPool()


class FusedShade(torch.autograd.Function):
    """(P, 4) RGB + alpha from the seven per-pixel inputs of :data:`INPUTS` (CPU tensors of
    one float dtype) and a constant frame/lighting tuple ``const`` = (nrm (P, 3), tng (P, 4),
    view (P, 3), diffuse map (1, h, w + 2, 3), specular levels (K, h, w + 2, 3), BRDF table
    (1, S, S, 2)) as numpy arrays; differentiable w.r.t. the seven inputs. When a backward
    is possible the forward keeps (P, NAUX) lookup values and derivatives (132 bytes per
    pixel in float32) instead of repeating the lookups."""

    @staticmethod
    def forward(ctx, base, rough, metal, ao, emissive, normal_ts, alpha, const):
        ts = tuple(
            t.detach().contiguous() for t in (base, rough, metal, ao, emissive, normal_ts, alpha)
        )
        grad = any(ctx.needs_input_grad[:7])
        if grad:
            aux = AUX_POOL.get(ts[0].shape[0], base.dtype)
        else:
            aux = torch.empty(numba.config.NUMBA_NUM_THREADS, NAUX, dtype=base.dtype)
        out = torch.empty(base.shape[0], 4, dtype=base.dtype)
        _set_threads()
        _shade_fwd(*(t.numpy() for t in ts), *const, out.numpy(), aux.numpy())
        if grad:
            ctx.save_for_backward(*ts, aux)
            ctx.frame = const[:3]
        return out

    @staticmethod
    def backward(ctx, grad_out):
        *ts, aux = ctx.saved_tensors
        grads = tuple(torch.empty(t.shape, dtype=t.dtype) for t in ts)
        _set_threads()
        _shade_bwd(
            _np(grad_out.to(ts[0].dtype)),
            *(t.numpy() for t in ts),
            *ctx.frame,
            aux.numpy(),
            tuple(g.numpy() for g in grads),
        )
        return (*grads, None)


def light_tables(light, lut: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel views of an EnvLight's prefiltered maps and of the BRDF table: diffuse
    (1, h, w + 2, 3), specular (K, h, w + 2, 3), LUT (1, S, S, 2); float32, no copies."""
    diff = light.diffuse_map.detach().float().contiguous().numpy()[None]
    spec = light.spec_levels.detach().float().contiguous().numpy()
    table = lut.detach().float().cpu().contiguous().numpy()[None]
    return diff, spec, table


def supported(*tensors: torch.Tensor) -> bool:
    """Whether the fused kernels can run on these tensors (CPU, float32/float64)."""
    return all(t.device.type == "cpu" for t in tensors) and all(
        t.dtype in (torch.float32, torch.float64) for t in tensors
    )


def shade_fused(inputs: dict[str, torch.Tensor], nrm, tng, view, light, lut) -> torch.Tensor:
    """(P, 4) linear RGB + alpha of :func:`shade.shade` from ``inputs`` (the dict of
    :func:`shade.material_inputs`: base (P, 4), rough/metal/ao (P, 1), emissive (P, 3),
    normal_ts (P, 3), alpha (P, 1), one float dtype), the G-buffer's nrm (P, 3), tng (P, 4)
    and view (P, 3), an EnvLight and the BRDF table (S, S, 2); differentiable w.r.t. the
    inputs. CPU only."""
    dtype = inputs["base"].dtype
    ts = [inputs[k].to(dtype) for k, _ in INPUTS]
    for (k, c), t in zip(INPUTS, ts, strict=True):
        if t.dim() != 2 or t.shape[1] != c:
            raise ValueError(f"fused shading input {k} must be (P, {c}), got {tuple(t.shape)}")
    const = (_np(nrm), _np(tng), _np(view), *light_tables(light, lut))
    return FusedShade.apply(*ts, const)
