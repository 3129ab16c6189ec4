"""Fit and validate the LR-kernel classifier (:mod:`pbrsr_core.kernel_estimate`) on a CC0
texture folder: ``pbrsr kernel fit``.

Every map of every material (basecolor, normal, the scalar maps) is made LR at x2 and x4 by
each kernel of ``KERNELS``, stored as 8-bit values; half the (material, scale, kernel) groups
are JPEG-compressed first (quality 70-95, chroma 4:4:4 or 4:2:0), as real assets ship their
maps. The classifier is fitted on the training materials and scored on the held-out ones
(the split of :func:`.data.split_materials`, the priors'): per map, and per group, the maps
of a material made one way pooled as :func:`~pbrsr_core.kernel_estimate.estimate_kernel`
pools an asset's.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ...asset.jpeg import compress, standard_quant
from ...degrade import KERNELS
from ...kernel_estimate import KernelClassifier, informative, pool, spectrum_features
from .data import Material, degrade_pair, load_materials, read_manifest, split_materials

SCALES = (2, 4)
JPEG_QUALITIES = (70, 95)
L2 = 1e-3
"""Weight decay of the logistic regression (on standardised features)."""


def _seed(*parts: object) -> int:
    return int(hashlib.sha256(repr(parts).encode()).hexdigest()[:8], 16)


def samples(materials: list[Material]) -> Iterator[tuple[str, int, np.ndarray]]:
    """(group, kernel index, features) of every informative LR map: a group is one material
    at one scale by one kernel, JPEG-compressed or not as a whole (even odds, seeded by its
    name)."""
    for mat in materials:
        for s in SCALES:
            for ki, kernel in enumerate(KERNELS):
                group = f"{mat.name}@x{s}/{kernel}"
                rng = np.random.default_rng(_seed(group))
                quant = None
                if rng.random() < 0.5:
                    quality = int(rng.integers(JPEG_QUALITIES[0], JPEG_QUALITIES[1] + 1))
                    quant = standard_quant(quality, subsampled=bool(rng.random() < 0.5))
                for key, px in mat.maps.items():
                    hr = torch.from_numpy(px).permute(2, 0, 1)[None].float() / 255.0
                    hr = hr.expand(1, 3, *hr.shape[2:]) if hr.shape[1] == 1 else hr
                    lr = degrade_pair(hr, s, "normal" if key == "normal" else "colour", kernel)
                    if quant is not None:
                        lr = compress(lr, quant)
                    lr8 = (lr[0].permute(1, 2, 0).numpy() * 255.0).round() / 255.0
                    if informative(lr8):
                        yield group, ki, spectrum_features(lr8)


def fit(features: np.ndarray, labels: np.ndarray, meta: dict) -> KernelClassifier:
    """Multinomial logistic regression (L-BFGS, weight decay :data:`L2`) on standardised
    features, deterministic."""
    mean, std = features.mean(0), features.std(0) + 1e-9
    x = torch.from_numpy((features - mean) / std)
    y = torch.from_numpy(labels).long()
    w = torch.zeros(x.shape[1], len(KERNELS), dtype=torch.float64, requires_grad=True)
    b = torch.zeros(len(KERNELS), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], max_iter=500, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = torch.nn.functional.cross_entropy(x @ w + b, y) + L2 * w.square().sum()
        loss.backward()
        return loss

    opt.step(closure)
    return KernelClassifier(
        KERNELS, mean, std, w.detach().numpy().copy(), b.detach().numpy().copy(), meta
    )


def score(clf: KernelClassifier, groups: list[str], labels: np.ndarray, feats: np.ndarray) -> dict:
    """Accuracy and confusion (rows: the kernel that made the maps, columns: the estimate),
    per map and per group (its maps pooled as an asset's are)."""
    lp = clf.log_probs(feats)
    n = len(KERNELS)
    per_map = np.zeros((n, n), int)
    np.add.at(per_map, (labels, lp.argmax(1)), 1)
    rows: dict[str, list[int]] = {}
    for i, g in enumerate(groups):
        rows.setdefault(g, []).append(i)
    per_group = np.zeros((n, n), int)
    for idx in rows.values():
        per_group[labels[idx[0]], int(np.argmax(pool(lp[idx])))] += 1
    return {
        "map_accuracy": round(float(np.trace(per_map) / per_map.sum()), 4),
        "group_accuracy": round(float(np.trace(per_group) / per_group.sum()), 4),
        "map_confusion": per_map.tolist(),
        "group_confusion": per_group.tolist(),
        "maps": int(per_map.sum()),
        "groups": int(per_group.sum()),
    }


def _collect(materials: list[Material]) -> tuple[list[str], np.ndarray, np.ndarray]:
    rows = list(samples(materials))
    if not rows:
        return [], np.zeros(0, int), np.zeros((0, 0))
    groups, labels, feats = zip(*rows, strict=True)
    return list(groups), np.array(labels), np.stack(feats)


def fit_kernel_classifier(root: Path, command: str) -> KernelClassifier:
    """The classifier fitted on the training materials of the texture folder ``root``, its
    held-out scores in ``meta["held_out"]``."""
    manifest = read_manifest(root)
    train_names, held_names = split_materials(manifest)
    _, y_train, x_train = _collect(load_materials(root, train_names, manifest))
    if len(set(y_train.tolist())) < len(KERNELS):
        raise ValueError("too few informative training maps to fit the kernel classifier")
    meta = {
        "command": command,
        "data": f"{root.name}: {len(train_names)} training materials, the maps at x"
        + " and x".join(map(str, SCALES))
        + f", half the groups JPEG {JPEG_QUALITIES[0]}-{JPEG_QUALITIES[1]}",
        "train_maps": len(y_train),
        "held_out_materials": held_names,
    }
    clf = fit(x_train, y_train, meta)
    groups, y_held, x_held = _collect(load_materials(root, held_names, manifest))
    if len(y_held):
        clf.meta["held_out"] = score(clf, groups, y_held, x_held)
    return clf
