"""The direct-prior baseline on texture maps (what the paper's image-SR baselines do), and the
bicubic reference on the same terms.

Maps are numpy (H, W, C) float32 in [0, 1] as stored (sRGB for colour maps, encoded normals).
The prior sees three channels at a time:

- colour maps (``base_color``, ``emissive``, kind ``colour``) as the sRGB images they are;
- data maps (``metallic_roughness``/ORM, ``occlusion``, kind ``data``) channel by channel,
  each as a greyscale image (its value in R, G and B; the mean of the result is taken
  back): an ORM image's occlusion, roughness and metallic are unrelated images, and run
  together through a network's colour channels they bleed into each other (pbr-srmd's data
  network on the ToyCar's roughness at x4: +2.85 dB over bicubic packed, +8.87 on its own);
- normal maps (``normal``): the encoded RGB image is upscaled, then decoded (n = 2t - 1),
  z clamped positive; the direction is the upscaled one, the length the input's (|n| of the
  LR map, bicubic-upscaled: :func:`normal_length`), then re-encoded. Shaders normalise after
  sampling, so the length carries no shading; an input stored at |n| < 1 (JPEG, mipmapped
  bakes) keeps its encoding, which is what a map metric compares;
- 1-channel images are replicated to RGB and the mean of the result is taken back; 2-channel
  images are grey + alpha (PNG "LA");
- alpha (the last channel of 2- and 4-channel images) is upscaled on its own with bicubic
  interpolation and kept. Bicubic, not the prior: alpha is coverage, not an image; a
  photo-trained prior sharpens soft cut-out edges into halos, and it would cost one more full
  prior pass per map.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .backproject import back_project
from .base import Prior, TileProgress
from .bicubic import bicubic_upscale

_NORMAL = {"normal"}
_MIN_Z = 1e-3
_LENGTH_RANGE = (1e-3, 1.0)


def map_kind(role: str) -> str:
    """``normal``, ``colour`` or ``data`` for a material role or an already-known kind."""
    if role in _NORMAL:
        return "normal"
    if role in ("base_color", "emissive", "colour", "color"):
        return "colour"
    if role in ("metallic_roughness", "occlusion", "data", "orm"):
        return "data"
    raise ValueError(
        f"unknown map role {role!r}: use base_color, emissive, metallic_roughness, occlusion, "
        "normal (or the kinds colour, data, normal)"
    )


def _as_hwc(pixels: np.ndarray) -> np.ndarray:
    a = np.asarray(pixels)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"a map must be (H, W, C) with C in 1..4, got shape {a.shape}")
    a = np.nan_to_num(a.astype(np.float32, copy=False), nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(a, 0.0, 1.0)


def _split(a: np.ndarray) -> tuple[torch.Tensor, torch.Tensor | None, int]:
    """(H, W, C) -> colour (1, 3, H, W), alpha (1, 1, H, W) or None, colour channel count."""
    t = torch.from_numpy(np.ascontiguousarray(a)).permute(2, 0, 1)[None]
    c = a.shape[2]
    n_colour = 3 if c >= 3 else 1
    colour, alpha = t[:, :n_colour], (t[:, n_colour:] if c in (2, 4) else None)
    if n_colour == 1:
        colour = colour.expand(1, 3, *colour.shape[2:])
    return colour.contiguous(), alpha, n_colour


def _merge(
    rgb: torch.Tensor,
    alpha: torch.Tensor | None,
    n_colour: int,
    kind: str,
    length: torch.Tensor | None = None,
) -> np.ndarray:
    """rgb (1, 3, sH, sW) + alpha (1, 1, sH, sW) -> (sH, sW, C) float32 in [0, 1]; normal
    maps get unit length, or ``length`` (1, 1, sH, sW) where given."""
    if kind == "normal":
        rgb = renormalize_encoded_normals(rgb, length)
    colour = rgb if n_colour == 3 else rgb.mean(dim=1, keepdim=True)
    parts = [colour] if alpha is None else [colour, alpha]
    out = torch.cat(parts, 1).clamp(0.0, 1.0)[0].permute(1, 2, 0)
    return np.ascontiguousarray(out.detach().cpu().numpy(), dtype=np.float32)


def renormalize_encoded_normals(
    t: torch.Tensor, length: torch.Tensor | None = None
) -> torch.Tensor:
    """Encoded tangent-space normals (N, 3, H, W) in [0, 1] -> decoded, z clamped to >= 1e-3,
    unit length (or ``length``, (N, 1, H, W)), re-encoded to [0, 1]. Same shape."""
    n = t * 2.0 - 1.0
    n = torch.cat([n[:, :2], n[:, 2:3].clamp_min(_MIN_Z)], 1)
    # sum of squares, not Tensor.norm(dim=1): torch's strided channel norm is ~30x slower on CPU
    scale = (n * n).sum(1, keepdim=True).clamp_min(1e-24).rsqrt()
    if length is not None:
        scale = scale * length
    return ((n * scale + 1.0) * 0.5).clamp(0.0, 1.0)


def normal_length(lr: torch.Tensor, scale: int) -> torch.Tensor:
    """The length |2t - 1| of encoded normals (N, 3, H, W), bicubic-upscaled by ``scale`` and
    kept in [1e-3, 1] -> (N, 1, sH, sW): the length an upscaled normal map is stored at (never
    longer than unit: longer encodings exist only towards the corners of the cube, and a
    direction moved by the method would leave it)."""
    n = lr * 2.0 - 1.0
    length = (n * n).sum(1, keepdim=True).sqrt()
    return bicubic_upscale(length, scale).clamp(*_LENGTH_RANGE)


def keep_normal_length(hr: np.ndarray, lr: np.ndarray, scale: int) -> np.ndarray:
    """An HR normal map (sH, sW, C) with its directions kept and the length of its LR map
    (H, W, C) (:func:`normal_length`); alpha kept."""
    colour, alpha, n_colour = _split(_as_hwc(hr))
    with torch.inference_mode():
        length = normal_length(_split(_as_hwc(lr))[0], scale)
        return _merge(colour, alpha, n_colour, "normal", length)


def prior_factor(prior: Prior, scale: int, max_scale: int | None) -> int:
    """The factor the prior upscales by when it may do at most ``max_scale`` of ``scale``:
    the largest of its scales that divides ``scale`` and is at most ``max_scale`` or made in
    one pass of its network (``max_scale`` bounds the cost of one pass at the input's size,
    which such a pass has); the full scale when ``max_scale`` is None, no such scale exists,
    or the prior is not a network (bicubic costs the same either way)."""
    if max_scale is None or max_scale >= scale or not prior.is_network:
        return scale
    fits = [f for f in prior.scales if 2 <= f <= max_scale and scale % f == 0]
    fits += [f for f in prior.one_pass_scales if scale % f == 0]
    return max(fits, default=scale)


Wrap = tuple[str | None, str | None]
"""How a map continues past its edges along x (glTF wrapS) and y (wrapT): "repeat",
"mirror", or None (clamped: the edge is a border)."""
WRAP_CONTEXT = 16
"""LR texels of wrapped (or mirrored) context added at a tiling map's edges."""


