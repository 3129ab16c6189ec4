"""Differentiable PBR shading of a sparse G-buffer (glTF metallic-roughness, split-sum IBL).

Per covered pixel, with material factors multiplying textures as glTF says (a slot without a
texture uses its factor alone)::

    base  = base_color_factor * baseColor(uv)            (linear RGBA; textures given linear)
    rough = roughness_factor * MR.g,  metal = metallic_factor * MR.b    (clamped to [0, 1])
    N     = normalize(T nx + B ny + N_geo nz),  n = (2 t - 1) * (scale, scale, 1), renormalised
    F0    = 0.04 (1 - metal) + metal * base.rgb
    diff  = base.rgb (1 - metal) * env.diffuse(N)
    spec  = env.specular(reflect(-V, N), rough) * (F0 * A + B),  (A, B) = LUT(N.V, rough)
    ao    = 1 + occlusion_strength * (occlusion.r - 1)       multiplies diff AND spec
    rgb   = ao * (diff + spec) + emissive_factor * emissive(uv) * emissive_strength
    alpha = OPAQUE: 1;  MASK: base.a >= alpha_cutoff;  BLEND: base.a

Guards so that no output or gradient is NaN/Inf: safe normalisation with fallbacks (a zero
normal-map vector becomes (0, 0, 1), a degenerate mapped normal becomes the geometric one),
N.V clamped to [1e-4, 1], roughness/metallic/colours clamped to their ranges; the split-sum
tables are finite everywhere (the LUT uses alpha >= ``light.ALPHA_MIN``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch

from .. import runtime
from ..asset.model import DEFAULT_MATERIAL, Material, TextureRef
from ..colour import linear_to_srgb
from .light import EnvLight, brdf_lut, lookup_brdf
from .raster import GBuffer
from .shade_kernels import DecodeNormal, shade_fused, supported
from .texture import gather, prepare

NDOTV_MIN = 1e-4


def safe_normalize(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit vectors along the last axis; zero vectors stay (nearly) zero, gradients finite."""
    return x / (x * x).sum(-1, keepdim=True).clamp_min(eps * eps).sqrt()


def _material(materials, index: int) -> Material:
    if index < 0:
        return DEFAULT_MATERIAL
    if isinstance(materials, Mapping):
        if index not in materials:
            raise ValueError(f"material {index} is used by the mesh but not given to shade()")
        return materials[index]
    if index >= len(materials):
        raise ValueError(f"material {index} is used by the mesh but only {len(materials)} given")
    return materials[index]


class _Sampler:
    """Samples each (image, texcoord, transform, wrap) once per shade() call; the texel taps
    of a (material, texcoord, transform, wrap, map size) are cached on the G-buffer."""

    def __init__(
        self,
        gb: GBuffer,
        textures: Mapping[int, torch.Tensor],
        rows: torch.Tensor | None,
        material: int,
    ):
        self.gb, self.textures, self.rows, self.material = gb, textures, rows, material
        self.memo: dict[tuple, torch.Tensor] = {}

    def __call__(self, ref: TextureRef) -> torch.Tensor:
        key = (ref.image, ref.texcoord, ref.uv_transform, ref.wrap_s, ref.wrap_t)
        if key not in self.memo:
            if ref.image not in self.textures:
                raise ValueError(f"texture image {ref.image} is referenced but not given")
            if ref.texcoord not in self.gb.uv:
                raise ValueError(f"the mesh has no TEXCOORD_{ref.texcoord} for image {ref.image}")
            tex = self.textures[ref.image]
            if tex.dim() != 3:
                raise ValueError(f"texture {ref.image} must be (H, W, C), got {tuple(tex.shape)}")
            h, w = int(tex.shape[0]), int(tex.shape[1])
            tkey = ("taps", self.material, key[1:], h, w, tex.device, tex.dtype == torch.float64)
            taps = self.gb.derived().get(tkey)
            if taps is None:
                uv = self.gb.uv[ref.texcoord]
                uv = uv if self.rows is None else uv[self.rows]
                if tex.dtype == torch.float64:
                    uv = uv.double()
                taps = prepare(uv.to(tex.device), h, w, ref)
                self.gb.derived()[tkey] = taps
            self.memo[key] = gather(tex, *taps)
        return self.memo[key]


