"""Bilinear texture sampling with glTF conventions, differentiable w.r.t. the texels.

UVs follow glTF: (0, 0) is the image's top-left corner, texel (x, y) has its centre at
``((x + 0.5) / W, (y + 0.5) / H)``. ``KHR_texture_transform`` is applied first (row-major 3x3
on ``(u, v, 1)``), then the sampler's wrap modes per axis (REPEAT, CLAMP_TO_EDGE,
MIRRORED_REPEAT). Filtering is always bilinear (no mip maps: the caller picks a render
resolution that matches the texel density, see ``GBuffer.uv_grad``).

Sampling is one gather of the four taps of every point from the flattened texture; the
backward scatters the weighted output gradients into a zero texture (:class:`_Bilinear`).
On the CPU both are numba loops (measured: far cheaper than torch's gather + ``index_add_``,
which materialise a (P, 4, C) temporary); elsewhere plain torch. Non-finite UVs are treated
as 0.
"""

from __future__ import annotations

import numba
import torch

from ..asset.model import CLAMP_TO_EDGE, MIRRORED_REPEAT, REPEAT, TextureRef

UV_LIMIT = 1.0e6  # |u|, |v| beyond this are clamped (keeps float32 texel indices exact)


def apply_uv_transform(uv: torch.Tensor, transform: tuple[float, ...] | None) -> torch.Tensor:
    """(P, 2) -> (P, 2): ``M @ (u, v, 1)`` for a row-major 3x3 ``transform`` (None = id)."""
    if transform is None:
        return uv
    if len(transform) != 9:
        raise ValueError(f"uv_transform must have 9 entries (row-major 3x3), got {len(transform)}")
    m = torch.tensor(transform, dtype=uv.dtype, device=uv.device).view(3, 3)
    return uv @ m[:2, :2].T + m[:2, 2]


def wrap_index(i: torch.Tensor, n: int, mode: int) -> torch.Tensor:
    """Integer texel indices (any shape) wrapped into [0, n) by a glTF wrap ``mode``."""
    if mode == CLAMP_TO_EDGE:
        return i.clamp(0, n - 1)
    if mode == MIRRORED_REPEAT:
        j = torch.remainder(i, 2 * n)
        return torch.where(j >= n, 2 * n - 1 - j, j)
    if mode == REPEAT:
        return torch.remainder(i, n)
    raise ValueError(f"unknown glTF wrap mode {mode}; expected 10497, 33071 or 33648")


def _taps(n: int, coord: torch.Tensor, mode: int) -> tuple[torch.Tensor, ...]:
    """Texel indices (i0, i1) and the weight of i1 along one axis; ``coord`` in [0, 1]."""
    x = coord * n - 0.5
    x0 = torch.floor(x)
    f = x - x0
    i0 = x0.long()
    return wrap_index(i0, n, mode), wrap_index(i0 + 1, n, mode), f


@numba.njit(parallel=True, cache=True)
def _gather4_numba(tex, idx, w, out):
    for p in numba.prange(idx.shape[0]):
        for c in range(tex.shape[1]):
            acc = w[p, 0] * tex[idx[p, 0], c]
            for k in range(1, 4):
                acc += w[p, k] * tex[idx[p, k], c]
            out[p, c] = acc


@numba.njit(cache=True)
def _scatter4_numba(grad_out, idx, w, grad_tex):
    for p in range(idx.shape[0]):  # serial: no write conflicts, one pass over memory
        for k in range(4):
            i = idx[p, k]
            wk = w[p, k]
            for c in range(grad_out.shape[1]):
                grad_tex[i, c] += wk * grad_out[p, c]


def _use_numba(*tensors: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" for t in tensors) and tensors[0].dtype in (
        torch.float32,
        torch.float64,
    )


