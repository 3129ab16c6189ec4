"""Fused CPU shading: the per-pixel part of :func:`shade.shade` in one numba pass.

:func:`shade.shade_terms` (the reference, and the path on CUDA) is a chain of ~25 pointwise
torch ops plus three ``grid_sample`` lookups per pixel; on a CPU its time goes into memory
traffic of (P, 3) temporaries and autograd bookkeeping. Here the same arithmetic runs once per
pixel in registers: :func:`shade_fused` takes the per-pixel material values that
:func:`shade.material_inputs` produces and the G-buffer frame, and returns the (P, 4) RGB +
alpha; its backward is a second kernel that recomputes the forward of a pixel and returns
the exact derivatives w.r.t. every per-pixel input (autograd chains them back into the
texel-side scatter of ``texture.gather``).

Exactness: every clamp, guard and lookup is the reference's, including what its autograd
does at the edges: ``clamp`` passes the gradient on its closed interval, ``where`` only to
the taken branch, and ``grid_sample`` (bilinear, ``padding_mode="border"``,
``align_corners=True``) gives a zero gradient w.r.t. a coordinate clipped to, or lying
exactly on, the border, treats a tap past the last texel as zero, and its bilinear /
trilinear gradients are the one-sided slopes of the cell ``floor(coordinate)``. The kernels
compute in float64 whatever the input dtype (float32 inputs therefore match the float32
reference to rounding, ~1e-6 relative) and write the input dtype.

Threads: the kernels run on ``min(torch.get_num_threads(), NUMBA_NUM_THREADS)`` numba
threads (numba's OpenMP layer shares the thread count with torch).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

NDOTV_MIN = 1e-4  # = shade.NDOTV_MIN
NORMAL_MIN2 = 1e-12  # a mapped / tangent-space normal with |v|^2 <= this is degenerate
NORM_EPS2 = 1e-24  # safe_normalize's clamp of |v|^2
POLE_MIN2 = 1e-12  # envmaps.dir_to_uv: x^2 + z^2 below this is a pole
POLE_X = 1e-6
ACOS_LIM = 1.0 - 1e-6
INV_2PI = 1.0 / (2.0 * math.pi)
INV_PI = 1.0 / math.pi

_JIT = {"cache": True, "fastmath": False}
_f64 = np.float64  # (numba's float() keeps a float32 a float32)


@numba.njit(**_JIT)
def _clamp01(x):
    """(value, gradient mask) of clamp(x, 0, 1): torch passes the gradient on [0, 1]."""
    if x < 0.0:
        return 0.0, 0.0
    if x > 1.0:
        return 1.0, 0.0
    return x, 1.0


@numba.njit(**_JIT)
def _clip(x, size):
    """grid_sample's border clip of a pixel coordinate to [0, size - 1]: (coordinate,
    gradient); the gradient is zero on and past the border (as in ATen)."""
    hi = size - 1.0
    if x <= 0.0:
        return 0.0, 0.0
    if x >= hi:
        return hi, 0.0
    return x, 1.0


@numba.njit(**_JIT)
def _dir_uv(x, y, z):
    """envmaps.dir_to_uv of one direction: (u, v, du/dx, du/dz, dv/dy)."""
    pole = x * x + z * z < POLE_MIN2
    xe = POLE_X if pole else x
    den = xe * xe + z * z
    u = 0.5 + math.atan2(xe, -z) * INV_2PI
    du_dx = 0.0 if pole else -z / den * INV_2PI
    du_dz = xe / den * INV_2PI
    yc, gy = y, 1.0
    if y < -ACOS_LIM:
        yc, gy = -ACOS_LIM, 0.0
    elif y > ACOS_LIM:
        yc, gy = ACOS_LIM, 0.0
    v = math.acos(yc) * INV_PI
    dv_dy = -gy * INV_PI / math.sqrt(1.0 - yc * yc)
    return u, v, du_dx, du_dz, dv_dy


@numba.njit(**_JIT)
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


@numba.njit(**_JIT)
def _env_coords(u, v, h, wp):
    """Equirect UV -> clipped pixel coordinates of a wrap-padded (h, wp) map and the
    derivatives d(ix)/du, d(iy)/dv (EnvLight._grid_xy + grid_sample, align_corners)."""
    ix, gx = _clip(u * (wp - 2) + 0.5, wp)
    iy, gy = _clip(v * h - 0.5, h)
    return ix, iy, gx * (wp - 2), gy * h


@numba.njit(**_JIT)
def _forward_pixel(p, base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, diff, spec, lut):
    """Everything the forward of pixel p computes, as one flat tuple (outputs first, then the
    intermediates and local derivatives the backward needs)."""
    # -- material values (clamped as in shade_terms) -----------------------------------
    k0, mk0 = _clamp01(_f64(base[p, 0]))
    k1, mk1 = _clamp01(_f64(base[p, 1]))
    k2, mk2 = _clamp01(_f64(base[p, 2]))
    rg, mr = _clamp01(_f64(rough[p, 0]))
    mt, mm = _clamp01(_f64(metal[p, 0]))
    oc, mo = _clamp01(_f64(ao[p, 0]))
    al, ma = _clamp01(_f64(alpha[p, 0]))
    # -- perturbed normal (perturb_normal) -----------------------------------------------
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
    r0, r1, r2 = q0 / rs, q1 / rs, q2 / rs
    # -- lookups: diffuse(n), specular(r, rough), LUT(ndv, rough) -------------------------
    ud, vd, dud_x, dud_z, dvd_y = _dir_uv(n0, n1, nz)
    dix, diy, ddu, ddv = _env_coords(ud, vd, diff.shape[1], diff.shape[2])
    ld0, ldx0, ldy0 = _bilerp(diff, 0, dix, diy, 0)
    ld1, ldx1, ldy1 = _bilerp(diff, 0, dix, diy, 1)
    ld2, ldx2, ldy2 = _bilerp(diff, 0, dix, diy, 2)
    us, vs, dus_x, dus_z, dvs_y = _dir_uv(r0, r1, r2)
    six, siy, sdu, sdv = _env_coords(us, vs, spec.shape[1], spec.shape[2])
    siz, gz = _clip(rg * (spec.shape[0] - 1), spec.shape[0])
    z0 = int(math.floor(siz))
    fz = siz - z0
    z1 = z0 + 1
    has1 = z1 < spec.shape[0]
    ls0 = ls1 = ls2 = 0.0
    lsx = lsy = lsz = 0.0
    lsx0 = lsx1 = lsx2 = lsy0 = lsy1 = lsy2 = lsz0 = lsz1 = lsz2 = 0.0
    for c in range(3):
        a, ax, ay = _bilerp(spec, z0, six, siy, c)
        bv, bx, by = 0.0, 0.0, 0.0
        if has1:
            bv, bx, by = _bilerp(spec, z1, six, siy, c)
        val = (1.0 - fz) * a + fz * bv
        lsx = (1.0 - fz) * ax + fz * bx
        lsy = (1.0 - fz) * ay + fz * by
        lsz = bv - a
        if c == 0:
            ls0, lsx0, lsy0, lsz0 = val, lsx, lsy, lsz
        elif c == 1:
            ls1, lsx1, lsy1, lsz1 = val, lsx, lsy, lsz
        else:
            ls2, lsx2, lsy2, lsz2 = val, lsx, lsy, lsz
    ns = lut.shape[1]
    lix, lgx = _clip(rg * (ns - 1), ns)
    liy, lgy = _clip(ndv * (ns - 1), ns)
    la, lax, lay = _bilerp(lut, 0, lix, liy, 0)
    lb, lbx, lby = _bilerp(lut, 0, lix, liy, 1)
    # -- combine ---------------------------------------------------------------------------
    km = 1.0 - mt
    f00 = 0.04 * km + mt * k0
    f01 = 0.04 * km + mt * k1
    f02 = 0.04 * km + mt * k2
    d0, d1, d2 = k0 * km * ld0, k1 * km * ld1, k2 * km * ld2
    sa0, sa1, sa2 = f00 * la + lb, f01 * la + lb, f02 * la + lb
    s0, s1, s2_ = ls0 * sa0, ls1 * sa1, ls2 * sa2
    e0, e1, e2 = _f64(emis[p, 0]), _f64(emis[p, 1]), _f64(emis[p, 2])
    out0 = oc * (d0 + s0) + max(e0, 0.0)
    out1 = oc * (d1 + s1) + max(e1, 0.0)
    out2 = oc * (d2 + s2_) + max(e2, 0.0)
    return (
        (out0, out1, out2, al),
        (k0, k1, k2, mk0, mk1, mk2, rg, mr, mt, mm, oc, mo, ma, e0, e1, e2),
        (t0, t1, t2, b0, b1, b2, gnx, gny, gnz, mapped, sn, n0, n1, nz, w0, w1, w2, ndr, mndv),
        (s2, rs, r0, r1, r2),
        (ld0, ld1, ld2, ldx0, ldx1, ldx2, ldy0, ldy1, ldy2, ddu, ddv, dud_x, dud_z, dvd_y),
        (ls0, ls1, ls2, lsx0, lsx1, lsx2, lsy0, lsy1, lsy2, lsz0, lsz1, lsz2),
        (sdu, sdv, dus_x, dus_z, dvs_y, gz, spec.shape[0] - 1.0),
        (la, lb, lax, lay, lbx, lby, lgx, lgy, ns - 1.0),
        (km, f00, f01, f02, d0, d1, d2, s0, s1, s2_, sa0, sa1, sa2),
    )


@numba.njit(**_JIT)
def _backward_pixel(p, g, fw, g_base, g_rough, g_metal, g_ao, g_emis, g_nts, g_alpha):
    """Derivatives of sum(g[p] * output[p]) w.r.t. pixel p's inputs, from its forward tuple."""
    _, mat, frame, refl, dif, spc, spc_d, lt, comb = fw
    k0, k1, k2, mk0, mk1, mk2, rg, mr, mt, mm, oc, mo, ma, e0, e1, e2 = mat
    t0, t1, t2, b0, b1, b2, gnx, gny, gnz, mapped, sn, n0, n1, nz, w0, w1, w2, ndr, mndv = frame
    s2, rs, r0, r1, r2 = refl
    ld0, ld1, ld2, ldx0, ldx1, ldx2, ldy0, ldy1, ldy2, ddu, ddv, dud_x, dud_z, dvd_y = dif
    ls0, ls1, ls2, lsx0, lsx1, lsx2, lsy0, lsy1, lsy2, lsz0, lsz1, lsz2 = spc
    sdu, sdv, dus_x, dus_z, dvs_y, gz, kz = spc_d
    la, lb, lax, lay, lbx, lby, lgx, lgy, ks = lt
    km, f00, f01, f02, d0, d1, d2, s0, s1, s2_, sa0, sa1, sa2 = comb
    o0, o1, o2, oa = _f64(g[p, 0]), _f64(g[p, 1]), _f64(g[p, 2]), _f64(g[p, 3])
    g_alpha[p, 0] = oa * ma
    g_emis[p, 0] = o0 if e0 >= 0.0 else 0.0
    g_emis[p, 1] = o1 if e1 >= 0.0 else 0.0
    g_emis[p, 2] = o2 if e2 >= 0.0 else 0.0
    g_ao[p, 0] = (o0 * (d0 + s0) + o1 * (d1 + s1) + o2 * (d2 + s2_)) * mo
    q0g, q1g, q2g = oc * o0, oc * o1, oc * o2  # d/d(diffuse_c) = d/d(specular_c)
    g_base[p, 0] = q0g * (km * ld0 + ls0 * la * mt) * mk0
    g_base[p, 1] = q1g * (km * ld1 + ls1 * la * mt) * mk1
    g_base[p, 2] = q2g * (km * ld2 + ls2 * la * mt) * mk2
    g_base[p, 3] = 0.0
    gm = q0g * (-k0 * ld0 + ls0 * la * (k0 - 0.04))
    gm += q1g * (-k1 * ld1 + ls1 * la * (k1 - 0.04))
    gm += q2g * (-k2 * ld2 + ls2 * la * (k2 - 0.04))
    g_metal[p, 0] = gm * mm
    # gradients of the looked-up values
    gld0, gld1, gld2 = q0g * k0 * km, q1g * k1 * km, q2g * k2 * km
    gls0, gls1, gls2 = q0g * sa0, q1g * sa1, q2g * sa2
    gla = q0g * ls0 * f00 + q1g * ls1 * f01 + q2g * ls2 * f02
    glb = q0g * ls0 + q1g * ls1 + q2g * ls2
    # roughness: the specular level coordinate and the LUT column
    gr = (gls0 * lsz0 + gls1 * lsz1 + gls2 * lsz2) * gz * kz
    gr += (gla * lax + glb * lbx) * lgx * ks
    g_rough[p, 0] = gr * mr
    # N.V through the LUT row
    gndr = (gla * lay + glb * lby) * lgy * ks * mndv
    # reflection direction through the specular lookup
    gu = (gls0 * lsx0 + gls1 * lsx1 + gls2 * lsx2) * sdu
    gv = (gls0 * lsy0 + gls1 * lsy1 + gls2 * lsy2) * sdv
    gr0, gr1, gr2 = gu * dus_x, gv * dvs_y, gu * dus_z
    if s2 >= NORM_EPS2:
        rd = r0 * gr0 + r1 * gr1 + r2 * gr2
        gq0, gq1, gq2 = (gr0 - r0 * rd) / rs, (gr1 - r1 * rd) / rs, (gr2 - r2 * rd) / rs
    else:
        gq0, gq1, gq2 = gr0 / rs, gr1 / rs, gr2 / rs
    gndr += 2.0 * (gq0 * n0 + gq1 * n1 + gq2 * nz)
    # shading normal: diffuse lookup, reflection, N.V
    gu = (gld0 * ldx0 + gld1 * ldx1 + gld2 * ldx2) * ddu
    gv = (gld0 * ldy0 + gld1 * ldy1 + gld2 * ldy2) * ddv
    gn0 = gu * dud_x + 2.0 * ndr * gq0 + gndr * w0
    gn1 = gv * dvd_y + 2.0 * ndr * gq1 + gndr * w1
    gn2 = gu * dud_z + 2.0 * ndr * gq2 + gndr * w2
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


