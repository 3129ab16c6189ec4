"""sRGB <-> linear, done once at the edges: maps become linear when they become parameters and
return to sRGB when they are written. Works on numpy arrays and torch tensors alike."""

from __future__ import annotations

import numpy as np
import torch


def srgb_to_linear(x):
    """IEC 61966-2-1 decoding of values in [0, 1] (clamped first)."""
    if isinstance(x, torch.Tensor):
        x = x.clamp(0.0, 1.0)
        return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055).clamp_min(1e-12) ** 2.4)
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def linear_to_srgb(x):
    """IEC 61966-2-1 encoding of values in [0, 1] (clamped first)."""
    if isinstance(x, torch.Tensor):
        x = x.clamp(0.0, 1.0)
        return torch.where(
            x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055
        )
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(
        x <= 0.0031308, x * 12.92, 1.055 * np.power(np.maximum(x, 1e-12), 1.0 / 2.4) - 0.055
    ).astype(np.float32)
