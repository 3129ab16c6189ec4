"""Whole-map operations of the optimiser, each one pass over the texels.

Every optimisation step touches every texel of every HR map several times outside the
renderer (TV, projection to valid ranges, gradient masking); at 2048^2 and above these passes,
not the shading, set the step's time. On CPU tensors each operation here is one fused numba
loop (parallel over rows); on other devices the same numbers come from plain torch ops.

* :func:`tv_loss`: ``sum_T mean|grad_x T| + mean|grad_y T|`` with its gradient computed in the
  same pass (a custom autograd function; the subgradient of ``|0|`` is 0, as torch's).
* :func:`project_`: values into [0, 1], NaN -> 0, normal maps renormalised with z > 0.
* :class:`MapAdam`: Adam with a learning rate per channel, fused with the projection.
* :func:`mask_grad_`: zero non-finite gradient entries and those outside a texel/channel mask.
* :func:`accumulate_map_grad_`: the step's whole-map gradient in one pass: TV's gradient and
  the PBR-consistency gradient (computed at LR size on the pooled map) added to the
  renderer's, then masked.
* :func:`dilate_islands`: pad UV islands ring by ring for mip-mapping at export.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from .losses import MapGroup

_JIT = {"cache": True, "parallel": True}
NORMAL_Z_MIN = 1e-3


def _on_cpu(*ts: torch.Tensor) -> bool:
    return all(t.device.type == "cpu" for t in ts)


def _threads() -> None:
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))


# ---------------------------------------------------------------------------------------------
# TV
# ---------------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _tv_at(t, wx, wy, i, j, c, h, w):
    """TV of texel (i, j, c): its share of the value (differences to the right and below) and
    d TV / d t[i, j, c]."""
    ax, ay = wx[c], wy[c]
    v = t[i, j, c]
    val = 0.0
    g = 0.0
    if j + 1 < w:
        d = t[i, j + 1, c] - v
        val += ax * abs(d)
        g -= ax * np.sign(d)
    if j > 0:
        g += ax * np.sign(v - t[i, j - 1, c])
    if i + 1 < h:
        d = t[i + 1, j, c] - v
        val += ay * abs(d)
        g -= ay * np.sign(d)
    if i > 0:
        g += ay * np.sign(v - t[i - 1, j, c])
    return val, g


@numba.njit(**_JIT)
def _tv_kernel(t, wx, wy, grad):
    h, w, nc = t.shape
    rows = np.zeros(h)
    for i in numba.prange(h):
        acc = 0.0
        for j in range(w):
            for c in range(nc):
                val, g = _tv_at(t, wx, wy, i, j, c, h, w)
                acc += val
                grad[i, j, c] = g
        rows[i] = acc
    return rows.sum()


@numba.njit(**_JIT)
def _step_grad_kernel(t, wx, wy, lam, grad, pool_grad, s, texels, channels):
    h, w, nc = t.shape
    rows = np.zeros(h)
    for i in numba.prange(h):
        acc = 0.0
        for j in range(w):
            keep = texels[i, j]
            for c in range(nc):
                val, g = _tv_at(t, wx, wy, i, j, c, h, w)
                acc += val
                g = lam * g + grad[i, j, c] + pool_grad[i // s, j // s, c]
                if not (keep and channels[c]) or not np.isfinite(g):
                    g = 0.0
                grad[i, j, c] = g
        rows[i] = acc
    return rows.sum()


class _TV(torch.autograd.Function):
    @staticmethod
    def forward(ctx, t, wx, wy):
        x = t.detach().contiguous()
        grad = torch.empty_like(x)
        _threads()
        val = _tv_kernel(x.numpy(), wx.numpy(), wy.numpy(), grad.numpy())
        ctx.save_for_backward(grad)
        return t.new_tensor(val)

    @staticmethod
    def backward(ctx, g):
        (grad,) = ctx.saved_tensors
        return grad * g, None, None


def _tv_weights(shape, groups: list[MapGroup]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel weights of |dx| and |dy| so that the weighted sums are the groups' means."""
    h, w, c = shape
    wx, wy = torch.zeros(c, dtype=torch.float64), torch.zeros(c, dtype=torch.float64)
    for g in groups:
        ch = [k for k in g.channels if k < c]
        if not ch:
            continue
        if w > 1:
            wx[ch] += 1.0 / (h * (w - 1) * len(ch))
        if h > 1:
            wy[ch] += 1.0 / ((h - 1) * w * len(ch))
    return wx, wy


