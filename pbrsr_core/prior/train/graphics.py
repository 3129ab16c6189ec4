"""Procedural drawings for colour crops: flat-coloured text, rectangles, ellipses and lines.

Game textures carry drawn content (labels, decals, panel markings, printed text) that the
CC0 material photographs of the training set seldom show: hard edges between flat colours,
thin strokes, glyphs. :func:`graphics_crop` draws such a crop from a random generator, so a
training run can give a share of its colour samples to them (``TrainConfig.graphics``):
useful where the target does not need a true HR image, as when a later-pass network learns
its first network's own second pass (``--distill``). Everything is drawn at twice the crop
size and box-filtered down, so edges are antialiased as a rasterised texture's are; text uses
Pillow's built-in font (the same glyphs on every machine)."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

GLYPHS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-+.%/&#"


def _colour(rng: np.random.Generator) -> tuple[int, int, int]:
    r, g, b = (int(v) for v in rng.integers(0, 256, 3))
    return r, g, b


def graphics_crop(rng: np.random.Generator, patch: int) -> np.ndarray:
    """A (patch, patch, 3) uint8 drawing: a flat background and 3-8 shapes (text of 2-11
    glyphs, a rectangle or an ellipse, filled or outlined, or a line), each of one colour,
    at random places and sizes (some partly outside the crop)."""
    side = 2 * patch
    img = Image.new("RGB", (side, side), _colour(rng))
    draw = ImageDraw.Draw(img)
    for _ in range(int(rng.integers(3, 9))):
        colour = _colour(rng)
        shape = int(rng.integers(4))
        x0, y0 = (int(v) for v in rng.integers(-side // 4, side, 2))
        w, h = (int(v) for v in rng.integers(max(side // 16, 1), max(side // 2, 2), 2))
        stroke = int(rng.integers(1, 9))
        if shape == 0:
            text = "".join(
                GLYPHS[i] for i in rng.integers(len(GLYPHS), size=int(rng.integers(2, 12)))
            )
            font = ImageFont.load_default(size=int(rng.integers(10, max(side // 3, 11))))
            draw.text((x0, y0), text, fill=colour, font=font)
        elif shape == 1:
            fill = colour if rng.random() < 0.6 else None
            draw.rectangle([x0, y0, x0 + w, y0 + h], fill=fill, outline=colour, width=stroke)
        elif shape == 2:
            fill = colour if rng.random() < 0.6 else None
            draw.ellipse([x0, y0, x0 + w, y0 + h], fill=fill, outline=colour, width=stroke)
        else:
            draw.line([x0, y0, x0 + w, y0 + h], fill=colour, width=stroke)
    return np.asarray(img.resize((patch, patch), Image.Resampling.BOX), dtype=np.uint8).copy()