def with_wrap(fn, pixels: np.ndarray, scale: int, wrap: Wrap | None) -> np.ndarray:
    """``fn(pixels) -> (s*H, s*W, C)`` with the map continued past its edges as ``wrap``
    says, so that a tiling map upscales without a seam where it repeats."""
    a = _as_hwc(pixels)
    h, w = a.shape[:2]
    if wrap is None or wrap == (None, None):
        return fn(a)
    padded = a
    pad = [0, 0]  # x, y
    for axis, how in ((0, wrap[1]), (1, wrap[0])):  # array axis 0 is y (wrapT), 1 is x
        if how is None:
            continue
        n = min(WRAP_CONTEXT, a.shape[axis])
        widths = [(0, 0)] * 3
        widths[axis] = (n, n)
        padded = np.pad(padded, widths, mode="wrap" if how == "repeat" else "symmetric")
        pad[1 - axis] = n
    pad_x, pad_y = pad
    out = fn(np.ascontiguousarray(padded))
    y0, x0 = pad_y * scale, pad_x * scale
    return np.ascontiguousarray(out[y0 : y0 + h * scale, x0 : x0 + w * scale])


def fill_transparent(colour: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Colour (H, W, C) with the texels ``visible`` (H, W) does not mark replaced by their
    visible neighbours' (push-pull: an average pyramid of the visible texels, pulled back down
    where a level has none), so that no filter or network smears the colour hidden under
    alpha 0 (often black) into the visible edges."""
    if visible.all() or not visible.any():
        return colour
    c = torch.from_numpy(np.ascontiguousarray(colour, dtype=np.float32)).permute(2, 0, 1)[None]
    w = torch.from_numpy(visible.astype(np.float32))[None, None]
    levels = [(c * w, w)]
    while min(levels[-1][1].shape[-2:]) > 1:
        cw, ww = levels[-1]
        pad = (0, ww.shape[-1] % 2, 0, ww.shape[-2] % 2)
        cw, ww = F.pad(cw, pad, mode="replicate"), F.pad(ww, pad, mode="replicate")
        levels.append((F.avg_pool2d(cw, 2), F.avg_pool2d(ww, 2)))
    cw, ww = levels[-1]
    filled = cw / ww.clamp_min(1e-12)
    for cw, ww in reversed(levels[:-1]):
        up = F.interpolate(filled, size=cw.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(ww > 0, cw / ww.clamp_min(1e-12), up)
    return np.ascontiguousarray(filled[0].permute(1, 2, 0).numpy())


HIDDEN_ALPHA = 0.5 / 255
"""Alpha at or below which a texel is transparent whatever the material."""


BLACK = 2.0 / 255
"""The largest colour value under alpha 0 that still counts as black (premultiplied)."""


def filled_cutout(pixels: np.ndarray, seen_from: float = HIDDEN_ALPHA) -> np.ndarray:
    """A cutout's map (colour + alpha) with the colour of its texels whose alpha is not above
    ``seen_from`` (a MASK material's alphaCutoff: the renderer discards them) filled from the
    ones that are (:func:`fill_transparent`); alpha as it was.

    When the colour under alpha 0 is black, the map's colour is premultiplied by its alpha
    (the edge texels of a cutout resized over black are darkened by it), so the seen texels'
    colour is divided by their alpha first: the fill and every filter then see the leaf's own
    colour at its edges, not a dark rim."""
    a = _as_hwc(pixels)
    n = a.shape[2] - 1
    alpha = a[..., n]
    visible = alpha > seen_from
    if a.shape[2] not in (2, 4) or visible.all():
        return a
    filled = a.copy()
    colour = a[..., :n]
    hidden = alpha <= HIDDEN_ALPHA
    if hidden.any() and float(colour[hidden].max()) <= BLACK:
        straight = colour / np.maximum(alpha, HIDDEN_ALPHA)[..., None]
        colour = np.where(visible[..., None], np.clip(straight, 0.0, 1.0), colour)
    filled[..., :n] = fill_transparent(colour, visible)
    return filled


def restore_hidden(hr: np.ndarray, pixels: np.ndarray, scale: int) -> np.ndarray:
    """``hr`` with the colour the input ``pixels`` had under alpha 0 put back (bicubic)
    where ``hr`` is transparent: what no viewer sees stays what it was."""
    a = _as_hwc(pixels)
    if a.shape[2] not in (2, 4):
        return hr
    n = a.shape[2] - 1
    hidden = hr[..., n] <= HIDDEN_ALPHA
    if hidden.any():
        plain = _bicubic_map(a, "colour" if n == 3 else "data", scale)
        hr = hr.copy()
        hr[hidden, :n] = plain[hidden, :n]
    return hr


def with_cutout(fn, pixels: np.ndarray, scale: int, cutout: float | None) -> np.ndarray:
    """``fn`` on a cutout's map (colour + alpha, a material with alphaMode MASK or BLEND;
    ``cutout``: the alpha up to which its texels are not seen, None: not a cutout) with
    those texels filled first, and the colour under alpha 0 back afterwards
    (:func:`filled_cutout`, :func:`restore_hidden`)."""
    a = _as_hwc(pixels)
    if cutout is None or a.shape[2] not in (2, 4):
        return fn(a)
    return restore_hidden(fn(filled_cutout(a, cutout)), a, scale)


def upscale_map(
    prior: Prior,
    pixels: np.ndarray,
    role: str,
    scale: int,
    *,
    max_prior_scale: int | None = None,
    progress: TileProgress | None = None,
    wrap: Wrap | None = None,
    cutout: float | None = None,
    channels: Sequence[int] | None = None,
) -> np.ndarray:
    """Apply ``prior`` to one stored map. pixels (H, W, C) float32 in [0, 1], C in 1..4;
    ``role`` a material role or kind (see :func:`map_kind`). Returns (s*H, s*W, C) float32
    in [0, 1].

    ``max_prior_scale``: the prior upscales by at most this factor (:func:`prior_factor`),
    bicubic interpolation does the rest, and a back-projecting prior's result is projected
    once more onto the map at the full scale. A network's cost grows with its output's
    pixels: waifu2x-photo's x2 pass on a 512² map costs a sixth of its x4 (two passes).
    ``wrap``: a tiling map's continuation past its edges (:func:`with_wrap`); ``cutout``: a
    cutout's transparent texels filled first (:func:`with_cutout`). ``channels``: of a data
    map, the colour channels the prior runs on (all when None); the others are bicubic's."""

    def run(a: np.ndarray) -> np.ndarray:
        return _upscale_map(prior, a, role, scale, max_prior_scale, progress, channels)

    return with_cutout(lambda a: with_wrap(run, a, scale, wrap), pixels, scale, cutout)