def tv_loss(t: torch.Tensor, groups: list[MapGroup]) -> torch.Tensor:
    """``sum_T mean|grad_x T| + mean|grad_y T|`` over the groups of an (H, W, C) map.

    A 1-pixel-wide map has no differences along that axis and contributes 0 there.
    """
    if t.ndim != 3:
        raise ValueError(f"map must be (H, W, C), got {tuple(t.shape)}")
    if _on_cpu(t):
        wx, wy = _tv_weights(tuple(t.shape), groups)
        return _TV.apply(t, wx.to(t.dtype), wy.to(t.dtype))
    total = t.new_zeros(())
    for g in groups:
        x = t[..., list(g.channels)]
        if x.shape[1] > 1:
            total = total + (x[:, 1:] - x[:, :-1]).abs().mean()
        if x.shape[0] > 1:
            total = total + (x[1:] - x[:-1]).abs().mean()
    return total


def accumulate_map_grad_(
    t: torch.Tensor,
    grad: torch.Tensor,
    groups: list[MapGroup],
    lambda_tv: float,
    pool_grad: torch.Tensor,
    scale: int,
    texels: torch.Tensor,
    channels: torch.Tensor,
) -> float:
    """The optimiser's whole-map gradient pass, in place on ``grad`` (H, W, C) of map ``t``:
    ``grad += lambda_tv * d tv_loss(t, groups) / dt + d L / d AvgPool_s(t)`` (``pool_grad``
    (H/s, W/s, C), the gradient at the pooled map, spread over each s x s block as AvgPool's
    backward does), then :func:`mask_grad_`. Returns ``tv_loss(t, groups)``."""
    wx, wy = _tv_weights(tuple(t.shape), groups)
    pg = pool_grad.detach() / float(scale * scale)
    if _on_cpu(t, grad, pg) and grad.is_contiguous():
        _threads()
        x = t.detach().contiguous()
        return float(
            _step_grad_kernel(
                x.numpy(),
                wx.to(t.dtype).numpy(),
                wy.to(t.dtype).numpy(),
                float(lambda_tv),
                grad.numpy(),
                pg.to(t.dtype).contiguous().numpy(),
                int(scale),
                texels.contiguous().numpy(),
                channels.numpy(),
            )
        )
    x = t.detach().requires_grad_(True)
    with torch.enable_grad():
        tv = tv_loss(x, groups)
        (g_tv,) = torch.autograd.grad(lambda_tv * tv, x, allow_unused=True)
    if g_tv is not None:
        grad.add_(g_tv)
    up = pg.repeat_interleave(scale, 0).repeat_interleave(scale, 1)
    grad.add_(up)
    mask_grad_(grad, texels, channels)
    return float(tv.detach())


# ---------------------------------------------------------------------------------------------
# Projection and gradient masking
# ---------------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _project_texel(t, i, j, nc, normal):
    one, zero, two = np.float32(1.0), np.float32(0.0), np.float32(2.0)  # float32 maps stay float32
    for c in range(nc):
        v = t[i, j, c]
        if not (v >= zero):  # negative or NaN
            v = zero
        elif v > one:
            v = one
        t[i, j, c] = v
    if normal:
        x = t[i, j, 0] * two - one
        y = t[i, j, 1] * two - one
        z = max(t[i, j, 2] * two - one, np.float32(NORMAL_Z_MIN))
        inv = np.float32(0.5) / np.sqrt(x * x + y * y + z * z)
        t[i, j, 0] = min(max(x * inv + np.float32(0.5), zero), one)
        t[i, j, 1] = min(max(y * inv + np.float32(0.5), zero), one)
        t[i, j, 2] = min(max(z * inv + np.float32(0.5), zero), one)


