"""The LR-kernel estimate (pbrsr_core.kernel_estimate): the spectrum features against
analytic filters, the shipped classifier on procedural power-law textures made LR by each
kernel, what it leaves out, and its file."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from pbrsr_core.degrade import KERNELS, degrade_image
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.kernel_estimate import (
    BINS,
    FEATURES,
    REFERENCE,
    KernelClassifier,
    estimate_kernel,
    informative,
    load_classifier,
    spectrum_features,
)


def band_centres() -> np.ndarray:
    edges = np.linspace(0.0, 0.5, BINS + 1)
    return 0.5 * (edges[:-1] + edges[1:])


def power_law_texture(size: int, slope: float, seed: int, channels: int = 3) -> np.ndarray:
    """(size, size, channels) in [0, 1]: noise whose power falls as f^-slope, as natural
    textures' does, each channel its own."""
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.maximum(np.hypot(fx, fy), 1.0 / size)
    out = []
    for _ in range(channels):
        spec = (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)) * f ** (-slope / 2)
        x = np.fft.irfft2(spec, s=(size, size))
        out.append((x - x.mean()) / (6 * x.std()) + 0.5)
    return np.clip(np.stack(out, -1), 0.0, 1.0).astype(np.float32)


def test_white_noise_has_flat_features_and_a_gaussian_blur_its_own_response():
    """White noise: every band's power equals the reference's (features ~ 0). Blurred by a
    Gaussian of sigma texels: each band is down by the filter's |H(f)|^2 = exp(-4 pi^2
    sigma^2 f^2), relative to the reference bands (the blur made in the Fourier domain;
    compared away from the window's leakage near DC and the Nyquist edge)."""
    rng = np.random.default_rng(0)
    noise = rng.normal(0.5, 0.1, size=(1024, 1024, 3))
    flat = spectrum_features(noise)
    assert flat.shape == (FEATURES,)
    assert np.abs(flat).max() < 0.08, flat

    sigma = 0.8
    f = np.hypot(np.fft.fftfreq(1024)[:, None], np.fft.fftfreq(1024)[None, :])
    h = np.exp(-2 * math.pi**2 * sigma**2 * f**2)
    blurred = np.stack(
        [np.real(np.fft.ifft2(np.fft.fft2(noise[..., c]) * h)) for c in range(3)], -1
    )
    got = spectrum_features(blurred)
    # one axis's power spectrum of a separable filter: the other axis integrates out
    log_h2 = -4 * math.pi**2 * sigma**2 * band_centres() ** 2
    want = (log_h2 - log_h2[REFERENCE].mean())[1:]
    band = slice(8, BINS - 2)  # away from the window's leakage at DC and the Nyquist edge
    assert np.abs(got[band] - want[band]).max() < 0.1, (got, want)


def test_features_ignore_contrast_brightness_and_channel_order():
    img = power_law_texture(512, 2.0, seed=1)
    base = spectrum_features(img)
    np.testing.assert_allclose(spectrum_features(0.3 * img + 0.2), base, atol=1e-6)
    np.testing.assert_allclose(spectrum_features(img[..., ::-1]), base, atol=1e-9)
    # a non-square map and one smaller than a tile are both read
    assert np.isfinite(spectrum_features(img[:200, :512])).all()


@pytest.mark.parametrize("kernel", KERNELS)
def test_the_shipped_classifier_names_the_kernel_that_made_a_procedural_asset(kernel):
    """Maps of power-law textures (slopes 1.6 to 2.6, as measured textures span), made LR at
    x4 by ``kernel`` and stored 8-bit: the maps of one 'asset' together point to it."""
    maps = []
    for i, slope in enumerate((1.6, 2.0, 2.3, 2.6)):
        hr = power_law_texture(1024, slope, seed=10 + i)
        lr = degrade_image(hr, 4, kernel=kernel)
        maps.append(np.round(lr * 255) / 255)
    est = estimate_kernel(maps)
    assert est.kernel == kernel, est
    assert est.maps == 4 and est.posterior[kernel] == max(est.posterior.values())
    assert abs(sum(est.posterior.values()) - 1.0) < 1e-9
    # each map's own probabilities, in the order given
    assert len(est.per_map) == 4
    for probs, lr in zip(est.per_map, maps, strict=True):
        assert probs is not None and abs(sum(probs.values()) - 1.0) < 1e-9
        assert probs == pytest.approx(estimate_kernel([lr]).per_map[0], abs=1e-12)


def test_flat_small_and_non_finite_maps_tell_nothing():
    flat = np.full((256, 256, 3), 0.5, np.float32)
    tiny = power_law_texture(32, 2.0, seed=3)
    bad = power_law_texture(128, 2.0, seed=4)
    bad[3, 3, 0] = np.nan
    assert not any(informative(m) for m in (flat, tiny, bad))
    est = estimate_kernel([flat, tiny, bad])
    assert est.kernel == "gaussian" and est.maps == 0 and est.per_map == (None, None, None)
    assert est.to_json()["estimated"] is False
    # a flat map beside an informative one does not change the estimate
    lr = degrade_image(power_law_texture(512, 2.0, seed=5), 2, kernel="area")
    both = estimate_kernel([lr, flat])
    assert both.posterior == estimate_kernel([lr]).posterior and both.per_map[1] is None


def test_the_classifier_file_round_trips_and_a_wrong_one_is_refused(tmp_path):
    clf = load_classifier()
    assert clf.kernels == KERNELS
    assert clf.meta["held_out"]["group_accuracy"] > 0.5  # measured on held-out materials
    again = KernelClassifier.from_json(json.loads(json.dumps(clf.to_json())))
    x = np.random.default_rng(0).normal(size=(3, FEATURES))
    np.testing.assert_allclose(again.log_probs(x), clf.log_probs(x))
    np.testing.assert_allclose(np.exp(clf.log_probs(x)).sum(1), 1.0)

    other = clf.to_json() | {"features": {"tile": 64, "bins": 8, "reference": [1, 2]}}
    (tmp_path / "other.json").write_text(json.dumps(other))
    with pytest.raises(InvalidOptions, match="other features"):
        load_classifier(tmp_path / "other.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InvalidOptions, match="cannot read the kernel classifier"):
        load_classifier(tmp_path / "bad.json")
    unknown = clf.to_json() | {"kernels": ["gaussian", "box", "area", "lanczos"]}
    with pytest.raises(InvalidOptions, match="unknown kernels"):
        KernelClassifier.from_json(unknown)


def test_log_probs_stay_finite_for_extreme_features():
    clf = load_classifier()
    lp = clf.log_probs(np.full(FEATURES, 1e6))
    assert np.isfinite(lp).all() and torch.isfinite(torch.from_numpy(lp)).all()