def _upscale_map(prior, pixels, role, scale, max_prior_scale, progress, channels) -> np.ndarray:
    kind = map_kind(role)
    a = _as_hwc(pixels)
    colour, alpha, n_colour = _split(a)
    if kind == "data" and n_colour == 3:
        run = sorted(set(range(3) if channels is None else channels))
        rgb = _channel_by_channel(prior.for_kind(kind), colour, scale, run, max_prior_scale,
                                  progress)  # fmt: skip
    else:
        rgb = upscale_rgb(
            prior.for_kind(kind), colour, scale, max_prior_scale=max_prior_scale, progress=progress
        )
    with torch.inference_mode():
        up_alpha = None if alpha is None else bicubic_upscale(alpha, scale)
        length = normal_length(colour, scale) if kind == "normal" else None
        return _merge(rgb.cpu(), up_alpha, n_colour, kind, length)


def _channel_by_channel(prior, colour, scale, run, max_prior_scale, progress) -> torch.Tensor:
    """A data map's colour channels (1, 3, H, W) -> (1, 3, sH, sW): each channel of ``run``
    through ``prior`` as a greyscale image, one at a time (a run's output is one image's, as
    for a colour map), the others bicubic's; ``progress`` sees the runs as one. A channel of
    ``run`` equal to an earlier one (a grey image is read as three equal channels) takes that
    one's output: the prior runs once on each distinct channel."""
    h, w = colour.shape[-2:]
    with torch.inference_mode():
        if len(run) == 3:
            out = torch.empty(1, 3, h * scale, w * scale)
        else:
            out = bicubic_upscale(colour, scale).clamp_(0.0, 1.0)
    tiles = [0]  # tiles per run, as the prior reports them
    for k, c in enumerate(run):
        same = next((d for d in run[:k] if torch.equal(colour[:, c], colour[:, d])), None)
        if same is not None:
            with torch.inference_mode():
                out[0, c] = out[0, same]
            if progress is not None and tiles[0]:
                progress((k + 1) * tiles[0], len(run) * tiles[0])
            continue
        tick = None
        if progress is not None:

            def tick(done: int, total: int, k: int = k) -> None:
                tiles[0] = total
                progress(k * total + done, len(run) * total)

        up = upscale_rgb(prior, colour[:, c : c + 1].expand(-1, 3, -1, -1), scale,
                         max_prior_scale=max_prior_scale, progress=tick)[0]  # fmt: skip
        with torch.inference_mode():  # the mean of the three, exact where they agree
            out[0, c] = (up[0] + (up[1] - up[0]) / 3 + (up[2] - up[0]) / 3).cpu()
    return out