def _channels(t: torch.Tensor, n: int, fill: float) -> torch.Tensor:
    """(P, C) -> (P, n): drop extra channels, pad missing ones (grey -> RGB replicated)."""
    c = t.shape[1]
    if c >= n:
        return t[:, :n]
    if c == 1 and n >= 3:
        t = t.expand(-1, 3)
        c = 3
    if c == 2 and n >= 3:  # grey + alpha
        t = torch.cat([t[:, :1].expand(-1, 3), t[:, 1:2]], 1)
        c = 4
        return t[:, :n]
    pad = torch.full((t.shape[0], n - c), fill, dtype=t.dtype, device=t.device)
    return torch.cat([t, pad], 1)


def material_inputs(
    gb: GBuffer,
    materials: Sequence[Material] | Mapping[int, Material],
    textures: Mapping[int, torch.Tensor],
    dtype: torch.dtype = torch.float32,
    *,
    fused_decode: bool = False,
) -> dict[str, torch.Tensor]:
    """Per-pixel material values for every covered pixel: ``base`` (P, 4) linear RGBA,
    ``rough``/``metal``/``ao`` (P, 1), ``emissive`` (P, 3) (already times strength),
    ``normal_ts`` (P, 3) decoded unit tangent-space normal, ``alpha`` (P, 1) after the
    material's alpha mode (OPAQUE 1, MASK step at the cutoff, BLEND base alpha).
    ``fused_decode``: decode normal maps with :class:`shade_kernels.DecodeNormal` (one numba
    pass each way, CPU) instead of the torch ops; the same values."""
    P = gb.num_pixels
    dev = gb.device
    fields = {
        "base": 4,
        "rough": 1,
        "metal": 1,
        "ao": 1,
        "emissive": 3,
        "normal_ts": 3,
        "alpha": 1,
    }
    parts: dict[str, list] = {k: [] for k in fields}
    rows_all = []
    groups = gb.derived().get("material_rows")
    if groups is None:  # [(material index, pixel rows or None for all)], cached per view
        mats = gb.mat if gb.mat is not None else torch.full((P,), -1, device=dev)
        ids = torch.unique(mats).tolist()
        if len(ids) == 1:
            groups = [(int(ids[0]), None)]
        else:
            groups = [(int(i), torch.nonzero(mats == i).squeeze(1)) for i in ids]
        gb.derived()["material_rows"] = groups
    for m_idx, rows in groups:
        n = P if rows is None else rows.numel()
        mat = _material(materials, m_idx)
        smp = _Sampler(gb, textures, rows, m_idx)

        def const(vals, n=n):
            return torch.tensor(vals, dtype=dtype, device=dev).expand(n, len(vals))

        def scaled(factors, tex):  # factor * texture, skipping a multiplication by ones
            if all(float(f) == 1.0 for f in factors):
                return tex
            return tex * torch.tensor(factors, dtype=dtype, device=dev)

        if mat.base_color is not None:
            base = scaled(mat.base_color_factor, _channels(smp(mat.base_color).to(dtype), 4, 1.0))
        else:
            base = const(mat.base_color_factor)
        if mat.metallic_roughness is not None:
            mr = _channels(smp(mat.metallic_roughness).to(dtype), 3, 0.0)
            rough = scaled((mat.roughness_factor,), mr[:, 1:2])
            metal = scaled((mat.metallic_factor,), mr[:, 2:3])
        else:
            rough = const((mat.roughness_factor,))
            metal = const((mat.metallic_factor,))
        ao = const((1.0,))
        if mat.occlusion is not None:
            occ = smp(mat.occlusion).to(dtype)[:, :1]
            ao = (
                occ if mat.occlusion_strength == 1.0 else 1.0 + mat.occlusion_strength * (occ - 1.0)
            )
        emis_f = tuple(float(e) * mat.emissive_strength for e in mat.emissive_factor)
        if mat.emissive is not None and any(f != 0.0 for f in emis_f):
            emis = scaled(emis_f, _channels(smp(mat.emissive).to(dtype), 3, 0.0))
        else:
            emis = const(emis_f)
        if mat.alpha_mode == "BLEND":
            alpha = base[:, 3:4]
        elif mat.alpha_mode == "MASK":
            alpha = (base[:, 3:4] >= mat.alpha_cutoff).to(dtype)
        else:
            alpha = const((1.0,))
        if mat.normal is not None:
            t = _channels(smp(mat.normal).to(dtype), 3, 1.0)
            s = mat.normal_scale
            if fused_decode and supported(t):
                nts = DecodeNormal.apply(t, s)  # the same arithmetic in one numba pass
            else:
                v = (2.0 * t - 1.0) * torch.tensor([s, s, 1.0], dtype=dtype, device=dev)
                n2 = (v * v).sum(-1, keepdim=True)
                up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=dev).expand_as(v)
                nts = torch.where(n2 > 1e-12, safe_normalize(v), up)
        else:
            nts = const((0.0, 0.0, 1.0))
        for k, val in (
            ("base", base),
            ("rough", rough),
            ("metal", metal),
            ("ao", ao),
            ("emissive", emis),
            ("normal_ts", nts),
            ("alpha", alpha),
        ):
            parts[k].append(val)
        rows_all.append(torch.arange(P, device=dev) if rows is None else rows)
    if len(rows_all) == 1:  # the common case: no scatter needed
        return {k: v[0] for k, v in parts.items()}
    order = torch.cat(rows_all)
    return {
        k: torch.zeros(P, c, dtype=dtype, device=dev).index_copy(0, order, torch.cat(parts[k]))
        for k, c in fields.items()
    }


