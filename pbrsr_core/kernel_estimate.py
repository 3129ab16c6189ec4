"""Which kernel (``degrade.KERNELS``) made an asset's LR maps, read off the maps themselves:
what ``lr_kernel = "auto"`` runs.

Each kernel leaves its frequency response on the maps it makes: the protocol's Gaussian
halves the power well below the LR Nyquist frequency, an area filter passes more of it and
folds the rest back (aliasing), Lanczos keeps the pass band flat up to near Nyquist. The
content's own spectrum varies far more than those imprints from map to map, so one map tells
the kernel only roughly; the maps of an asset, made by one pipeline, tell it together.

Features (:func:`spectrum_features`): the map's power spectrum along each axis (Welch: Hann-
windowed tiles of :data:`TILE` texels, averaged over tiles and channels), in :data:`BINS`
bands up to the LR Nyquist frequency, as log power relative to the bands at 1/12 to 1/6
cycles per texel. A multinomial logistic regression over them (:class:`KernelClassifier`,
fitted by ``pbrsr kernel fit`` on the training materials of the CC0 texture set, validated
on the held-out ones) gives each map's probabilities; an asset's estimate pools them over
its informative maps (:func:`estimate_kernel`, :func:`pool`), each map's vote bounded.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import runtime
from .degrade import KERNELS
from .errors import InvalidOptions

TILE = 256
"""Side of the Welch tiles (texels); a smaller map is one tile of its own size."""
MIN_SIDE = 64
"""Maps smaller than this on a side tell nothing (every band needs one FFT frequency)."""
BINS = 24
"""Bands of equal width from 0 to the Nyquist frequency (1/2 cycle per texel)."""
FEATURES = BINS - 1
"""The bands above the first."""
REFERENCE = slice(4, 8)
"""The bands the log power is taken relative to (1/12 to 1/6 cycles per texel)."""
MIN_STD = 2.0 / 255.0
"""A map whose values vary less than this (flat or nearly) is left out of the estimate."""
CLIP = 3.0
"""Standardised features are clipped to +-CLIP standard deviations of the training maps'."""
TRUST = 0.9
"""Each map's probabilities are mixed with the uniform, TRUST of them: however sure one map
is, it can outvote the others only by a bounded factor."""
CLASSIFIER = Path(__file__).resolve().parent / "prior" / "weights" / "lr-kernel" / "classifier.json"