@numba.njit(**_JIT)
def _project_kernel(t, normal):
    h, w, nc = t.shape
    for i in numba.prange(h):
        for j in range(w):
            _project_texel(t, i, j, nc, normal)


@torch.no_grad()
def project_(t: torch.Tensor, is_normal: bool) -> None:
    """In place: values into [0, 1]; for normal maps the decoded n = 2t - 1 gets z >= 1e-3 and
    unit length (a zero-length normal becomes (0, 0, 1)), then is re-encoded. NaN -> 0."""
    normal = bool(is_normal and t.shape[-1] >= 3)
    if _on_cpu(t) and t.ndim == 3 and t.is_contiguous():
        _threads()
        _project_kernel(t.numpy(), normal)
        return
    torch.nan_to_num_(t, nan=0.0, posinf=1.0, neginf=0.0)
    t.clamp_(0.0, 1.0)
    if normal:
        n = t[..., :3] * 2.0 - 1.0
        n[..., 2].clamp_(min=NORMAL_Z_MIN)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        t[..., :3] = (n * 0.5 + 0.5).clamp(0.0, 1.0)


@numba.njit(**_JIT)
def _adam_project_kernel(p, g, m, v, step_c, b1, b2, inv_bc2_sqrt, eps, normal):
    h, w, nc = p.shape
    one = np.float32(1.0)
    for i in numba.prange(h):
        for j in range(w):
            for c in range(nc):
                gi = g[i, j, c]
                mi = b1 * m[i, j, c] + (one - b1) * gi
                vi = b2 * v[i, j, c] + (one - b2) * gi * gi
                m[i, j, c] = mi
                v[i, j, c] = vi
                p[i, j, c] -= step_c[c] * mi / (np.sqrt(vi) * inv_bc2_sqrt + eps)
            _project_texel(p, i, j, nc, normal)


class MapAdam:
    """Adam over the HR maps with a learning rate per channel, fused with :func:`project_`:
    one pass per map reads the map, its gradient and both moments and writes the projected
    map (torch's Adam and a projection pass would read and write the map twice). The update is
    torch's Adam (no weight decay, no amsgrad) to float32 rounding.

    ``channel_lr[i]``: (C,) learning rates of map ``i``'s channels (0 freezes a channel);
    ``normal[i]``: whether map ``i`` is a normal map (projected to unit z > 0 normals)."""

    def __init__(
        self,
        maps: dict[int, torch.Tensor],
        channel_lr: dict[int, torch.Tensor],
        normal: dict[int, bool],
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ):
        self.maps = maps
        self.channel_lr = {i: channel_lr[i].to(torch.float32).cpu() for i in maps}
        self.normal = {i: bool(normal[i] and maps[i].shape[-1] >= 3) for i in maps}
        self.betas, self.eps = betas, eps
        self.m = {i: torch.zeros_like(t) for i, t in maps.items()}
        self.v = {i: torch.zeros_like(t) for i, t in maps.items()}
        self.steps = 0

    @torch.no_grad()
    def step(self) -> None:
        self.steps += 1
        b1, b2 = self.betas
        bc1 = 1.0 - b1**self.steps
        inv_bc2_sqrt = 1.0 / (1.0 - b2**self.steps) ** 0.5
        for i, p in self.maps.items():
            g, m, v = p.grad, self.m[i], self.v[i]
            if g is None:
                g = torch.zeros_like(p)
            step_c = self.channel_lr[i] / bc1
            if _on_cpu(p, g) and all(t.is_contiguous() for t in (p, g, m, v)) and p.ndim == 3:
                _threads()
                f32 = np.float32
                _adam_project_kernel(
                    p.detach().numpy(),
                    g.numpy(),
                    m.numpy(),
                    v.numpy(),
                    step_c.numpy(),
                    f32(b1),
                    f32(b2),
                    f32(inv_bc2_sqrt),
                    f32(self.eps),
                    self.normal[i],
                )
                continue
            m.mul_(b1).add_(g, alpha=1.0 - b1)
            v.mul_(b2).addcmul_(g, g, value=1.0 - b2)
            denom = v.sqrt().mul_(inv_bc2_sqrt).add_(self.eps)
            p.sub_(step_c.to(p.device) * m / denom)
            project_(p, self.normal[i])