def gather_torch(tex_flat: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Plain torch forward of the 4-tap gather (the GPU path; the CPU reference)."""
    taps = tex_flat[idx.reshape(-1)].view(idx.shape[0], 4, -1)
    return (taps * w.unsqueeze(-1)).sum(1)


def scatter_torch(grad_out: torch.Tensor, idx: torch.Tensor, w: torch.Tensor, n: int):
    """Plain torch backward of the 4-tap gather: (n, C) texel gradients."""
    c = grad_out.shape[1]
    contrib = (w.unsqueeze(-1) * grad_out.unsqueeze(1)).reshape(-1, c)
    grad = torch.zeros(n, c, dtype=grad_out.dtype, device=grad_out.device)
    return grad.index_add_(0, idx.reshape(-1), contrib)


class _Bilinear(torch.autograd.Function):
    """out[p] = sum_k w[p, k] * tex_flat[idx[p, k]]; idx (P, 4) int64, w (P, 4). On the CPU
    both directions are small numba kernels (one pass over memory, no (P, 4, C) temporary);
    elsewhere plain torch gather / index_add."""

    @staticmethod
    def forward(ctx, tex_flat: torch.Tensor, idx: torch.Tensor, w: torch.Tensor):
        ctx.save_for_backward(idx, w)
        ctx.n_texels = tex_flat.shape[0]
        if _use_numba(tex_flat, idx, w) and w.dtype == tex_flat.dtype:
            out = torch.empty(idx.shape[0], tex_flat.shape[1], dtype=tex_flat.dtype)
            _gather4_numba(
                tex_flat.detach().contiguous().numpy(),
                idx.contiguous().numpy(),
                w.contiguous().numpy(),
                out.numpy(),
            )
            return out
        return gather_torch(tex_flat, idx, w)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        idx, w = ctx.saved_tensors
        grad_tex = None
        if ctx.needs_input_grad[0]:
            if _use_numba(grad_out, idx, w) and w.dtype == grad_out.dtype:
                grad_tex = torch.zeros(ctx.n_texels, grad_out.shape[1], dtype=grad_out.dtype)
                _scatter4_numba(
                    grad_out.contiguous().numpy(),
                    idx.contiguous().numpy(),
                    w.contiguous().numpy(),
                    grad_tex.numpy(),
                )
            else:
                grad_tex = scatter_torch(grad_out, idx, w, ctx.n_texels)
        grad_w = None
        if ctx.needs_input_grad[2]:
            raise RuntimeError("texture.sample is not differentiable w.r.t. UVs")
        return grad_tex, None, grad_w


def prepare(
    uv: torch.Tensor, height: int, width: int, ref: TextureRef | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The texture-independent part of :func:`sample`: flat texel indices ``idx`` (P, 4)
    int64 and bilinear weights ``w`` (P, 4) of ``uv`` (P, 2) for an (height, width)
    texture. A G-buffer never changes, so callers cache this per view and map size."""
    if uv.dim() != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must be (P, 2), got shape {tuple(uv.shape)}")
    if uv.dtype != torch.float64:
        uv = uv.float()
    uv = uv.detach()
    uv = torch.nan_to_num(uv, nan=0.0, posinf=UV_LIMIT, neginf=-UV_LIMIT)
    uv = uv.clamp(-UV_LIMIT, UV_LIMIT)
    wrap_s, wrap_t = REPEAT, REPEAT
    if ref is not None:
        uv = apply_uv_transform(uv, ref.uv_transform)
        uv = torch.nan_to_num(uv, nan=0.0).clamp(-UV_LIMIT, UV_LIMIT)
        wrap_s, wrap_t = ref.wrap_s, ref.wrap_t
    x0, x1, fx = _taps(width, uv[:, 0], wrap_s)
    y0, y1, fy = _taps(height, uv[:, 1], wrap_t)
    idx = torch.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], 1)
    gx, gy = 1.0 - fx, 1.0 - fy
    return idx, torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], 1)


def gather(tex: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(P, C) = sum_k w[:, k] * tex[idx[:, k]] for ``tex`` (H, W, C) and :func:`prepare`'s
    ``idx``/``w``; differentiable w.r.t. ``tex``."""
    if tex.dim() != 3:
        raise ValueError(f"texture must be (H, W, C), got shape {tuple(tex.shape)}")
    h, wd, c = tex.shape
    return _Bilinear.apply(tex.reshape(h * wd, c), idx.to(tex.device), w.to(tex))


def sample(tex: torch.Tensor, uv: torch.Tensor, ref: TextureRef | None = None) -> torch.Tensor:
    """Bilinear lookup of ``tex`` (H, W, C) at ``uv`` (P, 2) -> (P, C), honouring
    ``ref.uv_transform`` and ``ref.wrap_s`` / ``ref.wrap_t`` (``ref=None``: identity,
    REPEAT). Differentiable w.r.t. ``tex`` (not ``uv``)."""
    if tex.dim() != 3:
        raise ValueError(f"texture must be (H, W, C), got shape {tuple(tex.shape)}")
    if tex.dtype == torch.float64:
        uv = uv.double()
    idx, w = prepare(uv.to(tex.device), tex.shape[0], tex.shape[1], ref)
    return gather(tex, idx, w)


def sample_reference(tex: torch.Tensor, uv: torch.Tensor, ref: TextureRef | None = None):
    """Plain per-point Python loop version of :func:`sample` (tests only; tiny inputs)."""
    import math

    h, w, _ = tex.shape
    out = []
    for u, v in uv.tolist():
        if ref is not None and ref.uv_transform is not None:
            m = ref.uv_transform
            u, v = m[0] * u + m[1] * v + m[2], m[3] * u + m[4] * v + m[5]
        ws = ref.wrap_s if ref is not None else REPEAT
        wt = ref.wrap_t if ref is not None else REPEAT
        x, y = u * w - 0.5, v * h - 0.5
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0

        def wr(i, n, mode):
            if mode == CLAMP_TO_EDGE:
                return min(max(i, 0), n - 1)
            if mode == MIRRORED_REPEAT:
                j = i % (2 * n)
                return 2 * n - 1 - j if j >= n else j
            return i % n

        a = wr(x0, w, ws), wr(x0 + 1, w, ws)
        b = wr(y0, h, wt), wr(y0 + 1, h, wt)
        out.append(
            (1 - fx) * (1 - fy) * tex[b[0], a[0]]
            + fx * (1 - fy) * tex[b[0], a[1]]
            + (1 - fx) * fy * tex[b[1], a[0]]
            + fx * fy * tex[b[1], a[1]]
        )
    return torch.stack(out)