def upscale_rgb(
    prior: Prior,
    rgb: torch.Tensor,
    scale: int,
    *,
    max_prior_scale: int | None = None,
    progress: TileProgress | None = None,
) -> torch.Tensor:
    """``prior`` on images (N, 3, H, W) in [0, 1] -> (N, 3, s*H, s*W), on their device: the
    prior upscales by :func:`prior_factor`, bicubic interpolation does the rest of the scale,
    and a back-projecting prior's result is then projected onto ``rgb`` at the full scale."""
    factor = prior_factor(prior, scale, max_prior_scale)
    out = prior.upscale(rgb, factor, progress=progress)
    if factor != scale:
        with torch.inference_mode():
            out = bicubic_upscale(out, scale // factor).clamp_(0.0, 1.0)
            if prior.back_project:
                out = back_project(out, rgb, scale)
        out = out.clone()  # outside inference mode, as Prior.upscale returns
    return out


def bicubic_map(
    pixels: np.ndarray,
    role: str,
    scale: int,
    wrap: Wrap | None = None,
    cutout: float | None = None,
) -> np.ndarray:
    """Bicubic upscaling of one stored map with the same conventions as :func:`upscale_map`
    (every channel interpolated, clamped; normal maps at the input's length; ``wrap``,
    ``cutout``). pixels (H, W, C) -> (s*H, s*W, C) float32 in [0, 1]."""
    if not isinstance(scale, int) or scale < 1:
        raise ValueError(f"scale must be a positive integer, got {scale!r}")

    def run(a: np.ndarray) -> np.ndarray:
        return with_wrap(lambda b: _bicubic_map(b, role, scale), a, scale, wrap)

    return with_cutout(run, pixels, scale, cutout)


def _bicubic_map(pixels: np.ndarray, role: str, scale: int) -> np.ndarray:
    kind = map_kind(role)
    a = _as_hwc(pixels)
    colour, alpha, n_colour = _split(a)
    with torch.inference_mode():
        rgb = bicubic_upscale(colour, scale).clamp(0.0, 1.0)
        up_alpha = None if alpha is None else bicubic_upscale(alpha, scale)
        length = normal_length(colour, scale) if kind == "normal" else None
        return _merge(rgb, up_alpha, n_colour, kind, length)


_STRIP_HALO = 8
"""LR rows each strip of :func:`project_map` reads beyond its own: the LR model's blur
(radius ceil(3 * 0.375 s) HR texels) and bicubic taps, and the bicubic upsampling of the
residual (2 LR texels), all fit in it, so a strip's rows come out as the whole map's."""


def project_map(
    hr: np.ndarray, lr: np.ndarray, scale: int, role: str, *, strip_rows: int = 128
) -> np.ndarray:
    """One back-projection step (prior/backproject.py) of a stored HR map (sH, sW, C) onto
    its LR map (H, W, C), with the conventions of :func:`upscale_map`: the colour channels
    are projected (normal maps then at the LR map's length), alpha is kept as it is.

    Done in strips of ``strip_rows`` LR rows (plus a halo), so its temporaries are a strip's,
    not the map's: several full-size copies of a 4096² map were the peak memory of a
    1024 -> 4096 run."""
    h = lr.shape[0]
    if hr.shape[0] != h * scale or h <= strip_rows + 2 * _STRIP_HALO:
        return _project_whole(hr, lr, scale, role)
    out: np.ndarray | None = None
    for y0 in range(0, h, strip_rows):
        y1 = min(h, y0 + strip_rows)
        a, b = max(0, y0 - _STRIP_HALO), min(h, y1 + _STRIP_HALO)
        part = _project_whole(hr[a * scale : b * scale], lr[a:b], scale, role)
        if out is None:  # (sH, sW, C) as the whole map's result, also for a 2-D input
            out = np.empty((hr.shape[0], *part.shape[1:]), dtype=np.float32)
        out[y0 * scale : y1 * scale] = part[(y0 - a) * scale : (y1 - a) * scale]
    assert out is not None  # h > strip_rows: at least one strip
    return out


def _project_whole(hr: np.ndarray, lr: np.ndarray, scale: int, role: str) -> np.ndarray:
    kind = map_kind(role)
    h = _as_hwc(hr)
    colour, alpha, n_colour = _split(h)
    lr_colour = _split(_as_hwc(lr))[0]
    with torch.inference_mode():
        rgb = back_project(colour, lr_colour, scale)
        length = normal_length(lr_colour, scale) if kind == "normal" else None
        return _merge(rgb, alpha, n_colour, kind, length)
