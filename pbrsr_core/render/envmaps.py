"""Equirectangular environment maps: geometry, file reading, built-in environments.

An environment is a torch (H, W, 3) float32 tensor of *linear* radiance. Direction <-> image
mapping (y up, as glTF; the same as Poly Haven / Blender HDRIs): ``u = 0.5 + atan2(x, -z) /
(2 pi)`` (the image centre looks down -z), ``v = acos(y) / pi`` (row 0 is the zenith).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InvalidOptions

MAX_RADIANCE = 1.0e7  # larger (and non-finite) values are clamped when reading a file


def dir_to_uv(d: torch.Tensor) -> torch.Tensor:
    """(P, 3) unit directions -> (P, 2) equirect UV in [0, 1]; gradient-safe at the poles."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    pole = (x * x + z * z) < 1e-12
    x = torch.where(pole, torch.full_like(x, 1e-6), x)
    u = 0.5 + torch.atan2(x, -z) / (2.0 * math.pi)
    v = torch.acos(y.clamp(-1.0 + 1e-6, 1.0 - 1e-6)) / math.pi
    return torch.stack([u, v], 1)


def texel_directions(h: int, w: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """(h, w, 3) unit direction of each texel centre."""
    th = (torch.arange(h, dtype=dtype, device=device) + 0.5) * (math.pi / h)
    ph = ((torch.arange(w, dtype=dtype, device=device) + 0.5) / w - 0.5) * (2.0 * math.pi)
    T, P = torch.meshgrid(th, ph, indexing="ij")
    return torch.stack([T.sin() * P.sin(), T.cos(), -T.sin() * P.cos()], -1)


def texel_solid_angles(h: int, w: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """(h, w) solid angle of each texel; they sum to ~4 pi."""
    th = (torch.arange(h, dtype=dtype, device=device) + 0.5) * (math.pi / h)
    return ((2.0 * math.pi / w) * (math.pi / h) * th.sin())[:, None].expand(h, w)


def resize_area(env: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(H, W, C) -> (h, w, C) by area averaging when shrinking, bilinear when growing."""
    if env.shape[0] == h and env.shape[1] == w:
        return env
    x = env.permute(2, 0, 1)[None]
    if h <= env.shape[0] and w <= env.shape[1]:
        y = F.adaptive_avg_pool2d(x, (h, w))
    else:
        y = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)
    return y[0].permute(1, 2, 0).contiguous()


def read_hdr(path: str | Path) -> torch.Tensor:
    """Read an equirectangular ``.hdr``/``.exr`` with OpenImageIO -> (H, W, 3) float32 linear
    radiance (grey maps are replicated, alpha dropped, NaN/negative -> 0, +Inf and values
    over ``MAX_RADIANCE`` clamped)."""
    import OpenImageIO as oiio

    p = Path(path)
    if not p.is_file():
        raise InvalidOptions(f"environment map '{p.name}' does not exist")
    if p.suffix.lower() not in (".hdr", ".exr"):
        raise InvalidOptions(f"environment map '{p.name}' must be a .hdr or .exr file")
    inp = oiio.ImageInput.open(str(p))
    if inp is None:
        raise InvalidOptions(f"environment map '{p.name}' could not be read as an image")
    try:
        spec = inp.spec()
        if spec.width * spec.height > 16384 * 8192:
            raise InvalidOptions(f"environment map '{p.name}' is too large")
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    finally:
        inp.close()
    if pixels is None:
        raise InvalidOptions(f"environment map '{p.name}' could not be decoded")
    a = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    a = a[:, :, :3] if a.shape[2] >= 3 else np.repeat(a[:, :, :1], 3, axis=2)
    a = np.nan_to_num(a, nan=0.0, posinf=MAX_RADIANCE, neginf=0.0)
    return torch.from_numpy(np.clip(a, 0.0, MAX_RADIANCE).copy())


def procedural_sky(h: int = 128, w: int = 256, sun: float = 60.0) -> torch.Tensor:
    """A built-in studio/sky HDR (h, w, 3) with structure, so relighting shows something:
    a blue-to-warm sky gradient, a darker ground, a small warm sun of peak radiance ``sun``
    (elevation 35 deg, toward -z/+x), and two soft rectangular studio panels (left/right)."""
    d = texel_directions(h, w)
    y = d[..., 1]
    zen = torch.tensor([0.35, 0.55, 1.0], dtype=torch.float64)
    hor = torch.tensor([1.0, 0.92, 0.8], dtype=torch.float64)
    gnd = torch.tensor([0.18, 0.15, 0.12], dtype=torch.float64)
    t = y.clamp(0, 1)[..., None] ** 0.5
    sky = hor * (1 - t) + zen * t
    ground = gnd * (1.0 + 0.5 * (1 + y.clamp(-1, 0))[..., None])
    env = torch.where(y[..., None] >= 0, sky, ground)
    e, a = math.radians(35.0), math.radians(40.0)
    s_dir = torch.tensor([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)])
    cos_s = (d * s_dir.double()).sum(-1)
    sun_col = torch.tensor([1.0, 0.9, 0.75], dtype=torch.float64)
    env = env + sun * sun_col * torch.exp((cos_s - 1.0) / 2e-4)[..., None]
    # two studio panels: azimuth bands at +-90 deg, elevations 10..45 deg
    phi = torch.atan2(d[..., 0], -d[..., 2])
    elev = torch.asin(y.clamp(-1, 1))
    for centre, gain in ((math.pi / 2, 4.0), (-math.pi / 2, 2.0)):
        dphi = torch.remainder(phi - centre + math.pi, 2 * math.pi) - math.pi
        box = torch.sigmoid((0.3 - dphi.abs()) * 40) * torch.sigmoid(
            (0.3 - (elev - 0.48).abs()) * 40
        )
        env = env + gain * box[..., None]
    return env.float().contiguous()
