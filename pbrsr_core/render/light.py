"""Image-based lighting by the split-sum approximation.

An :class:`EnvLight` holds, precomputed once from an equirectangular radiance map:

* ``diffuse(n)``: the cosine-weighted mean radiance around ``n``,
  ``sum L(l) max(n.l, 0) dw / sum max(n.l, 0) dw`` (= irradiance / pi), a brute-force
  convolution on a 32x64 map. A Lambertian surface of albedo a under it has radiance
  ``a * diffuse(n)`` (white furnace: exactly 1 for a uniform environment of 1).
* ``specular(r, roughness)``: the environment prefiltered with the GGX lobe under the split-sum
  assumption n = v = r (weights ``D(h) max(n.l, 0) dw``, normalised), at ``ROUGHNESS_LEVELS``
  (alpha = roughness^2), stored as one (K, H, W) stack and read trilinearly (direction x
  roughness). Roughness 0 is the (downsampled) environment itself.
* :func:`brdf_lut`: the split-sum BRDF table, ``(A, B)`` with ``int f cos = F0 * A + B`` as a
  function of (NdotV, roughness), integrated by GGX importance sampling with the separable
  Smith GGX G (exact G1) and Schlick's Fresnel. Computed by the code, cached in memory and
  on disk (the runtime's cache folder, :func:`pbrsr_core.runtime.cache_dir`),
  never shipped as a file.

Lookups use ``grid_sample`` so they are differentiable w.r.t. the direction and roughness
(and therefore w.r.t. normal and roughness maps); the environment itself is a constant.
"""

from __future__ import annotations

import hashlib
import math
import os
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .. import runtime
from .envmaps import (
    dir_to_uv,
    procedural_sky,
    read_hdr,
    resize_area,
    texel_solid_angles,
)

ROUGHNESS_LEVELS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
SPECULAR_RES = (128, 256)  # (H, W) of every prefiltered level
DIFFUSE_RES = (32, 64)
ALPHA_MIN = 1e-3
LUT_SIZE = 32
LUT_SAMPLES = 1024
_LUT_VERSION = 2


def ggx_d(n_dot_h: torch.Tensor, alpha: float | torch.Tensor) -> torch.Tensor:
    """GGX / Trowbridge-Reitz normal distribution D(h) for cos = n.h."""
    a2 = alpha * alpha
    c2 = n_dot_h * n_dot_h
    return a2 / (math.pi * (c2 * (a2 - 1.0) + 1.0) ** 2)


def smith_g1(n_dot_x: torch.Tensor, alpha: float | torch.Tensor) -> torch.Tensor:
    """Exact Smith GGX masking G1 for cos = n.x > 0."""
    a2 = alpha * alpha
    return 2.0 * n_dot_x / (n_dot_x + torch.sqrt(a2 + (1.0 - a2) * n_dot_x * n_dot_x))


def _convolve(src: torch.Tensor, out_h: int, weight_fn) -> torch.Tensor:
    """Normalised spherical convolution of the equirect ``src`` (h, w, 3) with a rotationally
    symmetric kernel, onto an ``out_h`` x w map:
    out(n) = sum_l W(n.l) dw_l L(l) / sum_l W(n.l) dw_l.

    For one output row (one polar angle) the kernel depends on the source row and the
    azimuth *difference* only, so each row is a circular convolution along the azimuth, done
    with real FFTs: O(out_h * h * w log w) instead of O(out_h * w * h * w)."""
    h, w = src.shape[:2]
    th_s = (torch.arange(h, dtype=torch.float64) + 0.5) * (math.pi / h)
    th_o = (torch.arange(out_h, dtype=torch.float64) + 0.5) * (math.pi / out_h)
    dphi = torch.arange(w, dtype=torch.float64) * (2.0 * math.pi / w)
    dw = texel_solid_angles(h, w)[:, 0]  # (h,)
    c = (
        th_o.sin()[:, None, None] * th_s.sin()[None, :, None] * dphi.cos()[None, None, :]
        + th_o.cos()[:, None, None] * th_s.cos()[None, :, None]
    )  # (out_h, h, w): cosine between output (row i, column 0) and source (row a, column d)
    k = weight_fn(c.clamp(-1.0, 1.0)) * dw[None, :, None]
    norm = k.sum((1, 2)).clamp_min(1e-300)  # (out_h,)
    kf = torch.fft.rfft(k, dim=2).permute(2, 0, 1)  # (F, out_h, h)
    lf = torch.fft.rfft(src.double(), dim=1).permute(1, 0, 2)  # (F, h, 3)
    kr, ki = kf.real.contiguous(), kf.imag.contiguous()  # real, contiguous bmm: fast on CPU
    lr, li = lf.real.contiguous(), lf.imag.contiguous()
    of = torch.complex(torch.bmm(kr, lr) - torch.bmm(ki, li), torch.bmm(kr, li) + torch.bmm(ki, lr))
    out = torch.fft.irfft(of.permute(1, 0, 2), n=w, dim=1) / norm[:, None, None]
    return out.clamp_min(0.0)