@numba.njit(**_JIT)
def _mask_grad_kernel(g, texels, channels):
    h, w, nc = g.shape
    for i in numba.prange(h):
        for j in range(w):
            keep = texels[i, j]
            for c in range(nc):
                v = g[i, j, c]
                if not (keep and channels[c]) or not np.isfinite(v):
                    g[i, j, c] = 0.0


@torch.no_grad()
def mask_grad_(g: torch.Tensor, texels: torch.Tensor, channels: torch.Tensor) -> None:
    """In place on an (H, W, C) gradient: entries that are not finite, or whose texel
    (``texels`` (H, W) bool) or channel (``channels`` (C,) bool) is False, become 0."""
    if _on_cpu(g, texels, channels) and g.is_contiguous():
        _threads()
        _mask_grad_kernel(g.numpy(), texels.contiguous().numpy(), channels.numpy())
        return
    torch.nan_to_num_(g, nan=0.0, posinf=0.0, neginf=0.0)
    g.mul_((texels[..., None] & channels).to(g.dtype))


# ---------------------------------------------------------------------------------------------
# UV-island dilation
# ---------------------------------------------------------------------------------------------


@numba.njit(**_JIT)
def _dilate_kernel(x, stamp, rings):
    h, w, nc = x.shape
    for r in range(1, rings + 1):
        added = 0
        for i in numba.prange(h):
            for j in range(w):
                if stamp[i, j] != -1:
                    continue
                n = 0
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        a, b = i + di, j + dj
                        if 0 <= a < h and 0 <= b < w and 0 <= stamp[a, b] < r:
                            n += 1
                if n == 0:
                    continue
                for c in range(nc):
                    s = 0.0
                    for di in range(-1, 2):
                        for dj in range(-1, 2):
                            a, b = i + di, j + dj
                            if 0 <= a < h and 0 <= b < w and 0 <= stamp[a, b] < r:
                                s += x[a, b, c]
                    x[i, j, c] = s / n
                stamp[i, j] = r
                added += 1
        if added == 0:
            break


def dilate_islands(map_: torch.Tensor | np.ndarray, covered_mask, pixels: int):
    """Pad UV islands: texels outside ``covered_mask`` within ``pixels`` steps of it take the
    mean of the 8-neighbours filled before them, ring by ring, so mipmaps and bilinear
    filtering near island borders do not pull in unrelated texels.

    ``map_`` (H, W, C) numpy or torch (returned in the same type, dtype, device);
    ``covered_mask`` (H, W) bool. Covered texels and texels beyond the padding are unchanged.
    """
    is_np = isinstance(map_, np.ndarray)
    t = torch.from_numpy(np.ascontiguousarray(map_)) if is_np else map_
    if t.ndim != 3:
        raise ValueError(f"map must be (H, W, C), got {tuple(t.shape)}")
    m = np.asarray(
        covered_mask.cpu().numpy() if isinstance(covered_mask, torch.Tensor) else covered_mask,
        dtype=bool,
    )
    if m.shape != tuple(t.shape[:2]):
        raise ValueError(f"mask {m.shape} does not match map {tuple(t.shape[:2])}")
    x = t.detach().cpu().numpy().astype(np.float64)
    stamp = np.where(m, 0, -1).astype(np.int32)
    _threads()
    _dilate_kernel(x, stamp, max(int(pixels), 0))
    out = torch.from_numpy(x).to(t.dtype)
    return out.numpy() if is_np else out.to(t.device)


__all__ = ["accumulate_map_grad_", "dilate_islands", "mask_grad_", "project_", "tv_loss"]
