"""A data channel as a blend of its upscales, weighted one scale down (prior/blend.py)."""

from __future__ import annotations

import numpy as np

from pbrsr_core.metrics import psnr
from pbrsr_core.prior.blend import MIN_WEIGHT, blend, blend_check, blend_plan, blend_weights


def _images(seed: int, n: int, shape=(48, 48)) -> list[np.ndarray]:
    g = np.random.default_rng(seed)
    return [g.random(shape).astype(np.float32) for _ in range(n)]


def test_the_weights_of_a_convex_blend_are_recovered():
    u1, u2, bic = _images(1, 3)
    ref = 0.3 * u1 + 0.5 * u2 + 0.2 * bic
    w = blend_weights([u1, u2], bic, ref)
    assert np.allclose(w, [0.3, 0.5], atol=1e-3)
    out = blend([u1, u2], bic, w)
    assert out.dtype == np.float32 and psnr(out, ref) > 60.0


def test_weights_are_clipped_and_slivers_dropped():
    u1, u2, bic = _images(2, 3)
    # an extrapolation past the first upscale: clipped to it alone, bicubic gets nothing
    w = blend_weights([u1, u2], bic, 1.5 * u1 - 0.5 * bic)
    assert w[0] == 1.0 and w[1] == 0.0
    # an upscale that carries nothing the reference has is dropped, not kept as a sliver
    noise = np.random.default_rng(3).random(u1.shape).astype(np.float32)
    w = blend_weights([u1, noise], bic, 0.6 * u1 + 0.4 * bic + 0.01 * (noise - 0.5))
    assert w[1] == 0.0 and abs(w[0] - 0.6) < 0.02
    assert all(x == 0.0 or x >= MIN_WEIGHT for x in w)


def test_only_the_masked_texels_count():
    u1, u2, bic = _images(4, 3)
    mask = np.zeros(u1.shape, bool)
    mask[:, :24] = True
    ref = np.where(mask, u1, u2)
    assert blend_weights([u1, u2], bic, ref, mask) == [1.0, 0.0]
    assert blend_weights([u1, u2], bic, ref, ~mask) == [0.0, 1.0]


def test_degenerate_upscales_give_finite_weights_and_maps():
    (bic,) = _images(5, 1)
    # upscales equal to bicubic (a flat map): nothing to weigh
    assert blend_weights([bic, bic.copy()], bic, bic) == [0.0, 0.0]
    flat = np.full((16, 16), 0.4, np.float32)
    assert blend_weights([flat], flat, flat) == [0.0]
    bad = bic.copy()
    bad[0, 0] = np.nan
    out = blend([bad], bic, [1.0])
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0


def test_the_check_scores_each_channel_and_names_the_guided_upscale():
    u1, u2, bic, paint = (
        np.stack(x, -1) for x in zip(*(_images(s, 4) for s in (6, 7, 8)), strict=True)
    )
    ref = 0.5 * u1 + 0.5 * bic  # half the first candidate, but the last channel follows the paint
    ref[..., 2] = paint[..., 2]
    mask = np.ones(ref.shape[:2], bool)

    def db(up, r):
        return psnr(up[mask], r[mask])

    kept = {"db": db, "crop": ref, "bicubic": bic, "mask": mask, "ups": {"a": u1, "b": u2}}
    fits = blend_check(kept, [0, 2], {2: paint[..., 2]}, network_db=0.1, margin=0.1)
    assert set(fits) == {0, 2}
    names, w, gain = fits[0]
    # b, weighed by no channel, is left out (its network would not run)
    assert names == ["a"] and np.allclose(w, [0.5], atol=1e-3) and gain > 40.0
    names, w, gain = fits[2]
    assert names == ["a", "guided"] and w == [0.0, 1.0] and gain > 40.0


def test_a_network_that_adds_little_is_not_run():
    u1, u2, bic = _images(9, 3)
    noise = np.random.default_rng(10).normal(0, 0.1, u1.shape).astype(np.float32)
    ref = (0.5 * u1 + 0.5 * bic + 0.08 * (u2 - bic) + noise)[..., None]
    mask = np.ones(u1.shape, bool)
    kept = {
        "db": lambda up, r: psnr(up[mask], r[mask]),
        "crop": ref,
        "bicubic": bic[..., None],
        "mask": mask,
        "ups": {"a": u1[..., None], "b": u2[..., None]},
    }
    names, w, both = blend_check(kept, [0], network_db=0.0, margin=0.0)[0]
    assert names == ["a", "b"] and w[1] > MIN_WEIGHT
    # b adds under 1 dB: left out
    names, w, one = blend_check(kept, [0], network_db=1.0, margin=0.0)[0]
    assert names == ["a"] and abs(w[0] - 0.5) < 0.06 and 0 < both - one < 1.0
    assert blend_check(kept, [0], network_db=0.1, margin=0.0)[0][0] == ["a", "b"]
    assert blend_check(kept, [0], network_db=1e3, margin=0.0)[0] == ([], [], 0.0)
    # a blend counts towards a network's worth only where it passes the margin
    assert blend_check(kept, [0], network_db=0.1, margin=1e3)[0] == ([], [], 0.0)