def _pad_wrap(m: torch.Tensor) -> torch.Tensor:
    """(..., H, W, 3) -> (..., H, W + 2, 3) with one wrapped column on each side."""
    return torch.cat([m[..., -1:, :], m, m[..., :1, :]], -2)


_ENV_MEMO: dict[str, EnvLight] = {}


class EnvLight:
    """A distant environment light with split-sum lookups (see the module doc).

    ``radiance`` is the (H, W, 3) linear equirectangular map it was built from (kept at a
    reduced size for backgrounds). Build with :meth:`from_file`, :meth:`procedural`,
    :meth:`uniform` or the constructor; move with :meth:`to`."""

    def __init__(self, radiance: torch.Tensor, name: str = "custom"):
        if radiance.dim() != 3 or radiance.shape[2] != 3:
            raise ValueError(f"radiance must be (H, W, 3), got {tuple(radiance.shape)}")
        env = torch.nan_to_num(radiance.detach().double().cpu(), nan=0.0, posinf=1e7)
        env = env.clamp(0.0, 1e7)
        if env.shape[0] < 4 or env.shape[1] < 8:
            env = resize_area(env, max(4, env.shape[0]), max(8, env.shape[1]))
        self.name = name
        sh, sw = SPECULAR_RES
        base = resize_area(env, min(sh, env.shape[0]), min(sw, env.shape[1]))
        self.radiance = base.float()
        spec, irr = prefiltered(base)
        self.spec_levels = _pad_wrap(spec)  # (K, H, W + 2, 3)
        self.diffuse_map = _pad_wrap(irr)  # (h, w + 2, 3)
        # channel-first layouts for grid_sample
        self._spec_vol = self.spec_levels.permute(3, 0, 1, 2)[None].contiguous()
        self._diff_img = self.diffuse_map.permute(2, 0, 1)[None].contiguous()

    # -- constructors --------------------------------------------------------------------
    @classmethod
    def from_file(cls, path: str | Path) -> EnvLight:
        """From an equirectangular ``.hdr``/``.exr`` (downsampled before prefiltering)."""
        return cls(read_hdr(path), name=Path(path).stem)

    @classmethod
    def procedural(cls) -> EnvLight:
        """The built-in sky/studio environment (:func:`envmaps.procedural_sky`); built once
        per process and shared (an EnvLight is never modified in place)."""
        if "procedural" not in _ENV_MEMO:
            _ENV_MEMO["procedural"] = cls(procedural_sky(), name="procedural")
        return _ENV_MEMO["procedural"]

    @classmethod
    def uniform(cls, value: float | tuple[float, float, float] = 1.0) -> EnvLight:
        """Constant radiance ``value`` (a grey level or an RGB triple) from every direction."""
        v = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
        if v.numel() == 1:
            v = v.expand(3)
        if v.numel() != 3:
            raise ValueError("uniform(value) takes a float or three floats")
        return cls(v.view(1, 1, 3).expand(8, 16, 3).clone(), name="uniform")

    def to(self, device: torch.device | str) -> EnvLight:
        new = object.__new__(EnvLight)
        new.__dict__.update(self.__dict__)
        for k in ("radiance", "spec_levels", "diffuse_map", "_spec_vol", "_diff_img"):
            setattr(new, k, getattr(self, k).to(device))
        return new

    @property
    def device(self) -> torch.device:
        return self._spec_vol.device

    # -- lookups --------------------------------------------------------------------------
    @staticmethod
    def _grid_xy(uv: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Equirect UV -> align_corners=True grid coordinates of the wrap-padded maps."""
        x = (uv[:, 0] * w + 0.5) * (2.0 / (w + 1)) - 1.0
        y = (uv[:, 1] * h - 0.5) * (2.0 / (h - 1)) - 1.0
        return x, y

    def diffuse(self, n: torch.Tensor) -> torch.Tensor:
        """(P, 3) unit normals -> (P, 3) cosine-weighted mean radiance (irradiance / pi)."""
        img = self._diff_img.to(dtype=n.dtype)
        h, w = img.shape[2], img.shape[3] - 2
        x, y = self._grid_xy(dir_to_uv(n), h, w)
        g = torch.stack([x, y], -1).view(1, 1, -1, 2)
        out = F.grid_sample(img, g, mode="bilinear", padding_mode="border", align_corners=True)
        return out[0, :, 0, :].T

    def specular(self, r: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
        """(P, 3) unit reflection directions, (P, 1) roughness in [0, 1] -> (P, 3) GGX-
        prefiltered radiance (linear interpolation between the roughness levels)."""
        vol = self._spec_vol.to(dtype=r.dtype)
        h, w = vol.shape[3], vol.shape[4] - 2
        x, y = self._grid_xy(dir_to_uv(r), h, w)
        z = roughness.reshape(-1).clamp(0.0, 1.0) * 2.0 - 1.0
        g = torch.stack([x, y, z.to(r.dtype)], -1).view(1, 1, 1, -1, 3)
        out = F.grid_sample(vol, g, mode="bilinear", padding_mode="border", align_corners=True)
        return out[0, :, 0, 0, :].T

    def background(self, d: torch.Tensor) -> torch.Tensor:
        """(P, 3) directions -> (P, 3) radiance of the (downsampled) environment."""
        return self.specular(d, torch.zeros(d.shape[0], 1, dtype=d.dtype, device=d.device))


_PREFILTER_VERSION = 1


def prefiltered(base: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The split-sum maps of an equirect radiance map ``base`` (H, W, 3) float64: the GGX
    prefiltered levels (K, H, W, 3) and the cosine-convolved diffuse map (h, w, 3), float32.

    Read from the disk cache (keyed by ``base``'s content, like :func:`brdf_lut`) or
    computed and cached: the convolutions of one light took 0.34 s on this project's 2-core
    AMD CPU, paid twice per process (the job's light and the preview's second one)."""
    base = base.detach().to(torch.float64).contiguous()
    h = hashlib.sha256(repr((_PREFILTER_VERSION, ROUGHNESS_LEVELS, DIFFUSE_RES)).encode())
    h.update(repr(tuple(base.shape)).encode())
    h.update(base.numpy().tobytes())
    path = _cache_dir() / f"envlight_v{_PREFILTER_VERSION}_{h.hexdigest()[:32]}.npz"
    dh, dw = min(DIFFUSE_RES[0], base.shape[0]), min(DIFFUSE_RES[1], base.shape[1])
    shapes = {
        "spec": (len(ROUGHNESS_LEVELS), *base.shape),
        "diffuse": (dh, dw, 3),
    }

    def compute() -> dict[str, np.ndarray]:
        levels = []
        for r in ROUGHNESS_LEVELS:
            if r == 0.0:
                levels.append(base)
                continue
            alpha = max(r * r, ALPHA_MIN)

            def lobe(c, alpha=alpha):
                cos_h = ((1.0 + c).clamp_min(0.0) * 0.5).sqrt()
                return ggx_d(cos_h, alpha) * c.clamp_min(0.0)

            # wide lobes (roughness >= 0.4: >= ~10 degrees) are convolved at half resolution
            src = base
            if r >= 0.4 and base.shape[0] >= 64:
                src = resize_area(base, base.shape[0] // 2, base.shape[1] // 2)
            levels.append(resize_area(_convolve(src, src.shape[0], lobe), *base.shape[:2]))
        irr = _convolve(resize_area(base, dh, dw), dh, lambda c: c.clamp_min(0.0))
        return {
            "spec": torch.stack(levels).float().numpy(),
            "diffuse": irr.float().numpy(),
        }

    arrays = disk_cached(path, compute, shapes)
    return torch.from_numpy(arrays["spec"]), torch.from_numpy(arrays["diffuse"])


def disk_cached(
    path: Path, compute: Callable[[], dict[str, np.ndarray]], shapes: dict[str, tuple]
) -> dict[str, np.ndarray]:
    """Float32 arrays from the ``.npz`` at ``path`` when it holds finite arrays of exactly
    ``shapes``; else ``compute()``, written there atomically (a read-only or missing cache
    folder only costs the computation)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in shapes}
        if all(
            a.dtype == np.float32 and a.shape == shapes[k] and np.isfinite(a).all()
            for k, a in arrays.items()
        ):
            return arrays
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        pass
    arrays = compute()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
        np.savez(tmp, **arrays)  # type: ignore[arg-type]  # numpy's stub: **kwds as allow_pickle
        os.replace(tmp, path)
    except OSError:
        pass
    return arrays


# -- BRDF lookup table ------------------------------------------------------------------
_LUT_MEMO: dict[tuple, torch.Tensor] = {}


def _cache_dir() -> Path:
    """The runtime's cache folder (:func:`pbrsr_core.runtime.cache_dir`), as for prior weights."""
    return runtime.cache_dir()


def _hammersley(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    i = torch.arange(n, dtype=torch.int64)
    rev = torch.zeros(n, dtype=torch.float64)
    bits, scale = i.clone(), 0.5
    for _ in range(32):
        rev += (bits & 1).double() * scale
        bits >>= 1
        scale *= 0.5
    return (i.double() + 0.5) / n, rev


def compute_brdf_lut(size: int = LUT_SIZE, samples: int = LUT_SAMPLES) -> torch.Tensor:
    """(size, size, 2) float32 table of (A, B) at NdotV = max(i / (size - 1), 1e-3) (rows)
    and roughness = j / (size - 1) (columns), alpha = max(roughness^2, ALPHA_MIN): the
    table's corners are the range's ends, so lookups need no extrapolation."""
    nv = torch.linspace(0.0, 1.0, size, dtype=torch.float64).clamp_min(1e-3)
    rough = torch.linspace(0.0, 1.0, size, dtype=torch.float64)
    alpha = (rough * rough).clamp_min(ALPHA_MIN)
    u1, u2 = _hammersley(samples)
    a = alpha[None, :, None]
    # GGX half-vector sampling: cos^2(theta_h) = (1 - u) / (1 + (a^2 - 1) u)
    cos_h = torch.sqrt((1.0 - u1) / (1.0 + (a * a - 1.0) * u1))  # (1, R, S)
    sin_h = torch.sqrt((1.0 - cos_h * cos_h).clamp_min(0.0))
    phi = 2.0 * math.pi * u2
    hx, hz = sin_h * torch.cos(phi), cos_h
    vx = torch.sqrt(1.0 - nv * nv)[:, None, None]
    vz = nv[:, None, None]
    v_dot_h = (vx * hx + vz * hz).clamp_min(0.0)  # (N, R, S)
    l_z = 2.0 * v_dot_h * hz - vz
    valid = l_z > 0.0
    n_dot_l = l_z.clamp_min(1e-12)
    g = smith_g1(vz.expand_as(n_dot_l), a) * smith_g1(n_dot_l, a)
    g_vis = g * v_dot_h / (hz * vz)
    fc = (1.0 - v_dot_h) ** 5
    g_vis = torch.where(valid, g_vis, torch.zeros_like(g_vis))
    A = ((1.0 - fc) * g_vis).mean(-1)
    B = (fc * g_vis).mean(-1)
    return torch.stack([A, B], -1).float()


def brdf_lut(size: int = LUT_SIZE, samples: int = LUT_SAMPLES) -> torch.Tensor:
    """The split-sum BRDF table (see :func:`compute_brdf_lut`), from memory, the disk cache,
    or computed (and cached) on first use. CPU float32 (size, size, 2)."""
    key = (size, samples, _LUT_VERSION)
    if key in _LUT_MEMO:
        return _LUT_MEMO[key]
    path = _cache_dir() / f"brdf_lut_v{_LUT_VERSION}_{size}x{size}_{samples}.npz"
    arrays = disk_cached(
        path, lambda: {"lut": compute_brdf_lut(size, samples).numpy()}, {"lut": (size, size, 2)}
    )
    lut = torch.from_numpy(arrays["lut"])
    _LUT_MEMO[key] = lut
    return lut


def lookup_brdf(lut: torch.Tensor, n_dot_v: torch.Tensor, roughness: torch.Tensor):
    """Bilinear (A, B) from ``lut`` (S, S, 2) at (P, 1) ``n_dot_v`` and ``roughness`` ->
    two (P, 1) tensors; differentiable w.r.t. both inputs, clamped to the table's range."""
    img = lut.permute(2, 0, 1)[None].to(device=n_dot_v.device, dtype=n_dot_v.dtype)
    x = roughness.reshape(-1).clamp(0.0, 1.0) * 2.0 - 1.0  # columns: roughness
    y = n_dot_v.reshape(-1).clamp(0.0, 1.0) * 2.0 - 1.0  # rows: NdotV
    g = torch.stack([x, y], -1).view(1, 1, -1, 2)
    out = F.grid_sample(img, g, mode="bilinear", padding_mode="border", align_corners=True)
    ab = out[0, :, 0, :]
    return ab[0][:, None], ab[1][:, None]
