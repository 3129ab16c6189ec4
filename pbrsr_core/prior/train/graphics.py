"""Procedural drawings for colour, data and normal crops: text, rectangles, ellipses and lines.

Game textures carry drawn and modelled content that the CC0 material scans of the training
set seldom show. Colour maps hold labels, decals, panel markings and printed text: hard edges
between flat colours, thin strokes, glyphs (:func:`graphics_crop`). Metallic, roughness and
occlusion maps of modelled parts hold masks and painted regions: flat levels with hard edges
(:func:`data_graphics_crop`). Normal maps baked from a high-poly model hold embossed and
engraved shapes: flat areas, bevelled rims, grooves, raised lettering
(:func:`normal_graphics_crop`). A training run can give a share of its samples to them
(``TrainConfig.graphics``); a drawing is its own HR ground truth, and
with ``--distill`` it needs none. Everything is drawn at twice the crop size and box-filtered
down, so edges are antialiased as a rasterised texture's are; text uses Pillow's built-in
font (the same glyphs on every machine)."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFilter, ImageFont

GLYPHS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-+.%/&#"


def _colour(rng: np.random.Generator) -> tuple[int, int, int]:
    r, g, b = (int(v) for v in rng.integers(0, 256, 3))
    return r, g, b


def _shape(draw: ImageDraw.ImageDraw, rng: np.random.Generator, side: int, fill) -> None:
    """One shape of value ``fill`` at a random place and size (some partly outside): text of
    2-11 glyphs, a rectangle or an ellipse (filled or outlined), or a line."""
    shape = int(rng.integers(4))
    x0, y0 = (int(v) for v in rng.integers(-side // 4, side, 2))
    w, h = (int(v) for v in rng.integers(max(side // 16, 1), max(side // 2, 2), 2))
    stroke = int(rng.integers(1, 9))
    if shape == 0:
        text = "".join(GLYPHS[i] for i in rng.integers(len(GLYPHS), size=int(rng.integers(2, 12))))
        font = ImageFont.load_default(size=int(rng.integers(10, max(side // 3, 11))))
        draw.text((x0, y0), text, fill=fill, font=font)
    elif shape in (1, 2):
        inside = fill if rng.random() < 0.6 else None
        box = [x0, y0, x0 + w, y0 + h]
        if shape == 1:
            draw.rectangle(box, fill=inside, outline=fill, width=stroke)
        else:
            draw.ellipse(box, fill=inside, outline=fill, width=stroke)
    else:
        draw.line([x0, y0, x0 + w, y0 + h], fill=fill, width=stroke)


def graphics_crop(rng: np.random.Generator, patch: int) -> np.ndarray:
    """A (patch, patch, 3) uint8 drawing: a flat background and 3-8 shapes (:func:`_shape`),
    each of one colour."""
    side = 2 * patch
    img = Image.new("RGB", (side, side), _colour(rng))
    draw = ImageDraw.Draw(img)
    for _ in range(int(rng.integers(3, 9))):
        _shape(draw, rng, side, _colour(rng))
    return np.asarray(img.resize((patch, patch), Image.Resampling.BOX), dtype=np.uint8).copy()


def data_graphics_crop(rng: np.random.Generator, patch: int) -> np.ndarray:
    """A (patch, patch, 3) uint8 scalar map, the same in its three channels: a flat level and
    3-8 shapes (:func:`_shape`), each of one level; half of them masks, every level 0 or
    255 (metal masks of modelled parts), the rest of any level (painted roughness and
    occlusion regions)."""
    side = 2 * patch
    binary = rng.random() < 0.5

    def level() -> int:
        return int(rng.integers(2)) * 255 if binary else int(rng.integers(256))

    img = Image.new("L", (side, side), level())
    draw = ImageDraw.Draw(img)
    for _ in range(int(rng.integers(3, 9))):
        _shape(draw, rng, side, level())
    grey = np.asarray(img.resize((patch, patch), Image.Resampling.BOX), dtype=np.uint8)
    return np.repeat(grey[..., None], 3, axis=2).copy()


def normal_graphics_crop(rng: np.random.Generator, patch: int) -> np.ndarray:
    """A (patch, patch, 3) uint8 tangent-space normal map (encoded, OpenGL: +X right, +Y up)
    of a height field: 2-7 shapes (:func:`_shape`), each raised or sunk by its own depth and
    bevelled by a Gaussian blur of its own radius (1 to 8 texels at the drawing's size), on a
    flat plane, at an overall strength drawn log-uniformly (a unit of depth 2-24 texels
    high). The normals are computed at twice the size, averaged down 2x2 and renormalised
    (:func:`height_normals`)."""
    side = 2 * patch
    height = np.zeros((side, side), np.float32)
    for _ in range(int(rng.integers(2, 8))):
        mask = Image.new("L", (side, side), 0)
        _shape(ImageDraw.Draw(mask), rng, side, 255)
        mask = mask.filter(ImageFilter.GaussianBlur(float(rng.uniform(1.0, 8.0))))
        depth = float(rng.uniform(0.3, 1.0)) * (1.0 if rng.random() < 0.6 else -1.0)
        height += depth * np.asarray(mask, np.float32) / 255.0
    strength = float(np.exp(rng.uniform(np.log(2.0), np.log(24.0))))  # texels of height a unit
    n = height_normals(height, strength, down=2)
    return np.clip(np.rint((n + 1.0) * 127.5), 0, 255).astype(np.uint8)


def height_normals(height: np.ndarray, strength: float, down: int = 1) -> np.ndarray:
    """Unit normals (H/down, W/down, 3) of a height field (H, W) whose rows run down the
    image, in the tangent frame of an OpenGL normal map (+X right, +Y up): heights are
    ``strength`` texels a unit, so a slope rising to the right leans the normal left. The
    unnormalised normals are averaged over ``down`` x ``down`` blocks, then normalised."""
    d_row, d_col = np.gradient(height)
    n = np.stack([-d_col * strength, d_row * strength, np.ones_like(d_row)], axis=-1)
    h, w = height.shape[0] // down, height.shape[1] // down
    n = n[: h * down, : w * down].reshape(h, down, w, down, 3).mean(axis=(1, 3))
    return n / np.linalg.norm(n, axis=-1, keepdims=True)