def _axis_power(x: torch.Tensor, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(frequencies, mean power) of tiles (T, C, n, n) along ``dim``, Hann-windowed."""
    n = x.shape[dim]
    shape = [1] * x.ndim
    shape[dim] = n
    window = torch.hann_window(n, periodic=False, dtype=x.dtype).view(shape)
    power = torch.fft.rfft(x * window, dim=dim).abs().square()
    dims = [d for d in range(x.ndim) if d != dim]
    return torch.fft.rfftfreq(n).numpy(), power.mean(dim=dims).numpy()


def _tiles(image: np.ndarray) -> torch.Tensor:
    """(T, C, t, t) float64 tiles of an (H, W, C) image, each less its own mean: a grid of
    :data:`TILE`-texel tiles (at most 64, spread evenly), or one square of the shorter side."""
    h, w = image.shape[:2]
    t = min(TILE, h, w)
    ys = np.linspace(0, h - t, max(1, min(8, h // t))).astype(int)
    xs = np.linspace(0, w - t, max(1, min(8, w // t))).astype(int)
    # the tiles cut first, then widened: a large map is never copied whole
    tiles = np.stack([image[y : y + t, x0 : x0 + t] for y in ys for x0 in xs]).astype(np.float64)
    out = torch.from_numpy(tiles).permute(0, 3, 1, 2)
    return out - out.mean(dim=(2, 3), keepdim=True)


def informative(image: np.ndarray) -> bool:
    """Whether a map can tell its kernel: at least :data:`MIN_SIDE` texels on a side, finite,
    and not flat."""
    arr = np.asarray(image)
    return (
        arr.ndim == 3
        and min(arr.shape[:2]) >= MIN_SIDE
        and bool(np.isfinite(arr).all())
        and float(arr.std()) >= MIN_STD
    )


def spectrum_features(image: np.ndarray) -> np.ndarray:
    """(FEATURES,) float64: the log power of an (H, W, C) map in each band above the first,
    less the mean log power of the :data:`REFERENCE` bands (both axes, every channel)."""
    tiles = _tiles(image)
    edges = np.linspace(0.0, 0.5, BINS + 1)
    band = np.zeros(BINS)
    for dim in (2, 3):
        f, p = _axis_power(tiles, dim)
        idx = np.clip(np.searchsorted(edges, f, side="left") - 1, 0, BINS - 1)
        band += np.bincount(idx, weights=p, minlength=BINS) / np.maximum(
            np.bincount(idx, minlength=BINS), 1
        )
    log_power = np.log(band / 2.0 + 1e-20)
    return (log_power - log_power[REFERENCE].mean())[1:]


_FEATURE_SPEC = {
    "tile": TILE,
    "bins": BINS,
    "reference": [REFERENCE.start, REFERENCE.stop],
}


@dataclass(frozen=True)
class KernelClassifier:
    """Multinomial logistic regression over standardised :func:`spectrum_features`."""

    kernels: tuple[str, ...]
    mean: np.ndarray  # (F,)
    std: np.ndarray  # (F,)
    weights: np.ndarray  # (F, K)
    bias: np.ndarray  # (K,)
    meta: dict

    def log_probs(self, features: np.ndarray) -> np.ndarray:
        """(N, K) log-probabilities of each kernel for (N, F) features, each standardised
        feature clipped to :data:`CLIP` (a map unlike any trained on cannot be certain)."""
        z = np.clip((np.atleast_2d(features) - self.mean) / self.std, -CLIP, CLIP)
        z = z @ self.weights + self.bias
        z = z - z.max(axis=1, keepdims=True)
        return z - np.log(np.exp(z).sum(axis=1, keepdims=True))

    def to_json(self) -> dict:
        return {
            "kernels": list(self.kernels),
            "features": _FEATURE_SPEC,
            "mean": self.mean.tolist(),
            "std": self.std.tolist(),
            "weights": self.weights.tolist(),
            "bias": self.bias.tolist(),
            **self.meta,
        }

    @classmethod
    def from_json(cls, data: dict) -> KernelClassifier:
        feats = data.get("features", {})
        if feats != _FEATURE_SPEC:
            raise InvalidOptions(f"kernel classifier made for other features: {feats}")
        kernels = tuple(data["kernels"])
        if not set(kernels) <= set(KERNELS):
            raise InvalidOptions(f"kernel classifier names unknown kernels: {kernels}")
        keys = ("kernels", "features", "mean", "std", "weights", "bias")
        return cls(
            kernels,
            np.asarray(data["mean"], dtype=np.float64),
            np.asarray(data["std"], dtype=np.float64),
            np.asarray(data["weights"], dtype=np.float64),
            np.asarray(data["bias"], dtype=np.float64),
            {k: v for k, v in data.items() if k not in keys},
        )


def load_classifier(path: Path | None = None) -> KernelClassifier:
    """The classifier in ``path``; by default the runtime's (``PBRSR_KERNEL_CLASSIFIER``),
    else the shipped one."""
    if path is None:
        path = runtime.current().kernel_classifier or CLASSIFIER
    try:
        return KernelClassifier.from_json(json.loads(Path(path).read_text(encoding="utf-8")))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InvalidOptions(f"cannot read the kernel classifier {path}: {exc}") from exc


@dataclass(frozen=True)
class KernelEstimate:
    """An asset's estimate: the kernel, its posterior over ``KERNELS`` (:func:`pool` over the
    maps, uniform prior), and how many maps told it; with none, the protocol's kernel.
    ``per_map``: each given map's own probabilities, None for a map that does not vote."""

    kernel: str
    posterior: dict[str, float]
    maps: int
    per_map: tuple[dict[str, float] | None, ...] = ()

    def to_json(self) -> dict:
        return {
            "kernel": self.kernel,
            "estimated": self.maps > 0,
            "maps": self.maps,
            "posterior": {k: round(v, 4) for k, v in self.posterior.items()},
        }


def pool(log_probs: np.ndarray) -> np.ndarray:
    """(K,) the log-likelihood of each kernel for maps of (N, K) log-probabilities, each
    map's probabilities mixed with the uniform (:data:`TRUST`)."""
    k = log_probs.shape[1]
    return np.log((1.0 - TRUST) / k + TRUST * np.exp(log_probs)).sum(axis=0)


def estimate_kernel(
    images: list[np.ndarray], classifier: KernelClassifier | None = None
) -> KernelEstimate:
    """The kernel that most likely made all of ``images`` ((H, W, C) maps in [0, 1], as
    stored), from the informative ones (:func:`informative`)."""
    clf = classifier or load_classifier()
    used = [i for i, im in enumerate(images) if informative(im)]
    if not used:
        uniform = {k: 1.0 / len(clf.kernels) for k in clf.kernels}
        return KernelEstimate("gaussian", uniform, 0, (None,) * len(images))
    log_probs = clf.log_probs(np.stack([spectrum_features(images[i]) for i in used]))
    total = pool(log_probs)
    post = np.exp(total - total.max())
    post /= post.sum()
    per_map: list[dict[str, float] | None] = [None] * len(images)
    for i, row in zip(used, np.exp(log_probs), strict=True):
        per_map[i] = dict(zip(clf.kernels, row.tolist(), strict=True))
    return KernelEstimate(
        clf.kernels[int(np.argmax(total))],
        dict(zip(clf.kernels, post.tolist(), strict=True)),
        len(used),
        tuple(per_map),
    )