@numba.njit(parallel=True, **_JIT)
def _shade_fwd(base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, diff, spec, lut, out):
    for p in numba.prange(base.shape[0]):
        o = _forward_pixel(
            p, base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, diff, spec, lut
        )[0]
        out[p, 0] = o[0]
        out[p, 1] = o[1]
        out[p, 2] = o[2]
        out[p, 3] = o[3]


@numba.njit(parallel=True, **_JIT)
def _shade_bwd(g, base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, diff, spec, lut, grads):
    g_base, g_rough, g_metal, g_ao, g_emis, g_nts, g_alpha = grads
    for p in numba.prange(base.shape[0]):
        fw = _forward_pixel(
            p, base, rough, metal, ao, emis, nts, alpha, nrm, tng, view, diff, spec, lut
        )
        _backward_pixel(p, g, fw, g_base, g_rough, g_metal, g_ao, g_emis, g_nts, g_alpha)


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
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class FusedShade(torch.autograd.Function):
    """(P, 4) RGB + alpha from the seven per-pixel inputs of :data:`INPUTS` (CPU tensors of
    one float dtype) and a constant frame/lighting tuple ``const`` = (nrm (P, 3), tng (P, 4),
    view (P, 3), diffuse map (1, h, w + 2, 3), specular levels (K, h, w + 2, 3), BRDF table
    (1, S, S, 2)) as numpy arrays; differentiable w.r.t. the seven inputs."""

    @staticmethod
    def forward(ctx, base, rough, metal, ao, emissive, normal_ts, alpha, const):
        ts = tuple(
            t.detach().contiguous() for t in (base, rough, metal, ao, emissive, normal_ts, alpha)
        )
        out = torch.empty(base.shape[0], 4, dtype=base.dtype)
        _set_threads()
        _shade_fwd(*(t.numpy() for t in ts), *const, out.numpy())
        ctx.save_for_backward(*ts)
        ctx.const = const
        return out

    @staticmethod
    def backward(ctx, grad_out):
        ins, const = [t.numpy() for t in ctx.saved_tensors], ctx.const
        dtype = ctx.saved_tensors[0].dtype
        grads = tuple(torch.empty(a.shape, dtype=dtype) for a in ins)
        _set_threads()
        _shade_bwd(_np(grad_out.to(dtype)), *ins, *const, tuple(g.numpy() for g in grads))
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
