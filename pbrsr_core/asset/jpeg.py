"""What a JPEG file says about its own compression, and taking part of it back out.

A JPEG texture's pixels are not the values its author made: each 8x8 block of Y, Cb and Cr
was DCT-transformed and every coefficient rounded to a multiple of the file's quantisation
table. PBR-SR holds its HR maps to their LR maps (the PBR-consistency term), so with JPEG
inputs it would reproduce that rounding noise at four times the size.

:func:`quant_tables` reads the tables and each component's sampling factors from the file
(DQT and SOF markers); it returns ``None`` for files it cannot model: Adobe-transformed
(RGB/CMYK stored without YCbCr), or not 1 or 3 components. :func:`deblock` is re-application
of JPEG at shifted block grids (Nosratinia, "Enhancement of JPEG-compressed images by
re-application of JPEG", 2001): the image is compressed again with the file's own tables on
each of the 64 grid offsets and the 64 results are averaged. Components stored at full
resolution take part. On the cabinet's three x4 LR maps (written by ``pbrsr degrade`` at
quality 95) it brings the decoded pixels 1.0-1.4 dB closer to the values that were
compressed, in 0.1 s per 256² map; its effect on PBR-SR is in docs/METHOD.md ("JPEG LR maps
are deblocked first"). Chroma stored at half resolution (4:2:0, as most JPEG maps are
written; 4:2:2) is most of such a file's error, and the re-application does not reach it
(its 8x8 grid is not the image's): it is rebuilt from the deblocked luma instead, fitted as a
linear function of it in small windows (:func:`_chroma_from_luma`; docs/METHOD.md, "Chroma
stored at half resolution").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..filters import box_mean

# zig-zag position -> natural (row-major) index of the 8x8 block
_ZIGZAG = (
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5,
    12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14, 21, 28,
    35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51,
    58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
)  # fmt: skip
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# JFIF (full range) RGB -> YCbCr, rows Y, Cb, Cr
_RGB_TO_YCC = torch.tensor(
    [[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]],
    dtype=torch.float64,
)


@dataclass(frozen=True)
class JpegQuant:
    """The quantisation table (8x8, natural order) of each colour component (Y, Cb, Cr or
    one grey component) of a JPEG file, and whether the component is stored at full
    resolution (its sampling factors are the frame's largest; all True for 4:4:4); ``steps``:
    by how many texels (down, across) each component's samples lie apart ((1, 1) at full
    resolution; (2, 2) for 4:2:0 chroma, (1, 2) for 4:2:2; by default (2, 2) where not
    ``full``)."""

    tables: tuple[np.ndarray, ...]
    full: tuple[bool, ...] = ()
    steps: tuple[tuple[int, int], ...] = ()

    def __post_init__(self) -> None:
        if not self.full:
            object.__setattr__(self, "full", (True,) * len(self.tables))
        if not self.steps:
            object.__setattr__(self, "steps", tuple((1, 1) if f else (2, 2) for f in self.full))


def quant_tables(data: bytes) -> JpegQuant | None:
    """The file's tables, or None when the file is not a JPEG this module models exactly."""
    if data[:2] != b"\xff\xd8":
        return None
    dqt: dict[int, np.ndarray] = {}
    comps: list[tuple[int, int]] | None = None  # (sampling byte, table id) per component
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        body = data[i + 4 : i + 2 + length]
        if marker == 0xDB:
            j = 0
            while j < len(body):
                precision, tid = body[j] >> 4, body[j] & 15
                size = 2 if precision else 1
                raw = body[j + 1 : j + 1 + 64 * size]
                if len(raw) < 64 * size:
                    return None
                zz = [int.from_bytes(raw[k * size : (k + 1) * size], "big") for k in range(64)]
                table = np.zeros(64)
                table[list(_ZIGZAG)] = zz
                dqt[tid] = table.reshape(8, 8)
                j += 1 + 64 * size
        elif marker in _SOF:
            n = body[5] if len(body) > 5 else 0
            if len(body) < 6 + 3 * n:
                return None  # truncated frame header
            comps = [(body[6 + 3 * k + 1], body[6 + 3 * k + 2]) for k in range(n)]
        elif marker == 0xEE and body[:5] == b"Adobe":
            return None  # Adobe APP14: the colour transform is the file's own
        elif marker == 0xDA:  # start of scan: every table and the frame are known
            break
        i += 2 + length
    if not comps or len(comps) not in (1, 3):
        return None  # no frame, or other component counts
    if any(t not in dqt or (dqt[t] <= 0).any() for _, t in comps):
        return None
    h_max, v_max = max(s >> 4 for s, _ in comps), max(s & 15 for s, _ in comps)
    if any(s >> 4 < 1 or s & 15 < 1 or h_max % (s >> 4) or v_max % (s & 15) for s, _ in comps):
        return None  # sampling factors that do not divide the frame's (no libjpeg writes them)
    steps = tuple((v_max // (s & 15), h_max // (s >> 4)) for s, _ in comps)
    full = tuple(step == (1, 1) for step in steps)
    return JpegQuant(tuple(dqt[t] for _, t in comps), full, steps)


def _dct_matrix() -> torch.Tensor:
    n = torch.arange(8, dtype=torch.float64)
    c = torch.cos((2 * n[None, :] + 1) * n[:, None] * math.pi / 16)
    scale = torch.where(n[:, None] == 0, math.sqrt(1 / 8), math.sqrt(2 / 8))
    return c * scale  # orthonormal: rows are the basis functions


_DCT = _dct_matrix()
_YCC_TO_RGB = torch.linalg.inv(_RGB_TO_YCC)


# libjpeg's base tables (JPEG Annex K, natural order), scaled by quality in standard_quant
_ANNEX_K_LUMA = (
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55,
    14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51, 87, 80, 62,
    18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99,
)  # fmt: skip
_ANNEX_K_CHROMA = (
    17, 18, 24, 47, 99, 99, 99, 99, 18, 21, 26, 66, 99, 99, 99, 99,
    24, 26, 56, 99, 99, 99, 99, 99, 47, 66, 99, 99, 99, 99, 99, 99,
) + (99,) * 32  # fmt: skip


def standard_quant(quality: int, subsampled: bool = False) -> JpegQuant:
    """The tables libjpeg (and so Pillow and OpenImageIO) writes at ``quality`` 1..100
    (``jpeg_set_quality``: the Annex K tables scaled by 5000/q percent below 50, 200 - 2q
    from 50); ``subsampled``: chroma stored at half resolution both ways (4:2:0)."""
    q = min(max(int(quality), 1), 100)
    s = 5000 // q if q < 50 else 200 - 2 * q

    def scaled(base: tuple[int, ...]) -> np.ndarray:
        return np.clip((np.array(base) * s + 50) // 100, 1, 255).astype(np.float64).reshape(8, 8)

    luma, chroma = scaled(_ANNEX_K_LUMA), scaled(_ANNEX_K_CHROMA)
    return JpegQuant((luma, chroma, chroma), (True, not subsampled, not subsampled))


def _requantise(img: torch.Tensor, q: torch.Tensor, dy: int = 0, dx: int = 0) -> torch.Tensor:
    """Components (K, H, W) through JPEG's lossy step on the 8x8 grid shifted by (dy, dx):
    DCT of each block (edges replicated), coefficients rounded to multiples of the tables
    ``q`` (K, 1, 1, 8, 8), inverse DCT."""
    k, h, w = img.shape
    d = _DCT.to(img.dtype)
    pad = (dx, (-(w + dx)) % 8, dy, (-(h + dy)) % 8)
    p = F.pad(img[None], pad, mode="replicate")[0]
    ph, pw = p.shape[1:]
    blocks = p.reshape(k, ph // 8, 8, pw // 8, 8).transpose(2, 3)
    coef = d @ blocks @ d.T
    back = d.T @ (torch.round(coef / q) * q) @ d
    return back.transpose(2, 3).reshape(k, ph, pw)[:, dy : dy + h, dx : dx + w]


def _pooled(x: torch.Tensor, step: tuple[int, int]) -> torch.Tensor:
    """(N, 1, H, W) -> the mean over each ``step`` block (the last ones edge-replicated): a
    subsampled component's samples."""
    h, w = x.shape[-2:]
    pad = (0, -w % step[1], 0, -h % step[0])
    return F.avg_pool2d(F.pad(x, pad, mode="replicate"), step)


def _spread(x: torch.Tensor, step: tuple[int, int], h: int, w: int) -> torch.Tensor:
    """Samples (N, 1, h', w') ``step`` texels apart -> (N, 1, h, w), bilinear between the
    sample centres (libjpeg's fancy upsampling for 2x)."""
    up = F.interpolate(x, scale_factor=step, mode="bilinear", align_corners=False)
    return up[..., :h, :w]


def _to_ycc(rgb: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) RGB in 0..255 -> level-shifted YCbCr (every component centred on 0)."""
    y = rgb @ _RGB_TO_YCC.to(rgb.dtype).T
    y[..., 0] -= 128.0
    return y


def _from_ycc(ycc: torch.Tensor) -> torch.Tensor:
    y = ycc.clone()
    y[..., 0] += 128.0
    return y @ _YCC_TO_RGB.to(ycc.dtype).T


def compress(pixels: torch.Tensor, quant: JpegQuant) -> torch.Tensor:
    """RGB images (N, 3, H, W) in [0, 1] and three-component tables, or grey ones (N, 1, H, W)
    and one table -> what a baseline JPEG with ``quant``'s tables decodes them to: 8-bit
    samples (YCbCr for RGB), chroma averaged over 2x2 where the tables say it is subsampled,
    each component's 8x8 DCT blocks quantised, samples rounded to 8 bits again, chroma
    upsampled (the triangle filter of libjpeg's fancy upsampling), RGB in 8-bit steps.
    Subsampled chroma is averaged over its ``steps`` (2x2 for 4:2:0, 1x2 for 4:2:2).
    Matches libjpeg's own encode and decode to within its integer arithmetic
    (tests/core/asset/test_jpeg.py)."""
    ncomp = len(quant.tables)
    if ncomp not in (1, 3) or pixels.shape[1] != ncomp:
        raise ValueError("compress takes RGB images and three tables, or grey ones and one")
    out = []
    for img in pixels.to(torch.float64):
        h, w = img.shape[1:]
        samples = torch.round(img.clamp(0.0, 1.0) * 255.0).permute(1, 2, 0)
        if ncomp == 3:
            ycc = torch.round(_to_ycc(samples)).permute(2, 0, 1)  # 8-bit samples, level-shifted
        else:
            ycc = samples.permute(2, 0, 1) - 128.0
        comps = []
        for c in range(ncomp):
            q = torch.from_numpy(quant.tables[c])[None, None, None]
            if quant.full[c]:
                comps.append(torch.round(_requantise(ycc[c : c + 1], q)[0]).clamp(-128, 127))
                continue
            step = quant.steps[c]
            small = torch.round(_requantise(_pooled(ycc[None, c : c + 1], step)[0], q))
            comps.append(_spread(small.clamp(-128, 127)[None], step, h, w)[0, 0])
        back = _from_ycc(torch.stack(comps, -1)) if ncomp == 3 else comps[0][..., None] + 128.0
        out.append(torch.round(back.clamp(0.0, 255.0)).permute(2, 0, 1) / 255.0)
    return torch.stack(out).to(pixels.dtype)


CHROMA_RADIUS = 1
"""Half-width, in chroma samples, of the windows in which :func:`_chroma_from_luma` fits
chroma to luma (3x3 samples: 6x6 texels of 4:2:0)."""
CHROMA_EPS = 1.0
"""Regularisation of that fit, in squared 8-bit levels: where the luma varies by less than
about a level in a window, the chroma stays the window's mean."""


def _chroma_from_luma(
    luma: torch.Tensor, chroma: torch.Tensor, step: tuple[int, int]
) -> torch.Tensor:
    """A subsampled chroma component (H, W; as the decoder spread it) at full resolution,
    guided by the full-resolution luma (H, W): within each window of samples the chroma is
    fitted as a linear function of the luma (the guided filter's local model, He, Sun and
    Tang 2010, fitted between the luma averaged over each sample's texels and the samples),
    the fits' coefficients averaged and spread to the texels, applied to the luma there, and
    one back-projection step: the difference between the samples and the result's means over
    their texels, spread, added (more steps measured no closer: ORM crops of 20 training
    materials at quality 85, 4:2:0, x4 LR, 36.29 / 36.76 / 36.76 / 36.74 dB for 0 / 1 / 3 /
    10 steps, colour 43.31 / 43.28 / 43.25 / 43.24)."""
    h, w = luma.shape
    lum, chr_ = luma[None, None], chroma[None, None]
    ls, cs = _pooled(lum, step), _pooled(chr_, step)
    r = CHROMA_RADIUS
    ml, mc = box_mean(ls, r), box_mean(cs, r)
    a = (box_mean(ls * cs, r) - ml * mc) / (box_mean(ls * ls, r) - ml * ml + CHROMA_EPS)
    b = mc - a * ml
    out = _spread(box_mean(a, r), step, h, w) * lum + _spread(box_mean(b, r), step, h, w)
    out = out + _spread(cs - _pooled(out, step), step, h, w)
    return out[0, 0]


def deblock(pixels: np.ndarray, quant: JpegQuant) -> np.ndarray:
    """(H, W, C) float32 [0, 1] as decoded -> the same with the block artefacts reduced in
    the components stored at full resolution, and chroma stored more coarsely than the luma
    (4:2:0, 4:2:2) rebuilt at full resolution from the deblocked luma
    (:func:`_chroma_from_luma`). Channels beyond the file's components (expanded grey,
    alpha) follow the first / stay."""
    arr = np.asarray(pixels, dtype=np.float32)
    h, w, c = arr.shape
    ncomp = len(quant.tables)
    if c < ncomp or not any(quant.full):
        return arr.copy()
    sel = [k for k in range(ncomp) if quant.full[k]]
    x = torch.from_numpy(arr[..., :ncomp].astype(np.float64)) * 255.0
    if ncomp == 3:
        x = _to_ycc(x)
    else:
        x[..., 0] -= 128.0  # level shift of the grey component
    q = torch.from_numpy(np.stack([quant.tables[k] for k in sel]))[:, None, None]  # (K,1,1,8,8)
    img = x.permute(2, 0, 1)[sel]  # (K, H, W): the full-resolution components
    acc = torch.zeros_like(img)
    for dy in range(8):
        for dx in range(8):
            acc += _requantise(img, q, dy, dx)
    y = x.clone()
    y[..., sel] = (acc / 64.0).permute(1, 2, 0)
    if ncomp == 3 and quant.full[0]:  # chroma sampled more coarsely: rebuilt from the luma
        for k in (1, 2):
            if not quant.full[k]:
                y[..., k] = _chroma_from_luma(y[..., 0], x[..., k], quant.steps[k])
    if ncomp == 3:
        y = _from_ycc(y)
    else:
        y[..., 0] += 128.0
    out = arr.copy()
    filled = min(c, 3) if ncomp == 1 else ncomp  # grey was expanded to RGB on reading
    out[..., :filled] = (y / 255.0).clamp(0.0, 1.0).to(torch.float32).numpy()
    return out


def stored_as(pixels: np.ndarray, quant: JpegQuant, deblocked: bool) -> np.ndarray:
    """(H, W, C) float32 [0, 1] -> what a JPEG file with ``quant``'s tables and chroma sampling
    decodes the image to (:func:`compress`; a one-component file stores the first channel,
    grey, as the file's reader expands it), then with ``deblocked`` what :func:`deblock`
    makes of that: an image as the pipeline sees a map stored so. Channels beyond the
    file's components stay."""
    arr = np.asarray(pixels, dtype=np.float32)
    ncomp = len(quant.tables)
    if arr.shape[2] < ncomp:
        return arr.copy()
    x = torch.from_numpy(np.ascontiguousarray(arr[..., :ncomp])).permute(2, 0, 1)[None]
    y = compress(x, quant)[0].permute(1, 2, 0).numpy()
    out = arr.copy()
    out[..., : ncomp if ncomp == 3 else min(3, arr.shape[2])] = y
    return deblock(out, quant) if deblocked else out