def test_a_network_runs_only_on_the_channels_it_adds_to():
    u1, u2, bic = _images(9, 3)
    noise = np.random.default_rng(10).normal(0, 0.1, u1.shape).astype(np.float32)
    ref = np.stack(
        [
            0.5 * u1 + 0.5 * bic + 0.08 * (u2 - bic) + noise,  # b adds under 1 dB here
            0.7 * u2 + 0.3 * bic,  # and all of it here
        ],
        -1,
    )
    mask = np.ones(u1.shape, bool)
    kept = {
        "db": lambda up, r: psnr(up[mask], r[mask]),
        "crop": ref,
        "bicubic": np.stack([bic, bic], -1),
        "mask": mask,
        "ups": {"a": np.stack([u1, u1], -1), "b": np.stack([u2, u2], -1)},
    }
    every = blend_check(kept, [0, 1], network_db=0.0, margin=0.0)
    assert every[0][0] == ["a", "b"] and min(every[0][1]) > MIN_WEIGHT
    for channel_db in (None, 0.0, 0.1):  # b adds more than 0.1 dB to channel 0
        assert blend_check(kept, [0, 1], network_db=0.0, margin=0.0, channel_db=channel_db) == every
    fits = blend_check(kept, [0, 1], network_db=0.0, margin=0.0, channel_db=1.0)
    names, w, gain = fits[0]
    assert names == ["a"] and abs(w[0] - 0.5) < 0.06 and 0 < every[0][2] - gain < 1.0
    assert fits[1] == every[1] and every[1][1][every[1][0].index("b")] > 0.6
    # what the run blends: both networks, each weighed by (run on) its own channel only
    sources, weights, use = blend_plan(fits, ["a", "b"], 2, 0.0)
    assert sources == ["a", "b"] and use == [True, True]
    assert weights[0][1] == 0.0 and weights[1][1] > 0.6
    # each channel's last network is dropped too where it adds less than channel_db
    assert blend_check(kept, [0, 1], network_db=0.0, margin=0.0, channel_db=1e3) == {
        0: ([], [], 0.0),
        1: ([], [], 0.0),
    }


def test_a_network_stays_where_the_blend_would_fall_below_its_pick():
    u1, u2, bic = _images(11, 3)
    g = np.random.default_rng(12)
    ref = 0.7 * u1 + 0.3 * bic + g.normal(0, 0.05, u1.shape)
    guide = 0.5 * ref + 0.5 * u2  # the guided fit follows the reference less closely
    mask = np.ones(u1.shape, bool)

    def db(up, r):
        return psnr(up[mask], r[mask])

    kept = {"db": db, "crop": ref[..., None], "bicubic": bic[..., None], "mask": mask,
            "ups": {"a": u1[..., None]}}  # fmt: skip
    pick = db(u1, ref) - db(bic, ref)
    alone = blend_check(kept, [0], {0: guide}, network_db=1e3, margin=0.0)[0]
    assert alone[0] == ["guided"] and alone[2] < pick  # the rule alone drops the network
    kept_a = blend_check(kept, [0], {0: guide}, network_db=1e3, margin=0.0,
                         picks={0: ("a", pick)})[0]  # fmt: skip
    assert kept_a[0] == ["a", "guided"] and kept_a[1][0] > 0.5 and kept_a[2] >= pick - 1e-3
    # a pick the guided fit alone reaches does not hold the network
    low = blend_check(kept, [0], {0: guide}, network_db=1e3, margin=0.0,
                      picks={0: ("a", alone[2] - 0.01)})[0]  # fmt: skip
    assert low == alone


def test_a_channel_keeps_its_pick_unless_the_blend_beats_it():
    names = ["a", "b", "guided"]
    fits = {  # per channel: (sources, weights, the blend's dB over bicubic one scale down)
        0: (["a", "guided"], [0.4, 0.5], 1.04),  # the pick "a" +1.00: within 0.05 dB of it
        1: (["a", "guided"], [0.2, 0.7], 1.30),  # beats the pick "b" (+1.00) by 0.30
        2: (["guided"], [0.9], 0.50),  # its check's pick lost to bicubic: the blend's margin
        3: (["guided"], [0.9], 0.05),
    }
    picks = {0: ("a", 1.0), 1: ("b", 1.0)}
    used, weights, use = blend_plan(fits, names, 4, 0.1, picks, 0.05)
    assert used == ["a", "guided"] and use == [True, True, True, False]
    assert weights == [[1.0, 0.0], [0.2, 0.7], [0.0, 0.9], [0.0, 0.0]]
    # without the pick rule (or without picks) every channel is weighed against bicubic only
    plain = blend_plan(fits, names, 4, 0.1)
    assert plain == blend_plan(fits, names, 4, 0.1, picks, None)
    assert plain[1] == [[0.4, 0.5], [0.2, 0.7], [0.0, 0.9], [0.0, 0.0]]
    # a pick the network rule left out of every blend still runs where a channel keeps it
    used, weights, _ = blend_plan(
        {0: (["guided"], [0.9], 0.2)}, names, 1, 0.1, {0: ("b", 0.6)}, 0.05
    )
    assert used == ["b"] and weights == [[1.0]]