def perturb_normal(gb: GBuffer, normal_ts: torch.Tensor) -> torch.Tensor:
    """World-space shading normal (P, 3) from a unit tangent-space normal (P, 3) and the
    G-buffer's TBN (B = w * cross(N, T)); falls back to the interpolated normal when the
    mapped one is degenerate."""
    nrm = gb.nrm.to(normal_ts.dtype)
    tng = gb.tng.to(normal_ts.dtype)
    t = tng[:, :3]
    b = tng[:, 3:4] * torch.cross(nrm, t, dim=-1)
    v = t * normal_ts[:, 0:1] + b * normal_ts[:, 1:2] + nrm * normal_ts[:, 2:3]
    n2 = (v * v).sum(-1, keepdim=True)
    return torch.where(n2 > 1e-12, safe_normalize(v), nrm)


def shade_terms(
    gb: GBuffer,
    materials: Sequence[Material] | Mapping[int, Material],
    textures: Mapping[int, torch.Tensor],
    light: EnvLight,
    lut: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The separate terms of :func:`shade`: ``diffuse``, ``specular`` (both before occlusion),
    ``ao`` (P, 1), ``emissive`` (P, 3), ``rgb`` = ao (diffuse + specular) + emissive,
    ``alpha`` (P, 1), and the shading ``normal`` (P, 3)."""
    dtype = next(iter(textures.values())).dtype if textures else torch.float32
    return terms_of(gb, material_inputs(gb, materials, textures, dtype), light, lut)


def terms_of(
    gb: GBuffer, m: dict[str, torch.Tensor], light: EnvLight, lut: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    """:func:`shade_terms` from the material inputs ``m`` (:func:`material_inputs`)."""
    dtype = m["base"].dtype
    base = m["base"].clamp(0.0, 1.0)
    kd = base[:, :3]
    rough = m["rough"].clamp(0.0, 1.0)
    metal = m["metal"].clamp(0.0, 1.0)
    ao = m["ao"].clamp(0.0, 1.0)
    n = perturb_normal(gb, m["normal_ts"])
    assert gb.view is not None, "shading needs the G-buffer's view directions"
    v = gb.view.to(dtype)
    n_dot_v_raw = (n * v).sum(-1, keepdim=True)
    n_dot_v = n_dot_v_raw.clamp(NDOTV_MIN, 1.0)
    r = safe_normalize(2.0 * n_dot_v_raw * n - v)
    f0 = 0.04 * (1.0 - metal) + metal * kd
    diffuse = kd * (1.0 - metal) * light.diffuse(n)
    a, b = lookup_brdf(brdf_lut() if lut is None else lut, n_dot_v, rough)
    specular = light.specular(r, rough) * (f0 * a + b)
    emissive = m["emissive"].clamp_min(0.0)
    alpha = m["alpha"].clamp(0.0, 1.0)
    return {
        "diffuse": diffuse,
        "specular": specular,
        "ao": ao,
        "emissive": emissive,
        "rgb": ao * (diffuse + specular) + emissive,
        "alpha": alpha,
        "normal": n,
    }


def use_fused(gb: GBuffer, textures: Mapping[int, torch.Tensor], light: EnvLight) -> bool:
    """Whether :func:`shade` takes the fused CPU kernels (:mod:`shade_kernels`): everything on
    the CPU in float32/float64 and the runtime's ``shade_reference`` off
    (``$PBRSR_SHADE_REFERENCE`` unset or 0)."""
    if runtime.current().shade_reference:
        return False
    return gb.device.type == "cpu" and light.device.type == "cpu" and supported(*textures.values())


def shade(
    gb: GBuffer,
    materials: Sequence[Material] | Mapping[int, Material],
    textures: Mapping[int, torch.Tensor],
    light: EnvLight,
    lut: torch.Tensor | None = None,
    *,
    reference: bool = False,
) -> torch.Tensor:
    """(P, 4) linear RGB radiance + alpha per covered pixel of ``gb`` (see the module doc).

    ``materials``: a list indexed by material index (or a dict); index -1 is glTF's default
    material. ``textures``: image index -> (H, W, C) tensor (colour maps linear, normal maps
    encoded in [0, 1]); differentiable w.r.t. every texture. ``lut``: the BRDF table
    (default :func:`light.brdf_lut`). On the CPU the per-pixel shading runs as one fused
    numba pass forward and one backward (:mod:`shade_kernels`, equal to the torch path to
    rounding); ``reference=True`` (or the runtime's ``shade_reference``) forces the torch path
    of :func:`shade_terms`, which is also the path on CUDA."""
    dtype = next(iter(textures.values())).dtype if textures else torch.float32
    if gb.num_pixels == 0:
        return torch.zeros(0, 4, dtype=dtype, device=gb.device)
    fused = not reference and use_fused(gb, textures, light)
    m = material_inputs(gb, materials, textures, dtype, fused_decode=fused)
    return shade_inputs(gb, m, light, lut, fused=fused)


def shade_inputs(
    gb: GBuffer,
    m: dict[str, torch.Tensor],
    light: EnvLight,
    lut: torch.Tensor | None = None,
    *,
    fused: bool,
) -> torch.Tensor:
    """:func:`shade` from the material inputs ``m`` (:func:`material_inputs`, with
    ``fused_decode=fused``): the textures sampled once serve several lights. ``fused``: the
    fused CPU kernels (as :func:`use_fused` decides), else the torch path."""
    if fused:
        return shade_fused(m, gb.nrm, gb.tng, gb.view, light, brdf_lut() if lut is None else lut)
    t = terms_of(gb, m, light, lut)
    return torch.cat([t["rgb"], t["alpha"]], 1)


def to_image(
    gb: GBuffer, values: torch.Tensor, background: float | torch.Tensor = 0.0
) -> torch.Tensor:
    """Scatter per-pixel ``values`` (P, C) into an (H, W, C) image over ``background`` (a
    number, a (C,) colour or an (H, W, C) image); differentiable w.r.t. ``values``."""
    h, w = gb.resolution
    c = values.shape[1]
    bg = torch.as_tensor(background, dtype=values.dtype, device=values.device)
    flat = bg.reshape(h * w, c) if bg.dim() == 3 else None
    img = flat if flat is not None else bg.reshape(1, -1).expand(h * w, c).contiguous()
    return img.index_copy(0, gb.pix, values).view(h, w, c)


def tonemap(rgb: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Linear radiance (..., C) -> display sRGB in [0, 1]: ``srgb_oetf(clamp(rgb * exposure,
    0, 1))`` on the first three channels (a 4th, alpha, is clamped and kept linear). Simple
    and invertible below 1, which is what an image prior trained on sRGB photos expects."""
    if rgb.shape[-1] == 4:
        return torch.cat([tonemap(rgb[..., :3], exposure), rgb[..., 3:].clamp(0.0, 1.0)], -1)
    return linear_to_srgb(rgb * exposure)
